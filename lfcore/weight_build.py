"""The stored sparse voxel-to-pixel weights: building them, and applying them as an operator.

A projector (:class:`~lfcore.projector.LightFieldProjector`) binds cameras and a grid on a
device; this module builds its weights, as tomography toolkits keep geometry, operator and
algorithm apart, and :class:`Weights` applies them: it is the :class:`~lfcore.operator.Operator`
of every kind that stores its rows (ray-traced DRT weights, line-of-sight weights, the matrix-free
templates' images, pinhole and joint weights; :attr:`Weights.kind` says which). Two kinds are
built here, both voxel-major CSR in chunks of whole voxels:

- dense ray tracing (DRT, DRT-MART): one raw entry per (sub-aperture, lenslet, pixel), the
  entries of a voxel that share a pixel then summed (a sort by pixel within each voxel), so
  each (voxel, pixel) is stored once: about a third of the raw entries. Built in two passes
  (count, then write at the counted offsets) or in a single pass into slots of a guessed
  capacity;
- line of sight (LOS, the MART baseline and MLOS-MART): each pixel of a voxel met once, so the
  entries are stored as emitted; or, where they do not fit, made again in each iteration from
  each voxel's stored weight sum (:meth:`WeightBuilder.trace_los` modes 2 and 3).

Every build checks its size against a memory budget first and says what to change when the
weights do not fit (:class:`~lfcore.device.MemoryBudgetError`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lfcore.device import (
    MemoryBudgetError,
    PerBlock,
    PrivateCopies,
    RowOffset,
    Rows,
    available_bytes,
    cpu_threads,
    launch_rows,
    out_of_memory_is_budget_error,
    warp,
)
from lfcore.operator import LINE_OF_SIGHT, STORAGE, TEMPLATE_IMAGES, TRACED, gather, scatter_voxels

__all__ = ["ADVICE", "BUILDS", "BYTES_PER_WEIGHT", "CHUNK_ENTRIES", "LANES", "ON_THE_FLY_BYTES_PER_VOXEL", "STORAGE",
           "Binding", "WeightBuilder", "WeightChunk", "Weights", "device_range"]

#: Bytes per stored weight: an int32 pixel index and a float32 value.
BYTES_PER_WEIGHT = 8
#: Raw (unmerged) entries built at once; bounds the scratch memory of a weight build.
CHUNK_ENTRIES = {"cpu": 1 << 25, "cuda": 1 << 28}
#: Scratch bytes per raw entry of a two-pass DRT build, by merge (per voxel or not): pixels and
#: sort order (twice each, three times per voxel), the raw value, the merged pixel and value.
MERGE_SCRATCH_BYTES = {False: 28, True: 44}
#: Raw-entry slots per chunk of the single-pass DRT build: small enough to stay in the caches.
SINGLE_PASS_ENTRIES = 1 << 21
#: The single-pass line-of-sight build packs its chunks into one array of this many times the entries the
#: capacity sample's mean gives (:meth:`WeightBuilder._los_single_pass`): a margin for a sample's error.
LOS_PACKED_MARGIN = 1.1
#: Voxels whose entries are counted to size the slots of the single-pass build.
CAPACITY_SAMPLE = 256
#: What to change when the weights do not fit.
ADVICE = "use a coarser --pvr, a smaller volume, or fewer sub-apertures"
#: Ways to build DRT weights (see :meth:`WeightBuilder.weights`).
BUILDS = ("auto", "single-pass", "two-pass")
#: GPU threads that share one voxel's row of weights in the MART kernels (a warp).
LANES = 32
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


@dataclass(eq=False)
class Binding:
    """What applying stored weights needs of the projector that made them.

    Attributes
    ----------
    device
        The Warp device of the weights.
    n_pixels
        Pixels of all the projector's cameras (the length of a projection).
    shape
        (nz, ny, nx) of the projector's grid (a depth slab's own), for the scatter.
    builder
        The :class:`WeightBuilder` that makes line-of-sight weights again in every iteration
        (None where every weight is stored).
    parts
        The projector's private images for the CPU blocks of a projection (kept between calls).
    """

    device: str
    n_pixels: int
    shape: tuple[int, int, int]
    builder: WeightBuilder | None
    parts: PrivateCopies


@dataclass(eq=False)
class Weights:
    """Sparse voxel-to-pixel weights on the device, voxel-major, in chunks of whole voxels: the
    :class:`~lfcore.operator.Operator` of every kind that stores its rows.

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
    kind
        What the rows are (:data:`lfcore.operator.ALL_KINDS`): ``"traced weights"`` (ray-traced DRT),
        ``"line-of-sight weights"``, ``"template images"`` (the matrix-free templates' images,
        :meth:`TemplateOperator.expanded <lfcore.matrix_free.TemplateOperator.expanded>`),
        ``"pinhole weights"`` or ``"joint weights"``.
    binding
        What applying them needs of their projector (:class:`Binding`; set by the projector that
        made them, which :meth:`forward`, :meth:`update` and :meth:`scatter` need).
    """

    voxels: object
    chunks: list[WeightChunk]
    nnz: int
    sums: object = None
    min_weight: float = 1e-6
    kind: str = TRACED
    binding: Binding | None = field(default=None, repr=False)
    #: Let go by :meth:`restrict` with ``spend``: no rows held, none to apply.
    spent: bool = field(default=False, repr=False)

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
    def from_templates(self) -> bool:
        """True where the entries are the matrix-free templates' images, not ray traced."""
        return self.kind == TEMPLATE_IMAGES

    @property
    def nbytes(self) -> int:
        held = sum(c.nnz for c in self.chunks)
        return BYTES_PER_WEIGHT * held + 12 * self.n_stored + ON_THE_FLY_BYTES_PER_VOXEL * self.n_on_the_fly

    @property
    def device(self) -> str:
        return self.binding.device if self.spent and self.binding is not None else self._bound().device

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

    # --- the operator -------------------------------------------------------------------------------
    def _bound(self) -> Binding:
        if self.spent:
            raise ValueError("these weights were spent by restrict(rows, spend=True); apply the weights it returned")
        if self.binding is None:
            raise ValueError("these weights are not bound to a projector; make them with a projector's operator() "
                             "or weights()")
        return self.binding

    def forward(self, e, *, out=None) -> object:
        """Project voxel intensities ``e`` (n,) to all pixels; returns ``out`` (n_pixels,) float32
        (zeroed first; None: a new array)."""
        from lfcore._kernels import mart as km

        b = self._bound()
        wp = warp()
        out = wp.zeros(b.n_pixels, dtype=float, device=b.device) if out is None else out
        out.zero_()
        # The projection accumulates into pixels with atomics, which are plain adds on the CPU:
        # there each CPU block sums into a private image, and the images are added after.
        parts = b.parts.open(out)
        k = self.n_stored
        if k < self.n_voxels:
            b.builder.trace_los(self.voxels[k:], 2, self.min_weight, sums=self.sums, e=e[k:self.n_voxels], proj=parts)
        for c in self.chunks:
            if b.device == "cpu":  # a thread per voxel
                launch_rows(km.project_rows, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), e, parts],
                            b.device)
            else:  # a warp's lanes per voxel
                launch_rows(km.project, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), LANES, e,
                                              parts], b.device, rest=(LANES,))
        b.parts.close(out)
        return out

    def update(self, ratio, e, relaxation: float) -> None:
        """One simultaneous multiplicative (SMART) update of ``e`` in place:
        ``E_v <- E_v exp(mu sum_i w_iv ratio_i)``, ``ratio`` the (n_pixels,) float32 log ratios of
        :func:`lfcore.operator.log_ratio`."""
        from lfcore._kernels import mart as km

        b = self._bound()
        wp = warp()
        mu = float(relaxation)
        k = self.n_stored
        if k < self.n_voxels:
            b.builder.trace_los(self.voxels[k:], 3, self.min_weight, sums=self.sums, e=e[k:self.n_voxels],
                                ratio=ratio, relaxation=mu)
        for c in self.chunks:
            if b.device == "cpu":
                launch_rows(km.smart_update, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first),
                                                   ratio, mu, e], b.device)
            elif c.n:  # a warp per voxel, its lanes' sums added by a block reduction
                wp.launch_tiled(km.smart_update_tiled, dim=[c.n], block_dim=LANES, device=b.device,
                                inputs=[c.offsets, c.pix, c.w, c.first, ratio, mu, e])

    def scatter(self, e, *, out=None) -> object:
        """The dense (z, y, x) float32 volume with ``e`` at these voxels, zero elsewhere, on the
        device (``out`` zeroed and written; None: a new array)."""
        b = self._bound()
        return scatter_voxels(self.voxels, e, b.shape, device=b.device, out=out)

    def to_volume(self, e) -> np.ndarray:
        """Like :meth:`scatter`, as a host (z, y, x) float32 array."""
        return self.scatter(e).numpy()

    def restrict(self, rows, *, spend: bool = False) -> Weights:
        """The weights of some of these voxels: ``rows`` (k,) int32 row indices (ascending, on the
        device); row t of the result is row ``rows[t]`` of these, copied (new arrays, so these may be
        let go). Rows made on the fly stay so (their sums are kept); ``nnz`` then counts the stored
        entries only.

        ``spend``: these weights are let go chunk by chunk as each chunk's kept rows are copied, so
        that beside the rows kept so far stands one chunk's copy at a time (:func:`restrict_bytes`), not
        the copy of every kept row beside all of these; they are then spent (applying them raises).
        """
        from lfcore._kernels import weights as kw

        b = self._bound()
        wp = warp()
        dev = b.device
        rows_h = np.asarray(rows.numpy(), dtype=np.int64)
        k = self.n_stored
        stored = rows_h[rows_h < k]
        chunks, first, total = [], 0, 0
        old = self.chunks
        if spend:  # this object holds no chunk from here on: each goes once copied (or passed over)
            self.chunks, self.spent = [], True
        for i, c in enumerate(old):
            if spend:
                old[i] = None
            sel = stored[(stored >= c.first) & (stored < c.first + c.n)] - c.first
            if sel.size == 0:
                continue
            offs = c.offsets.numpy()
            new = np.zeros(sel.size + 1, dtype=np.int64)
            np.cumsum(offs[sel + 1] - offs[sel], out=new[1:])
            nnz = int(new[-1])
            offsets = wp.array(new, dtype=wp.int64, device=dev)
            pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=dev)
            w = wp.empty(max(nnz, 1), dtype=float, device=dev)
            if nnz:
                starts = wp.array(offs[sel], dtype=wp.int64, device=dev)
                launch_rows(kw.copy_rows, int(sel.size), [Rows(starts), Rows(offsets, extra=1), c.pix, c.w, pix, w],
                            dev)
            chunks.append(WeightChunk(first=first, n=int(sel.size), offsets=offsets, pix=pix, w=w, nnz=nnz))
            first += int(sel.size)
            total += nnz
            del c  # a spent chunk goes here, before the next one is copied
        del old
        sums = None
        if self.sums is not None and rows_h.size > stored.size:  # the rows made on the fly: their sums
            sums = gather(self.sums, wp.array((rows_h[stored.size:] - k).astype(np.int32), dtype=wp.int32,
                                              device=dev))
        return Weights(voxels=gather(self.voxels, rows), chunks=chunks, nnz=total, sums=sums,
                       min_weight=self.min_weight, kind=self.kind, binding=self.binding)

    def transpose(self) -> tuple:
        """Pixel-major copy of the weights for the sequential form: (p_offsets, vox, w, rows)."""
        wp, b = warp(), self._bound()
        offsets, pix, w = self.to_numpy()
        vox = np.repeat(np.arange(self.n_voxels, dtype=np.int32), np.diff(offsets))
        order = np.argsort(pix, kind="stable")
        p_offsets = np.zeros(b.n_pixels + 1, dtype=np.int64)
        np.cumsum(np.bincount(pix, minlength=b.n_pixels), out=p_offsets[1:])
        rows = np.flatnonzero(np.diff(p_offsets)).astype(np.int32)
        dev = b.device
        return (wp.array(p_offsets, device=dev), wp.array(vox[order], device=dev),
                wp.array(w[order], device=dev), wp.array(rows, device=dev))

    def sweep(self, transposed, image, e, relaxation: float, floor: float) -> None:
        """One sequential sweep of eq. 4.1 over every pixel with weights (a single thread);
        ``transposed`` from :meth:`transpose`."""
        from lfcore._kernels import mart as km

        p_offsets, vox, w, rows = transposed
        warp().launch(km.mart_sequential, dim=1, device=self._bound().device,
                      inputs=[p_offsets, vox, w, rows, image, float(floor), float(relaxation), e])


def device_range(n: int, *, device: str) -> object:
    """0 .. n - 1 as an (n,) int32 Warp array made on ``device`` (a host range to copy would be gigabytes)."""
    from lfcore._kernels import weights as kw

    wp = warp()
    out = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(kw.iota, dim=n, inputs=[out], device=device)
    return out


class WeightBuilder:
    """Builds the weights of one camera set and grid, already on the device.

    Parameters
    ----------
    grid
        The grid as the weight kernels see it (:class:`lfcore._kernels.weights.Grid`).
    views
        (cameras,) :class:`lfcore._kernels.weights.View` Warp array: each camera's optics,
        pose, sub-apertures and line-of-sight constants.
    sub_a, sub_w
        (sub-apertures,) ``vec2`` centroids (mm, on the main lens) and float32 shares of every
        camera's sub-apertures, camera after camera (the views index them).
    overlap
        float32 tables of the line-of-sight circle overlap, one per camera (the views index them).
    device
        The Warp device all of these live on.

    Notes
    -----
    A :class:`~lfcore.projector.Projector` makes one for its geometry; use
    :meth:`Projector.weights <lfcore.projector.Projector.weights>`.
    """

    def __init__(self, grid, views, sub_a, sub_w, overlap, *, device: str) -> None:
        from lfcore._kernels import weights as kw

        self.wp = warp()
        self._kw = kw
        self.grid = grid
        self.views = views
        self.n_views = int(views.shape[0])
        self.sub_a = sub_a
        self.sub_w = sub_w
        self.overlap = overlap
        self.device = device
        wp = self.wp
        # stand-ins for the arrays a kernel mode does not use
        self._i64 = wp.empty(1, dtype=wp.int64, device=device)
        self._f32 = wp.empty(1, dtype=float, device=device)
        self._i32 = wp.empty(1, dtype=wp.int32, device=device)

    def weights(self, voxels, *, method: str = "drt", min_weight: float = 1e-6, budget_bytes: int | None = None,
                build: str = "auto", sort: str = "auto", storage: str = "stored") -> Weights:
        """Sparse weights of ``voxels``.

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
            (n,) int32 flat indices into the (z, y, x) grid, on the builder's device.
        method
            ``"drt"``: dense ray tracing; ``"los"``: the conventional line-of-sight cylinder
            and voxel sphere (MART baseline).
        min_weight
            Raw entries below this are dropped.
        budget_bytes
            Memory the weights may take; default: what the device has free.
        build
            ``"auto"`` (single-pass on the CPU, else two-pass), ``"single-pass"`` or ``"two-pass"``.
            LOS weights are built in one pass only where they are all stored (``storage`` ``"stored"``,
            or ``"auto"`` with room for them all); both builds give the same weights to the bit.
        sort
            Merge of a two-pass build: ``"auto"`` (per voxel on the CPU, the library's on a GPU),
            ``"per-voxel"`` or ``"library"``. A single-pass build always sorts per voxel.
        storage
            ``"stored"``; ``"on-the-fly"``: only each voxel's weight sum is kept, and the
            projection and the update compute the weights again where they use them
            (line-of-sight weights only: the same iterations, to float round-off, in
            ``ON_THE_FLY_BYTES_PER_VOXEL`` bytes per voxel, at the cost of tracing every weight
            twice an iteration);
            ``"auto"``: as many voxels' weights stored as fit in ``budget_bytes``, the rest
            made on the fly (DRT weights are always stored).

        Returns
        -------
        Weights
            The weights, on the builder's device.

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
        if method == "los" and build == "single-pass" and storage != "on-the-fly" and n:
            single = self._los_single_pass(voxels, float(min_weight), budget, held=storage == "stored")
            if single is not None:
                return single
        counts = wp.zeros(max(n, 1), dtype=wp.int64, device=self.device)
        sums = wp.zeros(max(n, 1), dtype=float, device=self.device)
        offsets = wp.zeros(n + 1, dtype=wp.int64, device=self.device)

        def launch(lo, hi, fill, pix, w, origin=0):
            if method == "los":
                self.trace_los(voxels[lo:hi], fill, min_weight, counts=counts[lo:hi], sums=sums[lo:hi],
                               offsets=offsets[lo:hi + 1], origin=origin, pix=pix, w=w)
                return
            launch_rows(kw.drt_weights, hi - lo, [self.grid, self.views, self.n_views, self.sub_a, self.sub_w,
                                                  Rows(voxels[lo:hi]), Rows(offsets[lo:hi + 1]), wp.int64(origin),
                                                  float(min_weight), fill, wp.int64(2**62), Rows(counts[lo:hi]), pix,
                                                  w], self.device)

        if n:
            launch(0, n, 0, self._i32, self._f32)
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
                                                     merged_pix, merged_w, Rows(kept), 0.0], self.device)
                del tmp_pix, tmp_ord
            else:
                order = device_range(scratch, device=self.device)
                wp.utils.segmented_sort_pairs(pix, order, m, starts, ends)
                launch_rows(kw.merge_sorted, hi - lo, [Rows(starts), Rows(ends), pix, order, w_raw, merged_pix,
                                                       merged_w, Rows(kept), 0.0], self.device)
            del pix, order, w_raw
            chunk = self._pack(lo, hi, starts, kept, merged_pix, merged_w, total, n, budget)
            total += chunk.nnz
            chunks.append(chunk)
        if stored_n < n:  # the rest made on the fly: keep their sums, free their counts
            return Weights(voxels=voxels, chunks=chunks, nnz=int(raw[n]), sums=sums[stored_n:n], kind=LINE_OF_SIGHT,
                           min_weight=float(min_weight))
        return Weights(voxels=voxels, chunks=chunks, nnz=total, kind=TRACED if method == "drt" else LINE_OF_SIGHT)

    def _packed_chunk(self, packed, offsets: list[np.ndarray], total: int) -> WeightChunk:
        """The chunk of the voxels packed so far into ``packed`` ((pix, w) arrays; ``offsets`` their rows'
        offsets, in pieces), from the first voxel on: views of the first ``total`` entries."""
        c_off = np.concatenate(offsets)
        end = max(total, 1)
        return WeightChunk(first=0, n=c_off.size - 1, offsets=self.wp.array(c_off, device=self.device),
                           pix=packed[0][:end], w=packed[1][:end], nnz=total)

    def _sample_counts(self, voxels, count) -> np.ndarray:
        """The entries of a sample of ``voxels`` spread over the list (:data:`CAPACITY_SAMPLE`), counted by
        ``count(sample, counts)`` into (m,) int64 ``counts``: (m,) int64 on the host."""
        n = int(voxels.shape[0])
        take = np.unique(np.linspace(0, n - 1, min(n, CAPACITY_SAMPLE)).astype(np.int64))
        sample = self.wp.array(voxels.numpy()[take], dtype=self.wp.int32, device=self.device)
        counts = self.wp.zeros(len(take), dtype=self.wp.int64, device=self.device)
        count(sample, counts)
        return counts.numpy()

    def _slot_capacity(self, voxels, count) -> int:
        """Entries a single-pass build's slot holds: the most of a sample of ``voxels`` spread over the
        list (:data:`CAPACITY_SAMPLE`), counted by ``count(sample, counts)`` into (m,) int64 ``counts``,
        plus a margin."""
        return int(1.25 * int(self._sample_counts(voxels, count).max())) + 32

    def _los_single_pass(self, voxels, min_weight: float, budget: int, *, held: bool) -> Weights | None:
        """Line-of-sight weights of ``voxels`` traced once (:func:`~lfcore._kernels.weights.los_weights`
        mode 4: counted, summed and written into slots of a capacity guessed from a sample, then
        divided and packed), the same weights as the two-pass build's to the bit, in about half its
        tracing. None where they might not all be stored within ``budget`` (unless ``held``: storage
        ``"stored"``, which refuses what does not fit as the two-pass build does): the two-pass build
        then chooses which to store and which to make on the fly."""
        wp, kw, dev = self.wp, self._kw, self.device
        n = int(voxels.shape[0])

        def trace(vox, slots, fill, counts, sums, pix, w):
            self.trace_los(vox, fill, min_weight, counts=counts, sums=sums, offsets=slots, pix=pix, w=w)

        sampled = self._sample_counts(voxels, lambda sample, counts: trace(
            sample, None, 0, counts, wp.zeros(counts.shape[0], dtype=float, device=dev), None, None))
        cap = int(1.25 * int(sampled.max())) + 32
        if not held and BYTES_PER_WEIGHT * cap * n + (ON_THE_FLY_BYTES_PER_VOXEL + 28) * n > budget:
            return None  # perhaps not all stored: the two-pass build counts them first
        per_chunk = max(1, SINGLE_PASS_ENTRIES // cap)
        limit = CHUNK_ENTRIES["cpu" if dev == "cpu" else "cuda"]
        # On the CPU the chunks packed straight into one array where the sample's mean says they fit it (with
        # a margin): no copy to join them (:meth:`_joined`), one allocation instead of one per chunk (the
        # array's unwritten end is never touched there; a GPU's memory would hold it, and its copies are
        # cheap). A chunk that would pass its end (the guess too low) ends it; the rest then goes as before.
        guess = int(LOS_PACKED_MARGIN * float(sampled.mean()) * n) + cap
        packed = None
        if (dev == "cpu" and n > per_chunk and guess <= limit
                and BYTES_PER_WEIGHT * (guess + cap * per_chunk) <= budget):
            packed = (wp.empty(guess, dtype=wp.int32, device=dev), wp.empty(guess, dtype=float, device=dev))
        packed_offsets = [np.zeros(1, dtype=np.int64)]
        # the slots of one chunk, kept for the next (their pages touched once)
        slot_pix = wp.empty(min(n, per_chunk) * cap, dtype=wp.int32, device=dev)
        slot_w = wp.empty(min(n, per_chunk) * cap, dtype=float, device=dev)
        chunks, group, total = [], [], 0
        for lo in range(0, n, per_chunk):
            hi = min(n, lo + per_chunk)
            m = hi - lo
            vox = voxels[lo:hi]
            slots = wp.array(np.arange(m + 1, dtype=np.int64) * cap, device=dev)
            pix, w_raw = slot_pix[: m * cap], slot_w[: m * cap]
            counts = wp.zeros(m, dtype=wp.int64, device=dev)
            sums = wp.zeros(m, dtype=float, device=dev)
            trace(vox, slots, 4, counts, sums, pix, w_raw)
            cnt = counts.numpy()
            c_off = np.zeros(m + 1, dtype=np.int64)
            np.cumsum(cnt, out=c_off[1:])
            nnz = int(c_off[-1])
            self._check_budget(total + nnz, n, budget)
            offsets = wp.array(c_off, device=dev)
            into = packed is not None and total + nnz <= guess
            if packed is not None and not into:  # the guess was low: what is packed (if any) is one chunk
                if len(packed_offsets) > 1:  # voxels packed (their entries perhaps none)
                    group.append(self._packed_chunk(packed, packed_offsets, total))
                packed = None
            if into:
                out_pix, out_w = packed[0][total: total + nnz], packed[1][total: total + nnz]
            else:
                out_pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=dev)
                out_w = wp.empty(max(nnz, 1), dtype=float, device=dev)
            if nnz and int(cnt.max()) > cap:  # a voxel overflowed its slot: this chunk written again at exact offsets
                trace(vox, offsets, 1, None, sums, out_pix, out_w)
            elif nnz:
                launch_rows(kw.pack_line_of_sight, m, [Rows(slots), Rows(counts), Rows(sums), pix, w_raw,
                                                       Rows(offsets), out_pix, out_w], dev)
            total += nnz
            if into:
                packed_offsets.append(c_off[1:] + (total - nnz))
                continue
            chunk = WeightChunk(first=lo, n=m, offsets=offsets, pix=out_pix, w=out_w, nnz=nnz)
            if group and sum(c.nnz for c in group) + nnz > limit:
                chunks += self._joined(group, total - nnz, budget)
                group = []
            group.append(chunk)
        del slot_pix, slot_w
        if packed is not None:
            chunks.append(self._packed_chunk(packed, packed_offsets, total))
        chunks += self._joined(group, total, budget)
        return Weights(voxels=voxels, chunks=chunks, nnz=total, kind=LINE_OF_SIGHT)

    def trace_los(self, voxels, fill: int, min_weight: float, *, counts=None, sums, offsets=None, origin: int = 0,
                  pix=None, w=None, e=None, proj=None, ratio=None, relaxation: float = 0.0) -> None:
        """Launch the line-of-sight kernel over ``voxels`` in mode ``fill``.

        Modes (see :func:`lfcore._kernels.weights.los_weights`): 0 count each voxel's weights
        into ``counts`` and their sum into ``sums``; 1 write them to ``pix``/``w`` from
        ``offsets`` (less ``origin``); 2 project intensities ``e`` into ``proj`` (the
        :class:`~lfcore.device.PerBlock` output of a projection); 3 update ``e`` in place from the
        pixels' log ``ratio`` with ``relaxation``; 4 count and sum as 0 does and write the weights, not
        yet divided by their sum, to ``pix``/``w`` in the slots ``offsets`` bound (the single-pass
        build). Arrays a mode does not use may be left out.
        """
        wp = self.wp

        def rows(a, empty):
            return empty if a is None else Rows(a)

        if proj is None:  # a stand-in for every CPU block (one PerBlock array would make it one block)
            proj = PerBlock((self._f32,) * cpu_threads())

        launch_rows(self._kw.los_weights, int(voxels.shape[0]),
                    [self.grid, self.views, self.n_views, Rows(voxels),
                     self._i64 if offsets is None else Rows(offsets, extra=1),  # mode 4 reads a slot's end
                     wp.int64(origin), float(min_weight), fill, rows(counts, self._i64), Rows(sums),
                     self._i32 if pix is None else pix, self._f32 if w is None else w, rows(e, self._f32),
                     proj, self._f32 if ratio is None else ratio,
                     float(relaxation), self.overlap], self.device)

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

    def merged(self, voxels, trace: Callable, *, budget_bytes: int | None = None, floor: float = 0.0) -> Weights:
        """Stored weights of ``voxels`` from another maker of raw entries, merged and packed as the
        DRT build's are (the matrix-free templates' entries: :meth:`TemplateOperator.expanded
        <lfcore.matrix_free.TemplateOperator.expanded>`).

        Parameters
        ----------
        voxels
            (n,) int32 flat voxel indices on the builder's device.
        trace
            ``trace(voxels, offsets, fill, limit, counts, pix, w)`` launches a kernel with
            :func:`lfcore._kernels.weights.drt_weights`' interface on ``voxels`` (its own entries
            dropped below its own least weight).
        budget_bytes
            Memory the weights may take; default: what the device has free.
        floor
            Merged entries at or below this are dropped, each voxel's others scaled to keep its
            light (0: none dropped).

        Raises
        ------
        MemoryBudgetError
            If the weights would not fit, with their size.
        """
        budget = available_bytes(self.device) if budget_bytes is None else budget_bytes
        with out_of_memory_is_budget_error(self.device, f"the weights of {int(voxels.shape[0]):,} voxels", ADVICE):
            return self._drt_single_pass(voxels, 0.0, budget, trace, floor=floor)

    def _drt_single_pass(self, voxels, min_weight: float, budget: int, trace: Callable | None = None, *,
                         floor: float = 0.0) -> Weights:
        """DRT weights traced once per voxel into fixed-capacity slots (see :meth:`weights`), or
        ``trace``'s entries (see :meth:`merged`)."""
        wp, kw = self.wp, self._kw
        dev = self.device
        n = int(voxels.shape[0])
        if n == 0:
            return Weights(voxels=voxels, chunks=[], nnz=0)
        common = [self.grid, self.views, self.n_views, self.sub_a, self.sub_w]

        if trace is None:
            def trace(vox, offs, fill, limit, counts, pix, w):
                launch_rows(kw.drt_weights, vox.shape[0], [*common, Rows(vox), Rows(offs), wp.int64(0), min_weight,
                                                           fill, wp.int64(limit), Rows(counts), pix, w], dev)

        cap = self._slot_capacity(voxels, lambda sample, counts: trace(
            sample, wp.zeros(counts.shape[0] + 1, dtype=wp.int64, device=dev), 0, 0, counts, self._i32, self._f32))
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
                                           merged_w, Rows(kept), floor], dev)
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
