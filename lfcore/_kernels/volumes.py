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


@wp.kernel
def convolve_axis(
    src: wp.array3d(dtype=float),
    taps: wp.array(dtype=float),
    radius: int,
    axis: int,
    dst: wp.array3d(dtype=float),
):
    """dst = src convolved along ``axis`` (0 z, 1 y, 2 x) with symmetric ``taps`` (2 radius + 1);
    zero outside the volume (SciPy's mode="constant")."""
    z, y, x = wp.tid()
    n = src.shape[axis]
    pos = z
    if axis == 1:
        pos = y
    elif axis == 2:
        pos = x
    acc = float(0.0)
    for k in range(-radius, radius + 1):
        q = pos + k
        if q >= 0 and q < n:
            v = float(0.0)
            if axis == 0:
                v = src[q, y, x]
            elif axis == 1:
                v = src[z, q, x]
            else:
                v = src[z, y, q]
            acc += taps[k + radius] * v
    dst[z, y, x] = acc


@wp.kernel
def max_along(
    vol: wp.array3d(dtype=float),
    axis: int,
    out: wp.array2d(dtype=float),
):
    """Maximum-intensity projection along ``axis``; ``out`` is the volume's shape without it."""
    a, b = wp.tid()
    n = vol.shape[axis]
    m = float(-3.0e38)
    for k in range(n):
        v = float(0.0)
        if axis == 0:
            v = vol[k, a, b]
        elif axis == 1:
            v = vol[a, k, b]
        else:
            v = vol[a, b, k]
        m = wp.max(m, v)
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
    if axis == 0:
        out[a, b] = vol[index, a, b]
    elif axis == 1:
        out[a, b] = vol[a, index, b]
    else:
        out[a, b] = vol[a, b, index]
