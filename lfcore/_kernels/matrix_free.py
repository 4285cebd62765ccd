"""Kernels of the matrix-free DRT operator (:mod:`lfcore.matrix_free`).

A template is the DRT image of one camera-frame point, kept as the spots the dense ray tracing
makes (:func:`lfcore._kernels.weights.drt_weights`, sharing its footprint arithmetic:
:func:`~lfcore._kernels.weights.footprint`, :func:`~lfcore._kernels.weights.inside_cell`,
:func:`~lfcore._kernels.weights.part_spot`) before they are cut into pixels: a spot is the part
of one sub-aperture's footprint that enters one lenslet, landing on the sensor as a box of
half-sizes (hx, hy) pixels around a sensor point, with a share of the voxel's light.

A voxel whose footprint centre on the MLA sits at g = g_b + L + delta (g_b the centre of the
phase bin nearest it, L a lattice vector, delta within half a bin) lands where the template of
point g_b lands, shifted on the sensor by (1 + f_ml / si) L + (f_ml / si) delta: the lenslets
move with L, and within a lenslet a footprint moving by delta lands f_ml / si delta further.
That is exact for a rigid spot (its footprint inside one lenslet over the whole bin); a cut
spot (its footprint meets a lenslet edge somewhere in the bin) is also moved and resized
linearly in delta and its share taken bilinearly from probes around the bin centre. The spots
are then cut into the pixels they cover, exactly as the stored weights are (pixel overlap of
the box, clipped at the sensor's edges, entries at or below ``min_weight`` dropped).
"""

from __future__ import annotations

import warp as wp

from lfcore._kernels.mart import multiplied
from lfcore._kernels.optics import HEX_ROW, CameraParams, lenslet_centre
from lfcore._kernels.weights import (
    Footprint,
    Grid,
    Overlap,
    View,
    cell_overlap,
    footprint,
    from_lattice,
    inside_cell,
    keep_light,
    lattice_box,
    part_spot,
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

    depth_axis: int  # grid axis (0 x, 1 y, 2 z) along which the camera's depth changes; -1: none (sampled depths)
    n_depth: int
    depth_base: int  # this view's first entry of the per-depth tables (first template, phase bins)
    k_spot: float  # f_ml / si
    z_first: float  # depth_axis -1: the camera depth (mm) of the first sampled depth
    inv_dz: float  # and one over the samples' spacing (1/mm)


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


#: Least half-size of a cut spot, pixels.
MIN_HALF = wp.constant(1.0e-3)


@wp.struct
class RigidSpot:
    """A spot of a footprint inside one lenslet over the whole phase bin: it moves rigidly."""

    geo: wp.vec4  # (column, row, hx, hy) pixels
    density: float  # its share of the light per pixel area


#: Fixed-point vectors of the cut spots' probe shares (conversions inline on every device).
vec4us = wp.types.vector(length=4, dtype=wp.uint16)
#: Step of the fixed-point shares (over the part's peak).
SHARE_STEP = wp.constant(1.0 / 65535.0)


@wp.func
def to_fraction(v: wp.vec4) -> vec4us:
    """Fractions 0..1 in steps of :data:`SHARE_STEP`."""
    q = wp.min(wp.max(v / SHARE_STEP, wp.vec4(0.0)), wp.vec4(65535.0)) + wp.vec4(0.5)
    return vec4us(wp.uint16(int(q[0])), wp.uint16(int(q[1])), wp.uint16(int(q[2])), wp.uint16(int(q[3])))


@wp.struct
class CutSpot:
    """The part of a footprint that meets a lenslet edge somewhere in the phase bin and enters one
    lenslet. Its geometry's changes in the phase are float32 (decoding 16-bit steps for every voxel
    took about a tenth of the operator's time on the CPU); its probe shares are fixed point
    (steps of 1.5e-5 of the part's most light)."""

    geo: wp.vec4  # (column, row, hx, hy) pixels at the bin centre
    share: float  # share of the light at the bin centre
    peak: float  # the most of the centre's and the probes' shares
    d0: wp.vec4  # the geometry's change per bin along lattice axis 0, less the rigid shift (pixels)
    d1: wp.vec4  # and along axis 1
    axes: vec4us  # the share at half a bin up and down lattice axis 0, then axis 1, over peak (SHARE_STEP)
    diag: vec4us  # the share at the bin's corners (+0 +1, -0 +1, +0 -1, -0 -1), over peak


@wp.struct
class Tables:
    """The templates of all views (see :class:`lfcore.matrix_free.DrtTemplates`)."""

    depth_first: wp.array(dtype=wp.int32)  # per depth plane of every view: its first template
    depth_phase: wp.array(dtype=wp.int32)  # and its phase bins per lattice axis
    rigid_offsets: wp.array(dtype=wp.int32)  # per template: its range of rigid spots
    rigid: wp.array(dtype=RigidSpot)
    cut_offsets: wp.array(dtype=wp.int32)  # per template: its range of cut spots
    cut: wp.array(dtype=CutSpot)


@wp.struct
class Placement:
    tmpl: int  # global template index; -1 if the view cannot see the voxel
    shift: wp.vec2  # sensor-plane shift of the template's spots, mm
    phase: wp.vec2  # the voxel's phase from the bin centre, in bins (each within -1/2 .. 1/2)


@wp.func
def place(grid: Grid, view: View, plan: Plan, depth_first: wp.array(dtype=wp.int32),
          depth_phase: wp.array(dtype=wp.int32), v: int) -> Placement:
    """The template of the phase bin nearest voxel v's phase in one view, the shift of its spots
    and the voxel's phase from the bin's centre (see the module docstring)."""
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
    d = iz + grid.z0  # the box's plane (the templates are the box's)
    if plan.depth_axis == 0:
        d = ix
    elif plan.depth_axis == 1:
        d = iy
    elif plan.depth_axis < 0:  # a camera off the grid axes: the sampled depth nearest the voxel's own
        d = wp.clamp(int(wp.floor((p[2] - plan.z_first) * plan.inv_dz + 0.5)), 0, plan.n_depth - 1)
    lat = cam.si / sop
    # footprint centre on the MLA (a = 0 part), in the lattice frame relative to the MLA's offset
    gx = -p[0] * lat - cam.off_x
    gy = -p[1] * lat - cam.off_y
    u = cam.cos_t * gx + cam.sin_t * gy
    w = -cam.sin_t * gx + cam.cos_t * gy
    f = lattice_basis_inv(cam.hex, cam.pitch, wp.vec2(u, w))
    n_phase = depth_phase[plan.depth_base + d]
    nph = float(n_phase)
    # bin centres sit at (b + 1/2) / n_phase: the nearest along each axis, and the phase from it
    t0 = f[0] * nph - 0.5
    t1 = f[1] * nph - 0.5
    c0 = wp.floor(t0 + 0.5)
    c1 = wp.floor(t1 + 0.5)
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
    out.phase = wp.vec2(t0 - c0, t1 - c1)
    return out


@wp.struct
class Part:
    geo: wp.vec4  # column and row of the spot's centre, half-sizes hx, hy (pixels)
    share: float  # its share of the voxel's light (0: the footprint misses the lenslet)


@wp.func
def spot_part(view: View, c: wp.vec2, fp: Footprint, dx: float, dy: float, ax: float, ay: float, wk: float) -> Part:
    """The spot of the part of footprint ``fp`` moved by (dx, dy) mm on the MLA that enters the
    lenslet centred at c (sub-aperture point (ax, ay) of weight wk), as drt_weights makes it."""
    out = Part()
    ov = cell_overlap(view, c[0], c[1], fp.qx - fp.fx + dx, fp.qx + fp.fx + dx, fp.qy - fp.fy + dy,
                      fp.qy + fp.fy + dy)
    if ov.area <= 0.0:
        return out
    out.geo = part_spot(view, c, ov, ax, ay, fp)
    out.share = wk * ov.area / (4.0 * fp.fx * fp.fy)
    return out


@wp.func
def per_bin(m: Part, plus: Part, minus: Part, rigid: wp.vec4) -> wp.vec4:
    """Change per bin of a cut spot's geometry along one lattice axis, less the rigid shift
    (``rigid``: a half bin's move of a spot inside one lenslet), from probes half a bin either
    side: the secant where the part is there at both, else one-sided from the centre."""
    gp = plus.geo - rigid
    gm = minus.geo + rigid
    if plus.share > 0.0 and minus.share > 0.0:
        return gp - gm
    if plus.share > 0.0:
        return 2.0 * (gp - m.geo)
    if minus.share > 0.0:
        return 2.0 * (m.geo - gm)
    return wp.vec4(0.0, 0.0, 0.0, 0.0)


@wp.kernel
def template_spots(
    views: wp.array(dtype=View),
    sub_a: wp.array(dtype=wp.vec2),
    sub_w: wp.array(dtype=float),
    t_view: wp.array(dtype=wp.int32),
    t_point: wp.array(dtype=wp.vec3),
    t_probe: wp.array(dtype=wp.vec4),
    fill: int,
    rigid_offsets: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    rigid_counts: wp.array(dtype=wp.int32),
    cut_counts: wp.array(dtype=wp.int32),
    tables: Tables,
):
    """The spots of template ``tid``: view ``t_view[tid]`` seeing camera-frame point ``t_point[tid]``,
    whose footprint centre on the MLA moves by ``(t_probe[tid][0], t_probe[tid][1])`` mm per half
    bin along lattice axis 0 and by ``(t_probe[tid][2], t_probe[tid][3])`` along axis 1.

    The body is :func:`lfcore._kernels.weights.drt_weights`'s for one view, stopping where that
    kernel cuts a spot into pixels. A sub-aperture's footprint that stays inside one lenslet over
    the whole bin gives one rigid spot (it moves with the template's shift alone); one that meets
    a lenslet edge gives a cut spot per lenslet it meets, with its change per bin along each
    lattice axis (from probes half a bin either side). ``fill = 0`` counts the spots into
    ``rigid_counts`` and ``cut_counts``; ``fill = 1`` writes them to ``tables`` from
    ``rigid_offsets[tid]`` and ``cut_offsets[tid]`` (the tables' own offsets, given apart so that
    a CPU block sees its templates' rows).
    """
    tid = wp.tid()
    view = views[t_view[tid]]
    cam = view.cam
    p = t_point[tid]
    probe = t_probe[tid]
    d0 = wp.vec2(probe[0], probe[1])
    d1 = wp.vec2(probe[2], probe[3])
    reach_x = wp.abs(d0[0]) + wp.abs(d1[0])
    reach_y = wp.abs(d0[1]) + wp.abs(d1[1])
    nr = int(0)
    nc = int(0)
    rbase = int(0)
    cbase = int(0)
    if fill == 1:
        rbase = rigid_offsets[tid]
        cbase = cut_offsets[tid]
    sop = cam.so - p[2]
    if sop * cam.inv_f > 1.0:
        inv = 1.0 / sop
        a = 1.0 - cam.si * (cam.inv_f - inv)
        gx = -p[0] * cam.si * inv
        gy = -p[1] * cam.si * inv
        dq = cam.si * inv * inv * view.half[2]
        lat = cam.si * inv
        k_spot = cam.f_ml / cam.si
        # a half bin's rigid move of a spot on the sensor, in pixels (columns run against x)
        r0 = wp.vec4(-k_spot * d0[0] / cam.pixel, k_spot * d0[1] / cam.pixel, 0.0, 0.0)
        r1 = wp.vec4(-k_spot * d1[0] / cam.pixel, k_spot * d1[1] / cam.pixel, 0.0, 0.0)
        for k in range(view.sub_first, view.sub_first + view.sub_count):
            ax = sub_a[k][0]
            ay = sub_a[k][1]
            wk = sub_w[k]
            fp = footprint(view, p, a, gx, gy, lat, dq, ax, ay)
            home = lenslet_centre(cam, fp.qx, fp.qy)
            # inside its lenslet wherever the voxel's phase is in the bin: one rigid spot
            if inside_cell(view, fp.qx, fp.qy, home, fp.fx + reach_x, fp.fy + reach_y) == 1:
                if fill == 1:
                    whole = Overlap()
                    whole.area = 4.0 * fp.fx * fp.fy
                    whole.cx = fp.qx
                    whole.cy = fp.qy
                    whole.wx = 2.0 * fp.fx
                    whole.wy = 2.0 * fp.fy
                    rs = RigidSpot()
                    rs.geo = part_spot(view, home, whole, ax, ay, fp)
                    # the share per pixel area of the spot: a pixel's weight is this times its overlap
                    rs.density = wk / (4.0 * rs.geo[2] * rs.geo[3])
                    tables.rigid[rbase + nr] = rs
                nr += 1
                continue
            # every lenslet the footprint meets anywhere in the bin (the box it sweeps)
            sx0 = fp.qx - fp.fx - reach_x
            sx1 = fp.qx + fp.fx + reach_x
            sy0 = fp.qy - fp.fy - reach_y
            sy1 = fp.qy + fp.fy + reach_y
            box = lattice_box(cam, sx0, sx1, sy0, sy1, view.cell_r)
            h = row_step(cam)
            j0 = int(wp.ceil(box[2] / h))
            j1 = int(wp.floor(box[3] / h))
            for j in range(j0, j1 + 1):
                shift = row_shift(cam, j)
                i0 = int(wp.ceil((box[0] - shift) / cam.pitch))
                i1 = int(wp.floor((box[1] - shift) / cam.pitch))
                for i in range(i0, i1 + 1):
                    c = from_lattice(cam, float(i) * cam.pitch + shift, float(j) * h)
                    # a lenslet the swept box meets gets a spot (the count needs no probes; one that
                    # no probe's footprint meets is kept with no light)
                    if cell_overlap(view, c[0], c[1], sx0, sx1, sy0, sy1).area <= 0.0:
                        continue
                    if fill == 1:
                        dp = d0 + d1
                        dm = d1 - d0
                        m = spot_part(view, c, fp, 0.0, 0.0, ax, ay, wk)
                        p0 = spot_part(view, c, fp, d0[0], d0[1], ax, ay, wk)
                        m0 = spot_part(view, c, fp, -d0[0], -d0[1], ax, ay, wk)
                        p1 = spot_part(view, c, fp, d1[0], d1[1], ax, ay, wk)
                        m1 = spot_part(view, c, fp, -d1[0], -d1[1], ax, ay, wk)
                        pp = spot_part(view, c, fp, dp[0], dp[1], ax, ay, wk)
                        mp = spot_part(view, c, fp, dm[0], dm[1], ax, ay, wk)
                        pm = spot_part(view, c, fp, -dm[0], -dm[1], ax, ay, wk)
                        mm = spot_part(view, c, fp, -dp[0], -dp[1], ax, ay, wk)
                        cs = CutSpot()
                        centre = m.geo
                        if m.share <= 0.0:
                            # a part only the moved footprint reaches: its geometry where it is there
                            # (less that probe's rigid move), unchanged over the bin
                            if p0.share > 0.0:
                                centre = p0.geo - r0
                            elif m0.share > 0.0:
                                centre = m0.geo + r0
                            elif p1.share > 0.0:
                                centre = p1.geo - r1
                            elif m1.share > 0.0:
                                centre = m1.geo + r1
                            elif pp.share > 0.0:
                                centre = pp.geo - r0 - r1
                            elif mp.share > 0.0:
                                centre = mp.geo + r0 - r1
                            elif pm.share > 0.0:
                                centre = pm.geo - r0 + r1
                            else:
                                centre = mm.geo + r0 + r1
                        else:
                            cs.d0 = per_bin(m, p0, m0, r0)
                            cs.d1 = per_bin(m, p1, m1, r1)
                        cs.geo = centre
                        # the share at the centre and at the eight probes around it
                        axes = wp.vec4(p0.share, m0.share, p1.share, m1.share)
                        diag = wp.vec4(pp.share, mp.share, pm.share, mm.share)
                        peak = wp.max(m.share, wp.max(wp.max(wp.max(axes[0], axes[1]), wp.max(axes[2], axes[3])),
                                                      wp.max(wp.max(diag[0], diag[1]), wp.max(diag[2], diag[3]))))
                        if peak > 0.0:
                            cs.share = m.share
                            cs.peak = peak
                            cs.axes = to_fraction(axes / peak)
                            cs.diag = to_fraction(diag / peak)
                        tables.cut[cbase + nc] = cs
                    nc += 1
    rigid_counts[tid] = nr
    cut_counts[tid] = nc


@wp.func
def entry(mode: int, pix: wp.array(dtype=wp.int32), w: wp.array(dtype=float), k: wp.int64, end: wp.int64, q: int,
          wt: float, min_weight: float) -> wp.int64:
    """A voxel's weight wt on pixel q, where wt passes ``min_weight``; the next k. ``mode`` 2:
    entry k (pixel, weight), written if k is before ``end``. ``mode`` 3, merged in place: ``w``
    is a dense image that gathers the voxel's weight per pixel (zero where the voxel has none
    yet), and ``pix[k]`` lists each pixel it lights once, in the order they are first met."""
    if wt <= min_weight:
        return k
    if mode == 3:
        n = k
        if w[q] == 0.0:
            pix[k] = q
            n = k + wp.int64(1)
        w[q] = w[q] + wt
        return n
    if k < end:
        pix[k] = q
        w[k] = wt
    return k + wp.int64(1)


@wp.func
def cut_spot(mode: int, cam: CameraParams, base: int, colc: float, rowc: float, hx: float, hy: float, wk: float,
             min_weight: float, ej: float, values: wp.array(dtype=float), pix: wp.array(dtype=wp.int32),
             at: wp.int64, end: wp.int64) -> float:
    """One spot (centre column, row, half-sizes in pixels; ``wk`` its share per pixel area) cut
    into the pixels of a camera as the stored weights are: ``mode`` 0 adds w ``ej`` to
    ``values[pixel]``, 1 returns sum w ``values[pixel]``, 2 writes its entries (pixel, w) to
    ``pix[k]``, ``values[k]`` from k = ``at`` on, those before ``end``, and returns how many it
    has (a float, exact below 2**24), 3 merges them into the dense ``values`` and returns how
    many pixels it lit first (see :func:`entry`)."""
    ncols = cam.ncols
    nrows = cam.nrows
    total = float(0.0)
    lo_c = colc - hx
    hi_c = colc + hx
    lo_r = rowc - hy
    hi_r = rowc + hy
    # int() truncates where floor would round down, but only below 0, where the range is
    # clamped to 0 anyway (or, wholly left of the sensor, meets pixel 0 with no overlap)
    c0 = int(lo_c)
    r0 = int(lo_r)
    if (lo_c >= 0.0 and lo_r >= 0.0 and hi_c < float(c0 + 2) and hi_r < float(r0 + 2) and c0 < ncols - 1
            and r0 < nrows - 1):
        # within 2 x 2 pixels of the sensor (nearly every spot: they are about a pixel wide):
        # their four weights without loops, a pixel the spot misses getting weight 0
        fc = float(c0 + 1)
        fr = float(r0 + 1)
        ox0 = wp.min(fc, hi_c) - lo_c
        ox1 = wp.max(hi_c - fc, 0.0)
        oy0 = wk * (wp.min(fr, hi_r) - lo_r)
        oy1 = wk * wp.max(hi_r - fr, 0.0)
        w00 = oy0 * ox0
        w01 = oy0 * ox1
        w10 = oy1 * ox0
        w11 = oy1 * ox1
        q = base + r0 * ncols + c0
        if mode == 1:
            total = (wp.where(w00 > min_weight, w00 * values[q], 0.0)
                     + wp.where(w01 > min_weight, w01 * values[q + 1], 0.0)
                     + wp.where(w10 > min_weight, w10 * values[q + ncols], 0.0)
                     + wp.where(w11 > min_weight, w11 * values[q + ncols + 1], 0.0))
        elif mode == 0:
            # all four, those at or below min_weight as 0 (no branches to mispredict)
            wp.atomic_add(values, q, wp.where(w00 > min_weight, w00 * ej, 0.0))
            wp.atomic_add(values, q + 1, wp.where(w01 > min_weight, w01 * ej, 0.0))
            wp.atomic_add(values, q + ncols, wp.where(w10 > min_weight, w10 * ej, 0.0))
            wp.atomic_add(values, q + ncols + 1, wp.where(w11 > min_weight, w11 * ej, 0.0))
        else:
            k = at
            k = entry(mode, pix, values, k, end, q, w00, min_weight)
            k = entry(mode, pix, values, k, end, q + 1, w01, min_weight)
            k = entry(mode, pix, values, k, end, q + ncols, w10, min_weight)
            k = entry(mode, pix, values, k, end, q + ncols + 1, w11, min_weight)
            total = float(k - at)
        return total
    c0 = wp.max(0, c0)
    c1 = wp.min(ncols - 1, int(hi_c))
    r0 = wp.max(0, r0)
    r1 = wp.min(nrows - 1, int(hi_r))
    k = at
    for r in range(r0, r1 + 1):
        oy = wk * pixel_overlap(lo_r, hi_r, r)
        q = base + r * ncols
        for cc in range(c0, c1 + 1):
            wt = oy * pixel_overlap(lo_c, hi_c, cc)
            if wt > min_weight:
                if mode == 0:
                    wp.atomic_add(values, q + cc, wt * ej)
                elif mode == 1:
                    total += wt * values[q + cc]
                else:
                    k = entry(mode, pix, values, k, end, q + cc, wt, min_weight)
    if mode >= 2:
        total = float(k - at)
    return total


@wp.func
def apply_templates(
    mode: int,
    grid: Grid,
    view: View,
    plan: Plan,
    tables: Tables,
    min_weight: float,
    v: int,
    ej: float,
    values: wp.array(dtype=float),
    pix: wp.array(dtype=wp.int32),
    at: wp.int64,
    end: wp.int64,
) -> float:
    """Voxel v's pixels in one view, from the template of its nearest phase bin: ``mode`` 0 adds
    w ``ej`` to ``values[pixel]`` (projection), 1 returns sum w ``values[pixel]`` (the update's
    gather), 2 writes its entries (pixel, w) to ``pix[k]``, ``values[k]`` from k = ``at`` on,
    those before ``end``, and returns how many it has, 3 merges them per pixel (see
    :func:`cut_spot`).

    Each spot is shifted by the template's placement (a cut spot also moved, resized and
    reweighted linearly in the voxel's phase within the bin) and cut into pixels as the stored
    weights are (box overlap, clipped at the sensor, entries at or below ``min_weight`` dropped).
    """
    cam = view.cam
    total = float(0.0)
    pl = place(grid, view, plan, tables.depth_first, tables.depth_phase, v)
    if pl.tmpl < 0:
        return total
    inv_pix = 1.0 / cam.pixel
    base = view.pix_offset
    k = at  # modes 2 and 3: where the next entry goes
    move = wp.vec4(-pl.shift[0] * inv_pix, pl.shift[1] * inv_pix, 0.0, 0.0)  # columns run against x, rows with y
    for t in range(tables.rigid_offsets[pl.tmpl], tables.rigid_offsets[pl.tmpl + 1]):
        rs = tables.rigid[t]
        st = rs.geo + move
        total += cut_spot(mode, cam, base, st[0], st[1], st[2], st[3], rs.density, min_weight, ej, values, pix, k,
                          end)
        if mode >= 2:
            k = at + wp.int64(int(total))
    u0 = pl.phase[0]
    u1 = pl.phase[1]
    # the share is bilinear in the quadrant of the probes the phase is in (never below 0, and over
    # a sub-aperture's parts its sum, the sub-aperture's light, is whole at every phase): the
    # quadrant's probes and the four bilinear weights, once per voxel
    ia = wp.where(u0 > 0.0, 0, 1)
    ib = wp.where(u1 > 0.0, 2, 3)
    iab = wp.where(u1 > 0.0, 0, 2) + wp.where(u0 > 0.0, 0, 1)
    a = wp.min(2.0 * wp.abs(u0), 1.0)
    b = wp.min(2.0 * wp.abs(u1), 1.0)
    c00 = (1.0 - a) * (1.0 - b)
    ca = a * (1.0 - b) * SHARE_STEP
    cb = (1.0 - a) * b * SHARE_STEP
    cab = a * b * SHARE_STEP
    g0 = u0
    g1 = u1
    for t in range(tables.cut_offsets[pl.tmpl], tables.cut_offsets[pl.tmpl + 1]):
        cs = tables.cut[t]
        s = c00 * cs.share + cs.peak * (ca * float(cs.axes[ia]) + cb * float(cs.axes[ib]) + cab * float(cs.diag[iab]))
        # a pixel's weight is at most the spot's share: at or below min_weight, every one is dropped
        if s <= min_weight:
            continue
        st = cs.geo + g0 * cs.d0 + g1 * cs.d1 + move
        # a part that (extrapolated) shrinks to nothing still lands its share
        hx = wp.max(st[2], MIN_HALF)
        hy = wp.max(st[3], MIN_HALF)
        total += cut_spot(mode, cam, base, st[0], st[1], hx, hy, s / (4.0 * hx * hy), min_weight, ej, values, pix, k,
                          end)
        if mode >= 2:
            k = at + wp.int64(int(total))
    return total


@wp.kernel
def template_key(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    tables: Tables,
    voxels: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
):
    """key[tid]: the template voxel ``voxels[tid]`` takes in the first view (-1 where that view
    cannot see it), the order in which the operator's launches visit the voxels: voxels of one
    template one after another, so that its spots are read from the cache."""
    tid = wp.tid()
    key[tid] = place(grid, views[0], plans[0], tables.depth_first, tables.depth_phase, voxels[tid]).tmpl


@wp.kernel
def project(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    tables: Tables,
    n_views: int,
    min_weight: float,
    order: wp.array(dtype=wp.int32),
    voxels: wp.array(dtype=wp.int32),
    e: wp.array(dtype=float),
    proj: wp.array(dtype=float),
    none: wp.array(dtype=wp.int32),
):
    """proj[pixel] += w E of voxel ``voxels[order[tid]]``, every view (see :func:`apply_templates`;
    ``order`` a permutation of the voxels, see :func:`template_key`; ``none`` is unused)."""
    k = order[wp.tid()]
    ej = e[k]
    if ej == 0.0:
        return
    for iv in range(n_views):
        apply_templates(0, grid, views[iv], plans[iv], tables, min_weight, voxels[k], ej, proj, none, wp.int64(0),
                        wp.int64(0))


@wp.kernel
def smart_update(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    tables: Tables,
    n_views: int,
    min_weight: float,
    order: wp.array(dtype=wp.int32),
    voxels: wp.array(dtype=wp.int32),
    ratio: wp.array(dtype=float),
    relaxation: float,
    e: wp.array(dtype=float),
    none: wp.array(dtype=wp.int32),
):
    """E_v <- E_v exp(mu sum_i w_iv ratio_i), a gather per voxel ``voxels[order[tid]]`` (see
    :func:`lfcore._kernels.mart.smart_update`; ``none`` is unused)."""
    k = order[wp.tid()]
    ej = e[k]
    if ej == 0.0:
        return
    s = float(0.0)
    for iv in range(n_views):
        s += apply_templates(1, grid, views[iv], plans[iv], tables,
                             min_weight, voxels[k], ej, ratio, none, wp.int64(0), wp.int64(0))
    e[k] = multiplied(ej, s, relaxation)


@wp.kernel
def template_entries(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    tables: Tables,
    n_views: int,
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int64),
    origin: wp.int64,
    fill: int,
    limit: wp.int64,
    counts: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
):
    """The raw entries (pixel, weight) of voxel ``voxels[tid]`` from its templates, every view:
    :func:`lfcore._kernels.weights.drt_weights`' interface (its entries unmerged, in the same
    units), so that the stored weights' build merges and packs them.

    With ``fill = 1`` the first ``limit`` entries go to ``pix``/``w`` from ``offsets[tid] -
    origin``. ``counts[tid]`` gets the voxel's number of entries in both modes.
    """
    tid = wp.tid()
    at = wp.int64(0)
    end = wp.int64(0)
    if fill == 1:
        at = offsets[tid] - origin
        end = at + limit
    n = wp.int64(0)
    for iv in range(n_views):
        got = apply_templates(2, grid, views[iv], plans[iv], tables, min_weight, voxels[tid], 1.0, w, pix, at + n,
                              end)
        n += wp.int64(int(got))
    counts[tid] = n


@wp.func
def sift_down(a: wp.array(dtype=wp.int32), root: int, end: int):
    """Move ``a[root]`` down the max-heap ``a[0 .. end - 1]`` to its place."""
    r = root
    while 2 * r + 1 < end:
        c = 2 * r + 1
        if c + 1 < end and a[c + 1] > a[c]:
            c += 1
        if a[r] >= a[c]:
            return
        t = a[r]
        a[r] = a[c]
        a[c] = t
        r = c


@wp.func
def heap_sort(a: wp.array(dtype=wp.int32), n: int):
    """Sort ``a[0 .. n - 1]`` ascending in place (heap sort: no scratch, n log n)."""
    for k in range(n // 2):
        sift_down(a, n // 2 - 1 - k, n)
    for k in range(n - 1):
        last = n - 1 - k
        t = a[0]
        a[0] = a[last]
        a[last] = t
        sift_down(a, 0, last)


@wp.kernel
def template_merged(
    grid: Grid,
    views: wp.array(dtype=View),
    plans: wp.array(dtype=Plan),
    tables: Tables,
    n_views: int,
    min_weight: float,
    voxels: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int64),
    fill: int,
    counts: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    dense: wp.array(dtype=float),
    touched: wp.array(dtype=wp.int32),
    floor: float,
):
    """The merged weights of voxel ``voxels[tid]`` from its templates, every view, one entry per
    pixel: ``counts[tid]`` gets their number, and with ``fill = 1`` they go to ``pix``/``w`` from
    ``offsets[tid]``, sorted by pixel as the stored build sorts its own (the iterations' scattered
    reads and writes then walk the image in order). Merged entries at or below ``floor`` are
    dropped and the voxel's others scaled to keep its light (as
    :func:`lfcore._kernels.weights.sort_merge` does).

    A CPU block's threads run one after another, so each block gathers its voxels' weights in its
    own dense image ``dense`` (all pixels, zero between voxels) and lists the pixels met in
    ``touched`` (as long as the image): a merge without a sort (CPU only).
    """
    tid = wp.tid()
    n = wp.int64(0)
    cap = wp.int64(touched.shape[0])
    for iv in range(n_views):
        got = apply_templates(3, grid, views[iv], plans[iv], tables, min_weight, voxels[tid], 1.0, dense, touched, n,
                              cap)
        n += wp.int64(int(got))
    base = wp.int64(0)
    if fill == 1:
        base = offsets[tid]
        heap_sort(touched, int(n))
    m = wp.int64(0)
    total = float(0.0)
    for j in range(int(n)):
        q = touched[j]
        v = dense[q]
        total += v
        if v > floor:
            if fill == 1:
                pix[base + m] = q
                w[base + m] = v
            m += wp.int64(1)
        dense[q] = 0.0
    counts[tid] = m
    if fill == 1 and floor > 0.0:
        keep_light(w, base, m, total)
