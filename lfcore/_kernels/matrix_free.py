"""Kernels of the matrix-free DRT operator (:mod:`lfcore.matrix_free`).

A template is the DRT image of one camera-frame point, kept as the spots the dense ray tracing
makes (:func:`lfcore._kernels.weights.drt_weights`, the same arithmetic line by line) before
they are cut into pixels: a spot is the part of one sub-aperture's footprint that enters one
lenslet, landing on the sensor as a box of half-sizes (hx, hy) pixels around a sensor point
(sx, sy) mm, with a share w of the voxel's light.

A voxel whose footprint centre on the MLA sits at g = g_b + L + delta (L a lattice vector,
delta within its phase bin) lands where the template of point g_b lands, shifted on the sensor
by (1 + f_ml / si) L + (f_ml / si) delta: the lenslets move with L, and within a lenslet a
footprint moving by delta lands f_ml / si delta further. The spots are then cut into the pixels
the voxel's shifted spots cover, exactly as the stored weights are (pixel overlap of the box,
clipped at the sensor's edges, entries at or below ``min_weight`` dropped).
"""

from __future__ import annotations

import warp as wp

from lfcore._kernels.mart import multiplied
from lfcore._kernels.optics import HEX_ROW, lenslet_centre
from lfcore._kernels.weights import (
    Grid,
    Overlap,
    View,
    cell_overlap,
    from_lattice,
    lattice_box,
    pixel_overlap,
    row_shift,
    row_step,
    view_point,
    voxel_centre,
)
from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.struct
class Plan:
    """How one view finds a voxel's template."""

    depth_axis: int  # grid axis (0 x, 1 y, 2 z) along which the camera's depth changes
    n_depth: int
    depth_base: int  # this view's first entry of the per-depth tables (first template, phase bins)
    k_spot: float  # f_ml / si


@wp.func
def lattice_basis_inv(cam: wp.int32, pitch: float, f: wp.vec2) -> wp.vec2:
    """Lattice-frame (u, v) -> fractional lattice coordinates (hexagonal or square)."""
    if cam == 1:
        h = pitch * HEX_ROW
        f2 = f[1] / h
        return wp.vec2((f[0] - 0.5 * pitch * f2) / pitch, f2)
    return wp.vec2(f[0] / pitch, f[1] / pitch)


@wp.func
def lattice_vector(hexagonal: wp.int32, pitch: float, a: float, b: float) -> wp.vec2:
    """Fractional lattice coordinates -> lattice-frame (u, v) vector."""
    if hexagonal == 1:
        return wp.vec2(pitch * (a + 0.5 * b), pitch * HEX_ROW * b)
    return wp.vec2(pitch * a, pitch * b)


@wp.struct
class Placement:
    tmpl: int  # global template index; -1 if the view cannot see the voxel
    shift: wp.vec2  # sensor-plane shift of the template's spots, mm
    weight: float  # the template's share of the voxel (bilinear in the phase)


@wp.func
def place(grid: Grid, view: View, plan: Plan, depth_first: wp.array(dtype=wp.int32),
          depth_phase: wp.array(dtype=wp.int32), v: int, corner: int) -> Placement:
    """One of the three templates around voxel v's phase in one view (``corner`` 0-2), its
    weight (linear in the phase) and the shift of its spots (see the module docstring)."""
    out = Placement()
    out.tmpl = -1
    cam = view.cam
    p = view_point(view, voxel_centre(grid, v))
    sop = cam.so - p[2]
    if sop * cam.inv_f <= 1.0:
        return out
    plane = grid.nx * grid.ny
    iz = v // plane
    r = v - iz * plane
    iy = r // grid.nx
    ix = r - iy * grid.nx
    d = iz
    if plan.depth_axis == 0:
        d = ix
    elif plan.depth_axis == 1:
        d = iy
    lat = cam.si / sop
    # footprint centre on the MLA (a = 0 part), in the lattice frame relative to the MLA's offset
    gx = -p[0] * lat - cam.off_x
    gy = -p[1] * lat - cam.off_y
    u = cam.cos_t * gx + cam.sin_t * gy
    w = -cam.sin_t * gx + cam.cos_t * gy
    f = lattice_basis_inv(cam.hex, cam.pitch, wp.vec2(u, w))
    n_phase = depth_phase[plan.depth_base + d]
    nph = float(n_phase)
    # bin centres sit at (b + 1/2) / n_phase: the two either side of f along each axis
    t0 = f[0] * nph - 0.5
    t1 = f[1] * nph - 0.5
    c0 = wp.floor(t0)
    c1 = wp.floor(t1)
    a0 = t0 - c0
    a1 = t1 - c1
    # linear on the triangle of bin centres around f (the cell of four cut along its diagonal):
    # three templates, their barycentric weights
    wgt = float(0.0)
    if a0 + a1 <= 1.0:
        if corner == 0:
            wgt = 1.0 - a0 - a1
        elif corner == 1:
            c0 += 1.0
            wgt = a0
        else:
            c1 += 1.0
            wgt = a1
    else:
        if corner == 0:
            c0 += 1.0
            c1 += 1.0
            wgt = a0 + a1 - 1.0
        elif corner == 1:
            c0 += 1.0
            wgt = 1.0 - a1
        else:
            c1 += 1.0
            wgt = 1.0 - a0
    # the bin c in lattice cell n = floor(c / n_phase), as bin c - n n_phase of the templates (cell 0)
    n0 = wp.floor(c0 / nph)
    n1 = wp.floor(c1 / nph)
    b0 = int(c0 - n0 * nph)
    b1 = int(c1 - n1 * nph)
    lv = lattice_vector(cam.hex, cam.pitch, n0, n1)
    dv = lattice_vector(cam.hex, cam.pitch, f[0] - n0 - (float(b0) + 0.5) / nph, f[1] - n1 - (float(b1) + 0.5) / nph)
    su = (1.0 + plan.k_spot) * lv[0] + plan.k_spot * dv[0]
    sv = (1.0 + plan.k_spot) * lv[1] + plan.k_spot * dv[1]
    out.shift = wp.vec2(cam.cos_t * su - cam.sin_t * sv, cam.sin_t * su + cam.cos_t * sv)
    out.tmpl = depth_first[plan.depth_base + d] + b1 * n_phase + b0
    out.weight = wgt
    return out


@wp.kernel
def template_spots(
    views: wp.array(dtype=View),
    sub_a: wp.array(dtype=wp.vec2),
    sub_w: wp.array(dtype=float),
    t_view: wp.array(dtype=wp.int32),
    t_point: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=wp.int32),
    fill: int,
    counts: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
):
    """The spots of template ``tid``: view ``t_view[tid]`` seeing camera-frame point ``t_point[tid]``.

    The body is :func:`lfcore._kernels.weights.drt_weights`'s for one view, stopping where that
    kernel cuts a spot into pixels. ``fill = 0`` counts the spots into ``counts``; ``fill = 1``
    writes them from ``offsets[tid]``: ``spots`` (column and row of the centre, half-sizes
    hx, hy, all in pixels, as drt_weights places and sizes them) and ``shares``, the spot's share
    of the light per pixel area (share / (4 hx hy)).
    """
    tid = wp.tid()
    view = views[t_view[tid]]
    cam = view.cam
    p = t_point[tid]
    n = int(0)
    base = int(0)
    if fill == 1:
        base = offsets[tid]
    sop = cam.so - p[2]
    if sop * cam.inv_f > 1.0:
        inv = 1.0 / sop
        a = 1.0 - cam.si * (cam.inv_f - inv)
        gx = -p[0] * cam.si * inv
        gy = -p[1] * cam.si * inv
        dq = cam.si * inv * inv * view.half[2]
        lat = cam.si * inv
        k_spot = cam.f_ml / cam.si
        for k in range(view.sub_first, view.sub_first + view.sub_count):
            ax = sub_a[k][0]
            ay = sub_a[k][1]
            wk = sub_w[k]
            qx = a * ax + gx
            qy = a * ay + gy
            sprx = lat * view.half[0] + wp.abs(ax - p[0]) * dq
            spry = lat * view.half[1] + wp.abs(ay - p[1]) * dq
            wsub = wp.abs(a) * view.sub_side
            fx = 0.5 * wp.sqrt(wsub * wsub + 4.0 * sprx * sprx)
            fy = 0.5 * wp.sqrt(wsub * wsub + 4.0 * spry * spry)
            x0 = qx - fx
            x1 = qx + fx
            y0 = qy - fy
            y1 = qy + fy
            inv_area = 1.0 / (4.0 * fx * fy)
            # spot half-sizes on the sensor, in pixels
            wspot = wp.abs(1.0 - a) * view.sub_side
            hx_full = 0.5 * k_spot * wp.sqrt(wspot * wspot + 4.0 * sprx * sprx) / cam.pixel
            hy_full = 0.5 * k_spot * wp.sqrt(wspot * wspot + 4.0 * spry * spry) / cam.pixel
            home = lenslet_centre(cam, qx, qy)
            inside = int(1)
            for e in range(view.n_edges):
                nx = view.edge_nx[e]
                ny = view.edge_ny[e]
                if nx * (qx - home[0]) + ny * (qy - home[1]) + wp.abs(nx) * fx + wp.abs(ny) * fy > 0.5 * cam.pitch:
                    inside = int(0)
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
                        ov = cell_overlap(view, c[0], c[1], x0, x1, y0, y1)
                    if ov.area <= 0.0:
                        continue
                    if fill == 1:
                        sx = c[0] + cam.f_ml * (ov.cx - ax) / cam.si
                        sy = c[1] + cam.f_ml * (ov.cy - ay) / cam.si
                        hx = hx_full * ov.wx / (2.0 * fx)
                        hy = hy_full * ov.wy / (2.0 * fy)
                        spots[base + n] = wp.vec4(0.5 * float(cam.ncols) - sx / cam.pixel,
                                                  0.5 * float(cam.nrows) + sy / cam.pixel, hx, hy)
                        # the share per pixel area of the spot: a pixel's weight is this times its overlap
                        shares[base + n] = wk * ov.area * inv_area / (4.0 * hx * hy)
                    n += 1
    counts[tid] = n


@wp.func
def apply_templates(
    mode: int,
    grid: Grid,
    view: View,
    plan: Plan,
    depth_first: wp.array(dtype=wp.int32),
    depth_phase: wp.array(dtype=wp.int32),
    t_offsets: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
    min_weight: float,
    v: int,
    ej: float,
    values: wp.array(dtype=float),
    images: wp.array2d(dtype=float),
    row: int,
) -> float:
    """Voxel v's pixels in one view, from its three templates: ``mode`` 0 adds w ``ej`` to
    ``values[pixel]`` (projection), 1 returns sum w ``values[pixel]`` (the update's gather), 2 adds
    w to ``images[row, pixel]`` (checks).

    Each spot is shifted by its template's placement and cut into pixels as the stored weights
    are (box overlap, clipped at the sensor, entries at or below ``min_weight`` dropped).
    """
    cam = view.cam
    ncols = cam.ncols
    nrows = cam.nrows
    inv_pix = 1.0 / cam.pixel
    base = view.pix_offset
    total = float(0.0)
    for corner in range(3):
        pl = place(grid, view, plan, depth_first, depth_phase, v, corner)
        if pl.tmpl < 0 or pl.weight <= 0.0:
            continue
        dc = -pl.shift[0] * inv_pix  # the shift in pixels: columns run against x, rows with y
        dr = pl.shift[1] * inv_pix
        blend = pl.weight
        for t in range(t_offsets[pl.tmpl], t_offsets[pl.tmpl + 1]):
            st = spots[t]
            colc = st[0] + dc
            rowc = st[1] + dr
            hx = st[2]
            hy = st[3]
            wk = shares[t]
            # int() truncates where floor would round down, but only below 0, where the range is
            # clamped to 0 anyway (or, wholly left of the sensor, meets pixel 0 with no overlap)
            c0 = wp.max(0, int(colc - hx))
            c1 = wp.min(ncols - 1, int(colc + hx))
            r0 = wp.max(0, int(rowc - hy))
            r1 = wp.min(nrows - 1, int(rowc + hy))
            for r in range(r0, r1 + 1):
                oy = wk * pixel_overlap(rowc - hy, rowc + hy, r)
                for cc in range(c0, c1 + 1):
                    wt = oy * pixel_overlap(colc - hx, colc + hx, cc)
                    if wt > min_weight:
                        q = base + r * ncols + cc
                        if mode == 0:
                            wp.atomic_add(values, q, wt * blend * ej)
                        elif mode == 1:
                            total += wt * blend * values[q]
                        else:
                            images[row, q] += wt * blend
    return total


@wp.kernel
def project(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    depth_first: wp.array(dtype=wp.int32),
    depth_phase: wp.array(dtype=wp.int32),
    n_views: int,
    t_offsets: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
    none: wp.array2d(dtype=float),
):
    """proj[pixel] += w E of voxel ``voxels[tid]``, every view (see :func:`apply_templates`;
    ``none`` is unused)."""
    tid = wp.tid()
    ej = e[tid]
    if ej == 0.0:
        return
    for iv in range(n_views):
        apply_templates(0, grid, views[iv], plans[iv], depth_first, depth_phase, t_offsets, spots, shares,
                        min_weight, voxels[tid], ej, proj, none, 0)


@wp.kernel
def smart_update(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    depth_first: wp.array(dtype=wp.int32),
    depth_phase: wp.array(dtype=wp.int32),
    n_views: int,
    t_offsets: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    ratio: wp.array(dtype=float),
    relaxation: float,
    e: wp.array(dtype=float),
    none: wp.array2d(dtype=float),
):
    """E_v <- E_v exp(mu sum_i w_iv ratio_i), a gather per voxel (see :func:`lfcore._kernels.mart.smart_update`;
    ``none`` is unused)."""
    tid = wp.tid()
    ej = e[tid]
    if ej == 0.0:
        return
    s = float(0.0)
    for iv in range(n_views):
        s += apply_templates(1, grid, views[iv], plans[iv], depth_first, depth_phase, t_offsets, spots, shares,
                             min_weight, voxels[tid], ej, ratio, none, 0)
    e[tid] = multiplied(ej, s, relaxation)


@wp.kernel
def voxel_image(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    depth_first: wp.array(dtype=wp.int32),
    depth_phase: wp.array(dtype=wp.int32),
    n_views: int,
    t_offsets: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    images: wp.array2d(dtype=float),
    none: wp.array(dtype=float),
):
    """images[tid, pixel] += w of voxel ``voxels[tid]`` (for the fidelity checks; one row per voxel;
    ``none`` is unused)."""
    tid = wp.tid()
    for iv in range(n_views):
        apply_templates(2, grid, views[iv], plans[iv], depth_first, depth_phase, t_offsets, spots, shares,
                        min_weight, voxels[tid], 1.0, none, images, tid)
