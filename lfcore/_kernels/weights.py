"""Voxel-to-pixel weights of a plenoptic camera, and zero-voxel elimination.

Camera-frame thin-lens optics as in :mod:`lfcore._kernels.render`. For a voxel centred at P
(camera frame, depth P.z toward the lens) the ray through aperture point A meets the MLA at

    q = a A + g,   a = 1 - si / si',  g = -P_xy si / (so - P.z),

where si' is the image distance of P, and a ray entering the lenslet centred at c with MLA
point q lands on the sensor at c + f_ml (q - A) / si.

Dense ray tracing (DRT) weights: the aperture is cut into square sub-apertures of side s_A.
Each sub-bundle's footprint on the MLA is a square of half-side
0.5 |a| s_A + (spread of the voxel's own extent); w1 is the fraction of the footprint inside
each lenslet cell (exact, square or hexagonal cells: :func:`cell_overlap`); the part that enters a
lenslet lands as a square spot at c + f_ml (centroid - A) / si of half-side
f_ml / si (0.5 |1 - a| s_A + spread), and w2 is the fraction of the spot on each pixel. A
voxel's weight on a pixel is the sub-aperture's share of the aperture times w1 times w2, so the
weights of a voxel sum to the fraction of its light that reaches the sensor.

Line-of-sight (LOS) weights, the conventional MART baseline: each pixel sees along the line
through its lenslet's conjugate point on the focal plane and its sub-aperture; the weight is the
overlap area of the pixel's line-of-sight cylinder and the voxel's sphere, cut in the voxel's
depth plane, normalised so that a voxel's weights sum to one.

The kernels run twice with the same code path: once to count a voxel's weights (``fill = 0``),
once to write them at the offsets the counts give (``fill = 1``). The line-of-sight kernel can
also apply its weights as it computes them (``fill = 2, 3``: a MART iteration without stored
weights, for volumes whose weights do not fit in memory).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from lfcore._kernels.mart import multiplied
from lfcore._kernels.optics import HEX_ROW, CameraParams, lenslet_centre
from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})

vec6 = wp.types.vector(length=6, dtype=wp.float32)


@wp.struct
class Grid:
    """A box's voxels, or one depth slab of them (planes z0 .. z0 + nz - 1): the flat index v of a
    voxel counts from the slab's first plane, so that a box of more than 2**31 voxels is numbered
    in int32 slab by slab, while its centre is the whole box's voxel's, to the bit."""

    origin: wp.vec3  # world centre of the BOX's voxel [0, 0, 0], mm
    step: wp.vec3  # voxel edges (dx, dy, dz), mm
    nx: int
    ny: int
    nz: int  # planes of this grid (the slab's)
    z0: int  # the box's plane of this grid's first (0: the whole box)


@wp.struct
class View:
    """One camera looking at the grid."""

    cam: CameraParams
    rot: wp.mat33  # world -> camera
    focus: wp.vec3  # world point the focal plane is centred on, mm
    half: wp.vec3  # half-extent of a voxel along the camera's x, y, z, mm
    pix_offset: int  # first global pixel index of this camera
    sub_first: int  # this camera's range in the sub-aperture table
    sub_count: int
    check_first: int  # this camera's range in the elimination's check order
    check_count: int
    sub_side: float  # side of a sub-aperture, mm
    n_edges: int  # lenslet cell: 4 (square) or 6 (hexagon)
    edge_nx: vec6  # outward normals of the cell's edges (camera frame)
    edge_ny: vec6
    cell_r: float  # circumradius of a cell, mm
    magnification: float
    los_radius: float  # LOS cylinder radius + voxel sphere radius (MART baseline), mm
    los_first: int  # this camera's range in the overlap table (see overlap_table)
    los_d0: float  # distance below which the smaller circle lies inside the larger, mm
    los_dinv: float  # OVERLAP_SAMPLES / (los_radius - los_d0), 1/mm


@wp.func
def voxel_centre(g: Grid, v: int) -> wp.vec3:
    plane = g.nx * g.ny
    z = v // plane
    r = v - z * plane
    y = r // g.nx
    x = r - y * g.nx
    return g.origin + wp.cw_mul(g.step, wp.vec3(float(x), float(y), float(z + g.z0)))


@wp.struct
class Overlap:
    area: float
    cx: float  # centroid
    cy: float
    wx: float  # extent of the overlap along x and y
    wy: float


@wp.struct
class Boundary:
    """Running sums over the boundary segments of a counter-clockwise region (Green's theorem)."""

    area2: float  # 2 x area
    mx6: float  # 6 x first moment in x
    my6: float
    lo: wp.vec2  # extent of the segments' ends
    hi: wp.vec2


@wp.func
def add_segment(b: Boundary, sx: float, sy: float, dx: float, dy: float, t0: float, t1: float) -> Boundary:
    """Add the segment (sx, sy) + t (dx, dy), t0 <= t <= t1, if it is not empty."""
    if t1 <= t0:
        return b
    p = wp.vec2(sx + t0 * dx, sy + t0 * dy)
    q = wp.vec2(sx + t1 * dx, sy + t1 * dy)
    cr = p[0] * q[1] - q[0] * p[1]
    b.area2 += cr
    b.mx6 += (p[0] + q[0]) * cr
    b.my6 += (p[1] + q[1]) * cr
    b.lo = wp.min(b.lo, wp.min(p, q))
    b.hi = wp.max(b.hi, wp.max(p, q))
    return b


@wp.struct
class EdgeSpans:
    """Where each edge of a view's lenslet cell begins and ends along its own direction (the edge's
    t0 .. t1 in :func:`cell_overlap`'s parametrisation): the same for every cell of the camera."""

    t0: vec6
    t1: vec6


@wp.func
def edge_spans(view: View) -> EdgeSpans:
    """The :class:`EdgeSpans` of ``view``'s cell: each edge clipped to the other edges."""
    h = 0.5 * view.cam.pitch
    out = EdgeSpans()
    for e in range(view.n_edges):
        nx = view.edge_nx[e]
        ny = view.edge_ny[e]
        dx = -ny  # counter-clockwise along the edge (outward normal on the right)
        dy = nx
        t0 = float(-1.0e30)
        t1 = float(1.0e30)
        for f in range(view.n_edges):
            den = view.edge_nx[f] * dx + view.edge_ny[f] * dy
            if f != e and wp.abs(den) > 1.0e-6:
                t = (h - h * (view.edge_nx[f] * nx + view.edge_ny[f] * ny)) / den
                if den > 0.0:
                    t1 = wp.min(t1, t)
                else:
                    t0 = wp.max(t0, t)
        out.t0[e] = t0
        out.t1[e] = t1
    return out


@wp.func
def cell_overlap(view: View, cx: float, cy: float, x0: float, x1: float, y0: float, y1: float) -> Overlap:
    """The part of rectangle [x0, x1] x [y0, y1] inside the lenslet cell centred at (cx, cy).

    Exact for the convex cell (square or hexagon: the half-planes n_e . p <= pitch / 2): the
    boundary of the intersection is the cell's edges clipped to the rectangle plus the
    rectangle's edges clipped to the cell, both run counter-clockwise, and its area, centroid
    and extent follow from those segments alone (Green's theorem). Everything stays in
    registers: no polygon is built, which on a GPU would live in slow local memory.
    """
    return spans_overlap(view, edge_spans(view), cx, cy, x0, x1, y0, y1)


@wp.func
def spans_overlap(view: View, spans: EdgeSpans, cx: float, cy: float, x0: float, x1: float, y0: float,
                  y1: float) -> Overlap:
    """:func:`cell_overlap` with the cell's :func:`edge_spans` computed once by the caller (a voxel's
    footprints meet hundreds of cells of the same camera: the clipping of the cell's edges to each
    other, a third of the work, is the same for all of them). The same arithmetic, the same result."""
    # Work relative to the cell centre so single precision keeps sub-micrometre detail.
    rx0 = x0 - cx
    rx1 = x1 - cx
    ry0 = y0 - cy
    ry1 = y1 - cy
    h = 0.5 * view.cam.pitch
    tol = 1.0e-6 * h
    bd = Boundary()
    bd.lo = wp.vec2(1.0e30, 1.0e30)
    bd.hi = wp.vec2(-1.0e30, -1.0e30)
    # the cell's edges, each clipped to the other edges (its own length) and to the rectangle
    for e in range(view.n_edges):
        nx = view.edge_nx[e]
        ny = view.edge_ny[e]
        dx = -ny  # counter-clockwise along the edge (outward normal on the right)
        dy = nx
        t0 = spans.t0[e]  # the edge clipped to the cell's other edges
        t1 = spans.t1[e]
        # the rectangle's slabs (Liang-Barsky)
        bx = h * nx
        by = h * ny
        if wp.abs(dx) > 1.0e-6:
            ta = (rx0 - bx) / dx
            tb = (rx1 - bx) / dx
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
        elif bx < rx0 - tol or bx > rx1 + tol:  # the same tolerance as the rectangle's edges below
            t1 = t0 - 1.0
        if wp.abs(dy) > 1.0e-6:
            ta = (ry0 - by) / dy
            tb = (ry1 - by) / dy
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
        elif by < ry0 - tol or by > ry1 + tol:
            t1 = t0 - 1.0
        bd = add_segment(bd, bx, by, dx, dy, t0, t1)
    # the rectangle's edges (bottom, right, top, left), each clipped to the cell (Cyrus-Beck)
    for k in range(4):
        sx = rx0
        sy = ry0
        ex = rx1
        ey = ry0
        if k == 1:
            sx = rx1
            ex = rx1
            ey = ry1
        elif k == 2:
            sx = rx1
            sy = ry1
            ex = rx0
            ey = ry1
        elif k == 3:
            sy = ry1
            ex = rx0
        ddx = ex - sx
        ddy = ey - sy
        t0 = float(0.0)
        t1 = float(1.0)
        for f in range(view.n_edges):
            nx = view.edge_nx[f]
            ny = view.edge_ny[f]
            num = h - (nx * sx + ny * sy)
            den = nx * ddx + ny * ddy
            if wp.abs(den) <= 1.0e-12 * (wp.abs(ddx) + wp.abs(ddy)):
                # parallel to this cell edge: wholly outside, or lying on it from inside, where
                # the cell's edge already counts it (counting it twice would double its share)
                outward = nx * ddy - ny * ddx  # the rectangle edge's outward normal . n_f
                if num < -tol or (wp.abs(num) <= tol and outward > 0.0):
                    t1 = -1.0
            elif den > 0.0:
                t1 = wp.min(t1, num / den)
            else:
                t0 = wp.max(t0, num / den)
        bd = add_segment(bd, sx, sy, ddx, ddy, t0, t1)
    out = Overlap()
    if bd.area2 > 1.0e-20:
        out.area = 0.5 * bd.area2
        out.cx = cx + bd.mx6 / (3.0 * bd.area2)
        out.cy = cy + bd.my6 / (3.0 * bd.area2)
        out.wx = bd.hi[0] - bd.lo[0]
        out.wy = bd.hi[1] - bd.lo[1]
    return out


@wp.func
def to_lattice(cam: CameraParams, x: float, y: float) -> wp.vec2:
    dx = x - cam.off_x
    dy = y - cam.off_y
    return wp.vec2(cam.cos_t * dx + cam.sin_t * dy, -cam.sin_t * dx + cam.cos_t * dy)


@wp.func
def from_lattice(cam: CameraParams, u: float, v: float) -> wp.vec2:
    return wp.vec2(cam.cos_t * u - cam.sin_t * v + cam.off_x, cam.sin_t * u + cam.cos_t * v + cam.off_y)


@wp.func
def lattice_box(cam: CameraParams, x0: float, x1: float, y0: float, y1: float, reach: float) -> wp.vec4:
    """Lattice-frame bounding box (umin, umax, vmin, vmax) of a camera-frame box, grown by reach."""
    a = to_lattice(cam, x0, y0)
    b = to_lattice(cam, x1, y0)
    c = to_lattice(cam, x1, y1)
    d = to_lattice(cam, x0, y1)
    umin = wp.min(wp.min(a[0], b[0]), wp.min(c[0], d[0])) - reach
    umax = wp.max(wp.max(a[0], b[0]), wp.max(c[0], d[0])) + reach
    vmin = wp.min(wp.min(a[1], b[1]), wp.min(c[1], d[1])) - reach
    vmax = wp.max(wp.max(a[1], b[1]), wp.max(c[1], d[1])) + reach
    return wp.vec4(umin, umax, vmin, vmax)


@wp.func
def row_step(cam: CameraParams) -> float:
    if cam.hex == 1:
        return cam.pitch * HEX_ROW
    return cam.pitch


@wp.func
def row_shift(cam: CameraParams, j: int) -> float:
    if cam.hex == 1 and (j % 2 + 2) % 2 == 1:
        return 0.5 * cam.pitch
    return 0.0


@wp.func
def pixel_overlap(lo: float, hi: float, k: int) -> float:
    """Length of [lo, hi] inside pixel [k, k + 1]."""
    return wp.max(0.0, wp.min(hi, float(k) + 1.0) - wp.max(lo, float(k)))


@wp.func
def view_point(view: View, pw: wp.vec3) -> wp.vec3:
    return view.rot * (pw - view.focus)


@wp.func
def corner_point(qx: float, qy: float, fx: float, fy: float, corner: int) -> wp.vec2:
    """The centre (corner 0) or a corner (1-4) of the footprint box q +- f on the MLA."""
    if corner == 0:
        return wp.vec2(qx, qy)
    return wp.vec2(qx + fx * float(2 * ((corner - 1) % 2) - 1), qy + fy * float(2 * ((corner - 1) // 2) - 1))


@wp.func
def landing_pixel(view: View, c: wp.vec2, ax: float, ay: float, pt: wp.vec2) -> int:
    """Global pixel where the ray from aperture point A through MLA point ``pt`` of the lenslet
    centred at ``c`` lands; -1 off the sensor."""
    cam = view.cam
    sx = c[0] + cam.f_ml * (pt[0] - ax) / cam.si
    sy = c[1] + cam.f_ml * (pt[1] - ay) / cam.si
    col = 0.5 * float(cam.ncols) - sx / cam.pixel
    row = 0.5 * float(cam.nrows) + sy / cam.pixel
    if col >= 0.0 and row >= 0.0 and col < float(cam.ncols) and row < float(cam.nrows):
        return view.pix_offset + int(row) * cam.ncols + int(col)
    return -1


@wp.func
def corner_pixel(view: View, ax: float, ay: float, qx: float, qy: float, fx: float, fy: float, corner: int) -> int:
    """Global pixel hit by the centre (corner 0) or a corner (1-4) of a sub-aperture's footprint.

    -1 if the point lands off the sensor.
    """
    pt = corner_point(qx, qy, fx, fy, corner)
    return landing_pixel(view, lenslet_centre(view.cam, pt[0], pt[1]), ax, ay, pt)


@wp.func
def check_footprint(view: View, a: float, gx: float, gy: float, inv: float, dq: float, p: wp.vec3, ax: float,
                    ay: float) -> wp.vec4:
    """Elimination's footprint of sub-aperture point A on the MLA: (qx, qy, fx, fy), centre q and
    half-sides f of a box that holds the sub-aperture's spot and the voxel's own extent."""
    cam = view.cam
    fx = 0.5 * wp.abs(a) * view.sub_side + cam.si * inv * view.half[0] + wp.abs(ax - p[0]) * dq
    fy = 0.5 * wp.abs(a) * view.sub_side + cam.si * inv * view.half[1] + wp.abs(ay - p[1]) * dq
    return wp.vec4(a * ax + gx, a * ay + gy, fx, fy)


@wp.func
def inside_sensor(view: View, ax: float, ay: float, qx: float, qy: float, fx: float, fy: float) -> bool:
    """True if the centre and corners of a footprint (see :func:`corner_pixel`) surely land on the sensor.

    A point p of the MLA lands at c + f_ml (p - A) / si with its lenslet centre c within a cell's
    circumradius of p, so over the footprint's box the landing point stays within a box that
    grows linearly with p; that box, with a hundredth of a pixel to spare, inside the sensor
    means every point is on it, without locating a single lenslet.
    """
    cam = view.cam
    k = cam.f_ml / cam.si
    margin = view.cell_r + 0.01 * cam.pixel
    half_w = 0.5 * float(cam.ncols) * cam.pixel
    half_h = 0.5 * float(cam.nrows) * cam.pixel
    x_lo = (qx - fx) * (1.0 + k) - k * ax - margin
    x_hi = (qx + fx) * (1.0 + k) - k * ax + margin
    y_lo = (qy - fy) * (1.0 + k) - k * ay - margin
    y_hi = (qy + fy) * (1.0 + k) - k * ay + margin
    return x_lo > -half_w and x_hi < half_w and y_lo > -half_h and y_hi < half_h


#: The most views elimination interleaves (:func:`eliminate`); a rig of more views checks them one after another.
MAX_INTERLEAVED = wp.constant(8)
ALL_CHECKS = wp.constant(1 << 30)
#: The most views whose counts a pass of :func:`eliminate_turns` carries to the next (8 bits each).
MAX_CARRIED = wp.constant(3)
vec_views = wp.types.vector(length=MAX_INTERLEAVED, dtype=wp.int32)


@wp.func
def view_checks(
    view: View,
    iv: int,
    n_views: int,
    v: int,
    pw: wp.vec3,
    sub_a: wp.array(dtype=wp.vec2),
    check_order: wp.array(dtype=wp.int32),
    lit: wp.array(dtype=wp.uint8),
    table: wp.array(dtype=wp.int32),
    n_table: int,
    lo: int,
    hi: int,
    dark_in: int,
    allowed: int,
):
    """Checks ``lo .. hi - 1`` of voxel v (centre ``pw``, world) in view ``iv``: wp.vec2i(seen, dark), the
    checks whose points all land on the sensor and those of them dark, dark counted on from ``dark_in``
    and stopped at the first check past ``allowed`` (the voxel is then dropped). seen = -1: the voxel
    lies where the view cannot image it (at or beyond the lens's front focal plane). See :func:`eliminate`."""
    cam = view.cam
    p = view_point(view, pw)
    sop = cam.so - p[2]
    if sop * cam.inv_f <= 1.0:
        return wp.vec2i(-1, dark_in)
    inv = 1.0 / sop
    a = 1.0 - cam.si * (cam.inv_f - inv)
    gx = -p[0] * cam.si * inv
    gy = -p[1] * cam.si * inv
    dq = cam.si * inv * inv * view.half[2]
    seen = int(0)
    dark = dark_in
    for mi in range(lo, hi):
        m = view.check_first + mi
        on = int(1)
        hit = int(0)
        if mi < n_table:
            row = ((v * n_views + iv) * n_table + mi) * 5
            if table[row] < 0:
                on = int(0)  # a point off the sensor: the table marks the whole check
            else:
                corner = int(0)
                while corner < 5 and hit == 0:
                    if lit[table[row + corner]] != wp.uint8(0):
                        hit = int(1)
                    corner += 1
        else:
            k = check_order[m]
            ax = sub_a[k][0]
            ay = sub_a[k][1]
            box = check_footprint(view, a, gx, gy, inv, dq, p, ax, ay)
            qx = box[0]
            qy = box[1]
            fx = box[2]
            fy = box[3]
            if inside_sensor(view, ax, ay, qx, qy, fx, fy):
                # Every point lands on the sensor, so the first lit one settles the check;
                # and a footprint well inside its centre's lenslet cell (inradius half a
                # pitch, square or hexagonal) needs that one lenslet only.
                c0 = lenslet_centre(cam, qx, qy)
                one_cell = wp.length(wp.vec2(qx - c0[0], qy - c0[1])) + wp.sqrt(fx * fx + fy * fy) < (
                    0.4999 * cam.pitch)
                corner = int(0)
                while corner < 5 and hit == 0:
                    pt = corner_point(qx, qy, fx, fy, corner)
                    c = c0
                    if corner > 0 and not one_cell:
                        c = lenslet_centre(cam, pt[0], pt[1])
                    if lit[landing_pixel(view, c, ax, ay, pt)] != wp.uint8(0):
                        hit = int(1)
                    corner += 1
            else:
                for corner in range(5):
                    q = corner_pixel(view, ax, ay, qx, qy, fx, fy, corner)
                    if q >= 0:
                        if lit[q] != wp.uint8(0):
                            hit = int(1)
                    else:
                        on = int(0)
        if on == 1:
            seen += 1
            if hit == 0:
                dark += 1
                if dark > allowed:
                    return wp.vec2i(seen, dark)
    return wp.vec2i(seen, dark)


@wp.func
def eliminated(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    check_order: wp.array(dtype=wp.int32),
    lit: wp.array(dtype=wp.uint8),
    min_seen: float,
    max_dark: float,
    table: wp.array(dtype=wp.int32),
    n_table: int,
    v: int,
    stage_checks: int,
    round_checks: int,
    lo0: int,
    carried: int,
):
    """wp.vec2i(keep, counts): 1 if voxel v is kept, 0 if not (:func:`eliminate_turns`' test of one voxel),
    and each view's seen and dark counts packed as :func:`eliminate_turns` carries them. ``lo0`` > 0: the
    checks before it were made already (the views taking turns), with the counts ``carried``."""
    pw = voxel_centre(grid, v)
    keep = int(1)
    step = round_checks
    if n_views > MAX_INTERLEAVED or step < 1:
        step = ALL_CHECKS  # one view after another
    seen = vec_views()
    dark = vec_views()
    lo = int(0)
    if lo0 > 0 and step < ALL_CHECKS and n_views <= MAX_CARRIED:
        lo = lo0
        for iv in range(n_views):
            seen[iv] = (carried >> (8 * iv)) & 15
            dark[iv] = (carried >> (8 * iv + 4)) & 15
    more = int(1)
    while keep == 1 and more == 1:
        more = int(0)
        for iv in range(n_views):
            view = views[iv]
            checks = wp.min(view.check_count, stage_checks)
            if lo < checks:
                allowed = int(max_dark * float(view.check_count))
                hi = wp.min(checks, lo + step)
                s = int(0)
                d = int(0)
                if step < ALL_CHECKS:
                    d = dark[iv]
                r = view_checks(view, iv, n_views, v, pw, sub_a, check_order, lit, table, n_table, lo, hi, d,
                                allowed)
                if r[0] < 0 or r[1] > allowed:
                    keep = int(0)
                    break
                if step < ALL_CHECKS:
                    s = seen[iv] + r[0]
                    seen[iv] = s
                    dark[iv] = r[1]
                else:
                    s = r[0]
                if hi < checks:
                    more = int(1)
                elif checks == view.check_count and float(s) < min_seen * float(view.check_count):
                    keep = int(0)
                    break
        lo += step
    counts = int(0)
    if step < ALL_CHECKS and n_views <= MAX_CARRIED:
        for iv in range(n_views):
            counts = counts | (wp.min(seen[iv], 15) << (8 * iv)) | (wp.min(dark[iv], 15) << (8 * iv + 4))
    return wp.vec2i(keep, counts)


@wp.kernel
def eliminate_turns(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    check_order: wp.array(dtype=wp.int32),
    lit: wp.array(dtype=wp.uint8),
    min_seen: float,
    max_dark: float,
    table: wp.array(dtype=wp.int32),
    n_table: int,
    voxels: wp.array(dtype=wp.int32),
    stage_checks: int,
    round_checks: int,
    carried_in: wp.array(dtype=wp.int32),
    lo0: int,
    first: int,
    active: wp.array(dtype=wp.int32),
    carried_out: wp.array(dtype=wp.int32),
):
    """active[i] = 1 if the checked sub-apertures of voxel v land on lit pixels in every view.

    A sub-aperture counts as lit if any of the pixels hit by the centre or the corners of its
    footprint is lit (the footprint may straddle lenslets). A sub-aperture with a point off the
    sensor is no evidence either way; a voxel seen through fewer than ``min_seen`` of its
    checked sub-apertures in some view is dropped, and so is one with more than ``max_dark``
    of them dark (a little tolerance for noise and for particles larger than a point, whose
    light near a lenslet edge may cross into the neighbour). The checks go in
    ``check_order``, spread over the aperture, so that most empty voxels are rejected after a
    few lookups.

    The views take turns, ``round_checks`` checks each (up to :data:`MAX_INTERLEAVED` views; more are
    checked one after another): a voxel on a particle's line of sight in one camera passes most of
    that camera's checks, and is dropped sooner by another camera's. The order changes which checks
    are made, not the result. With up to :data:`MAX_CARRIED` views a pass carries each view's seen and dark
    counts (4 bits each, 8 bits a view: ``carried_out[i]``, where not empty), so that the next pass, over
    the candidates, starts at check ``lo0`` from ``carried_in[i]`` (where not empty) instead of making
    the first pass's checks again.

    ``table`` may hold, from :func:`check_pixels`, the pixels of the first ``n_table`` checks
    of every voxel and view, which then need no tracing (``n_table = 0``: no table). Thread i
    takes voxel ``voxels[first + tid]``, or voxel ``first + tid`` of the grid if ``voxels`` is
    empty. ``stage_checks`` below a view's check count makes only that many checks and drops a
    voxel only for too many dark ones (the seen test needs them all): a first pass over the
    grid that rejects what a full pass would, cheaply, so that the full pass runs on a list of
    candidates in which a GPU warp's threads do similar work.
    """
    i = wp.tid() + first
    v = i
    if voxels.shape[0] > 0:
        v = voxels[i]
    start = int(0)
    carried = int(0)
    if carried_in.shape[0] > 0:
        start = lo0
        carried = carried_in[i]
    r = eliminated(grid, views, n_views, sub_a, check_order, lit, min_seen, max_dark, table, n_table, v,
                   stage_checks, round_checks, start, carried)
    active[i] = r[0]
    if carried_out.shape[0] > 0:
        carried_out[i] = r[1]


@wp.kernel
def eliminate(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    check_order: wp.array(dtype=wp.int32),
    lit: wp.array(dtype=wp.uint8),
    min_seen: float,
    max_dark: float,
    table: wp.array(dtype=wp.int32),
    n_table: int,
    voxels: wp.array(dtype=wp.int32),
    stage_checks: int,
    first: int,
    active: wp.array(dtype=wp.int32),
):
    """:func:`eliminate_turns` with one view after another (its test as it was before the views took turns;
    the tests compare the two)."""
    i = wp.tid() + first
    v = i
    if voxels.shape[0] > 0:
        v = voxels[i]
    active[i] = eliminated(grid, views, n_views, sub_a, check_order, lit, min_seen, max_dark, table, n_table, v,
                           stage_checks, 0, 0, 0)[0]


@wp.kernel
def check_pixels(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    check_order: wp.array(dtype=wp.int32),
    n_table: int,
    first: int,
    table: wp.array(dtype=wp.int32),
):
    """The pixels :func:`eliminate` looks up in the first ``n_table`` checks of voxel v, every view.

    ``table[((v * n_views + view) * n_table + check) * 5 + corner]``: the global pixel; -1 in all
    five if any of them lands off the sensor (such a check is no evidence), and for checks past
    the view's ``check_count``. Views that cannot see the
    voxel are never looked up. The launch covers voxels ``first + tid``.
    """
    v = wp.tid() + first
    pw = voxel_centre(grid, v)
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        p = view_point(view, pw)
        sop = cam.so - p[2]
        inv = float(0.0)
        if sop * cam.inv_f > 1.0:
            inv = 1.0 / sop
        a = 1.0 - cam.si * (cam.inv_f - inv)
        gx = -p[0] * cam.si * inv
        gy = -p[1] * cam.si * inv
        dq = cam.si * inv * inv * view.half[2]
        for mi in range(n_table):
            row = ((v * n_views + iv) * n_table + mi) * 5
            for corner in range(5):
                table[row + corner] = -1
            if mi < view.check_count and inv > 0.0:
                k = check_order[view.check_first + mi]
                ax = sub_a[k][0]
                ay = sub_a[k][1]
                box = check_footprint(view, a, gx, gy, inv, dq, p, ax, ay)
                qx = box[0]
                qy = box[1]
                fx = box[2]
                fy = box[3]
                off = int(0)
                for corner in range(5):
                    q = corner_pixel(view, ax, ay, qx, qy, fx, fy, corner)
                    table[row + corner] = q
                    if q < 0:
                        off = int(1)
                if off == 1:  # the check sees nothing: -1 throughout, so one read tells
                    for corner in range(5):
                        table[row + corner] = -1


@wp.struct
class Footprint:
    """One sub-aperture's footprint of a voxel on the MLA and the size of its spot on the sensor."""

    qx: float  # centre on the MLA, camera frame, mm
    qy: float
    fx: float  # half-sizes on the MLA, mm
    fy: float
    hx: float  # half-sizes on the sensor of the whole footprint's spot, pixels
    hy: float


@wp.func
def footprint(view: View, p: wp.vec3, a: float, gx: float, gy: float, lat: float, dq: float, ax: float,
              ay: float) -> Footprint:
    """The footprint through sub-aperture point (ax, ay) of camera-frame point p, with ``a``,
    ``g`` = (gx, gy), ``lat`` and ``dq`` the point's (see :func:`drt_weights`; the one copy of
    this arithmetic, which :mod:`lfcore._kernels.matrix_free` shares)."""
    cam = view.cam
    out = Footprint()
    out.qx = a * ax + gx
    out.qy = a * ay + gy
    # Footprint on the MLA: the sub-aperture's spread convolved with the voxel's own lateral and
    # depth extent, as the box with the same second moment (widths add in quadrature).
    sprx = lat * view.half[0] + wp.abs(ax - p[0]) * dq
    spry = lat * view.half[1] + wp.abs(ay - p[1]) * dq
    wsub = wp.abs(a) * view.sub_side
    out.fx = 0.5 * wp.sqrt(wsub * wsub + 4.0 * sprx * sprx)
    out.fy = 0.5 * wp.sqrt(wsub * wsub + 4.0 * spry * spry)
    # spot half-sizes on the sensor, in pixels
    k_spot = cam.f_ml / cam.si
    wspot = wp.abs(1.0 - a) * view.sub_side
    out.hx = 0.5 * k_spot * wp.sqrt(wspot * wspot + 4.0 * sprx * sprx) / cam.pixel
    out.hy = 0.5 * k_spot * wp.sqrt(wspot * wspot + 4.0 * spry * spry) / cam.pixel
    return out


@wp.func
def inside_cell(view: View, qx: float, qy: float, home: wp.vec2, ex: float, ey: float) -> int:
    """1 if the box (qx, qy) +- (ex, ey) lies inside the lenslet cell centred at ``home``, else 0."""
    inside = int(1)
    for e in range(view.n_edges):
        nx = view.edge_nx[e]
        ny = view.edge_ny[e]
        if nx * (qx - home[0]) + ny * (qy - home[1]) + wp.abs(nx) * ex + wp.abs(ny) * ey > 0.5 * view.cam.pitch:
            inside = int(0)
    return inside


@wp.func
def part_spot(view: View, c: wp.vec2, ov: Overlap, ax: float, ay: float, fp: Footprint) -> wp.vec4:
    """(column, row, hx, hy) pixels of the spot of the part ``ov`` of footprint ``fp`` that
    enters the lenslet centred at c: it lands around the image of the part's centroid, as a
    spot shrunk like the part's extent on the MLA."""
    cam = view.cam
    sx = c[0] + cam.f_ml * (ov.cx - ax) / cam.si
    sy = c[1] + cam.f_ml * (ov.cy - ay) / cam.si
    return wp.vec4(0.5 * float(cam.ncols) - sx / cam.pixel, 0.5 * float(cam.nrows) + sy / cam.pixel,
                   fp.hx * ov.wx / (2.0 * fp.fx), fp.hy * ov.wy / (2.0 * fp.fy))


@wp.func
def trace_point(
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    sub_w: wp.array(dtype=float),
    pw: wp.vec3,
    half: float,
    base: wp.int64,
    min_weight: float,
    fill: int,
    limit: wp.int64,
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
):
    """The dense ray-traced weights of world point ``pw`` (mm) in every view: the entries counted,
    and with ``fill = 1`` the first ``limit`` of them written to ``pix``/``w`` from ``base``. The
    point is a cube of the views' voxel half-extent, or with ``half > 0`` of that half-extent (mm)
    on every axis (see :func:`drt_weights` and :func:`drt_points`)."""
    n = wp.int64(0)
    for iv in range(n_views):
        view = views[iv]
        if half > 0.0:  # a particle's extent instead of the views' voxel extent
            view.half = wp.vec3(half, half, half)
        cam = view.cam
        p = view_point(view, pw)
        sop = cam.so - p[2]
        if sop * cam.inv_f <= 1.0:
            continue
        inv = 1.0 / sop
        a = 1.0 - cam.si * (cam.inv_f - inv)
        gx = -p[0] * cam.si * inv
        gy = -p[1] * cam.si * inv
        dq = cam.si * inv * inv * view.half[2]
        lat = cam.si * inv
        spans = edge_spans(view)
        for k in range(view.sub_first, view.sub_first + view.sub_count):
            ax = sub_a[k][0]
            ay = sub_a[k][1]
            wk = sub_w[k]
            fp = footprint(view, p, a, gx, gy, lat, dq, ax, ay)
            qx = fp.qx
            qy = fp.qy
            fx = fp.fx
            fy = fp.fy
            x0 = qx - fx
            x1 = qx + fx
            y0 = qy - fy
            y1 = qy + fy
            inv_area = 1.0 / (4.0 * fx * fy)
            # Most footprints near focus lie inside one lenslet: no clipping needed then.
            home = lenslet_centre(cam, qx, qy)
            inside = inside_cell(view, qx, qy, home, fx, fy)
            box = lattice_box(cam, x0, x1, y0, y1, view.cell_r)
            h = row_step(cam)
            j0 = int(wp.ceil(box[2] / h))
            j1 = int(wp.floor(box[3] / h))
            if inside == 1:
                j0 = int(0)
                j1 = int(0)
            for j in range(j0, j1 + 1):
                shift = row_shift(cam, j)
                i0 = int(wp.ceil((box[0] - shift) / cam.pitch))
                i1 = int(wp.floor((box[1] - shift) / cam.pitch))
                if inside == 1:
                    i0 = int(0)
                    i1 = int(0)
                for i in range(i0, i1 + 1):
                    c = home
                    ov = Overlap()
                    if inside == 1:
                        ov.area = 4.0 * fx * fy
                        ov.cx = qx
                        ov.cy = qy
                        ov.wx = 2.0 * fx
                        ov.wy = 2.0 * fy
                    else:
                        c = from_lattice(cam, float(i) * cam.pitch + shift, float(j) * h)
                        ov = spans_overlap(view, spans, c[0], c[1], x0, x1, y0, y1)
                    if ov.area <= 0.0:
                        continue
                    w1 = ov.area * inv_area
                    spot = part_spot(view, c, ov, ax, ay, fp)
                    colc = spot[0]
                    rowc = spot[1]
                    hx = spot[2]
                    hy = spot[3]
                    c0 = wp.max(0, int(wp.floor(colc - hx)))
                    c1 = wp.min(cam.ncols - 1, int(wp.floor(colc + hx)))
                    r0 = wp.max(0, int(wp.floor(rowc - hy)))
                    r1 = wp.min(cam.nrows - 1, int(wp.floor(rowc + hy)))
                    for r in range(r0, r1 + 1):
                        oy = pixel_overlap(rowc - hy, rowc + hy, r) / (2.0 * hy)
                        for cc in range(c0, c1 + 1):
                            ox = pixel_overlap(colc - hx, colc + hx, cc) / (2.0 * hx)
                            wt = wk * w1 * ox * oy
                            if wt > min_weight:
                                if fill == 1 and n < limit:
                                    pix[base + n] = view.pix_offset + r * cam.ncols + cc
                                    w[base + n] = wt
                                n += wp.int64(1)
    return n


@wp.kernel
def drt_weights(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    sub_w: wp.array(dtype=float),
    voxels: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int64),
    origin: wp.int64,
    min_weight: float,
    fill: int,
    limit: wp.int64,
    counts: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
):
    """Dense ray-traced weights of voxel ``voxels[tid]`` (see the module docstring).

    With ``fill = 1`` the first ``limit`` entries go to ``pix``/``w`` from
    ``offsets[tid] - origin``. ``counts[tid]`` gets the voxel's number of entries in both modes,
    so that a single pass into slots of a guessed capacity ``limit`` also tells which voxels
    did not fit.
    """
    tid = wp.tid()
    pw = voxel_centre(grid, voxels[tid])
    base = wp.int64(0)
    if fill == 1:
        base = offsets[tid] - origin
    counts[tid] = trace_point(views, n_views, sub_a, sub_w, pw, 0.0, base, min_weight, fill, limit, pix, w)


@wp.kernel
def drt_points(
    views: wp.array(dtype=View),
    n_views: int,
    sub_a: wp.array(dtype=wp.vec2),
    sub_w: wp.array(dtype=float),
    points: wp.array(dtype=wp.vec3),
    half: float,
    offsets: wp.array(dtype=wp.int64),
    origin: wp.int64,
    min_weight: float,
    fill: int,
    limit: wp.int64,
    counts: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
):
    """:func:`drt_weights` of world point ``points[tid]`` (mm) instead of a voxel centre, as a sphere of
    half-extent ``half`` mm (a particle's radius; a small positive value for a point: a footprint
    needs an area) instead of the views' voxel extent: the image of a particle at any point, not
    only at voxel centres (:mod:`lfcore.ipr`'s particle model). Same passes (``fill``), entries
    and units as :func:`drt_weights`.
    """
    tid = wp.tid()
    pw = points[tid]
    base = wp.int64(0)
    if fill == 1:
        base = offsets[tid] - origin
    counts[tid] = trace_point(views, n_views, sub_a, sub_w, pw, half, base, min_weight, fill, limit, pix, w)


#: Samples of a camera's sphere-cylinder overlap between full and no overlap (see overlap_table).
OVERLAP_SAMPLES = wp.constant(1024)


def overlap_table(r_cyl: float, r_sph: float, samples: int = OVERLAP_SAMPLES) -> np.ndarray:
    """The line-of-sight weight against distance, tabulated for :func:`tabulated_overlap`.

    The weight of a voxel on a pixel is the area shared by the pixel's line-of-sight cylinder
    (radius ``r_cyl``) and the voxel's sphere (radius ``r_sph``) in the voxel's depth plane,
    over the sphere's cross-section; both radii are fixed per camera, so it depends on the
    distance d of the line from the voxel centre alone. Returns ``samples + 1`` values at d
    evenly spaced from |r_cyl - r_sph| (one circle inside the other) to r_cyl + r_sph (apart,
    where it is 0), computed exactly in double precision.
    """
    r1, r2 = float(r_cyl), float(r_sph)
    d = np.linspace(abs(r1 - r2), r1 + r2, samples + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a1 = np.arccos(np.clip((d * d + r1 * r1 - r2 * r2) / (2.0 * d * r1), -1.0, 1.0))
        a2 = np.arccos(np.clip((d * d + r2 * r2 - r1 * r1) / (2.0 * d * r2), -1.0, 1.0))
    k = (-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)
    area = r1 * r1 * a1 + r2 * r2 * a2 - 0.5 * np.sqrt(np.maximum(k, 0.0))
    rm = min(r1, r2)
    area[0] = np.pi * rm * rm  # d = |r1 - r2|: the formula's 0/0 when r1 = r2
    area[-1] = 0.0
    return (area / (np.pi * r2 * r2)).astype(np.float32)


@wp.func
def tabulated_overlap(view: View, table: wp.array(dtype=float), d: float) -> float:
    """The line-of-sight weight at distance d (mm) of the line from the voxel centre, from the
    camera's :func:`overlap_table`, linearly interpolated.

    Two arc cosines a weight would otherwise take most of the kernel's time. The table is also
    the more accurate: within 1e-5 of the exact overlap (double precision) on the benchmark's
    cameras, where the same formula in single precision was off by up to 7e-4 (cancellation
    near full and near no overlap)."""
    x = (d - view.los_d0) * view.los_dinv
    if x >= float(OVERLAP_SAMPLES):
        return 0.0
    if x <= 0.0:
        return table[view.los_first]
    i = int(x)
    f = x - float(i)
    k = view.los_first + i
    return table[k] + f * (table[k + 1] - table[k])


@wp.kernel
def los_weights(
    grid: Grid,
    views: wp.array(dtype=View),
    n_views: int,
    voxels: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int64),
    origin: wp.int64,
    min_weight: float,
    fill: int,
    counts: wp.array(dtype=wp.int64),
    sums: wp.array(dtype=float),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
    log_ratio: wp.array(dtype=float),
    relaxation: float,
    overlap: wp.array(dtype=float),
):
    """Conventional sphere-cylinder weights of voxel ``voxels[tid]`` (the MART baseline).

    ``fill`` says what to do with them: 0 count them into ``counts`` and their sum into
    ``sums``; 1 write them, divided by ``sums[tid]``, to ``pix``/``w`` from ``offsets[tid]``;
    2 project the voxel, ``proj[pixel] += w e[tid]``; 3 update it, ``e[tid] <- e[tid]
    exp(relaxation sum w log_ratio[pixel])`` (:func:`lfcore._kernels.mart.multiplied`); 4 count
    them and their sum as mode 0 does and write them, not yet divided, to the slot ``offsets[tid]``
    .. ``offsets[tid + 1]`` (less ``origin``) as far as it holds them (:func:`pack_line_of_sight`
    then divides and packs them: mode 0 and mode 1 in one trace). Modes 2 and
    3 are the MART iteration on weights computed where they are used, never stored: exactly
    what :mod:`lfcore._kernels.mart` does with the weights of mode 1, in a fraction of the memory.

    The line of sight of the pixel at sensor point s under lenslet c passes through the
    lenslet's conjugate x_f = c / M on the focal plane and the aperture point
    A = c + (c - s) si / f_ml; at the voxel's depth dz it is at x_f + (A - x_f) dz / so. The
    pixels searched lie around the aperture point A* whose line passes through the voxel centre,
    within the lenslet's own pixels and its micro-image (the main lens's aperture seen through it;
    near the focal plane A* leaves the aperture and every pixel of the lenslet sees the voxel). A
    pixel's aperture test comes before its lenslet test (the lattice lookup): the same pixels, in
    35-40% less time on Mc2 (benchmarks/RESULTS.md, fourteenth session).
    """
    tid = wp.tid()
    ej = float(0.0)
    if fill == 2 or fill == 3:
        ej = e[tid]
        if ej == 0.0:
            return  # a dead voxel projects nothing and stays dead
    pw = voxel_centre(grid, voxels[tid])
    n = wp.int64(0)
    base = wp.int64(0)
    norm = float(1.0)
    if fill >= 1 and fill <= 3:
        norm = 1.0 / wp.max(sums[tid], 1.0e-30)
    end = wp.int64(0)
    if fill == 1 or fill == 4:
        base = offsets[tid] - origin
    if fill == 4:
        end = offsets[tid + 1] - origin
    total = float(0.0)
    log_sum = float(0.0)
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        p = view_point(view, pw)
        sop = cam.so - p[2]
        if sop * cam.inv_f <= 1.0:
            continue
        dz = p[2]
        if wp.abs(dz) < 1.0e-6:
            dz = float(1.0e-6)
        m = view.magnification
        # lenslets whose lines of sight can pass within los_radius of the voxel
        shrink = 1.0 - dz / cam.so
        cx = m * p[0] / shrink
        cy = m * p[1] / shrink
        reach = wp.abs(m) * (cam.aperture_r * wp.abs(dz) / cam.so + view.los_radius) / shrink
        box = lattice_box(cam, cx, cx, cy, cy, reach + view.cell_r)
        h = row_step(cam)
        j0 = int(wp.ceil(box[2] / h))
        j1 = int(wp.floor(box[3] / h))
        ratio = cam.si / cam.f_ml
        inner2 = 0.2499 * cam.pitch * cam.pitch  # (0.49995 pitch)^2: inside every cell's inscribed circle
        for j in range(j0, j1 + 1):
            shift = row_shift(cam, j)
            i0 = int(wp.ceil((box[0] - shift) / cam.pitch))
            i1 = int(wp.floor((box[1] - shift) / cam.pitch))
            for i in range(i0, i1 + 1):
                c = from_lattice(cam, float(i) * cam.pitch + shift, float(j) * h)
                xfx = c[0] / m
                xfy = c[1] / m
                # aperture point whose line of sight through this lenslet meets the voxel centre
                asx = xfx + (p[0] - xfx) * cam.so / dz
                asy = xfy + (p[1] - xfy) * cam.so / dz
                # the sensor point of that line, and the search radius around it (pixels)
                ssx = c[0] - (asx - c[0]) / ratio
                ssy = c[1] - (asy - c[1]) / ratio
                # A pixel at sensor point s has aperture point A = A* + (ss - s) ratio, and its
                # line passes |A - A*| |dz| / so from the voxel centre: it sees the voxel only if
                # its centre is within rad of ss (pixels; a hair more for round-off). Near the
                # focal plane the disc covers the whole lenslet: the clamp to the lenslet's own
                # pixels below bounds the loop, so the radius is not capped.
                rad = view.los_radius * cam.so / wp.abs(dz) / ratio / cam.pixel * 1.0001 + 1.0e-3
                # if no pixel of the disc can have its aperture point inside the aperture, none
                # of this lenslet's pixels sees the voxel
                reach_a = cam.aperture_r + ratio * rad * cam.pixel
                if asx * asx + asy * asy > reach_a * reach_a:
                    continue
                # pixel centres are at column + 0.5, row + 0.5 in these coordinates
                ccol = 0.5 * float(cam.ncols) - ssx / cam.pixel - 0.5
                crow = 0.5 * float(cam.nrows) + ssy / cam.pixel - 0.5
                # only this lenslet's own pixels: those within half a pitch of its centre
                lcol = 0.5 * float(cam.ncols) - c[0] / cam.pixel - 0.5
                lrow = 0.5 * float(cam.nrows) + c[1] / cam.pixel - 0.5
                half = 0.5 * cam.pitch / cam.pixel + 0.5
                # and only the lenslet's micro-image: the pixels whose aperture point (below) can be
                # inside the aperture lie in a disc of radius aperture_r / ratio about c (1 + ratio) /
                # ratio (pixels; 0.05 more for round-off: the exact test below still decides)
                mcol = 0.5 * float(cam.ncols) - c[0] * (1.0 + ratio) / ratio / cam.pixel - 0.5
                mrow = 0.5 * float(cam.nrows) + c[1] * (1.0 + ratio) / ratio / cam.pixel - 0.5
                mrad = cam.aperture_r / ratio / cam.pixel + 0.05
                r0 = wp.max(0, int(wp.ceil(wp.max(wp.max(crow - rad, lrow - half), mrow - mrad))))
                r1 = wp.min(cam.nrows - 1, int(wp.floor(wp.min(wp.min(crow + rad, lrow + half), mrow + mrad))))
                for r in range(r0, r1 + 1):
                    # the disc's chord on this row, and the micro-image's
                    dr = float(r) - crow
                    chord = wp.sqrt(wp.max(rad * rad - dr * dr, 0.0))
                    dm = float(r) - mrow
                    mchord = wp.sqrt(wp.max(mrad * mrad - dm * dm, 0.0))
                    c0 = wp.max(0, int(wp.ceil(wp.max(wp.max(ccol - chord, lcol - half), mcol - mchord))))
                    c1 = wp.min(cam.ncols - 1, int(wp.floor(wp.min(wp.min(ccol + chord, lcol + half),
                                                                   mcol + mchord))))
                    for cc in range(c0, c1 + 1):
                        sx = (0.5 * float(cam.ncols) - (float(cc) + 0.5)) * cam.pixel
                        sy = (float(r) + 0.5 - 0.5 * float(cam.nrows)) * cam.pixel
                        # the pixel's aperture point inside the aperture (a few products: tested first)
                        ax = c[0] + (c[0] - sx) * ratio
                        ay = c[1] + (c[1] - sy) * ratio
                        if ax * ax + ay * ay > cam.aperture_r * cam.aperture_r:
                            continue
                        # the pixel must lie under this lenslet (its nearest lenslet is c); inside
                        # the cell's inscribed circle it does without asking the lattice
                        if (sx - c[0]) * (sx - c[0]) + (sy - c[1]) * (sy - c[1]) > inner2:
                            own = lenslet_centre(cam, sx, sy)
                            if wp.abs(own[0] - c[0]) + wp.abs(own[1] - c[1]) > 1.0e-3 * cam.pitch:
                                continue
                        # the line of sight at the voxel's depth, xf + (A - xf) dz / so, against its centre
                        # (this form stays exact at the focal plane, where A* runs off to infinity)
                        ex = xfx - p[0] + (ax - xfx) * dz / cam.so
                        ey = xfy - p[1] + (ay - xfy) * dz / cam.so
                        d = wp.sqrt(ex * ex + ey * ey)
                        wt = tabulated_overlap(view, overlap, d)
                        if wt > min_weight:  # the same test in every mode
                            total += wt
                            q = view.pix_offset + r * cam.ncols + cc
                            if fill == 1:
                                pix[base + n] = q
                                w[base + n] = wt * norm
                            elif fill == 2:
                                wp.atomic_add(proj, q, wt * norm * ej)
                            elif fill == 3:
                                log_sum += wt * norm * log_ratio[q]
                            elif fill == 4 and base + n < end:
                                pix[base + n] = q
                                w[base + n] = wt
                            n += wp.int64(1)
    if fill == 0 or fill == 4:
        counts[tid] = n
        sums[tid] = total
    elif fill == 3:
        e[tid] = multiplied(ej, log_sum, relaxation)



@wp.kernel
def iota(out: wp.array(dtype=wp.int32)):
    """out[i] = i."""
    i = wp.tid()
    out[i] = i


@wp.kernel
def compact(mask: wp.array(dtype=wp.int32), scan: wp.array(dtype=wp.int32), values: wp.array(dtype=wp.int32),
            out: wp.array(dtype=wp.int32)):
    """The entries of ``values`` (their indices if it is empty) where ``mask`` is set, in order
    (``scan`` is the mask's inclusive prefix sum)."""
    v = wp.tid()
    if mask[v] != 0:
        x = v
        if values.shape[0] > 0:
            x = values[v]
        out[scan[v] - 1] = x


@wp.func
def _kept_run(p: int, acc: float, floor: float, s: int, m: int, out_pix: wp.array(dtype=wp.int32),
              out_w: wp.array(dtype=float)) -> int:
    """Write the merged entry (p, acc) at ``s + m`` where acc passes ``floor``; the next m."""
    if acc > floor:
        out_pix[s + m] = p
        out_w[s + m] = acc
        return m + 1
    return m


@wp.func
def keep_light(w: wp.array(dtype=float), s: wp.int64, m: wp.int64, total: float):
    """Scale a voxel's kept merged entries ``w[s .. s + m - 1]`` so that they carry its whole
    light ``total`` again (after the merge dropped its entries at or below a floor)."""
    kept = float(0.0)
    k = s
    while k < s + m:
        kept += w[k]
        k += wp.int64(1)
    if kept > 0.0 and kept < total:
        scale = total / kept
        k = s
        while k < s + m:
            w[k] = w[k] * scale
            k += wp.int64(1)


@wp.func
def _sum_runs(
    pix: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    w_raw: wp.array(dtype=float),
    s: int,
    e: int,
    floor: float,
    out_pix: wp.array(dtype=wp.int32),
    out_w: wp.array(dtype=float),
):
    """Sum the weights of entries ``s .. e - 1`` (sorted by pixel) that share a pixel, writing one
    entry per pixel from ``s``; returns how many. ``order`` maps sorted entries to ``w_raw``.

    Merged entries at or below ``floor`` are dropped and the voxel's others scaled so that its
    light is kept (:func:`lfcore.matrix_free.TemplateOperator.expanded`' faint fringe); with
    ``floor`` 0 none is (the raw entries are positive)."""
    m = int(0)
    prev = int(-1)
    acc = float(0.0)
    total = float(0.0)
    for t in range(s, e):
        p = pix[t]
        if p != prev and prev >= 0:
            total += acc
            m = _kept_run(prev, acc, floor, s, m, out_pix, out_w)
            acc = float(0.0)
        prev = p
        acc += w_raw[order[t]]
    if prev >= 0:
        total += acc
        m = _kept_run(prev, acc, floor, s, m, out_pix, out_w)
    if floor > 0.0:
        keep_light(out_w, wp.int64(s), wp.int64(m), total)
    return m


@wp.kernel
def merge_sorted(
    starts: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    pix_sorted: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    w_raw: wp.array(dtype=float),
    out_pix: wp.array(dtype=wp.int32),
    out_w: wp.array(dtype=float),
    counts: wp.array(dtype=wp.int32),
    floor: float,
):
    """Sum the entries of one voxel that share a pixel (its entries sorted by pixel), dropping
    merged ones at or below ``floor`` (see :func:`_sum_runs`)."""
    v = wp.tid()
    counts[v] = _sum_runs(pix_sorted, order, w_raw, starts[v], ends[v], floor, out_pix, out_w)


@wp.func
def _merge_pass(
    src_pix: wp.array(dtype=wp.int32),
    src_ord: wp.array(dtype=wp.int32),
    dst_pix: wp.array(dtype=wp.int32),
    dst_ord: wp.array(dtype=wp.int32),
    s: int,
    n: int,
    width: int,
):
    """Merge the sorted runs of ``width`` entries from ``s`` pairwise into ``dst`` (stable)."""
    lo = int(0)
    while lo < n:
        mid = wp.min(lo + width, n)
        hi = wp.min(lo + 2 * width, n)
        i = lo
        j = mid
        k = lo
        while k < hi:
            take_left = int(0)
            if i < mid:
                if j >= hi:
                    take_left = 1
                elif src_pix[s + i] <= src_pix[s + j]:
                    take_left = 1
            if take_left == 1:
                dst_pix[s + k] = src_pix[s + i]
                dst_ord[s + k] = src_ord[s + i]
                i += 1
            else:
                dst_pix[s + k] = src_pix[s + j]
                dst_ord[s + k] = src_ord[s + j]
                j += 1
            k += 1
        lo = hi


@wp.kernel
def sort_merge(
    starts: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    pix: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    tmp_pix: wp.array(dtype=wp.int32),
    tmp_ord: wp.array(dtype=wp.int32),
    w_raw: wp.array(dtype=float),
    out_pix: wp.array(dtype=wp.int32),
    out_w: wp.array(dtype=float),
    counts: wp.array(dtype=wp.int32),
    floor: float,
):
    """Sort one voxel's raw entries by pixel and sum those sharing a pixel, in one thread, dropping
    merged ones at or below ``floor`` (see :func:`_sum_runs`).

    The per-thread equivalent of ``segmented_sort_pairs`` followed by :func:`merge_sorted`,
    with the same result: a stable sort (insertion sort of blocks of 16, then bottom-up merge
    passes through ``tmp_pix``/``tmp_ord``), so entries sharing a pixel are summed in their raw
    order. Cheaper than the library sort on the CPU, where a voxel's few hundred entries stay
    in cache; the kernel traces emit them in short sorted runs.
    """
    v = wp.tid()
    s = starts[v]
    n = ends[v] - s
    block = int(16)
    for t in range(s, s + n):
        order[t] = t
    # insertion sort of each block
    b0 = int(0)
    while b0 < n:
        b1 = wp.min(b0 + block, n)
        for i in range(b0 + 1, b1):
            kp = pix[s + i]
            ko = order[s + i]
            j = i - 1
            while j >= b0 and pix[s + j] > kp:
                pix[s + j + 1] = pix[s + j]
                order[s + j + 1] = order[s + j]
                j -= 1
            pix[s + j + 1] = kp
            order[s + j + 1] = ko
        b0 = b1
    # merge passes, alternating between the raw arrays and the scratch
    width = block
    in_tmp = int(0)
    while width < n:
        if in_tmp == 0:
            _merge_pass(pix, order, tmp_pix, tmp_ord, s, n, width)
            in_tmp = 1
        else:
            _merge_pass(tmp_pix, tmp_ord, pix, order, s, n, width)
            in_tmp = 0
        width = 2 * width
    if in_tmp == 1:
        for t in range(s, s + n):
            pix[t] = tmp_pix[t]
            order[t] = tmp_ord[t]
    counts[v] = _sum_runs(pix, order, w_raw, s, s + n, floor, out_pix, out_w)


@wp.func
def _copy_run(
    src_pix: wp.array(dtype=wp.int32),
    src_w: wp.array(dtype=float),
    s: wp.int64,
    dst_pix: wp.array(dtype=wp.int32),
    dst_w: wp.array(dtype=float),
    d: wp.int64,
    n: wp.int64,
):
    """Copy ``n`` (pixel, weight) entries from ``s`` to ``d``."""
    k = wp.int64(0)
    while k < n:
        dst_pix[d + k] = src_pix[s + k]
        dst_w[d + k] = src_w[s + k]
        k += wp.int64(1)


@wp.kernel
def gather_merged(
    starts: wp.array(dtype=wp.int32),
    new_starts: wp.array(dtype=wp.int64),
    counts: wp.array(dtype=wp.int32),
    src_pix: wp.array(dtype=wp.int32),
    src_w: wp.array(dtype=float),
    dst_pix: wp.array(dtype=wp.int32),
    dst_w: wp.array(dtype=float),
):
    """Pack each voxel's merged entries (at ``starts``) contiguously (at ``new_starts``)."""
    v = wp.tid()
    _copy_run(src_pix, src_w, wp.int64(starts[v]), dst_pix, dst_w, new_starts[v], wp.int64(counts[v]))


@wp.kernel
def pack_line_of_sight(
    slots: wp.array(dtype=wp.int64),
    counts: wp.array(dtype=wp.int64),
    sums: wp.array(dtype=float),
    src_pix: wp.array(dtype=wp.int32),
    src_w: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int64),
    dst_pix: wp.array(dtype=wp.int32),
    dst_w: wp.array(dtype=float),
):
    """Pack voxel v's line-of-sight entries from its slot (at ``slots[v]``, :func:`los_weights` mode 4)
    to ``offsets[v]``, each divided by the voxel's sum as mode 1 divides it (the same float arithmetic:
    the same weights to the bit)."""
    v = wp.tid()
    norm = 1.0 / wp.max(sums[v], 1.0e-30)
    s = slots[v]
    d = offsets[v]
    k = wp.int64(0)
    while k < counts[v]:
        dst_pix[d + k] = src_pix[s + k]
        dst_w[d + k] = src_w[s + k] * norm
        k += wp.int64(1)


@wp.kernel
def copy_rows(
    src_start: wp.array(dtype=wp.int64),
    dst_offsets: wp.array(dtype=wp.int64),
    src_pix: wp.array(dtype=wp.int32),
    src_w: wp.array(dtype=float),
    dst_pix: wp.array(dtype=wp.int32),
    dst_w: wp.array(dtype=float),
):
    """Copy row t, ``dst_offsets[t + 1] - dst_offsets[t]`` entries from ``src_start[t]``, to ``dst_offsets[t]``."""
    t = wp.tid()
    d = dst_offsets[t]
    _copy_run(src_pix, src_w, src_start[t], dst_pix, dst_w, d, dst_offsets[t + 1] - d)
