"""Weights kept across frames: trace each voxel once, gather the active rows per frame.

A voxel's weights, dense ray-traced (DRT-MART) or line-of-sight (MLOS-MART), depend only on the
cameras and the grid, never on the image; only zero-voxel elimination does. A
:class:`WeightCache` binds a projector (:class:`~lfcore.operator.Projector`) and keeps, on its
device, the merged weights of every voxel it has been asked for. Each frame then costs the
elimination, tracing only the voxels never seen before, and one copy of the active rows into a
fresh :class:`~lfcore.weight_build.Weights`, the frame's operator (a few milliseconds where the
tracing took seconds on a CPU). The rows are the ones the projector's ``weights`` builds for the
same voxels, bit for bit.

It also has the projector store the pixels of each voxel's first elimination checks
(:meth:`LightFieldProjector.precompute_checks <lfcore.projector.LightFieldProjector.precompute_checks>`), so
that elimination mostly looks pixels up.

Memory: 8 bytes per stored weight (int32 pixel, float32 value) in a pool on the device, plus
12 bytes per grid voxel on the host (row start and length). A voxel has a few hundred weights
per camera at 10 pixels per lenslet (about 200 for the tiny rig's camera), so the whole of
``benchmarks/live.py --case S`` (two cameras, 161,704 voxels) would take about 0.5 GiB; in
practice only the voxels that elimination ever keeps are stored. The pool grows by doubling up
to ``budget_bytes`` (and at most 2**31 - 1 weights, the longest Warp array). When a frame's new
rows do not fit, its stored rows are copied out, its new rows are used as built, and the pool
is emptied and refilled with that frame's rows alone: the next frame (frame B of the pair, or
the next pair) shares more voxels with it than with older frames. The elimination table adds
``20 * max_checks`` bytes per voxel and camera, 1.6 kB at 10 pixels per lenslet
(0.5 GiB for case S, built in about 3.5 s on a CPU core, when the cache is made), fewer
checks if that would pass a quarter of the budget.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from lfcore._deprecation import keyword_options
from lfcore.device import Rows, available_bytes, launch_rows
from lfcore.operator import JOINT, LINE_OF_SIGHT, PINHOLE, TRACED
from lfcore.operator import Projector as AnyProjector
from lfcore.weight_build import BYTES_PER_WEIGHT, CHUNK_ENTRIES, WeightChunk, Weights

__all__ = ["DEFAULT_BUDGET_FRACTION", "WeightCache"]

#: Share of the device's free memory (when the cache is made) that the pool may grow to by default.
DEFAULT_BUDGET_FRACTION = 0.25
#: Entries the pool holds at first.
INITIAL_ENTRIES = 1 << 20
#: Most weights in the pool: a Warp array's length is a signed 32-bit integer.
MAX_ARRAY_ENTRIES = 2**31 - 1
#: Voxels traced at once by :meth:`WeightCache.prefill` (bounds its scratch memory).
PREFILL_VOXELS = 1 << 15
#: Room :meth:`WeightCache.prefill` makes for the voxels after its first part, as a multiple of what
#: they take at the first part's weights a voxel.
PREFILL_SLACK = 1.1


class WeightCache:
    """Merged weights of the voxels of one projector, kept on its device across frames.

    Parameters
    ----------
    projector
        The cameras and grid; the weights live on its device.
    method
        ``"drt"`` (dense ray tracing, DRT-MART) or ``"los"`` (line of sight, MLOS-MART).
    budget_bytes
        Most bytes the pool of weights may take; default: ``DEFAULT_BUDGET_FRACTION`` of what
        the device has free now.
    min_weight
        Raw entries below this are dropped (as in :meth:`Projector.weights`).
    checks
        Elimination checks per voxel and camera whose pixels the projector stores
        (:meth:`Projector.precompute_checks`, ``20 * checks`` bytes per voxel and camera), as
        many as fit in a quarter of the budget (on top of it); None: all; 0: none.
    """

    @keyword_options("budget_bytes", "min_weight", "checks", "method", since="0.1.0")
    def __init__(self, projector: AnyProjector, *, budget_bytes: int | None = None, min_weight: float = 1e-6,
                 checks: int | None = None, method: str = "drt") -> None:
        if method not in ("drt", "los"):
            raise ValueError(f"unknown weight method '{method}'; use 'drt' or 'los'")
        self.method = method
        self.projector = projector
        self.wp = projector.wp
        self.device = projector.device
        self.min_weight = float(min_weight)
        if budget_bytes is None:
            budget_bytes = int(DEFAULT_BUDGET_FRACTION * available_bytes(self.device))
        self.budget_bytes = int(budget_bytes)
        n = projector.grid.n_voxels
        self._start = np.full(n, -1, dtype=np.int64)  # row start in the pool; -1: not cached
        self._count = np.zeros(n, dtype=np.int32)
        self._pix = None
        self._w = None
        self._used = 0
        self.checks_bytes = projector.precompute_checks(n_checks=checks, budget_bytes=self.budget_bytes // 4)

    @property
    def kind(self) -> str:
        """The operator kind of the rows kept: a light-field projector's :data:`~lfcore.operator.TRACED`
        or :data:`~lfcore.operator.LINE_OF_SIGHT` ones, a pinhole or joint projector's own."""
        own = {"pinhole": PINHOLE, "joint": JOINT}.get(getattr(self.projector, "kind", ""))
        return own or (TRACED if self.method == "drt" else LINE_OF_SIGHT)

    @property
    def n_cached(self) -> int:
        """Voxels whose weights are stored."""
        return int(np.count_nonzero(self._start >= 0))

    def uncached(self, voxels) -> int:
        """How many of ``voxels`` ((n,) int32 flat indices, on the device or the host) have no
        stored weights, so that :meth:`weights` would trace them."""
        return int(np.count_nonzero(~self._hits(voxels)[1]))

    def _hits(self, voxels) -> tuple[np.ndarray, np.ndarray]:
        """``voxels`` on the host as (n,) int64, and which of them have stored weights."""
        vox_h = np.asarray(voxels.numpy() if hasattr(voxels, "numpy") else voxels, dtype=np.int64)
        return vox_h, self._start[vox_h] >= 0

    @property
    def nbytes(self) -> int:
        """Bytes of stored weights (the pool itself may be up to twice as large)."""
        return BYTES_PER_WEIGHT * self._used

    @property
    def device_bytes(self) -> int:
        """Device bytes the cache holds: its pool (stored rows and room for more) and the
        elimination's check table."""
        return BYTES_PER_WEIGHT * self._capacity() + int(self.checks_bytes)

    def _capacity(self) -> int:
        return 0 if self._pix is None else int(self._pix.shape[0])

    def clear(self) -> None:
        """Forget every stored row (the pool's memory is kept for the next ones)."""
        if self._used == 0:
            return  # nothing stored (the host tables are a gigabyte for a large grid)
        self._start.fill(-1)
        self._count.fill(0)
        self._used = 0

    def _reserve(self, entries: int, *, exact: bool = False) -> bool:
        """Make room for ``entries`` more weights (the pool doubling, or with ``exact`` growing to just
        that); False if that would pass the budget."""
        need = self._used + entries
        if BYTES_PER_WEIGHT * need > self.budget_bytes or need > MAX_ARRAY_ENTRIES:
            return False
        cap = self._capacity()
        if need <= cap:
            return True
        wp = self.wp
        grown = need if exact else max(need, 2 * cap, INITIAL_ENTRIES)
        new_cap = min(grown, self.budget_bytes // BYTES_PER_WEIGHT, MAX_ARRAY_ENTRIES)
        pix = wp.empty(new_cap, dtype=wp.int32, device=self.device)
        w = wp.empty(new_cap, dtype=float, device=self.device)
        if self._used:
            wp.copy(pix, self._pix, count=self._used)
            wp.copy(w, self._w, count=self._used)
        self._pix, self._w = pix, w
        return True

    def _store(self, voxels: np.ndarray, built: Weights) -> bool:
        """Append the rows of ``built`` (the weights of ``voxels``); False if over the budget."""
        wp = self.wp
        if not self._reserve(built.nnz):
            return False
        for c in built.chunks:
            offs = c.offsets.numpy()
            if c.nnz:
                wp.copy(self._pix, c.pix, dest_offset=self._used, count=c.nnz)
                wp.copy(self._w, c.w, dest_offset=self._used, count=c.nnz)
            vox = voxels[c.first : c.first + c.n]
            self._start[vox] = self._used + offs[:-1]
            self._count[vox] = np.diff(offs).astype(np.int32)
            self._used += c.nnz
        return True

    @keyword_options("voxels", since="0.1.0")
    def prefill(self, *, voxels: np.ndarray | None = None, whole: bool = False) -> int:
        """Trace ahead of time ``voxels`` (flat indices; default: the whole grid) not yet stored.

        Stops at the budget. Returns the number of voxels stored. After the first part, the pool
        grows once to what the rest takes at the first part's weights a voxel (and a little more),
        rather than doubling: a whole grid's rows would otherwise leave up to as much room again.
        ``whole``: stop after the first part where that estimate passes the budget (rather than
        tracing until the pool is full: the frames would then find their voxels mostly missing).
        """
        wp = self.wp
        todo = np.arange(self.projector.grid.n_voxels) if voxels is None else np.asarray(voxels, dtype=np.int64)
        todo = np.unique(todo[self._start[todo] < 0]).astype(np.int32)
        stored = 0
        for lo in range(0, todo.size, PREFILL_VOXELS):
            part = todo[lo : lo + PREFILL_VOXELS]
            built = self.projector.weights(wp.array(part, dtype=wp.int32, device=self.device), method=self.method,
                                           min_weight=self.min_weight, budget_bytes=self.budget_bytes)
            if not self._store(part, built):
                break
            stored += part.size
            if lo == 0 and todo.size > part.size:  # room for the rest at once (a miss only leaves the doubling)
                rest = int(PREFILL_SLACK * built.nnz / max(part.size, 1) * (todo.size - part.size))
                if not self._reserve(rest, exact=True) and whole:
                    break
        return stored

    def weights(self, voxels, *, host: np.ndarray | None = None) -> Weights:
        """The weights of ``voxels`` ((n,) int32 on the projector's device), as built directly;
        ``host``: the same indices on the host where the caller has them (saves their copy).

        Traces the voxels not yet stored and stores them, then copies every requested row out
        of the pool, in the order of ``voxels``. If the new rows do not fit next to the stored
        ones, the stored rows of the request are copied out first and the new ones follow as
        built (the returned ``voxels`` are then in that order); the pool is then cleared and
        refilled with this request's rows if they fit alone, since the next frame shares more
        voxels with this one than with older frames.
        """
        wp, p = self.wp, self.projector
        vox_h, hit = self._hits(voxels if host is None else host)
        if hit.all():
            return self._copy_out(voxels, vox_h)
        missing = vox_h[~hit]
        built = p.weights(wp.array(missing.astype(np.int32), dtype=wp.int32, device=self.device), method=self.method,
                          min_weight=self.min_weight)
        if self._store(missing, built):
            return self._copy_out(voxels, vox_h)
        hits = vox_h[hit]
        order = np.concatenate([hits, missing])
        stored = self._copy_out(None, hits)
        out = p.bind(Weights(voxels=wp.array(order.astype(np.int32), dtype=wp.int32, device=self.device),
                             chunks=stored.chunks + [replace(c, first=c.first + hits.size) for c in built.chunks],
                             nnz=stored.nnz + built.nnz), kind=self.kind)
        self.clear()
        self._store(order, out)  # nothing if the request alone passes the budget
        return out

    def _copy_out(self, voxels, vox: np.ndarray) -> Weights:
        """The stored rows of ``vox`` (flat indices, all stored) copied into chunks of whole rows;
        ``voxels`` is ``vox`` on the device if the caller has it (None: the result's ``voxels``
        is left to the caller)."""
        wp, p = self.wp, self.projector
        n = vox.size
        counts = self._count[vox]
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        per_chunk = CHUNK_ENTRIES["cpu" if self.device == "cpu" else "cuda"]
        chunks, lo = [], 0
        while lo < n:
            hi = max(lo + 1, int(np.searchsorted(offsets, offsets[lo] + per_chunk, side="right")) - 1)
            hi = min(hi, n)
            offs = offsets[lo:hi + 1] - offsets[lo]
            nnz = int(offs[-1])
            d_offsets = wp.array(offs, dtype=wp.int64, device=self.device)
            out_pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=self.device)
            out_w = wp.empty(max(nnz, 1), dtype=float, device=self.device)
            if nnz:
                starts = wp.array(self._start[vox[lo:hi]], dtype=wp.int64, device=self.device)
                launch_rows(p._kw.copy_rows, hi - lo, [Rows(starts), Rows(d_offsets, extra=1), self._pix, self._w,
                                                       out_pix, out_w], self.device)
            chunks.append(WeightChunk(first=lo, n=hi - lo, offsets=d_offsets, pix=out_pix, w=out_w, nnz=nnz))
            lo = hi
        return p.bind(Weights(voxels=voxels, chunks=chunks, nnz=int(offsets[-1])), kind=self.kind)
