"""Batched FFT cross-correlation of interrogation volumes.

Layout: a batch of ``n`` windows lives in one buffer of complex samples (``vec2f``) shaped
(n, Pz, Py, Px), the padded window size. Volume A goes in the real part and volume B in the
imaginary part, so one complex FFT transforms both (their spectra are separated again by
Hermitian symmetry in :func:`cross_spectrum`). Every vector quantity is a ``vec3`` ordered
(x, y, z); arrays are indexed (z, y, x) like the volumes.
"""

from __future__ import annotations

import functools

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.kernel
def count_nonfinite(vol: wp.array3d(dtype=wp.float32), count: wp.array(dtype=int)):
    """Count the voxels that are NaN or infinite (GPU launches only: atomics)."""
    z, y, x = wp.tid()
    if not wp.isfinite(vol[z, y, x]):
        wp.atomic_add(count, 0, 1)


@wp.func
def voxel(vol: wp.array3d(dtype=wp.float32), x: int, y: int, z: int) -> float:
    """Intensity of voxel (x, y, z); zero outside the volume."""
    if x < 0 or y < 0 or z < 0 or z >= vol.shape[0] or y >= vol.shape[1] or x >= vol.shape[2]:
        return 0.0
    return vol[z, y, x]


@wp.func
def near(vol: wp.array3d(dtype=wp.float32), p: wp.vec3) -> bool:
    """Whether p = (x, y, z) lies within 4 voxels of the volume: false for NaN and for points so
    far that their index would not fit an int (whose conversion is undefined)."""
    return (p[0] > -4.0 and p[1] > -4.0 and p[2] > -4.0 and p[0] < float(vol.shape[2]) + 4.0
            and p[1] < float(vol.shape[1]) + 4.0 and p[2] < float(vol.shape[0]) + 4.0)


@wp.func
def sample(vol: wp.array3d(dtype=wp.float32), p: wp.vec3) -> float:
    """Trilinear interpolation of the volume at voxel coordinates p = (x, y, z); zero outside."""
    if not near(vol, p):
        return 0.0
    fx = wp.floor(p[0])
    fy = wp.floor(p[1])
    fz = wp.floor(p[2])
    tx = p[0] - fx
    ty = p[1] - fy
    tz = p[2] - fz
    x = int(fx)
    y = int(fy)
    z = int(fz)
    c00 = voxel(vol, x, y, z) * (1.0 - tx) + voxel(vol, x + 1, y, z) * tx
    c10 = voxel(vol, x, y + 1, z) * (1.0 - tx) + voxel(vol, x + 1, y + 1, z) * tx
    c01 = voxel(vol, x, y, z + 1) * (1.0 - tx) + voxel(vol, x + 1, y, z + 1) * tx
    c11 = voxel(vol, x, y + 1, z + 1) * (1.0 - tx) + voxel(vol, x + 1, y + 1, z + 1) * tx
    c0 = c00 * (1.0 - ty) + c10 * ty
    c1 = c01 * (1.0 - ty) + c11 * ty
    return c0 * (1.0 - tz) + c1 * tz


@wp.func
def axis_weight(q: float, n: int) -> wp.vec3:
    """Lower index, upper index and weight of linear interpolation at grid coordinate q.

    Beyond the first or last grid point the end cell's line is extrapolated (the weight leaves
    [0, 1]), so that windows reaching past the outermost centres are deformed by the linear
    continuation of the predictor rather than by its edge value.
    """
    if n < 2:
        return wp.vec3(0.0, 0.0, 0.0)
    i0 = wp.clamp(int(wp.floor(q)), 0, n - 2)
    return wp.vec3(float(i0), float(i0 + 1), q - float(i0))


@wp.func
def predictor_at(pred: wp.array3d(dtype=wp.vec3), origin: wp.vec3, step: wp.vec3, p: wp.vec3) -> wp.vec3:
    """Trilinear interpolation of the predictor grid at voxel coordinates p, extrapolated linearly.

    ``pred`` holds displacements (x, y, z) in voxels at window centres origin + i * step.
    """
    ax = axis_weight((p[0] - origin[0]) / step[0], pred.shape[2])
    ay = axis_weight((p[1] - origin[1]) / step[1], pred.shape[1])
    az = axis_weight((p[2] - origin[2]) / step[2], pred.shape[0])
    x0 = int(ax[0])
    x1 = int(ax[1])
    y0 = int(ay[0])
    y1 = int(ay[1])
    z0 = int(az[0])
    z1 = int(az[1])
    tx = ax[2]
    ty = ay[2]
    tz = az[2]
    c00 = pred[z0, y0, x0] * (1.0 - tx) + pred[z0, y0, x1] * tx
    c10 = pred[z0, y1, x0] * (1.0 - tx) + pred[z0, y1, x1] * tx
    c01 = pred[z1, y0, x0] * (1.0 - tx) + pred[z1, y0, x1] * tx
    c11 = pred[z1, y1, x0] * (1.0 - tx) + pred[z1, y1, x1] * tx
    return (c00 * (1.0 - ty) + c10 * ty) * (1.0 - tz) + (c01 * (1.0 - ty) + c11 * ty) * tz


#: Pole of the cubic B-spline prefilter, sqrt(3) - 2.
BSPLINE_POLE = -0.2679491924311228


@wp.func
def bspline_weights(t: float) -> wp.vec4:
    """Cubic B-spline weights of the coefficients at -1, 0, 1, 2 for an offset t in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    u = 1.0 - t
    return wp.vec4(u * u * u / 6.0, (4.0 - 6.0 * t2 + 3.0 * t3) / 6.0, (1.0 + 3.0 * t + 3.0 * t2 - 3.0 * t3) / 6.0,
                   t3 / 6.0)


@wp.func
def sample_bspline(coef: wp.array3d(dtype=wp.float32), p: wp.vec3) -> float:
    """Cubic B-spline interpolation at voxel coordinates p = (x, y, z) from prefiltered coefficients."""
    if not near(coef, p):
        return 0.0
    fx = wp.floor(p[0])
    fy = wp.floor(p[1])
    fz = wp.floor(p[2])
    wx = bspline_weights(p[0] - fx)
    wy = bspline_weights(p[1] - fy)
    wz = bspline_weights(p[2] - fz)
    x = int(fx) - 1
    y = int(fy) - 1
    z = int(fz) - 1
    acc = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    if x >= 0 and y >= 0 and z >= 0 and x + 3 < coef.shape[2] and y + 3 < coef.shape[1] and z + 3 < coef.shape[0]:
        # inside the volume (nearly every sample): no test per coefficient
        for c in range(4):
            plane = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
            for b in range(4):
                row = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
                for a in range(4):
                    row += wx[a] * coef[z + c, y + b, x + a]
                plane += wy[b] * row
            acc += wz[c] * plane
        return acc
    for c in range(4):
        plane = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
        for b in range(4):
            row = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
            for a in range(4):
                row += wx[a] * voxel(coef, x + a, y + b, z + c)
            plane += wy[b] * row
        acc += wz[c] * plane
    return acc


@wp.kernel
def bspline_prefilter(coef: wp.array3d(dtype=wp.float32), axis: int, a0: int):
    """In place: samples to cubic B-spline coefficients along one axis (0 x, 1 y, 2 z).

    One thread filters one line; the launch covers lines (a0 + a, b) of the other two axes.

    The recursive filter of Unser (1999), gain 6 and pole z = sqrt(3) - 2, for a signal that is
    zero beyond the volume: c+[k] = s[k] + z c+[k-1] from c+[0] = s[0], then
    c-[k] = z (c-[k+1] - c+[k]) from c-[n-1] = -z / (1 - z^2) c+[n-1].
    """
    a, b = wp.tid()
    a += a0
    zp = BSPLINE_POLE
    n = coef.shape[2 - axis]
    prev = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    for k in range(n):
        z = a
        y = b
        x = k
        if axis == 1:
            x = b
            y = k
        elif axis == 2:
            y = a
            x = b
            z = k
        prev = coef[z, y, x] + zp * prev
        coef[z, y, x] = prev
    nxt = -zp / (1.0 - zp * zp) * prev
    for m in range(n):
        k = n - 1 - m
        z = a
        y = b
        x = k
        if axis == 1:
            x = b
            y = k
        elif axis == 2:
            y = a
            x = b
            z = k
        if m > 0:
            nxt = zp * (nxt - coef[z, y, x])
        coef[z, y, x] = 6.0 * nxt


@wp.kernel
def deform_volumes(
    vol_a: wp.array3d(dtype=wp.float32),
    vol_b: wp.array3d(dtype=wp.float32),
    pred: wp.array3d(dtype=wp.vec3),
    pred_origin: wp.vec3,
    pred_step: wp.vec3,
    bspline: int,
    z0: int,
    out_a: wp.array3d(dtype=wp.float32),
    out_b: wp.array3d(dtype=wp.float32),
):
    """Deform both volumes symmetrically by the predictor d: A at x - d(x)/2, B at x + d(x)/2.

    The launch covers planes z0 + z of the outputs (all of them from z0 = 0).

    A particle that moved by d(x) then sits at the same place in both, so the correlation of
    the deformed volumes measures only what the predictor missed. With ``bspline`` non-zero the
    inputs are cubic B-spline coefficients (:func:`bspline_prefilter`), otherwise samples
    interpolated trilinearly.
    """
    z, y, x = wp.tid()
    z += z0
    p = wp.vec3(float(x), float(y), float(z))
    h = 0.5 * predictor_at(pred, pred_origin, pred_step, p)
    if bspline != 0:
        out_a[z, y, x] = sample_bspline(vol_a, p - h)
        out_b[z, y, x] = sample_bspline(vol_b, p + h)
    else:
        out_a[z, y, x] = sample(vol_a, p - h)
        out_b[z, y, x] = sample(vol_b, p + h)


@wp.func
def gather_value(vol_a: wp.array3d(dtype=wp.float32), vol_b: wp.array3d(dtype=wp.float32), s: wp.vec3i,
                 sa: wp.vec3i, sb: wp.vec3i, size: wp.vec3i, k: int, j: int, i: int) -> wp.vec2f:
    """Buffer sample (i, j, k) of a window at ``s``: A (shifted by sa) real, B (by sb) imaginary, 0 in the padding."""
    if i >= size[0] or j >= size[1] or k >= size[2]:
        return wp.vec2f(0.0, 0.0)
    return wp.vec2f(voxel(vol_a, s[0] + i + sa[0], s[1] + j + sa[1], s[2] + k + sa[2]),
                    voxel(vol_b, s[0] + i + sb[0], s[1] + j + sb[1], s[2] + k + sb[2]))


@wp.kernel
def gather(
    vol_a: wp.array3d(dtype=wp.float32),
    vol_b: wp.array3d(dtype=wp.float32),
    start: wp.array(dtype=wp.vec3i),
    shift_a: wp.array(dtype=wp.vec3i),
    shift_b: wp.array(dtype=wp.vec3i),
    first: int,
    size: wp.vec3i,
    out: wp.array4d(dtype=wp.vec2f),
    sums: wp.array2d(dtype=wp.vec4),
):
    """Copy one row of each window into the buffer (A real, B imaginary, zero padding).

    The windows of B are offset from those of A by the integer window shift. Also writes the
    row's sums (a, b, a^2, b^2) for the window statistics. One thread a row: the CPU layout.
    """
    w, k, j = wp.tid()
    g = first + w
    acc = wp.vec4(0.0, 0.0, 0.0, 0.0)
    inside = j < size[1] and k < size[2]
    s = start[g]
    sa = shift_a[g]
    sb = shift_b[g]
    nz = vol_a.shape[0]
    ny = vol_a.shape[1]
    nx = vol_a.shape[2]
    xa = s[0] + sa[0]
    ya = s[1] + j + sa[1]
    za = s[2] + k + sa[2]
    xb = s[0] + sb[0]
    yb = s[1] + j + sb[1]
    zb = s[2] + k + sb[2]
    # rows wholly inside both volumes are copied without per-voxel bounds checks
    fast = (inside and ya >= 0 and ya < ny and za >= 0 and za < nz and yb >= 0 and yb < ny and zb >= 0 and zb < nz
            and xa >= 0 and xa + size[0] <= nx and xb >= 0 and xb + size[0] <= nx)
    for i in range(out.shape[3]):
        v = wp.vec2f(0.0, 0.0)
        if fast and i < size[0]:
            v = wp.vec2f(vol_a[za, ya, xa + i], vol_b[zb, yb, xb + i])
        elif inside:
            v = gather_value(vol_a, vol_b, s, sa, sb, size, k, j, i)
        acc += wp.vec4(v[0], v[1], v[0] * v[0], v[1] * v[1])
        out[w, k, j, i] = v
    sums[w, k * out.shape[2] + j] = acc


@wp.kernel
def gather_elements(
    vol_a: wp.array3d(dtype=wp.float32),
    vol_b: wp.array3d(dtype=wp.float32),
    start: wp.array(dtype=wp.vec3i),
    shift_a: wp.array(dtype=wp.vec3i),
    shift_b: wp.array(dtype=wp.vec3i),
    first: int,
    size: wp.vec3i,
    out: wp.array4d(dtype=wp.vec2f),
):
    """:func:`gather` with one thread a sample (the GPU layout: neighbouring threads read and
    write neighbouring addresses); the row sums come from :func:`row_sums`."""
    w, k, j, i = wp.tid()
    g = first + w
    out[w, k, j, i] = gather_value(vol_a, vol_b, start[g], shift_a[g], shift_b[g], size, k, j, i)


@wp.func
def moments(v: wp.vec2f) -> wp.vec4:
    return wp.vec4(v[0], v[1], v[0] * v[0], v[1] * v[1])


@functools.cache
def row_sums(length: int, rows: int):
    """A tiled kernel: sums (a, b, a^2, b^2) of ``rows`` buffer rows of ``length`` samples per block."""

    @wp.kernel(module="unique", enable_backward=False)
    def row_sums_kernel(buf: wp.array2d(dtype=wp.vec2f), sums: wp.array(dtype=wp.vec4)):
        b = wp.tid()
        t = wp.tile_load(buf, shape=(rows, length), offset=(b * rows, 0))
        wp.tile_store(sums, wp.tile_sum(wp.tile_map(moments, t), axis=1), offset=b * rows)

    return row_sums_kernel


@wp.kernel
def window_stats(sums: wp.array2d(dtype=wp.vec4), n_voxels: float, mean: wp.array(dtype=wp.vec2f),
                 scale: wp.array(dtype=float)):
    """Window means, and 1 / sqrt(sum a'^2 sum b'^2) with a' = a - mean (0 for a window without signal)."""
    w = wp.tid()
    s = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for t in range(sums.shape[1]):
        s += sums[w, t]
    ma = s[0] / n_voxels
    mb = s[1] / n_voxels
    va = s[2] - s[0] * ma
    vb = s[3] - s[1] * mb
    mean[w] = wp.vec2f(ma, mb)
    sc = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    # a window with (almost) no fluctuation in either volume has no correlation peak
    if va > 1.0e-6 * s[2] and vb > 1.0e-6 * s[3] and va > 0.0 and vb > 0.0:
        sc = 1.0 / wp.sqrt(va * vb)
    scale[w] = sc


@wp.func
def cmul(p: wp.vec2f, q: wp.vec2f) -> wp.vec2f:
    return wp.vec2f(p[0] * q[0] - p[1] * q[1], p[0] * q[1] + p[1] * q[0])


@wp.func
def pair_spectrum(z: wp.vec2f, m: wp.vec2f, mean: wp.vec2f, mask: wp.vec2f, s: float) -> wp.vec2f:
    """s conj(A') B' at one frequency f, from the spectrum Z of z = a + i b at f (z) and -f (m).

    a and b are real, so A(f) = (Z(f) + conj(Z(-f))) / 2 and B(f) = (Z(f) - conj(Z(-f))) / 2i.
    The window means are removed here: A' = A - mean_a M, with M the spectrum of the window's
    footprint in the (padded) buffer.
    """
    a = 0.5 * wp.vec2f(z[0] + m[0], z[1] - m[1]) - mean[0] * mask
    b = 0.5 * wp.vec2f(z[1] + m[1], m[0] - z[0]) - mean[1] * mask
    return s * cmul(wp.vec2f(a[0], -a[1]), b)


@wp.func
def packed_spectrum(spec: wp.array4d(dtype=wp.vec2f), mean: wp.array(dtype=wp.vec2f), scale: wp.array(dtype=float),
                    norm: float, myz: wp.vec2f, mask_x: wp.array(dtype=wp.vec2f), q: int, k: int, j: int,
                    i: int) -> wp.vec2f:
    """S0 + i S1 at frequency (i, j, k): the scaled cross-spectra of windows 2q and 2q + 1."""
    pz = spec.shape[1]
    py = spec.shape[2]
    px = spec.shape[3]
    mi = (px - i) % px
    mj = (py - j) % py
    mk = (pz - k) % pz
    mask = cmul(mask_x[i], myz)
    w0 = 2 * q
    r0 = pair_spectrum(spec[w0, k, j, i], spec[w0, mk, mj, mi], mean[w0], mask, scale[w0] * norm)
    r1 = wp.vec2f(0.0, 0.0)
    if w0 + 1 < spec.shape[0]:
        r1 = pair_spectrum(spec[w0 + 1, k, j, i], spec[w0 + 1, mk, mj, mi], mean[w0 + 1], mask, scale[w0 + 1] * norm)
    return wp.vec2f(r0[0] - r1[1], r0[1] + r1[0])


@wp.kernel
def cross_spectrum(spec: wp.array4d(dtype=wp.vec2f), mean: wp.array(dtype=wp.vec2f), scale: wp.array(dtype=float),
                   norm: float, mask_x: wp.array(dtype=wp.vec2f), mask_y: wp.array(dtype=wp.vec2f),
                   mask_z: wp.array(dtype=wp.vec2f), out: wp.array4d(dtype=wp.vec2f)):
    """Cross-spectra of windows 2q and 2q+1 packed as S0 + i S1 into slot q, one row (q, k, j) a thread.

    Both correlations are real, so one inverse FFT returns the first in the real part and the
    second in the imaginary part. Each is scaled to the correlation coefficient. The footprint
    spectrum M is separable: mask_x[i] mask_y[j] mask_z[k].
    """
    q, k, j = wp.tid()
    myz = cmul(mask_y[j], mask_z[k])
    for i in range(spec.shape[3]):
        out[q, k, j, i] = packed_spectrum(spec, mean, scale, norm, myz, mask_x, q, k, j, i)


@wp.kernel
def cross_spectrum_elements(spec: wp.array4d(dtype=wp.vec2f), mean: wp.array(dtype=wp.vec2f),
                            scale: wp.array(dtype=float), norm: float, mask_x: wp.array(dtype=wp.vec2f),
                            mask_y: wp.array(dtype=wp.vec2f), mask_z: wp.array(dtype=wp.vec2f),
                            out: wp.array4d(dtype=wp.vec2f)):
    """:func:`cross_spectrum` with one thread a frequency (the GPU layout)."""
    q, k, j, i = wp.tid()
    out[q, k, j, i] = packed_spectrum(spec, mean, scale, norm, cmul(mask_y[j], mask_z[k]), mask_x, q, k, j, i)


@wp.func
def unpack(c: wp.vec2f, odd: int) -> float:
    """The correlation of the even (real part) or odd (imaginary part) window of a packed slot."""
    if odd == 1:
        return c[1]
    return c[0]


@wp.func
def corr_value(corr: wp.array4d(dtype=wp.vec2f), w: int, k: int, j: int, i: int) -> float:
    """Correlation of window w at (k, j, i), wrapped cyclically (packed two windows per slot)."""
    pz = corr.shape[1]
    py = corr.shape[2]
    px = corr.shape[3]
    return unpack(corr[w // 2, (k + pz) % pz, (j + py) % py, (i + px) % px], w % 2)


@wp.func
def cyclic_distance(a: int, b: int, n: int) -> int:
    d = wp.abs(a - b) % n
    return wp.min(d, n - d)


@wp.kernel
def row_peaks(corr: wp.array4d(dtype=wp.vec2f), row_val: wp.array2d(dtype=float), row_i: wp.array2d(dtype=int)):
    """Highest value of each row (w, k, j) of every window's correlation, and its column (the
    lowest on ties). One thread a row; :func:`peak_partial` then works on these maxima."""
    w, r = wp.tid()
    py = corr.shape[2]
    px = corr.shape[3]
    k = r // py
    j = r - k * py
    slot = w // 2
    odd = w % 2
    best = float(-1.0e30)  # noqa: UP018 - a dynamic Warp variable, mutated below
    best_i = int(0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    for i in range(px):
        v = unpack(corr[slot, k, j, i], odd)
        if v > best:
            best = v
            best_i = i
    row_val[w, r] = best
    row_i[w, r] = best_i


@wp.kernel
def peak_partial(corr: wp.array4d(dtype=wp.vec2f), row_val: wp.array2d(dtype=float), row_i: wp.array2d(dtype=int),
                 threads: int, exclude: wp.array(dtype=wp.vec3i), radius: int, use_exclude: int,
                 part_val: wp.array2d(dtype=float), part_idx: wp.array2d(dtype=int)):
    """Per-thread maximum of each correlation volume, optionally outside a box around a first peak.

    Thread t of a window takes rows t, t + threads, ... of its (Pz * Py) rows from the row
    maxima of :func:`row_peaks`; only the few rows that cross the excluded box are scanned
    again, without the box. The result equals a scan of every value, lowest index on ties.
    """
    w, t = wp.tid()
    pz = corr.shape[1]
    py = corr.shape[2]
    px = corr.shape[3]
    best = float(-1.0e30)  # noqa: UP018 - a dynamic Warp variable, mutated below
    best_idx = int(-1)  # noqa: UP018 - a dynamic Warp variable, mutated below
    e = exclude[w]
    slot = w // 2
    odd = w % 2
    row = t
    while row < pz * py:
        k = row // py
        j = row - k * py
        near = use_exclude != 0 and cyclic_distance(j, e[1], py) <= radius and cyclic_distance(k, e[2], pz) <= radius
        if near:
            for i in range(px):
                if cyclic_distance(i, e[0], px) > radius:
                    v = unpack(corr[slot, k, j, i], odd)
                    if v > best:
                        best = v
                        best_idx = row * px + i
        else:
            v = row_val[w, row]
            if v > best:
                best = v
                best_idx = row * px + row_i[w, row]
        row += threads
    part_val[w, t] = best
    part_idx[w, t] = best_idx


@wp.kernel
def peak_reduce(part_val: wp.array2d(dtype=float), part_idx: wp.array2d(dtype=int), size: wp.vec3i,
                value: wp.array(dtype=float), where: wp.array(dtype=wp.vec3i)):
    """The maximum over the threads of each window; ties go to the lowest index (deterministic)."""
    w = wp.tid()
    best = float(-1.0e30)  # noqa: UP018 - a dynamic Warp variable, mutated below
    best_idx = int(-1)  # noqa: UP018 - a dynamic Warp variable, mutated below
    for t in range(part_val.shape[1]):
        v = part_val[w, t]
        ix = part_idx[w, t]
        if ix >= 0 and (v > best or (v == best and ix < best_idx)):
            best = v
            best_idx = ix
    value[w] = best
    if best_idx < 0:
        best_idx = 0
    where[w] = wp.vec3i(best_idx % size[0], (best_idx // size[0]) % size[1], best_idx // (size[0] * size[1]))


@wp.func
def subvoxel(lo: float, c: float, hi: float) -> wp.vec2:
    """Sub-voxel offset of a peak from three samples, and 1 if the centroid fallback was used.

    The 3-point Gaussian fit (exact for a Gaussian peak) needs three positive samples; otherwise
    the centroid of the positive parts is used.
    """
    if lo > 0.0 and c > 0.0 and hi > 0.0:
        llo = wp.log(lo)
        lc = wp.log(c)
        lhi = wp.log(hi)
        den = 2.0 * (llo - 2.0 * lc + lhi)
        if den < 0.0:
            return wp.vec2(wp.clamp((llo - lhi) / den, -0.5, 0.5), 0.0)
    plo = wp.max(lo, 0.0)
    pc = wp.max(c, 0.0)
    phi = wp.max(hi, 0.0)
    s = plo + pc + phi
    if s > 0.0:
        return wp.vec2(wp.clamp((phi - plo) / s, -0.5, 0.5), 1.0)
    return wp.vec2(0.0, 1.0)


@wp.func
def signed_shift(k: int, n: int) -> int:
    if k >= (n + 1) // 2:
        return k - n
    return k


@wp.kernel
def peak_fit(corr: wp.array4d(dtype=wp.vec2f), first: int, scale: wp.array(dtype=float),
             peak1: wp.array(dtype=wp.vec3i), value1: wp.array(dtype=float), value2: wp.array(dtype=float),
             displacement: wp.array(dtype=wp.vec3), height: wp.array(dtype=float), ratio: wp.array(dtype=float),
             fallback: wp.array(dtype=int), valid: wp.array(dtype=int)):
    """Sub-voxel peak position (the residual displacement, voxels), peak height and peak ratio."""
    w = wp.tid()
    g = first + w
    p = peak1[w]
    i = p[0]
    j = p[1]
    k = p[2]
    c = corr_value(corr, w, k, j, i)
    fx = subvoxel(corr_value(corr, w, k, j, i - 1), c, corr_value(corr, w, k, j, i + 1))
    fy = subvoxel(corr_value(corr, w, k, j - 1, i), c, corr_value(corr, w, k, j + 1, i))
    fz = subvoxel(corr_value(corr, w, k - 1, j, i), c, corr_value(corr, w, k + 1, j, i))
    displacement[g] = wp.vec3(float(signed_shift(i, corr.shape[3])) + fx[0],
                              float(signed_shift(j, corr.shape[2])) + fy[0],
                              float(signed_shift(k, corr.shape[1])) + fz[0])
    height[g] = value1[w]
    r = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    if value2[w] > 0.0:
        r = value1[w] / value2[w]
    elif value1[w] > 0.0:
        r = 1.0e6  # no second positive peak at all
    ratio[g] = r
    fallback[g] = int(fx[1] + fy[1] + fz[1] > 0.0)
    ok = int(0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    if scale[w] > 0.0 and value1[w] > 0.0:
        ok = 1
    valid[g] = ok


@functools.cache
def fft_lines(n: int, rows: int):
    """A tiled kernel that FFTs ``rows`` lines of length ``n`` (the last axis) per block, in place.

    Tile shapes are compile-time constants, so there is one kernel per (n, rows); they are
    cached here and in Warp's kernel cache. ``inverse`` non-zero gives the unnormalised inverse.
    """

    @wp.kernel(module="unique", enable_backward=False)
    def fft_lines_kernel(buf: wp.array2d(dtype=wp.vec2f), inverse: int):
        b = wp.tid()
        t = wp.tile_load(buf, shape=(rows, n), offset=(b * rows, 0))
        if inverse != 0:
            wp.tile_ifft(t)
        else:
            wp.tile_fft(t)
        wp.tile_store(buf, t, offset=(b * rows, 0))

    return fft_lines_kernel


@wp.func
def same(x: wp.vec2f) -> wp.vec2f:
    return x


@functools.cache
def fft_columns(n: int, cols: int):
    """A tiled kernel that FFTs, in place, ``cols`` columns of length ``n`` per block.

    The buffer is viewed 2-D, (groups * n, width): block (g, c) transforms columns
    c * cols .. c * cols + cols - 1 of rows g * n .. g * n + n - 1. Rows are loaded whole
    (neighbouring addresses), turned in shared memory so the transform axis is last, and turned
    back before the store, so the y and z transforms of a window need no pass that rotates
    the axes of the whole buffer in global memory. Columns past ``width`` read as zero and
    are not stored.
    """

    @wp.kernel(module="unique", enable_backward=False)
    def fft_columns_kernel(buf: wp.array2d(dtype=wp.vec2f), inverse: int):
        g, c = wp.tid()
        t = wp.tile_load(buf, shape=(n, cols), offset=(g * n, c * cols), storage="shared")
        turned = wp.tile_transpose(t)  # aliases t
        r = wp.tile_map(same, turned)  # a register copy: the tile FFT works on registers
        if inverse != 0:
            wp.tile_ifft(r)
        else:
            wp.tile_fft(r)
        wp.tile_assign(turned, r)
        wp.tile_store(buf, t, offset=(g * n, c * cols))

    return fft_columns_kernel


@functools.cache
def dft_columns(n: int, cols: int):
    """:func:`fft_columns` for short columns: a direct DFT from shared memory.

    Warp's tile FFT runs a transform of length n on at most n / 2 threads, which leaves a GPU's
    blocks nearly empty for the short depth axis (8 threads at n = 16). Here every thread of
    the block computes outputs from the loaded tile, n complex multiply-adds each (cheap next
    to the memory traffic for n <= 32). ``twiddle[m] = exp(-2 pi i m / n)``; the inverse uses
    the conjugates. The whole tile is loaded (and the block synchronised) before any output is
    written, so the transform is in place.
    """

    @wp.kernel(module="unique", enable_backward=False)
    def dft_columns_kernel(buf: wp.array2d(dtype=wp.vec2f), twiddle: wp.array(dtype=wp.vec2f), inverse: int):
        g, c, lane = wp.tid()
        t = wp.tile_load(buf, shape=(n, cols), offset=(g * n, c * cols), storage="shared")
        sign = float(1.0)  # noqa: UP018 - a dynamic Warp variable
        if inverse != 0:
            sign = -1.0
        e = lane
        while e < n * cols:
            k = e // cols
            col = e - k * cols
            acc = wp.vec2f(0.0, 0.0)
            for m in range(n):
                tw = twiddle[(k * m) % n]
                acc += cmul(t[m, col], wp.vec2f(tw[0], sign * tw[1]))
            x = c * cols + col
            if x < buf.shape[1]:
                buf[g * n + k, x] = acc
            e += wp.block_dim()

    return dft_columns_kernel


# --- direct correlation around the predictor (deformation passes) ---------------------------
#
# After deformation a window's residual displacement is small, so its correlation is needed only
# at lags within +-r voxels. Windows of one pass overlap (at 75% every voxel lies in 64 of
# them), so the products A(x) B(x + d) are summed once per block of voxels (a block divides
# both the window and the step) and a window's sum is the sum of its blocks. Each lag column
# holds (sum a b_d, sum b_d), b_d being B shifted by the lag; two more columns hold
# (sum a, sum a^2) and (sum b^2, sum b) of the unshifted block for the window's statistics.


@wp.func
def floor_half(n: int) -> int:
    """floor(n // 2) for either sign of n."""
    if n >= 0:
        return n // 2
    return -((1 - n) // 2)


@functools.cache
def block_lag_sums(block: tuple[int, int, int], radius: tuple[int, int, int]):
    """A tiled kernel: the lag sums of every block of voxels (a block of threads per block).

    ``block`` and ``radius`` are (x, y, z). The lag d is split between the volumes, A moved
    back by floor(d / 2) and B forward by the rest (sum over x in the block of
    A(x - floor(d/2)) B(x + ceil(d/2))), so that a window's edge cuts every particle image the
    same way at every lag: summed over the window, each particle pair then peaks at its own
    displacement whether or not it is cut (correlating a fixed window of A with B would pull
    each cut particle's peak inwards). Both blocks, grown by ceil(r / 2) on every side, are
    loaded into shared memory once. A thread then sums the two x lags 2k and 2k + 1 of one
    (y, z) lag, which read the same A (moved back by k) and neighbouring B samples, so that
    along a row each A and each B sample is read once for both. One more thread sums
    (sum a^2, sum b^2) at lag 0. The volumes are padded by at least ceil(r / 2) on every
    side, so that no load leaves them.
    """
    bx, by, bz = block
    rx, ry, rz = radius
    gx, gy, gz = (rx + 1) // 2, (ry + 1) // 2, (rz + 1) // 2  # margin of the grown blocks
    # with an even x radius the last pair's second lag (rx + 1, not stored) reads one more column
    hx, hy, hz = bx + 2 * gx + (1 - rx % 2), by + 2 * gy, bz + 2 * gz
    nlx, nly, nlz = 2 * rx + 1, 2 * ry + 1, 2 * rz + 1
    n_lags = nlx * nly * nlz
    k_lo = -((rx + 1) // 2)  # floor(-rx / 2): the x-lag pairs k_lo .. rx // 2
    ngx = rx // 2 - k_lo + 1
    n_tasks = lag_tasks(radius)
    n_rows = by * bz

    @wp.kernel(module="unique", enable_backward=False)
    def block_lag_sums_kernel(vol_a: wp.array3d(dtype=wp.float32), vol_b: wp.array3d(dtype=wp.float32),
                              origin: wp.vec3i, nblocks: wp.vec3i, out: wp.array2d(dtype=wp.vec3f)):
        blk, lane = wp.tid()
        ix = blk % nblocks[0]
        iy = (blk // nblocks[0]) % nblocks[1]
        iz = blk // (nblocks[0] * nblocks[1])
        x0 = origin[0] + ix * bx - gx
        y0 = origin[1] + iy * by - gy
        z0 = origin[2] + iz * bz - gz
        ta = wp.tile_load(vol_a, shape=(hz, hy, hx), offset=(z0, y0, x0), storage="shared")
        tb = wp.tile_load(vol_b, shape=(hz, hy, hx), offset=(z0, y0, x0), storage="shared")
        e = lane
        while e < n_tasks:
            if e == n_tasks - 1:
                # statistics of the unshifted block
                qa = float(0.0)  # noqa: UP018 - dynamic Warp variables, accumulated below
                qb = float(0.0)  # noqa: UP018
                for row in range(n_rows):
                    y = row % by + gy
                    z = row // by + gz
                    for x in range(bx):
                        a = ta[z, y, x + gx]
                        b = tb[z, y, x + gx]
                        qa += a * a
                        qb += b * b
                out[blk, n_lags] = wp.vec3f(qa, qb, 0.0)
            else:
                k = e % ngx + k_lo  # x lags 2k and 2k + 1
                ly = (e // ngx) % nly - ry
                lz = e // (ngx * nly) - rz
                ay = gy - floor_half(ly)  # A's block in its tile (y, z); x: gx - k
                az = gz - floor_half(lz)
                byo = ay + ly
                bzo = az + lz
                sab0 = float(0.0)  # noqa: UP018 - dynamic Warp variables, accumulated below
                sb0 = float(0.0)  # noqa: UP018
                sab1 = float(0.0)  # noqa: UP018
                sb1 = float(0.0)  # noqa: UP018
                sa = float(0.0)  # noqa: UP018
                for row in range(n_rows):
                    y = row % by
                    z = row // by
                    b_here = tb[z + bzo, y + byo, gx + k]  # B at x + k for x = 0
                    for x in range(bx):
                        a = ta[z + az, y + ay, x + gx - k]
                        b_next = tb[z + bzo, y + byo, x + gx + k + 1]
                        sab0 += a * b_here
                        sb0 += b_here
                        sab1 += a * b_next
                        sb1 += b_next
                        sa += a
                        b_here = b_next
                base = ((lz + rz) * nly + ly + ry) * nlx + rx
                if 2 * k >= -rx:
                    out[blk, base + 2 * k] = wp.vec3f(sab0, sb0, sa)
                if 2 * k + 1 <= rx:
                    out[blk, base + 2 * k + 1] = wp.vec3f(sab1, sb1, sa)
            e += wp.block_dim()

    return block_lag_sums_kernel


def lag_tasks(radius: tuple[int, int, int]) -> int:
    """Threads' tasks of :func:`block_lag_sums` per block of voxels: the x-lag pairs
    floor(-rx / 2) .. floor(rx / 2) by the y and z lags, plus the statistics."""
    rx, ry, rz = radius
    return (rx // 2 + (rx + 1) // 2 + 1) * (2 * ry + 1) * (2 * rz + 1) + 1


@wp.kernel
def window_sum_axis(src: wp.array4d(dtype=wp.vec3f), axis: int, m: int, stride: int,
                    dst: wp.array4d(dtype=wp.vec3f)):
    """Sums of ``m`` consecutive entries along ``axis`` (0, 1, 2 = z, y, x) starting every ``stride``.

    Applied along x, y and z in turn, it turns block lag sums (blocks z, y, x, column) into
    window lag sums (windows z, y, x, column).
    """
    i, j, k, c = wp.tid()
    acc = wp.vec3f(0.0, 0.0, 0.0)
    for t in range(m):
        if axis == 0:
            acc += src[i * stride + t, j, k, c]
        elif axis == 1:
            acc += src[i, j * stride + t, k, c]
        else:
            acc += src[i, j, k * stride + t, c]
    dst[i, j, k, c] = acc


@wp.func
def lag_value(sums: wp.array2d(dtype=wp.vec3f), w: int, lag: int, n_voxels: float, scale: float) -> float:
    """Correlation coefficient of a window at a lag, from (sum a b, sum b, sum a) over the lag's windows.

    sum (a - mean a)(b - mean b) = sum a b - sum a sum b / n, exactly; the scale is that of
    lag 0 (as the FFT path's).
    """
    s = sums[w, lag]
    return (s[0] - s[1] * s[2] / n_voxels) * scale


@wp.func
def lag_index(i: int, j: int, k: int, nl: wp.vec3i) -> int:
    return (k * nl[1] + j) * nl[0] + i


@wp.func
def parity_fit(sums: wp.array2d(dtype=wp.vec3f), w: int, p: int, n: int, lag_lo: int, lag_hi: int, best: float,
               n_voxels: float, scale: float) -> wp.vec3:
    """(offset in units of 2 lags, 1 if the centroid fallback was used, 1 if fitted) of a peak at
    lag index ``p`` of ``n`` along one axis, from the lags two below and two above (``lag_lo``,
    ``lag_hi``); not fitted (0) within two lags of the box's face."""
    if p < 2 or p > n - 3:
        return wp.vec3(0.0, 0.0, 0.0)
    f = subvoxel(lag_value(sums, w, lag_lo, n_voxels, scale), best, lag_value(sums, w, lag_hi, n_voxels, scale))
    return wp.vec3(f[0], f[1], 1.0)


@wp.kernel
def local_peak(sums: wp.array2d(dtype=wp.vec3f), first: int, nl: wp.vec3i, n_voxels: float, exclusion: int,
               displacement: wp.array(dtype=wp.vec3), height: wp.array(dtype=float), ratio: wp.array(dtype=float),
               fallback: wp.array(dtype=int), valid: wp.array(dtype=int)):
    """:func:`peak_fit` for windows correlated at lags within the search box (``nl`` lags per axis).

    A peak within two lags of the box's face cannot be fitted through lags of its parity and
    may not be the correlation's peak (the displacement may lie beyond the box), so the vector
    is invalid and will be replaced.
    """
    w = wp.tid()
    g = first + w
    n_lags = nl[0] * nl[1] * nl[2]
    s0 = sums[w, n_lags // 2]  # lag 0: (sum a b, sum b, sum a)
    sq = sums[w, n_lags]  # (sum a^2, sum b^2, 0)
    va = sq[0] - s0[2] * s0[2] / n_voxels
    vb = sq[1] - s0[1] * s0[1] / n_voxels
    sc = float(0.0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    if va > 1.0e-6 * sq[0] and vb > 1.0e-6 * sq[1] and va > 0.0 and vb > 0.0:
        sc = 1.0 / wp.sqrt(va * vb)
    best = float(-1.0e30)  # noqa: UP018
    bi = int(0)  # noqa: UP018
    for lag in range(n_lags):
        v = lag_value(sums, w, lag, n_voxels, sc)
        if v > best:
            best = v
            bi = lag
    pi = bi % nl[0]
    pj = (bi // nl[0]) % nl[1]
    pk = bi // (nl[0] * nl[1])
    second = float(-1.0e30)  # noqa: UP018
    for lag in range(n_lags):
        i = lag % nl[0]
        j = (lag // nl[0]) % nl[1]
        k = lag // (nl[0] * nl[1])
        if wp.max(wp.max(wp.abs(i - pi), wp.abs(j - pj)), wp.abs(k - pk)) > exclusion:
            second = wp.max(second, lag_value(sums, w, lag, n_voxels, sc))
    # lags of one parity share their windows (see block_lag_sums): fit through p - 2, p, p + 2
    fx = parity_fit(sums, w, pi, nl[0], lag_index(pi - 2, pj, pk, nl), lag_index(pi + 2, pj, pk, nl), best,
                    n_voxels, sc)
    fy = parity_fit(sums, w, pj, nl[1], lag_index(pi, pj - 2, pk, nl), lag_index(pi, pj + 2, pk, nl), best,
                    n_voxels, sc)
    fz = parity_fit(sums, w, pk, nl[2], lag_index(pi, pj, pk - 2, nl), lag_index(pi, pj, pk + 2, nl), best,
                    n_voxels, sc)
    displacement[g] = wp.vec3(float(pi - nl[0] // 2) + 2.0 * fx[0], float(pj - nl[1] // 2) + 2.0 * fy[0],
                              float(pk - nl[2] // 2) + 2.0 * fz[0])
    height[g] = best
    r = float(0.0)  # noqa: UP018
    if second > 0.0:
        r = best / second
    elif best > 0.0:
        r = 1.0e6  # no second positive peak in the box
    ratio[g] = r
    fallback[g] = int(fx[1] + fy[1] + fz[1] > 0.0)
    ok = int(0)  # noqa: UP018 - a dynamic Warp variable, mutated below
    if fx[2] > 0.0 and fy[2] > 0.0 and fz[2] > 0.0 and sc > 0.0 and best > 0.0:
        ok = 1
    valid[g] = ok


@wp.kernel
def advect_volume(
    vol: wp.array3d(dtype=wp.float32),
    pred: wp.array3d(dtype=wp.vec3),
    pred_origin: wp.vec3,
    pred_step: wp.vec3,
    z0: int,
    out: wp.array3d(dtype=wp.float32),
):
    """``vol`` carried along the predictor d: out(x) = vol(x - d(x)), trilinear, zero outside.

    What was at x - d(x) in one frame is at x in the next (d evaluated at the arrival point,
    which a smooth predictor allows). The launch covers planes z0 + z of ``out``.
    """
    z, y, x = wp.tid()
    z += z0
    p = wp.vec3(float(x), float(y), float(z))
    out[z, y, x] = sample(vol, p - predictor_at(pred, pred_origin, pred_step, p))
