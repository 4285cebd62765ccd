"""Dense-volume operations on the device: separable Gaussian smoothing, projections, slices.

Volumes are (z, y, x) float32 arrays. They let a reconstructed volume go from the
reconstruction to the correlation, and to the pictures a person looks at, without leaving the
device.
"""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.func
def along(vol: wp.array3d(dtype=float), axis: int, k: int, a: int, b: int):
    """The voxel at index ``k`` along ``axis`` (0 z, 1 y, 2 x), ``a`` and ``b`` the other two
    indices in array order."""
    if axis == 0:
        return vol[k, a, b]
    if axis == 1:
        return vol[a, k, b]
    return vol[a, b, k]


@wp.kernel
def convolve_axis(
    src: wp.array3d(dtype=float),
    taps: wp.array(dtype=float),
    radius: int,
    axis: int,
    z0: int,
    dst: wp.array3d(dtype=float),
):
    """dst = src convolved along ``axis`` (0 z, 1 y, 2 x) with symmetric ``taps`` (2 radius + 1);
    zero outside the volume (SciPy's mode="constant"). The launch covers planes ``z0 + z``."""
    z, y, x = wp.tid()
    z += z0
    n = src.shape[axis]
    pos, a, b = z, y, x
    if axis == 1:
        pos, a, b = y, z, x
    elif axis == 2:
        pos, a, b = x, z, y
    acc = float(0.0)
    for k in range(-radius, radius + 1):
        q = pos + k
        if q >= 0 and q < n:
            acc += taps[k + radius] * along(src, axis, q, a, b)
    dst[z, y, x] = acc


@wp.kernel
def max_along(
    vol: wp.array3d(dtype=float),
    axis: int,
    out: wp.array2d(dtype=float),
):
    """Maximum-intensity projection along ``axis``; ``out`` is the volume's shape without it."""
    a, b = wp.tid()
    m = float(-3.0e38)
    for k in range(vol.shape[axis]):
        m = wp.max(m, along(vol, axis, k, a, b))
    out[a, b] = m


@wp.kernel
def take_slice(
    vol: wp.array3d(dtype=float),
    axis: int,
    index: int,
    out: wp.array2d(dtype=float),
):
    """The plane ``index`` normal to ``axis``; ``out`` is the volume's shape without it."""
    a, b = wp.tid()
    out[a, b] = along(vol, axis, index, a, b)
