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
def project(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
):
    """proj[i] += sum_j w_ij E_j: forward projection, one thread per voxel of a chunk.

    The chunk's voxel t is voxel ``first + t`` of ``e``; its entries start at ``offsets[t]``.
    """
    t0 = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return
    t = offsets[t0]
    end = offsets[t0 + 1]
    while t < end:
        wp.atomic_add(proj, pix[t], w[t] * ej)
        t += wp.int64(1)


@wp.kernel
def smart_update(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    image: wp.array(dtype=float),
    proj: wp.array(dtype=float),
    floor: float,
    relaxation: float,
    e: wp.array(dtype=float),
):
    """Simultaneous multiplicative update E_j <- E_j exp(mu sum_i w_ij ln(I_i / proj_i)).

    With a voxel's weights summing to the fraction of its light on the sensor, the exponent is
    mu times the weight-averaged log ratio of measured to projected intensity: the per-voxel
    equivalent of one sweep of eq. 4.1 over the voxel's pixels. Pixels below ``floor`` count as
    ``floor``, so a dark pixel pulls its voxels down hard without zeroing them in one step.
    """
    t0 = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return
    s = float(0.0)
    t = offsets[t0]
    end = offsets[t0 + 1]
    while t < end:
        i = pix[t]
        p = proj[i]
        if p > 0.0:
            s += w[t] * wp.log(wp.max(image[i], floor) / p)
        t += wp.int64(1)
    # A bounded step (a factor of at most 1e3 either way) keeps float32 finite when a voxel's
    # pixels are far from their projection; it does not move the fixed point.
    ej = ej * wp.exp(wp.clamp(relaxation * s, -MAX_LOG_STEP, MAX_LOG_STEP))
    if ej < TINY:
        ej = 0.0  # a dead voxel stays dead and costs no more work
    e[j] = ej


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
        if p > 0.0:
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
