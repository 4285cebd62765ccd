"""The projector: light-field cameras bound to a voxel grid on a compute device.

It owns the geometry on the device and exposes what reconstruction algorithms need: which
voxels can hold a particle (zero-voxel elimination), the sparse voxel-to-pixel weights (dense
ray tracing, or the conventional line-of-sight baseline), forward projection, and the MART
updates. Algorithms (:mod:`lfcore.reconstruct`) only see this object.

Pixels of all cameras are numbered globally: camera k's pixel (row, column) is
``pixel_offsets[k] + row * columns + column``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lfcore.device import (
    MemoryBudgetError,
    PerBlock,
    PrivateCopies,
    RowOffset,
    Rows,
    available_bytes,
    launch_rows,
    out_of_memory_is_budget_error,
    resolve_device,
    warp,
)
from lfcore.rig import Camera
from lfcore.volume import VolumeGrid

__all__ = ["MemoryBudgetError", "Projector", "WeightChunk", "Weights"]

#: Bytes per stored weight: an int32 pixel index and a float32 value.
BYTES_PER_WEIGHT = 8
#: Raw (unmerged) entries built at once; bounds the scratch memory of a weight build.
CHUNK_ENTRIES = {"cpu": 1 << 25, "cuda": 1 << 28}
#: Scratch bytes per raw entry of a two-pass DRT build, by merge (per voxel or not): pixels and
#: sort order (twice each, three times per voxel), the raw value, the merged pixel and value.
MERGE_SCRATCH_BYTES = {False: 28, True: 44}
#: Raw-entry slots per chunk of the single-pass DRT build: small enough to stay in the caches.
SINGLE_PASS_ENTRIES = 1 << 21
#: Voxels whose entries are counted to size the slots of the single-pass build.
CAPACITY_SAMPLE = 256
#: Checks per view of elimination's first pass over the grid (see :meth:`Projector.eliminate`).
PREFILTER_CHECKS = 4
#: What to change when the weights do not fit.
ADVICE = "use a coarser --pvr, a smaller volume, or fewer sub-apertures"
#: GPU threads that share one voxel's row of weights in the MART kernels (a warp).
LANES = 32
#: Ways to build DRT weights (see :meth:`Projector.weights`).
BUILDS = ("auto", "single-pass", "two-pass")
#: Where weights live (see :meth:`Projector.weights`).
STORAGE = ("auto", "stored", "on-the-fly")
#: Bytes per voxel of weights made on the fly: its index and its weights' sum.
ON_THE_FLY_BYTES_PER_VOXEL = 8


@dataclass
class WeightChunk:
    """Weights of the voxels ``first .. first + n - 1`` (CSR).

    ``offsets`` (n + 1,) int64 index ``pix`` (int32 global pixel) and ``w`` (float32): voxel
    ``first + t`` has entries ``offsets[t] .. offsets[t + 1] - 1``, one per pixel it lights.
    """

    first: int
    n: int
    offsets: object
    pix: object
    w: object
    nnz: int


@dataclass
class Weights:
    """Sparse voxel-to-pixel weights on the device, voxel-major, in chunks of whole voxels.

    Attributes
    ----------
    voxels
        (n,) int32 flat indices into the (z, y, x) grid of the voxels that have weights.
    chunks
        The CSR chunks covering voxels 0 .. k - 1 in order, k = ``n_stored`` (all voxels unless
        some weights are made on the fly).
    nnz
        Entries: each (voxel, pixel) once, the fraction of the voxel's light on that pixel.
    sums
        Weights made on the fly (line-of-sight only) of voxels k .. n - 1: (n - k,) float32, the
        sum of each voxel's raw weights (they are divided by it, as stored ones are); None if
        every weight is stored.
    min_weight
        The raw weights below this were dropped (made on the fly, they are dropped again).
    """

    voxels: object
    chunks: list[WeightChunk]
    nnz: int
    sums: object = None
    min_weight: float = 1e-6

    @property
    def n_voxels(self) -> int:
        return int(self.voxels.shape[0])

    @property
    def n_on_the_fly(self) -> int:
        """Voxels whose weights are made in each iteration (the last ones) instead of stored."""
        return 0 if self.sums is None else int(self.sums.shape[0])

    @property
    def n_stored(self) -> int:
        """Voxels whose weights are stored (the first ones)."""
        return self.n_voxels - self.n_on_the_fly

    @property
    def stored(self) -> bool:
        """True if every weight is held in memory."""
        return self.sums is None

    @property
    def nbytes(self) -> int:
        held = sum(c.nnz for c in self.chunks)
        return BYTES_PER_WEIGHT * held + 12 * self.n_stored + ON_THE_FLY_BYTES_PER_VOXEL * self.n_on_the_fly

    def to_numpy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(offsets (n + 1,), pix (nnz,), w (nnz,)) of all chunks joined, on the host."""
        if not self.stored:
            raise ValueError("some of these weights are made on the fly, not stored; build them with "
                             "storage='stored'")
        offs, pix, w = [np.zeros(1, np.int64)], [], []
        base = 0
        for c in self.chunks:
            o = c.offsets.numpy()
            offs.append(o[1:] + base)
            pix.append(c.pix.numpy()[: c.nnz])
            w.append(c.w.numpy()[: c.nnz])
            base += c.nnz
        return (np.concatenate(offs), np.concatenate(pix) if pix else np.zeros(0, np.int32),
                np.concatenate(w) if w else np.zeros(0, np.float32))


def _sub_apertures(cam: Camera, n_sub: int, samples: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Square sub-apertures over the main-lens disc: centroids (k, 2) mm and area shares (k,)."""
    d = cam.aperture_mm
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


class Projector:
    """Cameras and a voxel grid bound on one device.

    Parameters
    ----------
    cameras
        One or more cameras (a joint reconstruction uses every camera's pixels).
    grid
        The voxel grid.
    sub_apertures
        Sub-apertures per axis of the main-lens aperture for the DRT weights; default: the
        camera's pixels per lenslet, so that one sub-aperture maps onto about one pixel.
    device
        Warp device; None for the first GPU, else the CPU.
    """

    def __init__(self, cameras: Sequence[Camera], grid: VolumeGrid, *, sub_apertures: int | None = None,
                 device: str | None = None) -> None:
        from lfcore._kernels import weights as kw
        from lfcore._kernels.optics import camera_params

        if sub_apertures is not None and sub_apertures < 1:
            raise ValueError(f"sub_apertures must be at least 1, got {sub_apertures}")
        self.wp = warp()
        self._kw = kw
        self.cameras = tuple(cameras)
        self.grid = grid
        self.device = resolve_device(device)
        wp = self.wp
        g = kw.Grid()
        g.origin = wp.vec3(*grid.origin_mm)
        g.step = wp.vec3(*grid.voxel_mm)
        g.nz, g.ny, g.nx = grid.shape
        self._grid = g
        self.pixel_offsets = np.cumsum([0] + [c.sensor_px[0] * c.sensor_px[1] for c in self.cameras])
        self.n_pixels = int(self.pixel_offsets[-1])
        self._parts = PrivateCopies()  # projection images of the CPU blocks (see forward)
        self._ratio = None  # the pixels' log ratios of smart_update
        if self.n_pixels >= 2**31 or grid.n_voxels >= 2**31:
            raise MemoryBudgetError("more than 2**31 pixels or voxels; use a coarser --pvr")

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

    # --- zero-voxel elimination ---------------------------------------------------------
    def eliminate(self, lit: Sequence[np.ndarray], min_seen: float = 0.5, max_dark: float = 0.05) -> object:
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

        Returns
        -------
        warp.array
            (n,) int32 flat voxel indices, ascending.
        """
        wp, kw = self.wp, self._kw
        if isinstance(lit, wp.array):
            if lit.dtype != wp.uint8 or lit.shape != (self.n_pixels,) or str(lit.device) != self.device:
                raise ValueError(f"a device lit mask must be ({self.n_pixels},) uint8 on {self.device}, got "
                                 f"{lit.shape} {lit.dtype.__name__} on {lit.device}")
            lit_dev = lit
        else:
            flat = np.concatenate([np.asarray(m, dtype=np.uint8).ravel() for m in lit])
            if flat.size != self.n_pixels:
                raise ValueError(f"lit masks hold {flat.size} pixels, the cameras {self.n_pixels}")
            lit_dev = wp.array(flat, dtype=wp.uint8, device=self.device)
        common = [self._grid, self.views, len(self.cameras), self.sub_a, self.check_order, lit_dev, float(min_seen),
                  float(max_dark), self._checks, self._n_checks]
        # First the whole grid with a few checks per view, then every check on the candidates
        # left: the same voxels as one full pass, but a warp no longer waits for its one kept voxel.
        n = self.grid.n_voxels
        mask = wp.zeros(n, dtype=wp.int32, device=self.device)
        none = wp.empty(0, dtype=wp.int32, device=self.device)
        launch_rows(kw.eliminate, n, [*common, none, PREFILTER_CHECKS, RowOffset(0), mask], self.device)
        candidates = self._compact(mask)
        n = int(candidates.shape[0])
        mask = wp.zeros(max(n, 1), dtype=wp.int32, device=self.device)
        launch_rows(kw.eliminate, n, [*common, candidates, 2**30, RowOffset(0), mask], self.device)
        return self._compact(mask[:n], candidates)

    def precompute_checks(self, n_checks: int | None = None, budget_bytes: int | None = None) -> int:
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

    def all_voxels(self) -> object:
        """Every voxel of the grid (no elimination), as (n,) int32 indices."""
        return self._arange(self.grid.n_voxels)

    def _arange(self, n: int) -> object:
        """0 .. n - 1 as int32, made on the device (a host range to copy would be gigabytes)."""
        out = self.wp.empty(n, dtype=self.wp.int32, device=self.device)
        self.wp.launch(self._kw.iota, dim=n, inputs=[out], device=self.device)
        return out

    def _compact(self, mask, values=None) -> object:
        """The indices where ``mask`` is set (or those entries of ``values``), as (n,) int32."""
        wp, kw = self.wp, self._kw
        scan = wp.empty_like(mask)
        wp.utils.array_scan(mask, scan, inclusive=True)
        count = int(scan[mask.shape[0] - 1 :].numpy()[0]) if mask.shape[0] else 0
        out = wp.empty(count, dtype=wp.int32, device=self.device)
        if values is None:
            values = wp.empty(0, dtype=wp.int32, device=self.device)
        if count:
            wp.launch(kw.compact, dim=mask.shape[0], device=self.device, inputs=[mask, scan, values, out])
        return out

    # --- weights ------------------------------------------------------------------------
    def weights(self, voxels, method: str = "drt", min_weight: float = 1e-6,
                budget_bytes: int | None = None, build: str = "auto", sort: str = "auto",
                storage: str = "stored") -> Weights:
        """Sparse weights of ``voxels`` (from :meth:`eliminate` or :meth:`all_voxels`).

        The DRT kernel emits one entry per (sub-aperture, lenslet, pixel); the entries of a
        voxel that share a pixel are then summed (a sort by pixel within each voxel), which
        stores each (voxel, pixel) once: about a third of the raw entries. The line-of-sight
        kernel meets each pixel of a voxel once, so its entries are stored as they are emitted.

        Two DRT builds give the same weights (to float round-off). ``"two-pass"`` traces every voxel
        twice, once to count its entries and once to write them. ``"single-pass"`` traces once
        into slots of a capacity guessed from a sample of voxels (re-tracing only a chunk with a
        voxel that overflowed), which is about 2.5x faster on the CPU. Entries are merged either
        by the library's segmented sort (fast on a GPU, one thread on the CPU) or by sorting each
        voxel in its own thread (:func:`sort_merge`, several times faster on the CPU); both are
        stable and give the same weights.

        Parameters
        ----------
        voxels
            (n,) int32 flat voxel indices on this projector's device.
        method
            ``"drt"``: dense ray tracing; ``"los"``: the conventional line-of-sight cylinder
            and voxel sphere (MART baseline).
        min_weight
            Raw entries below this are dropped.
        budget_bytes
            Memory the weights may take; default: what the device has free.
        build
            ``"auto"`` (single-pass for DRT weights on the CPU, else two-pass),
            ``"single-pass"`` or ``"two-pass"``. LOS weights are always built in two passes.
        sort
            Merge of a two-pass build: ``"auto"`` (per voxel on the CPU, the library's on a GPU),
            ``"per-voxel"`` or ``"library"``. A single-pass build always sorts per voxel.
        storage
            ``"stored"``; ``"on-the-fly"``: only each voxel's weight sum is kept, and
            :meth:`forward` and :meth:`smart_update` compute the weights again where they use
            them (line-of-sight weights only: the same iterations, to float round-off, in
            ``ON_THE_FLY_BYTES_PER_VOXEL`` bytes per voxel, at the cost of tracing every weight
            twice an iteration);
            ``"auto"``: as many voxels' weights stored as fit in ``budget_bytes``, the rest
            made on the fly (DRT weights are always stored).

        Raises
        ------
        MemoryBudgetError
            If the weights would not fit, with their size.
        """
        with out_of_memory_is_budget_error(self.device, f"the weights of {int(voxels.shape[0]):,} voxels", ADVICE):
            return self._weights(voxels, method, min_weight, budget_bytes, build, sort, storage)

    def _weights(self, voxels, method: str, min_weight: float, budget_bytes: int | None, build: str,
                 sort: str, storage: str) -> Weights:
        wp, kw = self.wp, self._kw
        n = int(voxels.shape[0])
        if method not in ("drt", "los"):
            raise ValueError(f"unknown weight method '{method}'; use 'drt' or 'los'")
        if storage not in STORAGE:
            raise ValueError(f"unknown weight storage '{storage}'; use one of {', '.join(STORAGE)}")
        if method == "drt" and storage == "on-the-fly":
            raise ValueError("DRT weights cannot be made on the fly; use stored ones, or line-of-sight weights "
                             "(mart, mlos-mart)")
        if build not in BUILDS:
            raise ValueError(f"unknown build '{build}'; use one of {', '.join(BUILDS)}")
        if build == "auto":
            build = "single-pass" if self.device == "cpu" else "two-pass"
        if sort not in ("auto", "per-voxel", "library"):
            raise ValueError(f"unknown sort '{sort}'; use auto, per-voxel or library")
        per_voxel = sort == "per-voxel" or (sort == "auto" and self.device == "cpu")
        budget = available_bytes(self.device) if budget_bytes is None else budget_bytes
        if method == "drt" and build == "single-pass":
            return self._drt_single_pass(voxels, float(min_weight), budget)
        counts = wp.zeros(max(n, 1), dtype=wp.int64, device=self.device)
        sums = wp.zeros(max(n, 1), dtype=float, device=self.device)
        offsets = wp.zeros(n + 1, dtype=wp.int64, device=self.device)
        dummy_i = wp.empty(1, dtype=wp.int32, device=self.device)
        dummy_f = wp.empty(1, dtype=float, device=self.device)

        def launch(lo, hi, fill, pix, w, origin=0):
            if method == "los":
                self._los(voxels[lo:hi], fill, min_weight, counts=counts[lo:hi], sums=sums[lo:hi],
                          offsets=offsets[lo:hi + 1], origin=origin, pix=pix, w=w)
                return
            launch_rows(kw.drt_weights, hi - lo, [self._grid, self.views, len(self.cameras), self.sub_a, self.sub_w,
                                                  Rows(voxels[lo:hi]), Rows(offsets[lo:hi + 1]), wp.int64(origin),
                                                  float(min_weight), fill, wp.int64(2**62), Rows(counts[lo:hi]), pix,
                                                  w], self.device)

        if n:
            launch(0, n, 0, dummy_i, dummy_f)
            wp.utils.array_scan(counts[:n], offsets[1:], inclusive=True)
        raw = offsets.numpy()
        stored_n = n
        if method == "los" and storage != "stored":
            # The most first voxels whose weights fit beside the rest's sums and indices, and beside
            # the build's counts and offsets (8 bytes each per voxel) while the chunks are made.
            held = BYTES_PER_WEIGHT * raw
            held += (12 - ON_THE_FLY_BYTES_PER_VOXEL) * np.arange(n + 1)
            held += (ON_THE_FLY_BYTES_PER_VOXEL + 16) * n
            fit = np.flatnonzero(held <= budget)
            del held
            stored_n = int(fit[-1]) if storage == "auto" and fit.size else 0
        per_chunk = CHUNK_ENTRIES["cpu" if self.device == "cpu" else "cuda"]
        # Chunks of whole voxels with at most `per_chunk` raw entries (a voxel with more gets its own).
        bounds = [0]
        while bounds[-1] < stored_n:
            lo = bounds[-1]
            hi = int(np.searchsorted(raw, raw[lo] + per_chunk, side="right")) - 1
            bounds.append(min(stored_n, max(hi, lo + 1)))
        if method == "los":
            self._check_budget(int(raw[stored_n]), n, budget)  # the raw entries are the weights (below)
        else:
            # the weights must leave room for one chunk's raw entries and their sort
            largest = max((int(raw[hi] - raw[lo]) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)), default=0)
            budget -= MERGE_SCRATCH_BYTES[per_voxel] * largest
        chunks, total = [], 0
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            m = int(raw[hi] - raw[lo])
            if method == "los":
                # A line-of-sight entry is a pixel under its own lenslet, and each lenslet is
                # visited once per camera, so a voxel never meets a pixel twice: the raw entries
                # are the weights, written where they stay (no sort, no merge, no scratch).
                c_offsets = wp.array(raw[lo:hi + 1] - raw[lo], device=self.device)
                pix = wp.empty(max(m, 1), dtype=wp.int32, device=self.device)
                w_raw = wp.empty(max(m, 1), dtype=float, device=self.device)
                launch(lo, hi, 1, pix, w_raw, origin=int(raw[lo]))
                chunks.append(WeightChunk(first=lo, n=hi - lo, offsets=c_offsets, pix=pix, w=w_raw, nnz=m))
                total += m
                continue
            scratch = max(2 * m, 2)
            pix = wp.empty(scratch, dtype=wp.int32, device=self.device)
            w_raw = wp.empty(max(m, 1), dtype=float, device=self.device)
            launch(lo, hi, 1, pix, w_raw, origin=int(raw[lo]))
            starts = wp.array((raw[lo:hi] - raw[lo]).astype(np.int32), device=self.device)
            ends = wp.array((raw[lo + 1:hi + 1] - raw[lo]).astype(np.int32), device=self.device)
            merged_pix = wp.empty(max(m, 1), dtype=wp.int32, device=self.device)
            merged_w = wp.empty(max(m, 1), dtype=float, device=self.device)
            kept = wp.empty(hi - lo, dtype=wp.int32, device=self.device)
            if per_voxel:
                # each voxel sorted and merged by its own thread: the same stable result as the
                # library's segmented sort, which runs on one CPU thread and is several times slower
                order, tmp_pix, tmp_ord = (wp.empty(scratch, dtype=wp.int32, device=self.device) for _ in range(3))
                launch_rows(kw.sort_merge, hi - lo, [Rows(starts), Rows(ends), pix, order, tmp_pix, tmp_ord, w_raw,
                                                     merged_pix, merged_w, Rows(kept)], self.device)
                del tmp_pix, tmp_ord
            else:
                order = self._arange(scratch)
                wp.utils.segmented_sort_pairs(pix, order, m, starts, ends)
                launch_rows(kw.merge_sorted, hi - lo, [Rows(starts), Rows(ends), pix, order, w_raw, merged_pix,
                                                       merged_w, Rows(kept)], self.device)
            del pix, order, w_raw
            chunk = self._pack(lo, hi, starts, kept, merged_pix, merged_w, total, n, budget)
            total += chunk.nnz
            chunks.append(chunk)
        if stored_n < n:  # the rest made on the fly: keep their sums, free their counts
            return Weights(voxels=voxels, chunks=chunks, nnz=int(raw[n]), sums=sums[stored_n:n],
                           min_weight=float(min_weight))
        return Weights(voxels=voxels, chunks=chunks, nnz=total)

    def _los(self, voxels, fill: int, min_weight: float, *, counts=None, sums, offsets=None, origin: int = 0,
             pix=None, w=None, e=None, proj=None, ratio=None, relaxation: float = 0.0) -> None:
        """Launch the line-of-sight kernel over ``voxels`` in mode ``fill`` (see :func:`los_weights`).

        Arrays a mode does not use may be left out; ``proj`` is the :class:`PerBlock` output of a
        projection.
        """
        wp = self.wp
        dev = self.device
        i64 = wp.empty(1, dtype=wp.int64, device=dev)
        f32 = wp.empty(1, dtype=float, device=dev)
        i32 = wp.empty(1, dtype=wp.int32, device=dev)

        def rows(a, empty):
            return empty if a is None else Rows(a)

        launch_rows(self._kw.los_weights, int(voxels.shape[0]),
                    [self._grid, self.views, len(self.cameras), Rows(voxels), rows(offsets, i64),
                     wp.int64(origin), float(min_weight), fill, rows(counts, i64), Rows(sums),
                     i32 if pix is None else pix, f32 if w is None else w, rows(e, f32),
                     PerBlock((f32,)) if proj is None else proj, f32 if ratio is None else ratio,
                     float(relaxation), self._overlap], dev)

    def _check_budget(self, entries: int, n: int, budget: int) -> None:
        """Raise :class:`MemoryBudgetError` if ``entries`` weights (of ``n`` voxels) pass ``budget`` bytes."""
        if BYTES_PER_WEIGHT * entries > budget:
            raise MemoryBudgetError(
                f"the weights need at least {BYTES_PER_WEIGHT * entries / 2**30:.1f} GiB for {n} voxels but "
                f"{self.device} has {budget / 2**30:.1f} GiB free; {ADVICE}")

    def _pack(self, lo: int, hi: int, starts, kept, merged_pix, merged_w, total: int, n: int,
              budget: int) -> WeightChunk:
        """The chunk of voxels ``lo .. hi - 1`` from their merged entries (at ``starts``, ``kept`` each)."""
        wp, kw = self.wp, self._kw
        kept_h = kept.numpy().astype(np.int64)
        c_off = np.zeros(hi - lo + 1, dtype=np.int64)
        np.cumsum(kept_h, out=c_off[1:])
        nnz = int(c_off[-1])
        self._check_budget(total + nnz, n, budget)
        c_offsets = wp.array(c_off, device=self.device)
        out_pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=self.device)
        out_w = wp.empty(max(nnz, 1), dtype=float, device=self.device)
        launch_rows(kw.gather_merged, hi - lo, [Rows(starts), Rows(c_offsets), Rows(kept), merged_pix, merged_w,
                                                out_pix, out_w], self.device)
        return WeightChunk(first=lo, n=hi - lo, offsets=c_offsets, pix=out_pix, w=out_w, nnz=nnz)

    def _drt_single_pass(self, voxels, min_weight: float, budget: int) -> Weights:
        """DRT weights traced once per voxel into fixed-capacity slots (see :meth:`weights`)."""
        wp, kw = self.wp, self._kw
        dev = self.device
        n = int(voxels.shape[0])
        if n == 0:
            return Weights(voxels=voxels, chunks=[], nnz=0)
        common = [self._grid, self.views, len(self.cameras), self.sub_a, self.sub_w]
        dummy_i = wp.empty(1, dtype=wp.int32, device=dev)
        dummy_f = wp.empty(1, dtype=float, device=dev)

        def trace(vox, offs, fill, limit, counts, pix, w):
            launch_rows(kw.drt_weights, vox.shape[0], [*common, Rows(vox), Rows(offs), wp.int64(0), min_weight, fill,
                                                       wp.int64(limit), Rows(counts), pix, w], dev)

        # Slot capacity: the most entries of a sample of voxels spread over the list, plus a margin.
        take = np.unique(np.linspace(0, n - 1, min(n, CAPACITY_SAMPLE)).astype(np.int64))
        sample = wp.array(voxels.numpy()[take], dtype=wp.int32, device=dev)
        counts = wp.zeros(len(take), dtype=wp.int64, device=dev)
        trace(sample, wp.zeros(len(take) + 1, dtype=wp.int64, device=dev), 0, 0, counts, dummy_i, dummy_f)
        cap = int(1.25 * int(counts.numpy().max())) + 32
        per_chunk = max(1, SINGLE_PASS_ENTRIES // cap)
        chunks, group, total = [], [], 0
        for lo in range(0, n, per_chunk):
            hi = min(n, lo + per_chunk)
            m = hi - lo
            vox = voxels[lo:hi]
            slots = np.arange(m + 1, dtype=np.int64) * cap
            pix = wp.empty(m * cap, dtype=wp.int32, device=dev)
            w_raw = wp.empty(m * cap, dtype=float, device=dev)
            counts = wp.zeros(m, dtype=wp.int64, device=dev)
            trace(vox, wp.array(slots, device=dev), 1, cap, counts, pix, w_raw)
            cnt = counts.numpy()
            if int(cnt.max()) > cap:  # a voxel overflowed its slot: re-trace the chunk at exact offsets
                slots = np.zeros(m + 1, dtype=np.int64)
                np.cumsum(cnt, out=slots[1:])
                pix = wp.empty(max(int(slots[-1]), 1), dtype=wp.int32, device=dev)
                w_raw = wp.empty(max(int(slots[-1]), 1), dtype=float, device=dev)
                trace(vox, wp.array(slots, device=dev), 1, 2**62, counts, pix, w_raw)
            starts = wp.array(slots[:-1].astype(np.int32), device=dev)
            ends = wp.array((slots[:-1] + cnt).astype(np.int32), device=dev)
            order = wp.empty(pix.shape[0], dtype=wp.int32, device=dev)
            tmp_pix = wp.empty(pix.shape[0], dtype=wp.int32, device=dev)
            tmp_ord = wp.empty(pix.shape[0], dtype=wp.int32, device=dev)
            merged_pix = wp.empty(pix.shape[0], dtype=wp.int32, device=dev)
            merged_w = wp.empty(pix.shape[0], dtype=float, device=dev)
            kept = wp.empty(m, dtype=wp.int32, device=dev)
            launch_rows(kw.sort_merge, m, [Rows(starts), Rows(ends), pix, order, tmp_pix, tmp_ord, w_raw, merged_pix,
                                           merged_w, Rows(kept)], dev)
            del pix, order, tmp_pix, tmp_ord, w_raw
            chunk = self._pack(lo, hi, starts, kept, merged_pix, merged_w, total, n, budget)
            total += chunk.nnz
            if group and sum(c.nnz for c in group) + chunk.nnz > CHUNK_ENTRIES["cpu" if dev == "cpu" else "cuda"]:
                chunks += self._joined(group, total - chunk.nnz, budget)
                group = []
            group.append(chunk)
        chunks += self._joined(group, total, budget)
        return Weights(voxels=voxels, chunks=chunks, nnz=total)

    def _joined(self, group: list[WeightChunk], total: int, budget: int) -> list[WeightChunk]:
        """Consecutive chunks as one, if its copy fits beside the ``total`` weights held.

        The single-pass build makes chunks of a few hundred voxels, and every chunk is one
        launch per kernel and iteration: on the CPU, where a launch is spread over the cores,
        a hundred chunks cost more in launches than in work.
        """
        nnz = sum(c.nnz for c in group)
        if len(group) < 2 or BYTES_PER_WEIGHT * (total + nnz) > budget:
            return group
        wp = self.wp
        pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=self.device)
        w = wp.empty(max(nnz, 1), dtype=float, device=self.device)
        offsets, at = [np.zeros(1, dtype=np.int64)], 0
        for c in group:
            if c.nnz:
                wp.copy(pix, c.pix, dest_offset=at, count=c.nnz)
                wp.copy(w, c.w, dest_offset=at, count=c.nnz)
            offsets.append(c.offsets.numpy()[1:] + at)
            at += c.nnz
        n = sum(c.n for c in group)
        return [WeightChunk(first=group[0].first, n=n, offsets=wp.array(np.concatenate(offsets), device=self.device),
                            pix=pix, w=w, nnz=nnz)]

    # --- projections and updates --------------------------------------------------------
    def forward(self, weights: Weights, e, out=None):
        """Project voxel intensities ``e`` (n,) to all pixels; returns (n_pixels,) float32."""
        from lfcore._kernels import mart as km

        wp = self.wp
        out = wp.zeros(self.n_pixels, dtype=float, device=self.device) if out is None else out
        out.zero_()
        # The projection accumulates into pixels with atomics, which are plain adds on the CPU:
        # there each CPU block sums into a private image, and the images are added after.
        parts = self._parts.open(out)
        k = weights.n_stored
        if k < weights.n_voxels:
            self._los(weights.voxels[k:], 2, weights.min_weight, sums=weights.sums, e=e[k:weights.n_voxels],
                      proj=parts)
        lanes = 1 if self.device == "cpu" else LANES
        for c in weights.chunks:
            launch_rows(km.project, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), lanes, e, parts],
                        self.device, rest=(lanes,))
        self._parts.close(out)
        return out

    def smart_update(self, weights: Weights, image, proj, e, relaxation: float, floor: float) -> None:
        """One simultaneous multiplicative update of ``e`` in place (see the kernel).

        ``image`` and ``proj`` are (n_pixels,) float32: the measured signal and the forward
        projection of ``e``; ``floor`` (counts) is the least a pixel's measurement counts as.
        """
        from lfcore._kernels import mart as km

        wp = self.wp
        if self._ratio is None or self._ratio.shape[0] != self.n_pixels:
            self._ratio = wp.empty(self.n_pixels, dtype=float, device=self.device)
        wp.launch(km.log_ratio, dim=self.n_pixels, inputs=[image, proj, float(floor), self._ratio], device=self.device)
        mu = float(relaxation)
        k = weights.n_stored
        if k < weights.n_voxels:
            self._los(weights.voxels[k:], 3, weights.min_weight, sums=weights.sums, e=e[k:weights.n_voxels],
                      ratio=self._ratio, relaxation=mu)
        for c in weights.chunks:
            if self.device == "cpu":
                launch_rows(km.smart_update, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first),
                                                   self._ratio, mu, e], self.device)
            elif c.n:  # a warp per voxel, its lanes' sums added by a block reduction
                wp.launch_tiled(km.smart_update_tiled, dim=[c.n], block_dim=LANES, device=self.device,
                                inputs=[c.offsets, c.pix, c.w, c.first, self._ratio, mu, e])

    def transpose(self, weights: Weights):
        """Pixel-major copy of the weights for the sequential form: (p_offsets, vox, w, rows)."""
        wp = self.wp
        offsets, pix, w = weights.to_numpy()
        vox = np.repeat(np.arange(weights.n_voxels, dtype=np.int32), np.diff(offsets))
        order = np.argsort(pix, kind="stable")
        p_offsets = np.zeros(self.n_pixels + 1, dtype=np.int64)
        np.cumsum(np.bincount(pix, minlength=self.n_pixels), out=p_offsets[1:])
        rows = np.flatnonzero(np.diff(p_offsets)).astype(np.int32)
        dev = self.device
        return (wp.array(p_offsets, device=dev), wp.array(vox[order], device=dev),
                wp.array(w[order], device=dev), wp.array(rows, device=dev))

    def mart_sweep(self, transposed, image, e, relaxation: float, floor: float) -> None:
        """One sequential sweep of eq. 4.1 over every pixel with weights (single thread)."""
        from lfcore._kernels import mart as km

        p_offsets, vox, w, rows = transposed
        self.wp.launch(km.mart_sequential, dim=1, device=self.device,
                       inputs=[p_offsets, vox, w, rows, image, float(floor), float(relaxation), e])

    def to_volume(self, weights: Weights, e) -> np.ndarray:
        """Dense (z, y, x) float32 volume with ``e`` at the weighted voxels, zero elsewhere."""
        return self.scatter(weights, e).numpy()

    def scatter(self, weights: Weights, e, out=None):
        """Like :meth:`to_volume`, but the (z, y, x) volume stays on the device.

        Parameters
        ----------
        weights, e
            The reconstructed voxels and their (n,) intensities.
        out
            (nz, ny, nx) float32 Warp array to write (zeroed first); None: a new one.

        Returns
        -------
        warp.array
            ``out`` (or the new array), (nz, ny, nx) float32 on the projector's device.
        """
        from lfcore._kernels import mart as km

        wp = self.wp
        if out is None:
            out = wp.zeros(self.grid.shape, dtype=float, device=self.device)
        else:
            if tuple(out.shape) != tuple(self.grid.shape):
                raise ValueError(f"the volume must be {self.grid.shape} (z, y, x), got {out.shape}")
            out.zero_()
        if weights.n_voxels:
            flat = out.reshape(self.grid.n_voxels)
            launch_rows(km.scatter_volume, weights.n_voxels, [Rows(weights.voxels), Rows(e), flat], self.device)
        return out
