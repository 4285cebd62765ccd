"""The light-field projector: light-field cameras bound to a voxel grid on a compute device.

:class:`LightFieldProjector` owns the cameras' geometry on the device and makes what
reconstruction needs of it (the :class:`~lfcore.operator.Projector` protocol): which voxels can
hold a particle (zero-voxel elimination) and the operator of a frame's active voxels, their
sparse voxel-to-pixel weights (dense ray tracing, or the conventional line-of-sight baseline;
built by :mod:`lfcore.weight_build`, applied by :class:`~lfcore.weight_build.Weights`).
Algorithms (:mod:`lfcore.reconstruct`) only see the operator.

:class:`BoundCameras` is what every projector (light-field, pinhole, joint) shares: the cameras'
pixels numbered globally (camera k's pixel (row, column) is ``pixel_offsets[k] + row * columns +
column``), the grid or a depth slab of it, and scratch buffers kept between calls (elimination's
masks, the projection's private images): one thread at a time may use a projector.
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Sequence

import numpy as np

from lfcore._deprecation import deprecated, keyword_options, moved_names
from lfcore.device import (
    MemoryBudgetError,
    PrivateCopies,
    RowOffset,
    available_bytes,
    launch_rows,
    resolve_device,
    warp,
)
from lfcore.operator import INDEX_LIMIT, LINE_OF_SIGHT, TRACED, check_indexable, log_ratio, max_planes
from lfcore.rig import Camera
from lfcore.volume import VolumeGrid
from lfcore.weight_build import (
    BUILDS,
    BYTES_PER_WEIGHT,
    LANES,
    STORAGE,
    Binding,
    WeightBuilder,
    WeightChunk,
    Weights,
    device_range,
)

# BUILDS, BYTES_PER_WEIGHT, STORAGE, WeightChunk and Weights live in lfcore.weight_build, INDEX_LIMIT,
# check_indexable and max_planes in lfcore.operator; they are importable from here too.
__all__ = ["BUILDS", "BYTES_PER_WEIGHT", "INDEX_LIMIT", "LANES", "BoundCameras", "LightFieldProjector",
           "MemoryBudgetError", "STORAGE", "WeightChunk", "Weights", "check_indexable", "grid_struct",
           "max_planes"]


def grid_struct(kw, box: VolumeGrid, *, z0: int = 0, z1: int | None = None):
    """The kernels' :class:`lfcore._kernels.weights.Grid` of planes ``z0 .. z1 - 1`` of ``box``
    (default: all of them): the origin is the box's, so that a slab's voxel centres are the
    box's to the bit."""
    wp = warp()
    g = kw.Grid()
    g.origin = wp.vec3(*box.origin_mm)
    g.step = wp.vec3(*box.voxel_mm)
    nz, g.ny, g.nx = box.shape
    g.nz = (nz if z1 is None else int(z1)) - int(z0)
    g.z0 = int(z0)
    return g

#: Checks per view of elimination's first pass over the grid (see :meth:`LightFieldProjector.eliminate`).
PREFILTER_CHECKS = 4
#: Checks of one view elimination makes before the next view's turn (:func:`lfcore._kernels.weights.eliminate_turns`).
ROUND_CHECKS = 4
#: :data:`PREFILTER_CHECKS` and :data:`ROUND_CHECKS` on the CPU where the table of
#: :meth:`LightFieldProjector.precompute_checks` holds every check: a check is then a lookup and a
#: turn's own cost (the view's geometry and counts) weighs, so longer turns take less time (about 18%
#: less on the demo's rig, benchmarks/RESULTS.md); the survivors are the same.
TABLE_PREFILTER_CHECKS = 8
TABLE_ROUND_CHECKS = 40


def _sub_apertures(cam: Camera, n_sub: int, samples: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Square sub-apertures over the main-lens disc: centroids (k, 2) mm and area shares (k,) (new arrays;
    each aperture's computed once a process, :func:`_disc_sub_apertures`)."""
    centres, shares = _disc_sub_apertures(float(cam.aperture_mm), int(n_sub), int(samples))
    return centres.copy(), shares.copy()


@functools.lru_cache(maxsize=64)
def _disc_sub_apertures(d: float, n_sub: int, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_sub_apertures` of a disc of diameter ``d`` mm (a projector's cameras share it, and a coarse
    grid's projector made for each frame's reconstructor, :func:`lfcore.reconstruct.coarse_reconstructor`,
    takes its cameras' again: 0.06 CPU s a camera of 14 pixels a lenslet in Python's loops)."""
    side = d / n_sub
    edges = -0.5 * d + side * np.arange(n_sub)
    fine = (np.arange(samples) + 0.5) / samples * side
    centres, shares = [], []
    for y0 in edges:
        for x0 in edges:
            xs, ys = np.meshgrid(x0 + fine, y0 + fine)
            inside = xs**2 + ys**2 <= (0.5 * d) ** 2
            if inside.any():
                centres.append([xs[inside].mean(), ys[inside].mean()])
                shares.append(inside.mean())
    shares_a = np.asarray(shares)
    return np.asarray(centres), shares_a


class BoundCameras:
    """Cameras bound to a voxel grid on one device: what every projector shares.

    The cameras' pixels numbered globally (:attr:`pixel_offsets`), the grid (or a depth slab of
    its box, :meth:`planes`), the kernels' view of it and scratch buffers kept between calls.
    :class:`LightFieldProjector`, :class:`~lfcore.pinhole_projector.PinholeProjector` and
    :class:`~lfcore.pinhole_projector.JointProjector` build on it, each its own kind of
    :class:`~lfcore.operator.Projector`.

    Parameters
    ----------
    cameras
        The cameras, in the order of their images.
    grid
        The voxel grid.
    device
        Warp device; None for the first GPU, else the CPU.
    """

    #: ``"light-field"``, ``"pinhole"`` or ``"joint"``: the kind of cameras bound.
    kind = ""

    def __init__(self, cameras: Sequence, grid: VolumeGrid, *, device: str | None = None) -> None:
        from lfcore._kernels import weights as kw

        self.wp = warp()
        self._kw = kw
        self.cameras = tuple(cameras)
        self.grid = grid
        self.device = resolve_device(device)
        self.box = grid  # the whole box (grid is one depth slab of it on a projector from planes())
        self.z0 = 0  # the box's plane of the grid's first
        self._grid = grid_struct(kw, grid)
        self.pixel_offsets = np.cumsum([0] + [c.sensor_px[0] * c.sensor_px[1] for c in self.cameras])
        self.n_pixels = int(self.pixel_offsets[-1])
        if self.n_pixels >= 2**31:
            raise MemoryBudgetError("more than 2**31 pixels; use fewer or smaller cameras")
        self._parts = PrivateCopies()  # projection images of the CPU blocks (see Weights.forward)
        self._buffers: dict[str, object] = {}  # scratch kept between calls (see _scratch)
        self._none = self.wp.empty(0, dtype=self.wp.int32, device=self.device)
        self.builder: WeightBuilder | None = None  # the light-field weight builder, where there is one

    def binding(self) -> Binding:
        """What applying this projector's stored weights needs (:class:`~lfcore.weight_build.Binding`)."""
        return Binding(device=self.device, n_pixels=self.n_pixels, shape=tuple(self.grid.shape), builder=self.builder,
                       parts=self._parts)

    def bind(self, weights: Weights, *, kind: str | None = None) -> Weights:
        """``weights`` (built for this projector's grid) bound to it as an operator, marked ``kind``
        (default: as they are); returned."""
        weights.binding = self.binding()
        if kind is not None:
            weights.kind = kind
        return weights

    def all_voxels(self) -> object:
        """Every voxel of the grid (no elimination), as (n,) int32 indices."""
        check_indexable(self.grid)
        return device_range(self.grid.n_voxels, device=self.device)

    def planes(self, z0: int, z1: int):
        """This projector on planes ``z0 .. z1 - 1`` of its grid: a depth slab whose voxels are
        numbered from its first plane (so a box of :data:`INDEX_LIMIT` voxels or more is numbered
        slab by slab), with the same cameras, device tables and scratch buffers.

        A slab's voxel has the box's voxel's centre to the bit, so its weights, its templates'
        images and its elimination are the box's (:mod:`lfcore.slabs`).

        Raises
        ------
        ValueError
            If the planes are not a non-empty range of the grid's.
        MemoryBudgetError
            If the slab itself has :data:`INDEX_LIMIT` voxels or more.
        """
        grid = self.grid.planes(z0, z1)
        check_indexable(grid)
        out = copy.copy(self)
        out.grid = grid
        out.z0 = self.z0 + int(z0)
        out._grid = grid_struct(self._kw, self.box, z0=out.z0, z1=out.z0 + grid.shape[0])
        return out

    def _lit_on_device(self, lit) -> object:
        """The lit mask as one (n_pixels,) uint8 device array: a device mask as it is (checked),
        per-camera host masks concatenated and uploaded into a kept scratch buffer."""
        wp = self.wp
        if isinstance(lit, wp.array):
            if lit.dtype != wp.uint8 or lit.shape != (self.n_pixels,) or str(lit.device) != self.device:
                raise ValueError(f"a device lit mask must be ({self.n_pixels},) uint8 on {self.device}, got "
                                 f"{lit.shape} {lit.dtype.__name__} on {lit.device}")
            return lit
        flat = np.concatenate([np.asarray(m, dtype=np.uint8).ravel() for m in lit])
        if flat.size != self.n_pixels:
            raise ValueError(f"lit masks hold {flat.size} pixels, the cameras {self.n_pixels}")
        lit_dev = self._scratch("lit", self.n_pixels, wp.uint8)
        wp.copy(lit_dev, wp.array(flat, dtype=wp.uint8, device="cpu", copy=False))
        return lit_dev

    def _scratch(self, name: str, n: int, dtype) -> object:
        """The first ``n`` elements of the scratch buffer ``name``, kept between calls (grown by
        half again when too short)."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape[0] < n or buf.dtype != dtype:
            size = n if buf is None else max(n, int(1.5 * buf.shape[0]))
            buf = self._buffers[name] = self.wp.empty(max(size, 1), dtype=dtype, device=self.device)
        return buf[:n]

    def _compact(self, mask, values=None, *, scratch: str | None = None) -> object:
        """The indices where ``mask`` is set (or those entries of ``values``), as (n,) int32.

        ``scratch``: the :meth:`_scratch` buffer to write them to (overwritten by a later call);
        None: a new array.
        """
        wp, kw = self.wp, self._kw
        scan = self._scratch("scan", mask.shape[0], wp.int32)
        wp.utils.array_scan(mask, scan, inclusive=True)
        count = int(scan[mask.shape[0] - 1 :].numpy()[0]) if mask.shape[0] else 0
        out = wp.empty(count, dtype=wp.int32, device=self.device) if scratch is None else self._scratch(scratch, count,
                                                                                                          wp.int32)
        if values is None:
            values = self._none
        if count:
            wp.launch(kw.compact, dim=mask.shape[0], device=self.device, inputs=[mask, scan, values, out])
        return out

    # --- the operator's own methods, kept for scripts written against the projector ------------------
    @deprecated("weights.forward(e, out=out)", since="0.1.0")
    @keyword_options("out", since="0.1.0")
    def forward(self, weights, e, *, out=None):
        """Deprecated: ``weights.forward(e, out=out)`` (:meth:`lfcore.operator.Operator.forward`)."""
        return weights.forward(e, out=out)

    @deprecated("weights.update(lfcore.operator.log_ratio(image, proj, floor, ratio), e, relaxation)",
                since="0.1.0")
    def smart_update(self, weights, image, proj, e, relaxation: float, floor: float) -> None:
        """Deprecated: :func:`lfcore.operator.log_ratio` then ``weights.update(ratio, e, relaxation)``."""
        ratio = log_ratio(image, proj, floor, self._scratch("ratio", self.n_pixels, self.wp.float32))
        weights.update(ratio, e, relaxation)

    @deprecated("weights.scatter(e, out=out)", since="0.1.0")
    @keyword_options("out", since="0.1.0")
    def scatter(self, weights, e, *, out=None):
        """Deprecated: ``weights.scatter(e, out=out)`` (:meth:`lfcore.operator.Operator.scatter`)."""
        return weights.scatter(e, out=out)

    @deprecated("weights.scatter(e).numpy()", since="0.1.0")
    def to_volume(self, weights, e) -> np.ndarray:
        """Deprecated: ``weights.scatter(e).numpy()``."""
        return weights.scatter(e).numpy()

    # --- the sequential form's pixel-major copy, kept for scripts written against the projector ------
    @deprecated("weights.transpose()", since="0.1.0")
    def transpose(self, weights: Weights):
        """Deprecated: ``weights.transpose()``."""
        return weights.transpose()

    @deprecated("weights.sweep(transposed, image, e, relaxation, floor)", since="0.1.0")
    def mart_sweep(self, transposed, image, e, relaxation: float, floor: float) -> None:
        """Deprecated: ``weights.sweep(transposed, image, e, relaxation, floor)``."""
        Weights(voxels=self._none, chunks=[], nnz=0, binding=self.binding()).sweep(transposed, image, e, relaxation,
                                                                                     floor)


class LightFieldProjector(BoundCameras):
    """Light-field cameras and a voxel grid bound on one device (DRT-MART's, MART's and MLOS-MART's
    :class:`~lfcore.operator.Projector`).

    Parameters
    ----------
    cameras
        One or more light-field cameras (a joint reconstruction uses every camera's pixels).
    grid
        The voxel grid.
    sub_apertures
        Sub-apertures per axis of the main-lens aperture for the DRT weights; default: the
        camera's pixels per lenslet, so that one sub-aperture maps onto about one pixel.
    device
        Warp device; None for the first GPU, else the CPU.

    Attributes
    ----------
    builder
        The :class:`~lfcore.weight_build.WeightBuilder` of this geometry (:meth:`weights` uses it).
    """

    kind = "light-field"

    def __init__(self, cameras: Sequence[Camera], grid: VolumeGrid, *, sub_apertures: int | None = None,
                 device: str | None = None) -> None:
        from lfcore._kernels.optics import camera_params

        if sub_apertures is not None and sub_apertures < 1:
            raise ValueError(f"sub_apertures must be at least 1, got {sub_apertures}")
        super().__init__(cameras, grid, device=device)
        kw = self._kw
        self.sub_apertures = sub_apertures  # None: each camera's pixels per lenslet
        wp = self.wp
        views, sub_a, sub_w, check_order, overlap = [], [], [], [], []
        rng = np.random.default_rng(0)
        half_world = 0.5 * np.asarray(grid.voxel_mm)
        for k, cam in enumerate(self.cameras):
            n_sub = sub_apertures or max(1, round(cam.pixels_per_lenslet))
            centres, shares = _sub_apertures(cam, n_sub)
            v = kw.View()
            v.cam = camera_params(cam)
            rot = cam.rotation.T  # world -> camera
            v.rot = wp.mat33(*rot.ravel())
            v.focus = wp.vec3(*cam.focus_mm)
            half = np.abs(rot) @ half_world
            v.half = wp.vec3(*half)
            v.pix_offset = int(self.pixel_offsets[k])
            first = sum(len(x) for x in sub_w)
            v.sub_first = first
            v.sub_count = len(shares)
            # Elimination checks the full sub-apertures in random order: neighbouring ones land
            # on neighbouring pixels and agree, far-apart ones disagree unless a particle is there.
            full = np.flatnonzero(shares >= 0.5)
            v.check_first = sum(len(x) for x in check_order)
            v.check_count = len(full)
            v.sub_side = cam.aperture_mm / n_sub
            hexagonal = cam.mla_grid == "hex"
            v.n_edges = 6 if hexagonal else 4
            step = 60.0 if hexagonal else 90.0
            ang = [math.radians(i * step + cam.mla_rotation_deg) for i in range(v.n_edges)]
            v.edge_nx = kw.vec6(*[math.cos(a) for a in ang], *[0.0] * (6 - v.n_edges))
            v.edge_ny = kw.vec6(*[math.sin(a) for a in ang], *[0.0] * (6 - v.n_edges))
            v.cell_r = cam.mla_pitch_mm / (math.sqrt(3.0) if hexagonal else math.sqrt(2.0))
            v.magnification = cam.magnification
            # MART baseline: the pixel's line-of-sight cylinder is as wide as its lenslet's
            # conjugate on the focal plane; the voxel's sphere as wide as the voxel laterally.
            r_cyl = 0.5 * cam.mla_pitch_mm / abs(cam.magnification)
            r_sph = 0.5 * (half[0] + half[1])
            v.los_radius = r_cyl + r_sph
            v.los_first = (kw.OVERLAP_SAMPLES + 1) * k
            v.los_d0 = abs(r_cyl - r_sph)  # the table spans d0 .. r_cyl + r_sph, 2 min(r) wide
            v.los_dinv = kw.OVERLAP_SAMPLES / (2.0 * min(r_cyl, r_sph))
            overlap.append(kw.overlap_table(r_cyl, r_sph))
            views.append(v)
            sub_a.append(centres)
            sub_w.append(shares / shares.sum())
            check_order.append((first + rng.permutation(full)).astype(np.int32))
        self.views = wp.array(views, dtype=kw.View, device=self.device)
        self._overlap = wp.array(np.concatenate(overlap), dtype=float, device=self.device)
        self.sub_a = wp.array(np.concatenate(sub_a).astype(np.float32), dtype=wp.vec2, device=self.device)
        self.sub_w = wp.array(np.concatenate(sub_w).astype(np.float32), dtype=float, device=self.device)
        self.check_order = wp.array(np.concatenate(check_order), dtype=wp.int32, device=self.device)
        self._checks = wp.zeros(1, dtype=wp.int32, device=self.device)  # see precompute_checks
        self.max_checks = max(len(c) for c in check_order)
        self._n_checks = 0
        self.builder = WeightBuilder(self._grid, self.views, self.sub_a, self.sub_w, self._overlap, device=self.device)


    # --- zero-voxel elimination ---------------------------------------------------------
    #: Whether :meth:`eliminate` takes ``within`` (coarse-to-fine elimination, :mod:`lfcore.coarse`).
    eliminates_within = True

    def eliminate(self, lit: Sequence[np.ndarray], *, min_seen: float = 0.5, max_dark: float = 0.05,
                  within=None) -> object:
        """Voxels that can hold a particle: their sub-apertures land on lit pixels.

        Parameters
        ----------
        lit
            One boolean (rows, columns) image per camera: pixels with signal; or, already on
            the projector's device, one (n_pixels,) uint8 Warp array of all cameras' pixels
            (see :class:`lfcore.device_ops.ImagePreprocessor`).
        min_seen
            Fraction of a voxel's checked sub-apertures that must land on a camera's sensor.
        max_dark
            Fraction of its checked sub-apertures a voxel may find dark and still be kept.
        within
            (m,) int32 Warp array on the device: flat voxel indices, ascending, the only candidates
            (a coarse pass's, :mod:`lfcore.coarse`); None: every voxel of the grid. The same test,
            so the result is those of a whole-grid pass that are in ``within``.

        Returns
        -------
        warp.array
            (n,) int32 flat voxel indices, ascending (a new array).

        Notes
        -----
        The scratch (two int32 masks of the grid, 8 bytes per voxel; the candidates of the first
        pass; host masks uploaded) is allocated on the first call and kept for the next ones.
        """
        check_indexable(self.grid)
        wp, kw = self.wp, self._kw
        lit_dev = self._lit_on_device(lit)
        common = [self._grid, self.views, len(self.cameras), self.sub_a, self.check_order, lit_dev, float(min_seen),
                  float(max_dark), self._checks, self._n_checks]
        # First the whole grid with a few checks per view, then every check on the candidates
        # left: the same voxels as one full pass, but a warp no longer waits for its one kept voxel.
        n = self.grid.n_voxels if within is None else int(within.shape[0])
        mask = self._scratch("mask", n, wp.int32)
        mask.zero_()
        given = self._none if within is None else within
        prefilter, rounds = PREFILTER_CHECKS, ROUND_CHECKS
        if self.device == "cpu" and self._n_checks >= self.max_checks:  # every check a lookup: longer turns
            prefilter, rounds = TABLE_PREFILTER_CHECKS, TABLE_ROUND_CHECKS
        # with the views taking turns, the full pass goes on from the first pass's counts (kernel's notes)
        carry = 0 < rounds and 0 < prefilter <= 15 and len(self.cameras) <= kw.MAX_CARRIED
        counts = self._scratch("counts", n, wp.int32) if carry else self._none
        launch_rows(kw.eliminate_turns, n, [*common, given, prefilter, rounds, self._none, 0,
                                            RowOffset(0), mask, counts], self.device)
        candidates = self._compact(mask, None if within is None else within, scratch="candidates")
        n = int(candidates.shape[0])
        if carry:
            counts = self._compact(mask, counts, scratch="carried")
        mask = mask[:max(n, 1)]  # the grid pass is compacted: its mask is free again
        mask.zero_()
        launch_rows(kw.eliminate_turns, n, [*common, candidates, 2**30, rounds, counts,
                                            prefilter if carry else 0, RowOffset(0), mask, self._none],
                    self.device)
        return self._compact(mask[:n], candidates)

    @keyword_options("n_checks", "budget_bytes", since="0.1.0")
    def precompute_checks(self, *, n_checks: int | None = None, budget_bytes: int | None = None) -> int:
        """Trace once the pixels of every voxel's first ``n_checks`` elimination checks.

        With the table, elimination looks those pixels up instead of tracing them (its result
        is the same): with every check stored it is about 10x faster on the CPU. The table takes
        ``20 * n_checks`` bytes per voxel and camera (int32 pixels of the centre and four
        corners of each checked footprint) on the device: 80 checks at 10 pixels per lenslet,
        so 1.6 kB per voxel and camera.

        Parameters
        ----------
        n_checks
            Checks per voxel and camera to store; None: all of them (``max_checks``); 0 drops
            the table. Fewer are stored if they would pass the budget.
        budget_bytes
            Most bytes the table may take; default: a quarter of what the device has free.

        Returns
        -------
        int
            Bytes of the table; 0 if there is none.
        """
        check_indexable(self.grid)
        wp, kw = self.wp, self._kw
        per_check = 20 * self.grid.n_voxels * len(self.cameras)
        budget = available_bytes(self.device) // 4 if budget_bytes is None else budget_bytes
        n_checks = self.max_checks if n_checks is None else min(int(n_checks), self.max_checks)
        n_checks = max(0, min(n_checks, budget // per_check, (2**31 - 1) // (per_check // 4)))
        entries = per_check // 4 * n_checks
        if n_checks == 0:
            self._checks, self._n_checks = wp.zeros(1, dtype=wp.int32, device=self.device), 0
            return 0
        table = wp.empty(entries, dtype=wp.int32, device=self.device)
        launch_rows(kw.check_pixels, self.grid.n_voxels, [self._grid, self.views, len(self.cameras), self.sub_a,
                                                          self.check_order, int(n_checks), RowOffset(0), table],
                    self.device)
        self._checks, self._n_checks = table, int(n_checks)
        return 4 * entries

    def planes(self, z0: int, z1: int) -> LightFieldProjector:
        """This projector on planes ``z0 .. z1 - 1`` of its grid (see :meth:`BoundCameras.planes`),
        its weight builder on the slab. The elimination's precomputed table
        (:meth:`precompute_checks`) is the box's numbering's and is not carried."""
        out = super().planes(z0, z1)
        out._checks, out._n_checks = self.wp.zeros(1, dtype=self.wp.int32, device=self.device), 0
        out.builder = copy.copy(self.builder)
        out.builder.grid = out._grid
        return out

    # --- the operator -------------------------------------------------------------------------
    @keyword_options("method", "min_weight", "budget_bytes", "build", "sort", "storage", since="0.1.0")
    def weights(self, voxels, *, method: str = "drt", min_weight: float = 1e-6, budget_bytes: int | None = None,
                build: str = "auto", sort: str = "auto", storage: str = "stored") -> Weights:
        """The operator of ``voxels`` (from :meth:`eliminate` or :meth:`all_voxels`): their sparse
        weights, built by this projector's :attr:`builder`, bound to it (weights made on the fly
        are made where :meth:`Weights.forward <lfcore.weight_build.Weights.forward>` and
        :meth:`~lfcore.weight_build.Weights.update` use them).

        Parameters
        ----------
        voxels
            (n,) int32 flat voxel indices on this projector's device.
        method, min_weight, budget_bytes, build, sort, storage
            As :meth:`WeightBuilder.weights <lfcore.weight_build.WeightBuilder.weights>` takes them;
            ``method`` is ``"drt"`` (dense ray tracing: ``"traced weights"``) or ``"los"`` (line of
            sight, the MART baseline's: ``"line-of-sight weights"``).

        Returns
        -------
        Weights

        Raises
        ------
        MemoryBudgetError
            If the weights would not fit, with their size.
        """
        w = self.builder.weights(voxels, method=method, min_weight=min_weight, budget_bytes=budget_bytes,
                                 build=build, sort=sort, storage=storage)
        return self.bind(w, kind=TRACED if method == "drt" else LINE_OF_SIGHT)

    def operator(self, voxels, *, method: str, min_weight: float = 1e-6, budget_bytes: int | None = None,
                 storage: str = "stored") -> Weights:
        """The :class:`~lfcore.operator.Operator` of ``voxels``: :meth:`weights` (what
        :class:`lfcore.operator.Projector` asks of every projector)."""
        return self.weights(voxels, method=method, min_weight=min_weight, budget_bytes=budget_bytes, storage=storage)

# the light-field projector's name until the operator protocol
__getattr__ = moved_names(__name__, {"Projector": lambda: LightFieldProjector}, since="0.1.0")
