"""The matrix-free DRT operator: templates per depth and lenslet phase instead of per-voxel weights.

An unfocused plenoptic camera's light field repeats with its lenslet lattice. In one depth
plane of the camera, every sub-aperture's footprint on the MLA of a voxel at lateral position
p sits at ``a A + g`` with ``g = -p si / (so - z)``: the whole pattern moves rigidly with g.
Moving g by a lattice vector L moves every lenslet it meets by L and every spot on the sensor by
``(1 + f_ml / si) L`` (the micro-image pitch). Within one lenslet period, a small move delta of
g moves the spots by ``(f_ml / si) delta`` as long as the lenslets met do not change.

So per camera and depth plane, the voxel images are a small set of templates: one per phase
bin of g within the lattice cell (``n`` per lattice axis, more near focus where footprints are
small: :data:`PHASES_PER_FOOTPRINT`), each the spots that the dense ray tracing of
:func:`lfcore._kernels.weights.drt_weights` makes for one point (the same arithmetic, stopped
before the spots are cut into pixels). A voxel takes the template of the bin nearest its
phase, shifts its spots by ``(1 + f_ml / si) L + (f_ml / si) delta`` and cuts them into pixels
exactly as the stored weights are cut. A template's spots are of two kinds:

- rigid: the sub-aperture's footprint stays inside one lenslet wherever the phase is in the
  bin; the spot only moves, and the shift is exact;
- cut: the footprint meets a lenslet edge somewhere in the bin, one spot per lenslet it meets.
  Such a part's geometry (centre, half-sizes) is moved on by its change per bin along each
  lattice axis (secants of probes half a bin either side), and its share of the light is
  interpolated bilinearly in the voxel's quadrant of the bin from its shares at the centre and
  at the 8 probes around it: never below 0, and over a sub-aperture's parts the shares sum to
  its whole light at every phase (the probes' do), so the voxel's light is kept.

What this handles exactly and what it bounds:

- drift of micro-images against the pixel grid and non-integer voxels per lenslet period:
  exact, since spots are shifted in millimetres and cut into pixels afterwards;
- rotated and offset (fitted) MLAs: exact, the phase is taken in the MLA's own lattice frame;
- the phase within a bin: exact for rigid spots; for cut ones, the parts' shares are exact
  where a footprint crosses one edge of a square or hexagonal cell (the overlap is linear in
  the move there) or two edges of a square one (bilinear), and their geometry to first order:
  the error that :func:`fidelity` measures against the stored weights (the reference):
  correlation >= 0.9995 and total light within 4e-5 on the tests' rigs, 0.9995 and 0.02% on S,
  0.9995 and 0.06% on Mc (200 active voxels each);
- vignetting at the sensor's edges: spots are clipped where the voxel's land;
- the depth extent's blur, which grows with the distance of a sub-aperture from the voxel's
  own lateral position (``|A - p| dq`` in the tracing), is taken at the template's point, near
  the optical axis: off by ``|p| dq`` at lateral position p, bounded relative to a
  footprint's lateral blur by :attr:`DrtTemplates.blur_error` (3% on S, 6% on Mc; no change in
  the fidelity figures was measurable when it was taken at the voxel's own p).

A camera looking along a grid axis has one template depth per grid plane (a voxel's depth is its
plane's). A camera off the grid axes (a fitted pose a fraction of a degree off, or a tilted one)
has :data:`DEPTH_SAMPLES_PER_VOXEL` evenly spaced template depths per voxel depth extent over the
box, and a voxel takes the nearest to its own camera depth: off by at most a twelfth of its
extent, which the fidelity figures bound (correlation >= 0.9993, light within 0.07% at tilts of
0.4 to 20 degrees on the tiny rig's optics). Pinhole cameras have no lenslets and need the stored
weights (:class:`MatrixFreeUnsupported`).

Memory: :data:`RIGID_SPOT_BYTES` per rigid spot and :data:`CUT_SPOT_BYTES` per cut one (seven
in eight on S, four in five on Mc) plus two offsets per template: set by the cameras, depth
planes and sub-apertures, not by the voxels (51 MiB for S, 449 MiB for Mc against its stored
weights' 1618 MiB), plus 8 bytes per reconstructed voxel (its index and its place in the order
the launches visit the voxels: those of one template together, so that its spots are read from
the cache). The work per voxel is one template's spots (about 190 on S, 330 on Mc), each cut
into (mostly) 2 x 2 pixels, where a stored voxel reads its merged weights (about 195 on S): on
a CPU it is still slower per iteration than stored weights (S 78-156 ms against 7-16 ms, 8-11x
as the shared machine's load goes; Mc 2.6-2.7 s against 0.33-0.37 s, 7.0-8.2x), 11-19% faster than with
16-bit spot changes and the voxels in their own order (run back to back; 27x and 13x with three
templates a voxel), and it is what is left where those do not fit. Where the memory allows,
:meth:`TemplateOperator.expanded` stores the templates' images of a frame's voxels once instead
(no ray tracing; merged per pixel, those at or below :data:`IMAGE_FLOOR` dropped with each voxel's
light kept), and the iterations run at the stored weights' speed (S 0.96x in one run, Mc 1.03x
in alternating rounds with 4% more entries before the floor).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from lfcore._deprecation import deprecated, keyword_options, moved_names
from lfcore.device import PerBlock, PrivateCopies, Rows, available_bytes, cpu_threads, launch_rows, warp
from lfcore.mla import HEX_ROW
from lfcore.operator import (
    PROJECTORS,
    TEMPLATE_IMAGES,
    TEMPLATES,
    MatrixFreeUnsupported,
    applied_by,
    gather,
    scatter_voxels,
)
from lfcore.projector import LightFieldProjector
from lfcore.weight_build import BYTES_PER_WEIGHT, CHUNK_ENTRIES, MemoryBudgetError, WeightChunk, Weights

__all__ = ["CUT_SPOT_BYTES", "IMAGE_FLOOR", "MAX_PHASES", "MIN_PHASES", "PHASES_PER_FOOTPRINT", "PROJECTORS",
           "RIGID_SPOT_BYTES", "DrtTemplates", "MatrixFreeUnsupported", "TemplateOperator",
           "applied_by", "fidelity",
           "phase_bins", "template_count"]

#: Phase bins per lattice axis of a depth's templates, per lenslet pitch over a sub-aperture's
#: footprint width on the MLA (bins a third of the footprint: correlation >= 0.9995 on the
#: tiny rig's voxels, hexagonal and square; at a half, 0.9989 on the hexagonal).
PHASES_PER_FOOTPRINT = 3.0
#: Fewest and most phase bins per lattice axis of a depth.
MIN_PHASES = 4
MAX_PHASES = 32
#: Bytes per rigid template spot: (column, row, hx, hy) float32 and its share per pixel area.
RIGID_SPOT_BYTES = 20
#: Bytes per cut template spot: (column, row, hx, hy) float32 at the bin centre, its share there
#: and the most of its shares (float32), the geometry's change per bin along each lattice axis
#: (float32) and its shares at the 8 probes around the centre (uint16 fractions of the most).
CUT_SPOT_BYTES = 72
#: The templates' images stored (:meth:`TemplateOperator.expanded`) drop their merged entries at
#: or below this and scale each voxel's others to keep its light: the faint fringe that the cut
#: spots' first-order geometry adds (on the Mc crop 4.5% of the images' entries and 0.014% of their
#: light; per voxel at most 0.12%), so that they have no more entries than the ray-traced weights
#: (210.1 M against 211.4 M there; 220.1 M unpruned), whose pass costs the same per entry.
IMAGE_FLOOR = 1.5e-5


#: Templates per voxel depth extent along the optical axis of a camera that does not look along a
#: grid axis (a fitted pose, a tilted camera): a voxel takes the template of the sampled depth
#: nearest its own, off by at most a twelfth of its depth extent. On the tiny rig's optics tilted
#: 3 and 2 degrees and rolled 10 (a voxel's depth there moving by about half its extent across the
#: box), hexagonal, the worst of 400 voxels' correlation with the ray-traced weights was 0.9989 at
#: 4 samples, 0.9995 at 6 (as a grid-aligned camera's) and 0.9995 at 8; at tilts of 5 to 20
#: degrees, 6 gave at least 0.9993 and light within 0.07% (tested). The templates take as many
#: times the memory of a grid-aligned camera's.
DEPTH_SAMPLES_PER_VOXEL = 6


def _corners(grid) -> np.ndarray:
    """(8, 3) world (x, y, z) mm of the centres of the box's corner voxels."""
    nz, ny, nx = grid.shape
    origin = np.asarray(grid.origin_mm, dtype=np.float64)
    step = np.asarray(grid.voxel_mm, dtype=np.float64)
    return np.array([origin + step * np.array([i * (nx - 1), j * (ny - 1), k * (nz - 1)])
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _depth_samples(cam, grid) -> np.ndarray:
    """Camera depths (mm) at which the templates of a camera off the grid axes are made: from the
    nearest to the farthest voxel centre of the box, :data:`DEPTH_SAMPLES_PER_VOXEL` per voxel depth
    extent along the optical axis, evenly spaced."""
    rot = cam.rotation.T  # world -> camera
    step = np.asarray(grid.voxel_mm, dtype=np.float64)
    z = ((_corners(grid) - np.asarray(cam.focus_mm)) @ rot.T)[:, 2]
    dz = 2.0 * float((np.abs(rot) @ (0.5 * step))[2]) / DEPTH_SAMPLES_PER_VOXEL
    n = int(np.ceil((z.max() - z.min()) / dz)) + 1
    return z.min() + dz * np.arange(n)


def _depth_axis(rot_world_to_cam: np.ndarray) -> tuple[int, int] | None:
    """Grid axis (0 x, 1 y, 2 z) along which the camera's depth changes, with its sign; None if
    the optical axis is not along a grid axis."""
    row = rot_world_to_cam[2]
    axis = int(np.argmax(np.abs(row)))
    others = np.delete(np.abs(row), axis)
    if np.max(others) > 1e-9:
        return None
    return axis, int(np.sign(row[axis]))


def _light_field_alone(projector: LightFieldProjector) -> None:
    """Raise :class:`MatrixFreeUnsupported` unless ``projector`` has light-field cameras alone (the
    pinhole and the joint, mixed-rig, projectors have no lenslets to take templates of)."""
    if getattr(projector, "kind", None) != "light-field":
        raise MatrixFreeUnsupported("the matrix-free projector is for light-field cameras alone; use --projector "
                                    "stored")


def _camera_depths(cam, grid) -> tuple[int, np.ndarray]:
    """The grid axis along which camera ``cam`` looks and the camera depth (mm) of each grid plane
    along it (the voxel centres' camera z); for a camera that looks along no grid axis (a fitted
    pose, a tilt), -1 and the depths of :func:`_depth_samples`, which a voxel picks from by its own
    camera depth."""
    rot = cam.rotation.T  # world -> camera
    found = _depth_axis(rot)
    if found is None:
        return -1, _depth_samples(cam, grid)
    axis = found[0]
    nz, ny, nx = grid.shape
    n_depth = (nx, ny, nz)[axis]
    origin = np.asarray(grid.origin_mm, dtype=np.float64)
    centres = np.zeros((n_depth, 3))
    centres[:] = origin
    centres[:, axis] = origin[axis] + np.asarray(grid.voxel_mm, dtype=np.float64)[axis] * np.arange(n_depth)
    return axis, ((centres - np.asarray(cam.focus_mm)) @ rot.T)[:, 2]


def phase_bins(projector: LightFieldProjector, *, phases_per_footprint: float = PHASES_PER_FOOTPRINT,
               max_phases: int = MAX_PHASES) -> list[np.ndarray]:
    """Phase bins per lattice axis of each depth plane, per camera: enough that a bin is a small
    part of a sub-aperture's footprint on the MLA (its width there: the sub-aperture's blur and
    the voxel's own lateral extent). A depth plane has the square of its count in templates.

    Returns
    -------
    list of numpy.ndarray
        Per camera, (depth planes,) int bins per axis, from :data:`MIN_PHASES` to ``max_phases``.

    Raises
    ------
    MatrixFreeUnsupported
        If the cameras are not light-field ones alone.
    """
    _light_field_alone(projector)
    step = np.asarray(projector.box.voxel_mm, dtype=np.float64)
    out = []
    for cam in projector.cameras:
        _, z_cam = _camera_depths(cam, projector.box)
        so, si = cam.object_distance_mm, cam.image_distance_mm
        n_sub = max(1, round(cam.pixels_per_lenslet)) if projector.sub_apertures is None else projector.sub_apertures
        half = np.abs(cam.rotation.T) @ (0.5 * step)
        sop = so - z_cam
        lat = si / sop
        a = 1.0 - si * (1.0 / cam.main_focal_length_mm - 1.0 / sop)
        width = np.hypot(np.abs(a) * cam.aperture_mm / n_sub, 2.0 * lat * min(half[0], half[1]))
        out.append(np.clip(np.ceil(phases_per_footprint * cam.mla_pitch_mm / width), MIN_PHASES,
                           max_phases).astype(np.int64))
    return out


def template_count(projector: LightFieldProjector, **bins) -> int:
    """Templates the projector's :class:`DrtTemplates` would have (keywords as :func:`phase_bins`),
    without building them."""
    return int(sum(int((b * b).sum()) for b in phase_bins(projector, **bins)))


class DrtTemplates:
    """The templates of a projector's cameras and grid (independent of the voxels reconstructed).

    Parameters
    ----------
    projector
        The projector (its cameras, grid, sub-apertures and device).
    phases_per_footprint
        Phase bins per lattice axis of a depth, per lenslet pitch over a sub-aperture's
        footprint width on the MLA (:data:`PHASES_PER_FOOTPRINT`).
    max_phases
        Most phase bins per lattice axis (at least :data:`MIN_PHASES`).
    budget_bytes
        Most bytes the templates may take; None: no limit beyond the device's.

    Attributes
    ----------
    nbytes
        Device bytes of the templates.
    n_templates, n_spots
        Templates (over cameras and depth planes, the depth's phase bins squared) and their
        spots in all.
    n_rigid, n_cut
        Of those spots, the rigid and the cut ones (see the module docstring).
    tables
        The device tables (:class:`lfcore._kernels.matrix_free.Tables`).
    build_s
        Seconds the build took.
    blur_error
        Largest relative change, over the grid's lateral extent, of a footprint's depth blur
        against the template's (see the module docstring).

    Raises
    ------
    MatrixFreeUnsupported
        If the cameras are not light-field ones alone.
    """

    def __init__(self, projector: LightFieldProjector, *, phases_per_footprint: float = PHASES_PER_FOOTPRINT,
                 max_phases: int = MAX_PHASES, budget_bytes: int | None = None) -> None:
        import time

        from lfcore._kernels import matrix_free as km

        t0 = time.perf_counter()
        _light_field_alone(projector)
        if not phases_per_footprint > 0 or max_phases < MIN_PHASES:
            raise ValueError(f"phases_per_footprint must be positive and max_phases at least {MIN_PHASES}")
        wp = warp()
        self.wp, self._km = wp, km
        self.projector = projector
        self.phases_per_footprint = float(phases_per_footprint)
        self.max_phases = int(max_phases)
        self.device = projector.device
        grid = projector.box  # the whole box's depth planes: a depth slab's projector shares them (on())
        step = np.asarray(grid.voxel_mm, dtype=np.float64)
        plans, t_view, t_point, t_probe, depth_first, depth_phase = [], [], [], [], [], []
        blur = 0.0
        bins = phase_bins(projector, phases_per_footprint=self.phases_per_footprint, max_phases=self.max_phases)
        for iv, cam in enumerate(projector.cameras):
            rot = cam.rotation.T  # world -> camera
            axis, z_cam = _camera_depths(cam, grid)
            n_depth = len(z_cam)
            so, si = cam.object_distance_mm, cam.image_distance_mm
            pitch = cam.mla_pitch_mm
            off = np.asarray(cam.mla_offset_um, dtype=np.float64) * 1e-3
            th = np.radians(cam.mla_rotation_deg)
            c, s = np.cos(th), np.sin(th)
            for d in range(n_depth):
                n_ph = int(bins[iv][d])
                lat = si / (so - z_cam[d])
                fr = (np.arange(n_ph) + 0.5) / n_ph
                f0, f1 = np.meshgrid(fr, fr)  # [b1, b0]
                f0, f1 = f0.ravel(), f1.ravel()
                if cam.mla_grid == "hex":
                    u, v = pitch * (f0 + 0.5 * f1), pitch * HEX_ROW * f1
                else:
                    u, v = pitch * f0, pitch * f1
                gx = c * u - s * v + off[0]
                gy = s * u + c * v + off[1]
                # half a bin along each lattice axis, in the camera frame (the cut spots' probes)
                h0 = np.array([0.5 * pitch / n_ph, 0.0])
                h1 = np.array([0.25 * pitch / n_ph, 0.5 * pitch * HEX_ROW / n_ph]) \
                    if cam.mla_grid == "hex" else np.array([0.0, 0.5 * pitch / n_ph])
                probe = [c * h0[0] - s * h0[1], s * h0[0] + c * h0[1], c * h1[0] - s * h1[1], s * h1[0] + c * h1[1]]
                t_probe.append(np.tile(np.asarray(probe, dtype=np.float32), (len(gx), 1)))
                depth_first.append(sum(len(x) for x in t_view))
                depth_phase.append(n_ph)
                pts = np.stack([-gx / lat, -gy / lat, np.full(gx.shape, z_cam[d])], axis=1)
                t_point.append(pts)
                t_view.append(np.full(len(pts), iv, dtype=np.int32))
            pl = km.Plan()
            pl.depth_axis = axis
            pl.n_depth = n_depth
            pl.z_first = float(z_cam[0])  # the sampled depths of a camera off the grid axes (axis -1)
            pl.inv_dz = float(1.0 / (z_cam[1] - z_cam[0])) if n_depth > 1 else 0.0
            pl.depth_base = len(depth_phase) - n_depth
            pl.k_spot = cam.mla_focal_length_mm / si
            plans.append(pl)
            # the depth blur's lateral term |A - p| dq against the voxel's own lateral blur
            p_cam = (_corners(grid) - np.asarray(cam.focus_mm)) @ rot.T
            half = np.abs(rot) @ (0.5 * step)
            sop = so - p_cam[:, 2]
            lateral = si / sop * half[0]
            dq = si / sop**2 * half[2]
            blur = max(blur, float(np.max(np.hypot(p_cam[:, 0], p_cam[:, 1]) * dq / lateral)))
        self.blur_error = blur
        self.plans = wp.array(plans, dtype=km.Plan, device=self.device)
        self.depth_phase = np.asarray(depth_phase, dtype=np.int32)
        t_view_a = np.concatenate(t_view)
        t_point_a = np.concatenate(t_point).astype(np.float32)
        n_t = len(t_view_a)
        self.n_templates = n_t
        views = projector.views
        tv = wp.array(t_view_a, dtype=wp.int32, device=self.device)
        tp = wp.array(t_point_a, dtype=wp.vec3, device=self.device)
        tq = wp.array(np.concatenate(t_probe), dtype=wp.vec4, device=self.device)
        tables = km.Tables()
        tables.depth_first = wp.array(np.asarray(depth_first, dtype=np.int32), dtype=wp.int32, device=self.device)
        tables.depth_phase = wp.array(self.depth_phase, dtype=wp.int32, device=self.device)
        rigid_counts = wp.zeros(n_t, dtype=wp.int32, device=self.device)
        cut_counts = wp.zeros(n_t, dtype=wp.int32, device=self.device)
        inputs = [views, projector.sub_a, projector.sub_w, Rows(tv), Rows(tp), Rows(tq)]
        # count (the offsets' places take the counts: unread when counting)
        launch_rows(km.template_spots, n_t, [*inputs, 0, Rows(rigid_counts), Rows(cut_counts), Rows(rigid_counts),
                                             Rows(cut_counts), tables], self.device)
        offsets = []
        for cnt in (rigid_counts, cut_counts):
            o = np.zeros(n_t + 1, dtype=np.int64)
            np.cumsum(cnt.numpy().astype(np.int64), out=o[1:])
            offsets.append(o)
        self.n_rigid, self.n_cut = int(offsets[0][-1]), int(offsets[1][-1])
        self.n_spots = self.n_rigid + self.n_cut
        need = RIGID_SPOT_BYTES * self.n_rigid + CUT_SPOT_BYTES * self.n_cut + 8 * (n_t + 1)
        if budget_bytes is not None and need > budget_bytes:
            raise MemoryBudgetError(f"the matrix-free templates need {need / 2**20:.1f} MiB, more than the "
                                    f"{budget_bytes / 2**20:.1f} MiB allowed; use fewer phase bins or sub-apertures")
        if max(self.n_rigid, self.n_cut) >= 2**31:
            raise MemoryBudgetError("more than 2**31 template spots; use fewer phase bins or sub-apertures")
        tables.rigid_offsets = wp.array(offsets[0].astype(np.int32), dtype=wp.int32, device=self.device)
        tables.cut_offsets = wp.array(offsets[1].astype(np.int32), dtype=wp.int32, device=self.device)
        nr, nc = max(self.n_rigid, 1), max(self.n_cut, 1)
        tables.rigid = wp.zeros(nr, dtype=km.RigidSpot, device=self.device)
        tables.cut = wp.zeros(nc, dtype=km.CutSpot, device=self.device)
        self.tables = tables
        # each block writes its own templates' spots, from their offsets (the global places in the tables)
        launch_rows(km.template_spots, n_t, [*inputs, 1, Rows(tables.rigid_offsets), Rows(tables.cut_offsets),
                                             Rows(rigid_counts), Rows(cut_counts), tables], self.device)
        self.nbytes = int(need)
        self._none1 = wp.empty(1, dtype=float, device=self.device)  # stand-ins for a kernel's unused outputs
        self._none_i = wp.empty(1, dtype=wp.int32, device=self.device)
        wp.synchronize_device(self.device)
        self.build_s = time.perf_counter() - t0

    def on(self, projector: LightFieldProjector) -> DrtTemplates:
        """These templates on another depth slab of their box (``projector``: from
        :meth:`LightFieldProjector.planes <lfcore.projector.LightFieldProjector.planes>` of the same
        projector's box): one set serves every slab.

        Raises
        ------
        ValueError
            If ``projector`` has other cameras or another box.
        """
        mine = self.projector
        if projector.box != mine.box or projector.views is not mine.views:  # the same cameras' device views
            raise ValueError("the templates belong to another box or cameras; build them on this projector")
        out = copy.copy(self)
        out.projector = projector
        return out

    def _common(self) -> list:
        p = self.projector
        return [p._grid, p.views, self.plans, self.tables, len(p.cameras)]


@dataclass(eq=False)
class TemplateOperator:
    """The voxels of one frame on the matrix-free templates, applied in every iteration: the
    :class:`~lfcore.operator.Operator` of kind ``"templates"`` (:meth:`expanded` stores their
    images instead, an operator of kind ``"template images"``).

    Attributes
    ----------
    templates
        The geometry's :class:`DrtTemplates`.
    voxels
        (n,) int32 flat voxel indices on the device.
    min_weight
        Pixel entries at or below this are dropped (as in the stored build).
    """

    templates: DrtTemplates
    voxels: object
    min_weight: float = 1e-6
    _order: object = field(default=None, init=False, repr=False, compare=False)

    kind = TEMPLATES
    nnz = 0
    sums = None
    chunks = ()

    @property
    def device(self) -> str:
        return self.templates.device

    @property
    def n_voxels(self) -> int:
        return int(self.voxels.shape[0])

    @property
    def n_on_the_fly(self) -> int:
        return 0

    @property
    def n_stored(self) -> int:
        return self.n_voxels

    @property
    def stored(self) -> bool:
        return False

    @property
    def nbytes(self) -> int:
        """The templates' bytes and the voxels' indices and order."""
        return self.templates.nbytes + 8 * self.n_voxels

    def order(self) -> object:
        """(n,) int32 on the device: the rows in the order the operator visits them, the voxels of
        one template (in the first view) together so that its spots are read from the cache
        (computed once, at the first use)."""
        if self._order is None:
            t, km, wp = self.templates, self.templates._km, self.templates.wp
            p = t.projector
            key = wp.empty(self.n_voxels, dtype=wp.int32, device=t.device)
            launch_rows(km.template_key, self.n_voxels, [p._grid, p.views, t.plans, t.tables, Rows(self.voxels),
                                                         Rows(key)], t.device)
            rows = np.argsort(key.numpy(), kind="stable").astype(np.int32)
            self._order = wp.array(rows, dtype=wp.int32, device=t.device)
        return self._order

    @keyword_options("out", since="0.1.0")
    def forward(self, e, *, out=None) -> object:
        """Project intensities ``e`` (n,) into ``out`` (n_pixels,) float32 (zeroed first; None: a new
        array), returned."""
        t, km = self.templates, self.templates._km
        if out is None:
            out = t.wp.zeros(t.projector.n_pixels, dtype=float, device=t.device)
        out.zero_()
        parts = PrivateCopies()
        per = parts.open(out)
        launch_rows(km.project, self.n_voxels, [*t._common(), float(self.min_weight), Rows(self.order()), self.voxels,
                                              e, per, t._none_i],
                    t.device)
        parts.close(out)
        return out

    def update(self, ratio, e, relaxation: float) -> None:
        """E_v <- E_v exp(mu sum_i w_iv ratio_i) in place, ``ratio`` the pixels' log ratios
        (:func:`lfcore.operator.log_ratio`)."""
        t, km = self.templates, self.templates._km
        launch_rows(km.smart_update, self.n_voxels, [*t._common(), float(self.min_weight), Rows(self.order()),
                                                     self.voxels, ratio, float(relaxation), e, t._none_i], t.device)

    def restrict(self, rows, *, spend: bool = False) -> TemplateOperator:
        """The templates' operator of some of these voxels: ``rows`` (k,) int32 row indices
        (ascending, on the device); row t of the result is voxel ``voxels[rows[t]]`` (``spend``: as
        :meth:`lfcore.operator.Operator.restrict`; the templates hold no rows, so nothing to let go)."""
        return TemplateOperator(self.templates, gather(self.voxels, rows), self.min_weight)

    @deprecated("op.update(ratio, e, relaxation)", since="0.1.0")
    def smart_update(self, ratio, e, relaxation: float) -> None:
        """Deprecated: :meth:`update` (its name until the operator protocol)."""
        self.update(ratio, e, relaxation)

    def scatter(self, e, *, out=None) -> object:
        """The dense (z, y, x) float32 volume of the projector's grid with ``e`` at these voxels, zero
        elsewhere, on the device (``out`` zeroed and written; None: a new array)."""
        return scatter_voxels(self.voxels, e, self.templates.projector.grid.shape, device=self.device, out=out)

    def _trace(self, vox, offs, fill, limit, counts, pix, w) -> None:
        """The templates' raw entries of ``vox``, with the interface of the stored weights' tracer
        (see :meth:`lfcore.weight_build.WeightBuilder.merged`)."""
        t, km, wp = self.templates, self.templates._km, self.templates.wp
        launch_rows(km.template_entries, int(vox.shape[0]),
                    [*t._common(), float(self.min_weight), Rows(vox), Rows(offs), wp.int64(0), fill, wp.int64(limit),
                     Rows(counts), pix, w], t.device)

    def expanded(self, *, budget_bytes: int | None = None, floor: float = IMAGE_FLOOR) -> Weights:
        """The templates' images of these voxels as stored weights: made once (no ray tracing; the
        same entries the operator applies, merged per pixel as the stored build merges its own,
        the faint ones dropped) so that the iterations run at the stored weights' speed where
        their memory allows.

        Parameters
        ----------
        budget_bytes
            Memory the weights may take; default: what the device has free.
        floor
            Merged entries at or below this are dropped and each voxel's others scaled to keep
            its light (:data:`IMAGE_FLOOR`; 0: the templates' operator exactly).

        Returns
        -------
        lfcore.weight_build.Weights
            Stored weights of kind ``"template images"``, bound to the templates' projector.

        Raises
        ------
        MemoryBudgetError
            If they would not fit.
        """
        t = self.templates
        budget = available_bytes(t.device) if budget_bytes is None else int(budget_bytes)
        if t.device == "cpu":
            out = self._merged_in_place(budget, float(floor))
        else:  # a thread per voxel: raw entries, sorted and merged as the stored build's
            out = t.projector.builder.merged(self.voxels, self._trace, budget_bytes=budget, floor=float(floor))
        out.min_weight = float(self.min_weight)
        return t.projector.bind(out, kind=TEMPLATE_IMAGES)

    def _merged_in_place(self, budget: int, floor: float) -> Weights:
        """The expansion on the CPU: each block merges its voxels' entries in a dense image of its
        own (:func:`lfcore._kernels.matrix_free.template_merged`), counted first, so that the
        weights' size is known before they are written."""
        t, km, wp = self.templates, self.templates._km, self.templates.wp
        n, dev, n_pix = self.n_voxels, t.device, t.projector.n_pixels
        # each block's dense image and list of pixels met (8 bytes a pixel: 0.5 GB a block for two
        # 29 MP cameras) take at most a quarter of the budget, and the voxels' counts 16 bytes each
        blocks = max(1, min(cpu_threads(), n, budget // 4 // (8 * n_pix)))
        scratch = 8 * n_pix * blocks + 16 * max(n, 1)
        budget -= scratch
        dense = PerBlock(tuple(wp.zeros(n_pix, dtype=float, device=dev) for _ in range(blocks)))
        touched = PerBlock(tuple(wp.empty(n_pix, dtype=wp.int32, device=dev) for _ in range(blocks)))
        common = [*t._common(), float(self.min_weight)]
        counts = wp.zeros(max(n, 1), dtype=wp.int64, device=dev)
        none_offsets = wp.zeros(max(n, 1), dtype=wp.int64, device=dev)
        launch_rows(km.template_merged, n, [*common, Rows(self.voxels), Rows(none_offsets), 0, Rows(counts), t._none_i,
                                            t._none1, dense, touched, floor], dev)
        per = counts.numpy()[:n].astype(np.int64)
        raw = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(per, out=raw[1:])
        total = int(raw[-1])
        if BYTES_PER_WEIGHT * total > budget:
            raise MemoryBudgetError(f"the matrix-free templates' images of {n:,} voxels need "
                                    f"{BYTES_PER_WEIGHT * total / 2**30:.2f} GiB but {budget / 2**30:.2f} GiB are free "
                                    f"beside the merge's {scratch / 2**20:.0f} MiB of scratch")
        chunks, lo = [], 0
        while lo < n:  # chunks of whole voxels with at most CHUNK_ENTRIES entries (a voxel with more alone)
            hi = int(np.searchsorted(raw, raw[lo] + CHUNK_ENTRIES["cpu"], side="right")) - 1
            hi = min(n, max(hi, lo + 1))
            local = raw[lo:hi + 1] - raw[lo]
            nnz = int(local[-1])
            offsets = wp.array(local, dtype=wp.int64, device=dev)
            pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=dev)
            w = wp.empty(max(nnz, 1), dtype=float, device=dev)
            launch_rows(km.template_merged, hi - lo, [*common, Rows(self.voxels[lo:hi]), Rows(offsets), 1,
                                                      Rows(counts[lo:hi]), pix, w, dense, touched, floor], dev)
            chunks.append(WeightChunk(first=lo, n=hi - lo, offsets=offsets, pix=pix, w=w, nnz=nnz))
            lo = hi
        return Weights(voxels=self.voxels, chunks=chunks, nnz=total)

    def entries_per_voxel(self, *, sample: int = 256) -> float:
        """Mean raw entries (before their merge) per voxel, over up to ``sample`` voxels spread
        over the list: what the expansion's scratch holds per voxel, an upper bound of its merged
        weights."""
        wp = self.templates.wp
        n = self.n_voxels
        if n == 0:
            return 0.0
        take = np.unique(np.linspace(0, n - 1, min(n, sample)).astype(np.int64))
        dev = self.templates.device
        vox = wp.array(self.voxels.numpy()[take], dtype=wp.int32, device=dev)
        counts = wp.zeros(len(take), dtype=wp.int64, device=dev)
        self._trace(vox, wp.zeros(len(take) + 1, dtype=wp.int64, device=dev), 0, 0, counts, self.templates._none_i,
                    self.templates._none1)
        return float(counts.numpy().mean())

    def images(self) -> np.ndarray:
        """(n, n_pixels) float32: each voxel's image, for checks on small rigs."""
        t, wp = self.templates, self.templates.wp
        n, dev = self.n_voxels, t.device
        counts = wp.zeros(max(n, 1), dtype=wp.int64, device=dev)
        zeros = wp.zeros(n + 1, dtype=wp.int64, device=dev)
        self._trace(self.voxels, zeros, 0, 0, counts, t._none_i, t._none1)
        offs = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts.numpy()[:n], out=offs[1:])
        pix = wp.empty(max(int(offs[-1]), 1), dtype=wp.int32, device=dev)
        w = wp.empty(max(int(offs[-1]), 1), dtype=float, device=dev)
        self._trace(self.voxels, wp.array(offs, dtype=wp.int64, device=dev), 1, 2**62, counts, pix, w)
        out = np.zeros((n, t.projector.n_pixels), dtype=np.float32)
        m = int(offs[-1])
        np.add.at(out, (np.repeat(np.arange(n), np.diff(offs)), pix.numpy()[:m]), w.numpy()[:m])
        return out


def fidelity(projector: LightFieldProjector, voxels: np.ndarray, templates: DrtTemplates, *, min_weight: float = 1e-6
             ) -> dict[str, np.ndarray]:
    """Per voxel, the matrix-free image against the stored DRT weights (the reference).

    Parameters
    ----------
    projector, templates
        The geometry and its templates.
    voxels
        (n,) int32 flat voxel indices (a few hundred at most: the images are dense).

    Returns
    -------
    dict
        ``"correlation"`` (n,) of the two images; ``"light"`` (n,) total light of the
        matrix-free image over the stored one's (1 where both are dark).
    """
    wp = warp()
    voxels = np.asarray(voxels, dtype=np.int32)
    corr = np.ones(len(voxels))
    light = np.ones(len(voxels))
    per = max(1, (1 << 28) // (12 * projector.n_pixels))  # dense images of about 256 MiB at a time
    for lo in range(0, len(voxels), per):
        part = voxels[lo:lo + per]
        vox = wp.array(part, dtype=wp.int32, device=projector.device)
        stored = projector.weights(vox, method="drt", min_weight=min_weight, storage="stored")
        offs, pix, w = stored.to_numpy()
        ref = np.zeros((len(part), projector.n_pixels), dtype=np.float64)
        np.add.at(ref, (np.repeat(np.arange(len(part)), np.diff(offs)), pix), w)
        mf = TemplateOperator(templates, vox, min_weight).images()
        for i in range(len(part)):
            a, b = ref[i], mf[i].astype(np.float64)
            if a.sum() > 0 or b.sum() > 0:
                light[lo + i] = b.sum() / a.sum() if a.sum() > 0 else np.inf
                da, db = a - a.mean(), b - b.mean()
                den = np.sqrt((da * da).sum() * (db * db).sum())
                corr[lo + i] = (da * db).sum() / den if den > 0 else 0.0
    return {"correlation": corr, "light": light}


# the name of TemplateOperator until the operator protocol
__getattr__ = moved_names(__name__, {"MatrixFreeWeights": lambda: TemplateOperator}, since="0.1.0")
