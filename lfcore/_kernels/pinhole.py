"""The pinhole camera model on the device, and Gaussian particle images of Tomo-PIV cameras.

The Warp twin of :mod:`lfcore.pinhole` (same conventions, world points in mm): the struct
:class:`PinholeParams` of one camera (:func:`pinhole_params`), ``pinhole_project`` (a world
point to its continuous (column, row) pixel position and its depth in front of the lens) and
``pinhole_ray`` (a pixel position to its world line of sight, through the lens centre
``cam.centre``), for kernels that render images or compute line-of-sight weights.
"""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init
from lfcore.pinhole import UNDISTORT_STEPS
from lfcore.rig import PinholeCamera

_init()
wp.set_module_options({"enable_backward": False})


@wp.struct
class PinholeParams:
    to_cam: wp.mat33  # world-to-camera rotation R^T
    focus: wp.vec3  # world focus point, mm (the camera frame's origin)
    centre: wp.vec3  # world lens centre, mm (every line of sight starts there)
    rot: wp.mat33  # camera-to-world rotation R
    so: float  # lens to focal plane, mm
    f_px: float  # si / pixel pitch
    cx: float  # principal point, continuous pixel coordinates
    cy: float
    k1: float  # OpenCV's radial and tangential distortion
    k2: float
    p1: float
    p2: float
    ncols: int
    nrows: int


def pinhole_params(camera: PinholeCamera) -> PinholeParams:
    """The kernel-side description of a pinhole camera."""
    p = PinholeParams()
    r = camera.rotation
    p.to_cam = wp.mat33(*r.T.ravel().tolist())
    p.rot = wp.mat33(*r.ravel().tolist())
    p.focus = wp.vec3(*camera.focus_mm)
    p.centre = wp.vec3(*camera.lens_centre_mm.tolist())
    p.so = camera.object_distance_mm
    p.f_px = camera.focal_length_px
    p.cx, p.cy = camera.principal_point
    p.k1, p.k2, p.p1, p.p2 = camera.distortion
    p.ncols, p.nrows = camera.sensor_px
    return p


@wp.func
def distort_xy(cam: PinholeParams, x: float, y: float) -> wp.vec2:
    """OpenCV's distortion of normalised coordinates (:func:`lfcore.pinhole.distort`)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (cam.k1 + cam.k2 * r2)
    return wp.vec2(x * radial + 2.0 * cam.p1 * x * y + cam.p2 * (r2 + 2.0 * x * x),
                   y * radial + cam.p1 * (r2 + 2.0 * y * y) + 2.0 * cam.p2 * x * y)


@wp.func
def pinhole_project(cam: PinholeParams, p: wp.vec3) -> wp.vec3:
    """(column, row, depth) of world point ``p``: its continuous pixel position and its distance
    in front of the lens, mm (at or below 0 the point is behind the lens and the position is
    meaningless)."""
    e = cam.to_cam * (p - cam.focus)
    depth = cam.so - e[2]
    inv = 1.0 / wp.max(depth, 1.0e-9)
    xy = distort_xy(cam, e[0] * inv, -e[1] * inv)
    return wp.vec3(cam.cx + cam.f_px * xy[0], cam.cy + cam.f_px * xy[1], depth)


@wp.func
def pinhole_ray(cam: PinholeParams, col: float, row: float) -> wp.vec3:
    """Unit world direction of the line of sight of pixel position (``col``, ``row``), from
    ``cam.centre`` into the scene (:func:`lfcore.pinhole.line_of_sight`)."""
    xd = (col - cam.cx) / cam.f_px
    yd = (row - cam.cy) / cam.f_px
    x = xd
    y = yd
    for _k in range(UNDISTORT_STEPS):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (cam.k1 + cam.k2 * r2)
        dr = 2.0 * (cam.k1 + 2.0 * cam.k2 * r2)
        f = distort_xy(cam, x, y) - wp.vec2(xd, yd)
        a = radial + x * x * dr + 2.0 * cam.p1 * y + 6.0 * cam.p2 * x
        b = x * y * dr + 2.0 * cam.p1 * x + 2.0 * cam.p2 * y
        d = radial + y * y * dr + 6.0 * cam.p1 * y + 2.0 * cam.p2 * x
        det = a * d - b * b
        x = x - (d * f[0] - b * f[1]) / det
        y = y - (-b * f[0] + a * f[1]) / det
    return wp.normalize(cam.rot * wp.vec3(x, -y, -1.0))


@wp.func
def pixel_share(lo: float, centre: float, scale: float) -> float:
    """Fraction of a unit Gaussian's light (centre, sigma = 1 / (scale sqrt 2)) in [lo, lo + 1)."""
    return 0.5 * (wp.erf((lo + 1.0 - centre) * scale) - wp.erf((lo - centre) * scale))


@wp.kernel
def splat_particles(
    cam: PinholeParams,
    points: wp.array(dtype=wp.vec3),
    quanta: wp.array(dtype=wp.float64),
    sigma_px: float,
    half: int,
    image: wp.array2d(dtype=wp.int64),
):
    """One thread per particle (world points, mm): its Gaussian image, integrated over each
    pixel of a (2 half + 1)^2 window, added in fixed-point quanta (``quanta``: the particle's
    whole signal)."""
    i = wp.tid()
    q = pinhole_project(cam, points[i])
    if q[2] <= 0.0:
        return
    u = q[0]
    v = q[1]
    # bounds in floating point: a point far off the axis lands beyond any int
    if u < -float(half) or v < -float(half) or u > float(cam.ncols + half) or v > float(cam.nrows + half):
        return
    scale = 1.0 / (sigma_px * 1.4142135623730951)
    c0 = int(wp.floor(u)) - half
    r0 = int(wp.floor(v)) - half
    total = quanta[i]
    for dr in range(2 * half + 1):
        r = r0 + dr
        if r >= 0 and r < cam.nrows:
            fy = pixel_share(float(r), v, scale)
            for dc in range(2 * half + 1):
                c = c0 + dc
                if c >= 0 and c < cam.ncols:
                    share = wp.float64(fy * pixel_share(float(c), u, scale))
                    wp.atomic_add(image, r, c, wp.int64(wp.round(total * share)))
