"""Line-of-sight weights of pinhole (Tomo-PIV) cameras and MLOS elimination, on the device.

A voxel's light reaches a pinhole camera at the image of its centre (``pinhole_project``,
distortion included) and spreads over the pixels there as a Gaussian footprint integrated over
each pixel (``pixel_share``): a smooth stand-in for the overlap of the voxel's projected disc
with the pixels, whose width follows the voxel's projected size. The kernels run one thread per
voxel; their outputs are fixed-capacity slots of ``cap`` entries per voxel (every camera's
window), compacted into CSR by :mod:`lfcore.pinhole_projector`.
"""

from __future__ import annotations

import warp as wp

from lfcore._kernels.pinhole import PinholeParams, pinhole_project, pixel_share
from lfcore._kernels.weights import Grid, voxel_centre
from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.struct
class PinholeView:
    """One pinhole camera looking at the grid."""

    cam: PinholeParams
    pix_offset: int  # first global pixel index of this camera
    sigma_px: float  # the footprint's Gaussian sigma, pixels
    reach_px: float  # the footprint covers the pixels within this of the voxel's image
    grow: int  # MLOS: pixels around the voxel's image that may be the lit one (calibration error)


@wp.kernel
def pinhole_los(
    grid: Grid,
    views: wp.array(dtype=PinholeView),
    n_views: int,
    voxels: wp.array(dtype=wp.int32),
    cap: int,
    min_weight: float,
    counts: wp.array(dtype=wp.int32),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
):
    """Each voxel's weights in every camera, into its ``cap`` slots from ``t * cap``.

    The weights of a voxel are divided by their sum over all cameras (as the light-field
    weights are), entries below ``min_weight`` of that dropped; ``counts[t]`` is how many were
    written (those first, in camera order, row-major within a camera's window).
    """
    t = wp.tid()
    p = voxel_centre(grid, voxels[t])
    base = t * cap
    k = int(0)
    total = float(0.0)
    for c in range(n_views):
        view = views[c]
        cam = view.cam
        q = pinhole_project(cam, p)
        if q[2] > 0.0:
            u = q[0]
            v = q[1]
            r = view.reach_px
            if u > -r and v > -r and u < float(cam.ncols) + r and v < float(cam.nrows) + r:
                scale = 1.0 / (view.sigma_px * 1.4142135623730951)
                c0 = int(wp.floor(u - r))
                c1 = int(wp.floor(u + r))
                r0 = int(wp.floor(v - r))
                r1 = int(wp.floor(v + r))
                for row in range(r0, r1 + 1):
                    if row >= 0 and row < cam.nrows:
                        fy = pixel_share(float(row), v, scale)
                        for col in range(c0, c1 + 1):
                            if col >= 0 and col < cam.ncols and k < cap:
                                share = fy * pixel_share(float(col), u, scale)
                                if share > 0.0:
                                    pix[base + k] = view.pix_offset + row * cam.ncols + col
                                    w[base + k] = share
                                    total += share
                                    k += 1
    # normalise, then drop the faint entries (kept ones stay first)
    kept = int(0)
    if total > 0.0:
        for i in range(k):
            s = w[base + i] / total
            if s >= min_weight:
                pix[base + kept] = pix[base + i]
                w[base + kept] = s
                kept += 1
    counts[t] = kept


@wp.kernel
def gather_slots(
    counts: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int64),
    cap: int,
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    out_pix: wp.array(dtype=wp.int32),
    out_w: wp.array(dtype=float),
):
    """Copy voxel t's ``counts[t]`` slot entries to ``offsets[t]`` of the CSR arrays."""
    t = wp.tid()
    src = t * cap
    dst = offsets[t]
    for i in range(counts[t]):
        out_pix[dst + wp.int64(i)] = pix[src + i]
        out_w[dst + wp.int64(i)] = w[src + i]


@wp.kernel
def mlos_eliminate(
    grid: Grid,
    views: wp.array(dtype=PinholeView),
    n_views: int,
    lit: wp.array(dtype=wp.uint8),
    first: int,
    mask: wp.array(dtype=wp.int32),
):
    """MLOS (Atkinson and Soria 2009): voxel v is kept (``mask[v] = 1``) only if the pixel of
    its image is lit in every camera (or one within ``grow`` pixels of it); a voxel imaged off
    any camera's sensor is dropped (the volume must be seen by every camera). Thread t is voxel
    ``first + t``, its flag ``mask[t]``."""
    t = wp.tid()
    p = voxel_centre(grid, first + t)
    keep = int(1)
    for c in range(n_views):
        if keep == 1:
            view = views[c]
            cam = view.cam
            q = pinhole_project(cam, p)
            seen = int(0)
            if q[2] > 0.0 and q[0] >= 0.0 and q[1] >= 0.0 and q[0] < float(cam.ncols) and q[1] < float(cam.nrows):
                col = int(wp.floor(q[0]))
                row = int(wp.floor(q[1]))
                g = view.grow
                for dr in range(-g, g + 1):
                    for dc in range(-g, g + 1):
                        rr = row + dr
                        cc = col + dc
                        if rr >= 0 and rr < cam.nrows and cc >= 0 and cc < cam.ncols:
                            if lit[view.pix_offset + rr * cam.ncols + cc] != wp.uint8(0):
                                seen = 1
            if seen == 0:
                keep = 0
    mask[t] = keep
