"""MART iterations on sparse weights.

Weights are stored voxel-major (CSR over the reconstructed voxels): voxel ``j``'s entries are
``offsets[j] .. offsets[j + 1] - 1`` of ``pix`` (global pixel index) and ``w``. The sequential
form walks them pixel-major (the transpose, with ``vox`` the voxel of each entry).
"""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})

MAX_LOG_STEP = wp.constant(6.907755)  # ln(1000)
TINY = wp.constant(1.0e-30)


@wp.kernel
def log_ratio(image: wp.array(dtype=float), proj: wp.array(dtype=float), floor: float, ratio: wp.array(dtype=float)):
    """ratio[i] = ln(max(I_i, floor) / proj_i), 0 where nothing projects onto pixel i or it is masked.

    The log of the measured-to-projected ratio is a property of the pixel, so it is taken once
    per pixel per iteration instead of once per weight.
    """
    i = wp.tid()
    p = proj[i]
    r = float(0.0)
    # a masked pixel (negative signal, lfcore.reconstruct.MASKED) measured nothing: no ratio
    if p > 0.0 and image[i] >= 0.0:
        r = wp.log(wp.max(image[i], floor) / p)
    ratio[i] = r


@wp.kernel
def positive_sum(a: wp.array(dtype=float), out: wp.array(dtype=wp.float64)):
    """out[0] += the positive entries of ``a`` (a measured signal without its masked pixels)."""
    v = a[wp.tid()]
    if v > 0.0:
        wp.atomic_add(out, 0, wp.float64(v))


@wp.kernel
def project(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    lanes: int,
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
):
    """proj[i] += sum_j w_ij E_j: forward projection over (voxels of a chunk, ``lanes``) threads.

    The chunk's voxel t is voxel ``first + t`` of ``e``; its entries start at ``offsets[t]``.
    Lane k takes entries k, k + lanes, ...: on a GPU the 32 lanes of a warp then read 32
    consecutive weights (one coalesced transaction) where a thread per voxel would read 32
    scattered rows. (The CPU runs :func:`project_rows`.)
    """
    t0, lane = wp.tid()
    ej = e[first + t0]
    if ej == 0.0:
        return
    t = offsets[t0] + wp.int64(lane)
    end = offsets[t0 + 1]
    while t < end:
        wp.atomic_add(proj, pix[t], w[t] * ej)
        t += wp.int64(lanes)


@wp.kernel
def project_rows(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
):
    """:func:`project` with a thread per voxel, four entries a step: the CPU's form.

    The four entries' pixels and weights are read before any of them is added to: the compiler
    cannot move a read of ``pix`` or ``w`` past a write to ``proj`` (they might alias), so one
    entry at a time waits on the last one's add. Four at a time took 10-13% less time a pass
    than one on the Mc crop's 220 M entries (2-core CPU, alternating rounds); eight no less.
    """
    t0 = wp.tid()
    ej = e[first + t0]
    if ej == 0.0:
        return
    t = offsets[t0]
    end = offsets[t0 + 1]
    while t + wp.int64(4) <= end:
        a0 = pix[t]
        a1 = pix[t + wp.int64(1)]
        a2 = pix[t + wp.int64(2)]
        a3 = pix[t + wp.int64(3)]
        v0 = w[t] * ej
        v1 = w[t + wp.int64(1)] * ej
        v2 = w[t + wp.int64(2)] * ej
        v3 = w[t + wp.int64(3)] * ej
        wp.atomic_add(proj, a0, v0)
        wp.atomic_add(proj, a1, v1)
        wp.atomic_add(proj, a2, v2)
        wp.atomic_add(proj, a3, v3)
        t += wp.int64(4)
    while t < end:
        wp.atomic_add(proj, pix[t], w[t] * ej)
        t += wp.int64(1)


@wp.func
def row_sum(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    ratio: wp.array(dtype=float),
    t0: int,
    lane: int,
    lanes: int,
) -> float:
    """sum_i w_ij ratio_i over entries lane, lane + lanes, ... of row ``t0`` (all of it for one lane)."""
    s = float(0.0)
    t = offsets[t0] + wp.int64(lane)
    end = offsets[t0 + 1]
    while t < end:
        s += w[t] * ratio[pix[t]]
        t += wp.int64(lanes)
    return s


@wp.func
def row_sum4(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    ratio: wp.array(dtype=float),
    t0: int,
) -> float:
    """sum_i w_ij ratio_i over row ``t0``, one thread, four entries a step (the CPU's form)."""
    # four partial sums, so that each add need not wait for the last (as in project_rows)
    t = offsets[t0]
    end = offsets[t0 + 1]
    s0 = float(0.0)
    s1 = float(0.0)
    s2 = float(0.0)
    s3 = float(0.0)
    while t + wp.int64(4) <= end:
        s0 += w[t] * ratio[pix[t]]
        s1 += w[t + wp.int64(1)] * ratio[pix[t + wp.int64(1)]]
        s2 += w[t + wp.int64(2)] * ratio[pix[t + wp.int64(2)]]
        s3 += w[t + wp.int64(3)] * ratio[pix[t + wp.int64(3)]]
        t += wp.int64(4)
    while t < end:
        s0 += w[t] * ratio[pix[t]]
        t += wp.int64(1)
    return (s0 + s1) + (s2 + s3)


@wp.func
def multiplied(ej: float, s: float, relaxation: float) -> float:
    """E_j exp(mu s), with the step bounded and a vanishing voxel set to zero."""
    # A bounded step (a factor of at most 1e3 either way) keeps float32 finite when a voxel's
    # pixels are far from their projection; it does not move the fixed point.
    ej = ej * wp.exp(wp.clamp(relaxation * s, -MAX_LOG_STEP, MAX_LOG_STEP))
    if ej < TINY:
        ej = 0.0  # a dead voxel stays dead and costs no more work
    return ej


@wp.kernel
def smart_update(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    ratio: wp.array(dtype=float),
    relaxation: float,
    e: wp.array(dtype=float),
):
    """Simultaneous multiplicative update E_j <- E_j exp(mu sum_i w_ij ln(I_i / proj_i)), a thread per voxel.

    With a voxel's weights summing to the fraction of its light on the sensor, the exponent is
    mu times the weight-averaged log ratio of measured to projected intensity: the per-voxel
    equivalent of one sweep of eq. 4.1 over the voxel's pixels. ``ratio`` is the pixels'
    :func:`log_ratio`, where pixels below the floor count as the floor, so a dark pixel pulls
    its voxels down hard without zeroing them in one step. The CPU's form (see
    :func:`smart_update_tiled` for the GPU's), four entries a step.
    """
    t0 = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return
    e[j] = multiplied(ej, row_sum4(offsets, pix, w, ratio, t0), relaxation)


@wp.kernel
def smart_update_tiled(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    ratio: wp.array(dtype=float),
    relaxation: float,
    e: wp.array(dtype=float),
):
    """:func:`smart_update` with a block of threads per voxel (launched tiled over the voxels).

    The block's threads take interleaved entries of the voxel, so on a GPU a warp reads
    consecutive weights (coalesced), and a block reduction adds their partial sums. (On the CPU a
    block is one thread; there :func:`smart_update` is used, since tile kernels must not run
    in concurrent CPU launches.)
    """
    t0, lane = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return  # the whole block shares the voxel, so it leaves together
    s = row_sum(offsets, pix, w, ratio, t0, lane, wp.block_dim())
    total = wp.tile_sum(wp.tile(s))
    if lane == 0:
        e[j] = multiplied(ej, total[0], relaxation)


@wp.kernel
def mart_sequential(
    p_offsets: wp.array(dtype=wp.int64),
    vox: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    rows: wp.array(dtype=wp.int32),
    image: wp.array(dtype=float),
    floor: float,
    relaxation: float,
    e: wp.array(dtype=float),
):
    """One sweep of eq. 4.1 over the pixels in ``rows``, one after the other (a single thread).

    For each pixel i: proj_i = sum_j w_ij E_j with the current E, then
    E_j <- E_j (I_i / proj_i)^(mu w_ij) for every voxel j it sees.
    """
    for r in range(rows.shape[0]):
        i = rows[r]
        t0 = p_offsets[i]
        t1 = p_offsets[i + 1]
        p = float(0.0)
        t = t0
        while t < t1:
            p += w[t] * e[vox[t]]
            t += wp.int64(1)
        if p > 0.0 and image[i] >= 0.0:  # a masked pixel (negative) measured nothing
            ratio = wp.max(image[i], floor) / p
            t = t0
            step = wp.clamp(wp.log(ratio), -MAX_LOG_STEP, MAX_LOG_STEP)
            while t < t1:
                j = vox[t]
                e[j] = e[j] * wp.exp(relaxation * w[t] * step)
                t += wp.int64(1)


@wp.kernel
def scatter_volume(voxels: wp.array(dtype=wp.int32), e: wp.array(dtype=float), volume: wp.array(dtype=float)):
    j = wp.tid()
    volume[voxels[j]] = e[j]


@wp.kernel
def gather(src: wp.array(dtype=float), rows: wp.array(dtype=wp.int32), dst: wp.array(dtype=float)):
    """dst[t] = src[rows[t]]: the intensities of the rows an operator keeps (see ``restrict``)."""
    t = wp.tid()
    dst[t] = src[rows[t]]


@wp.kernel
def gather_index(src: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    """dst[t] = src[rows[t]]: the voxel indices of the rows an operator keeps."""
    t = wp.tid()
    dst[t] = src[rows[t]]


@wp.kernel
def scale_shift(e: wp.array(dtype=float), a: float, b: float):
    """e = a e + b, in place."""
    i = wp.tid()
    e[i] = a * e[i] + b


@wp.kernel
def power_of_share(e: wp.array(dtype=float), inv_scale: float, p: float):
    """e = (max(e, 0) inv_scale) ^ p, in place (a warm start sharpened, :data:`lfcore.warm.WARM_POWER`)."""
    i = wp.tid()
    e[i] = wp.pow(wp.max(e[i] * inv_scale, 0.0), p)


@wp.kernel
def residual_sums(image: wp.array(dtype=float), proj: wp.array(dtype=float), out: wp.array(dtype=wp.float64)):
    """out[0] += (I_i - proj_i)^2 and out[1] += I_i^2 over the measured pixels (a masked one's signal is negative)."""
    i = wp.tid()
    b = image[i]
    if b >= 0.0:
        d = b - proj[i]
        wp.atomic_add(out, 0, wp.float64(d * d))
        wp.atomic_add(out, 1, wp.float64(b * b))
