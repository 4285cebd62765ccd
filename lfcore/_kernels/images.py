"""Raw-image preprocessing on the device: background subtraction, the lit mask, its growth.

The same rules as :func:`lfcore.reconstruct.preprocess`, so that a live pipeline can upload
raw 16-bit frames (half the bytes of float signal) and never bring pixels back to the host.
Images are flat: camera ``k``'s pixels are ``offset .. offset + rows * cols - 1`` of the
concatenated sensor, row-major.
"""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def subtract_threshold(
    raw: wp.array(dtype=wp.uint16),
    offset: int,
    level: float,
    threshold: float,
    signal: wp.array(dtype=float),
    lit: wp.array(dtype=wp.uint8),
):
    """signal = raw - level where that exceeds ``threshold`` (else 0); lit = 1 there."""
    i = offset + wp.tid()
    s = float(raw[i]) - level
    if s > threshold:
        signal[i] = s
        lit[i] = wp.uint8(1)
    else:
        signal[i] = 0.0
        lit[i] = wp.uint8(0)


@wp.kernel
def subtract_threshold_flat(
    raw: wp.array(dtype=wp.uint16),
    offset: int,
    dark: wp.array(dtype=float),
    inv_gain: wp.array(dtype=float),
    level: float,
    threshold: float,
    signal: wp.array(dtype=float),
    lit: wp.array(dtype=wp.uint8),
):
    """:func:`subtract_threshold` of the flat-field-corrected frame (raw - dark) / gain; a masked
    pixel (``inv_gain`` 0) gets the signal -1 (lfcore.reconstruct.MASKED) and counts as lit."""
    i = offset + wp.tid()
    g = inv_gain[i]
    if g == 0.0:
        signal[i] = -1.0
        lit[i] = wp.uint8(1)
        return
    s = (float(raw[i]) - dark[i]) * g - level
    if s > threshold:
        signal[i] = s
        lit[i] = wp.uint8(1)
    else:
        signal[i] = 0.0
        lit[i] = wp.uint8(0)


@wp.kernel
def dilate3x3(
    src: wp.array(dtype=wp.uint8),
    offset: int,
    rows: int,
    cols: int,
    r0: int,
    dst: wp.array(dtype=wp.uint8),
):
    """dst = binary dilation of ``src`` by a 3 x 3 square; pixels outside the image count as dark.
    The launch covers rows ``r0 + r``."""
    r, c = wp.tid()
    r += r0
    hit = wp.uint8(0)
    for dr in range(-1, 2):
        rr = r + dr
        if rr >= 0 and rr < rows:
            for dc in range(-1, 2):
                cc = c + dc
                if cc >= 0 and cc < cols:
                    if src[offset + rr * cols + cc] != wp.uint8(0):
                        hit = wp.uint8(1)
    dst[offset + r * cols + c] = hit
