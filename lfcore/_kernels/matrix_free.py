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
    voxel_centre,
    view_point,
)
from lfcore._kernels.optics import HEX_ROW, lenslet_centre
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
    px: float  # the voxel's camera-frame lateral position, mm
    py: float
    spr: wp.vec2  # its footprints' lateral blur on the MLA, before the |A - p| dq term, mm
    dq: float  # the depth extent's blur per mm of |A - p| (see drt_weights)
    wspot2: float  # (|1 - a| sub_side)^2: the sub-aperture's spot width on the sensor squared, mm^2


@wp.func
def place(grid: Grid, view: View, plan: Plan, depth_first: wp.array(dtype=wp.int32),
          depth_phase: wp.array(dtype=wp.int32), v: int, corner: int) -> Placement:
    """One of the four templates around voxel v's phase in one view (``corner`` 0-3), its
    bilinear weight and the shift of its spots (see the module docstring)."""
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
    wgt = float(1.0)
    if corner % 2 == 1:
        c0 += 1.0
        wgt *= a0
    else:
        wgt *= 1.0 - a0
    if corner >= 2:
        c1 += 1.0
        wgt *= a1
    else:
        wgt *= 1.0 - a1
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
    inv = 1.0 / sop
    a = 1.0 - cam.si * (cam.inv_f - inv)
    out.px = p[0]
    out.py = p[1]
    out.spr = wp.vec2(lat * view.half[0], lat * view.half[1])
    out.dq = cam.si * inv * inv * view.half[2]
    ws = wp.abs(1.0 - a) * view.sub_side
    out.wspot2 = ws * ws
    return out


@wp.func
def spot_size(view: View, pl: Placement, ax: float, ay: float, s: wp.vec4) -> wp.vec2:
    """Half-sizes (pixels) of a template spot for the voxel of ``pl``: the sub-aperture's spot
    with the voxel's own depth blur, |A - p| dq at the voxel's p (not the template's), times the
    spot's part of its footprint ``s[2], s[3]`` (as drt_weights sizes it)."""
    sprx = pl.spr[0] + wp.abs(ax - pl.px) * pl.dq
    spry = pl.spr[1] + wp.abs(ay - pl.py) * pl.dq
    k = 0.5 * view.cam.f_ml / (view.cam.si * view.cam.pixel)
    return wp.vec2(k * wp.sqrt(pl.wspot2 + 4.0 * sprx * sprx) * s[2], k * wp.sqrt(pl.wspot2 + 4.0 * spry * spry) * s[3])


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
    spot_sub: wp.array(dtype=wp.int32),
):
    """The spots of template ``tid``: view ``t_view[tid]`` seeing camera-frame point ``t_point[tid]``.

    The body is :func:`lfcore._kernels.weights.drt_weights`'s for one view, stopping where that
    kernel cuts a spot into pixels. ``fill = 0`` counts the spots into ``counts``; ``fill = 1``
    writes them from ``offsets[tid]``: ``spots`` (sx, sy mm, and the part's extent over the
    footprint's along x and y, which scale the spot's size), ``shares`` w, ``spot_sub`` the
    sub-aperture.
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
                        spots[base + n] = wp.vec4(sx, sy, ov.wx / (2.0 * fx), ov.wy / (2.0 * fy))
                        shares[base + n] = wk * ov.area * inv_area
                        spot_sub[base + n] = k
                    n += 1
    counts[tid] = n


@wp.func
def spot_pixels(view: View, s: wp.vec4, shift: wp.vec2) -> wp.vec4:
    """(column, row) of a spot's centre shifted by ``shift`` mm, in pixels (as the stored weights
    place it); the rest of the vector is unused."""
    cam = view.cam
    sx = s[0] + shift[0]
    sy = s[1] + shift[1]
    return wp.vec4(0.5 * float(cam.ncols) - sx / cam.pixel, 0.5 * float(cam.nrows) + sy / cam.pixel, s[2], s[3])


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
    spot_sub: wp.array(dtype=wp.int32),
    sub_a: wp.array(dtype=wp.vec2),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
):
    """proj[pixel] += w E of voxel ``voxels[tid]``'s shifted template spots, every view."""
    tid = wp.tid()
    ej = e[tid]
    if ej == 0.0:
        return
    v = voxels[tid]
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        for corner in range(4):
            pl = place(grid, view, plans[iv], depth_first, depth_phase, v, corner)
            if pl.tmpl < 0 or pl.weight <= 0.0:
                continue
            for t in range(t_offsets[pl.tmpl], t_offsets[pl.tmpl + 1]):
                st = spots[t]
                q = spot_pixels(view, st, pl.shift)
                colc = q[0]
                rowc = q[1]
                ak = sub_a[spot_sub[t]]
                hsz = spot_size(view, pl, ak[0], ak[1], st)
                hx = hsz[0]
                hy = hsz[1]
                wk = shares[t]
                c0 = wp.max(0, int(wp.floor(colc - hx)))
                c1 = wp.min(cam.ncols - 1, int(wp.floor(colc + hx)))
                r0 = wp.max(0, int(wp.floor(rowc - hy)))
                r1 = wp.min(cam.nrows - 1, int(wp.floor(rowc + hy)))
                for r in range(r0, r1 + 1):
                    oy = pixel_overlap(rowc - hy, rowc + hy, r) / (2.0 * hy)
                    for cc in range(c0, c1 + 1):
                        wt = wk * oy * pixel_overlap(colc - hx, colc + hx, cc) / (2.0 * hx)
                        if wt > min_weight:
                            wp.atomic_add(proj, view.pix_offset + r * cam.ncols + cc, wt * pl.weight * ej)


@wp.func
def weighted_sum(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    depth_first: wp.array(dtype=wp.int32),
    depth_phase: wp.array(dtype=wp.int32),
    n_views: int,
    t_offsets: wp.array(dtype=wp.int32),
    spots: wp.array(dtype=wp.vec4),
    shares: wp.array(dtype=float),
    spot_sub: wp.array(dtype=wp.int32),
    sub_a: wp.array(dtype=wp.vec2),
    min_weight: float,
    v: int,
    values: wp.array(dtype=float),
) -> float:
    """sum_i w_iv values[i] over the pixels i of voxel v's shifted template spots."""
    total = float(0.0)
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        for corner in range(4):
            pl = place(grid, view, plans[iv], depth_first, depth_phase, v, corner)
            if pl.tmpl < 0 or pl.weight <= 0.0:
                continue
            for t in range(t_offsets[pl.tmpl], t_offsets[pl.tmpl + 1]):
                st = spots[t]
                q = spot_pixels(view, st, pl.shift)
                colc = q[0]
                rowc = q[1]
                ak = sub_a[spot_sub[t]]
                hsz = spot_size(view, pl, ak[0], ak[1], st)
                hx = hsz[0]
                hy = hsz[1]
                wk = shares[t]
                c0 = wp.max(0, int(wp.floor(colc - hx)))
                c1 = wp.min(cam.ncols - 1, int(wp.floor(colc + hx)))
                r0 = wp.max(0, int(wp.floor(rowc - hy)))
                r1 = wp.min(cam.nrows - 1, int(wp.floor(rowc + hy)))
                for r in range(r0, r1 + 1):
                    oy = pixel_overlap(rowc - hy, rowc + hy, r) / (2.0 * hy)
                    for cc in range(c0, c1 + 1):
                        wt = wk * oy * pixel_overlap(colc - hx, colc + hx, cc) / (2.0 * hx)
                        if wt > min_weight:
                            total += wt * pl.weight * values[view.pix_offset + r * cam.ncols + cc]
    return total


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
    spot_sub: wp.array(dtype=wp.int32),
    sub_a: wp.array(dtype=wp.vec2),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    ratio: wp.array(dtype=float),
    relaxation: float,
    e: wp.array(dtype=float),
):
    """E_v <- E_v exp(mu sum_i w_iv ratio_i), a gather per voxel (see :func:`lfcore._kernels.mart.smart_update`)."""
    tid = wp.tid()
    ej = e[tid]
    if ej == 0.0:
        return
    s = weighted_sum(grid, views, plans, depth_first, depth_phase, n_views, t_offsets, spots, shares,
                     spot_sub, sub_a, min_weight, voxels[tid], ratio)
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
    spot_sub: wp.array(dtype=wp.int32),
    sub_a: wp.array(dtype=wp.vec2),
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    images: wp.array2d(dtype=float),
):
    """images[tid, pixel] += w of voxel ``voxels[tid]`` (for the fidelity checks; one row per voxel)."""
    tid = wp.tid()
    v = voxels[tid]
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        for corner in range(4):
            pl = place(grid, view, plans[iv], depth_first, depth_phase, v, corner)
            if pl.tmpl < 0 or pl.weight <= 0.0:
                continue
            for t in range(t_offsets[pl.tmpl], t_offsets[pl.tmpl + 1]):
                st = spots[t]
                q = spot_pixels(view, st, pl.shift)
                colc = q[0]
                rowc = q[1]
                ak = sub_a[spot_sub[t]]
                hsz = spot_size(view, pl, ak[0], ak[1], st)
                hx = hsz[0]
                hy = hsz[1]
                wk = shares[t]
                c0 = wp.max(0, int(wp.floor(colc - hx)))
                c1 = wp.min(cam.ncols - 1, int(wp.floor(colc + hx)))
                r0 = wp.max(0, int(wp.floor(rowc - hy)))
                r1 = wp.min(cam.nrows - 1, int(wp.floor(rowc + hy)))
                for r in range(r0, r1 + 1):
                    oy = pixel_overlap(rowc - hy, rowc + hy, r) / (2.0 * hy)
                    for cc in range(c0, c1 + 1):
                        wt = wk * oy * pixel_overlap(colc - hx, colc + hx, cc) / (2.0 * hx)
                        if wt > min_weight:
                            images[tid, view.pix_offset + r * cam.ncols + cc] += wt * pl.weight
