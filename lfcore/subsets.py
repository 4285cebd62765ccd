"""Ordered subsets for the simultaneous MART (OS-SMART, as OS-EM in emission tomography).

The pixels of every camera are split into ``S`` interleaved subsets, and one pass updates the
voxels from one subset's projections at a time: ``S`` updates for about the work of one full
iteration (each weight read once by a forward projection and once by an update per pass), each
worth nearly a full one where every subset sees every voxel. The subsets interleave the pixels
on a sheared lattice, ``k = (column + m row) mod S`` with ``m`` the rounded square root of ``S``
(a checkerboard for 2): within each micro-image a subset holds every S-th pixel, so it samples
every sub-aperture direction of a voxel (the phase groups of the micro-images, strided rather
than in blocks), and a voxel's light is shared about evenly between the subsets.

Each voxel's row of stored weights is split once by subset (:func:`split`), so a subset's
forward projection and update read only its own entries. A subset's update is scaled per voxel
by its whole weight over the subset's (``c_j = sum_i w_ij / sum_{i in k} w_ij``; at most
:data:`MAX_SCALE` ``S``): one subset's step is then as long as a full iteration's (the
rescaled block-iterative SMART of Byrne 1998, with a per-voxel normaliser).

Only stored weights (:class:`lfcore.weight_build.Weights` holding every row) are split; other
operators (templates, weights partly made on the fly) keep the plain simultaneous form
(:func:`split` returns None).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from lfcore.device import RowOffset, Rows, launch_rows, warp
from lfcore.operator import gather, log_ratio, scatter_voxels

__all__ = ["MAX_SCALE", "MAX_SUBSETS", "SUBSET_HALVING", "SubsetOperator", "groups_in_pass", "ordered_pass",
           "pixel_subsets", "split", "split_bytes"]

#: Most subsets (``ReconSettings.subsets``): beyond a few dozen a subset holds too few of a voxel's pixels.
MAX_SUBSETS = 64
#: ``ReconSettings.subset_halving``'s default: passes between the halvings of the subsets; 0, never.
#: Measured (``benchmarks/subsets.py``, ``benchmarks/RESULTS.md``): halving every 10 passes kept the
#: tiny rig's Q from falling past its best (0.783 against 0.769 at 100 passes of 4 subsets) but cost
#: the Mc crop, which converges slowly, its best (0.765 against 0.783 at 100 passes of 4 subsets).
SUBSET_HALVING = 0
#: GPU threads that share one voxel's row in a subset's update (a warp, as lfcore.weight_build.LANES).
LANES = 32
#: A subset's per-voxel scale is at most this many times the number of subsets: a voxel that a subset
#: barely sees is not moved far by the few pixels it has there.
MAX_SCALE = 2.0


def pixel_subsets(pixel_offsets, cameras, n_subsets: int) -> np.ndarray:
    """The subset of every pixel of the cameras, interleaved on a sheared lattice per camera.

    Parameters
    ----------
    pixel_offsets
        (n_cameras + 1,) where each camera's pixels begin in the global numbering
        (:attr:`lfcore.operator.Projector.pixel_offsets`).
    cameras
        The cameras, each with ``sensor_px`` (columns, rows).
    n_subsets
        S, 1 or more.

    Returns
    -------
    np.ndarray
        (n_pixels,) int32 subsets, ``(column + m row) mod S`` with ``m = round(sqrt(S))``.
    """
    s = int(n_subsets)
    m = max(1, round(math.sqrt(s)))
    out = np.empty(int(pixel_offsets[-1]), dtype=np.int32)
    for k, cam in enumerate(cameras):
        cols, rows = int(cam.sensor_px[0]), int(cam.sensor_px[1])
        r, c = np.divmod(np.arange(rows * cols, dtype=np.int64), cols)
        out[int(pixel_offsets[k]):int(pixel_offsets[k]) + rows * cols] = (c + m * r) % s
    return out


@dataclass(eq=False)
class SubsetOperator:
    """Stored weights split by pixel subset: an :class:`~lfcore.operator.Operator` whose
    :meth:`subset_forward` and :meth:`subset_update` read one subset's entries.

    Attributes
    ----------
    parts
        One stored-weights operator (:class:`lfcore.weight_build.Weights`) per subset, every voxel
        a row (empty where the subset holds none of its pixels), rows in the order of :attr:`voxels`.
    scales
        One (n,) float32 device array per subset: each voxel's whole weight over the subset's.
    """

    parts: list
    scales: list
    kind: str = field(init=False)
    _groups: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.kind = self.parts[0].kind

    @property
    def n_subsets(self) -> int:
        return len(self.parts)

    @property
    def device(self) -> str:
        return self.parts[0].device

    @property
    def voxels(self) -> object:
        return self.parts[0].voxels

    @property
    def n_voxels(self) -> int:
        return self.parts[0].n_voxels

    @property
    def nnz(self) -> int:
        return sum(p.nnz for p in self.parts)

    @property
    def nbytes(self) -> int:
        # each part counts the voxel indices (shared: once) and its offsets; a float32 scale per part
        return sum(p.nbytes for p in self.parts) + 4 * self.n_voxels

    @property
    def n_on_the_fly(self) -> int:
        return 0

    def forward(self, e, *, out=None) -> object:
        """The whole projection (every subset's entries), as the unsplit weights give it to float round-off."""
        joined = dataclasses.replace(self.parts[0], chunks=[c for part in self.parts for c in part.chunks],
                                     nnz=self.nnz)
        return joined.forward(e, out=out)

    def update(self, ratio, e, relaxation: float) -> None:
        """The whole (unscaled) simultaneous update, subset after subset: the plain SMART update
        (a product of exponentials; only each step's bound differs)."""
        for part in self.parts:
            part.update(ratio, e, relaxation)

    def groups(self, n_groups: int) -> list[tuple[list[int], object]]:
        """The subsets joined into ``n_groups`` (subset k in group ``k mod n_groups``; all of them
        apart at ``n_subsets`` or more), each with its per-voxel scale (the whole weight over the
        group's: ``1 / sum_k 1 / c_k``): a coarser split without splitting again."""
        g = max(1, min(int(n_groups), self.n_subsets))
        if g not in self._groups:
            members = [[k for k in range(self.n_subsets) if k % g == j] for j in range(g)]
            if g == self.n_subsets:
                self._groups[g] = [(m, self.scales[m[0]]) for m in members]
            else:
                wp, out = warp(), []
                for m in members:
                    share = sum(_inverse(self.scales[k].numpy()) for k in m)  # the group's share of each voxel's weight
                    with np.errstate(divide="ignore"):
                        scale = np.where(share > 0, np.minimum(1.0 / share, MAX_SCALE * g), 0.0).astype(np.float32)
                    out.append((m, wp.array(scale, dtype=float, device=self.device)))
                self._groups[g] = out
        return self._groups[g]

    def subset_forward(self, k: int | list[int], e, *, out) -> object:
        """Subset ``k``'s (or a group's: a list of subsets) projection of ``e`` into ``out``
        (n_pixels,) (zeroed first; other pixels 0)."""
        members = [k] if isinstance(k, int) else list(k)
        if len(members) == 1:
            return self.parts[members[0]].forward(e, out=out)
        joined = dataclasses.replace(self.parts[members[0]], chunks=[c for m in members for c in self.parts[m].chunks],
                                     nnz=sum(self.parts[m].nnz for m in members))
        return joined.forward(e, out=out)

    def subset_update(self, k: int | list[int], ratio, e, relaxation: float, *, scale=None) -> None:
        """Subset ``k``'s (or a group's) scaled update of ``e`` in place:
        ``E_j <- E_j exp(mu c_j sum_{i in k} w_ij ratio_i)``, ``c_j`` the subset's scale (a group's
        ``scale`` from :meth:`groups`)."""
        members = [k] if isinstance(k, int) else list(k)
        if scale is None:
            scale = self.scales[members[0]]
        for m in members:  # exp(mu c (a + b)) = exp(mu c a) exp(mu c b)
            self._update(self.parts[m], scale, ratio, e, relaxation)

    def _update(self, part, scale, ratio, e, relaxation: float) -> None:
        from lfcore._kernels import subsets as ks

        wp = warp()
        dev = self.device
        mu = float(relaxation)
        for c in part.chunks:
            if dev == "cpu":
                launch_rows(ks.smart_update_scaled, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first),
                                                          ratio, mu, scale, e], dev)
            elif c.n:
                wp.launch_tiled(ks.smart_update_scaled_tiled, dim=[c.n], block_dim=LANES, device=dev,
                                inputs=[c.offsets, c.pix, c.w, c.first, ratio, mu, scale, e])

    def scatter(self, e, *, out=None) -> object:
        p = self.parts[0]
        return scatter_voxels(p.voxels, e, p.binding.shape, device=p.device, out=out)

    def restrict(self, rows, *, spend: bool = False) -> SubsetOperator:
        """The split weights of some voxels (see :meth:`lfcore.operator.Operator.restrict`); ``spend``:
        each subset's weights let go chunk by chunk as they are copied (this operator is then spent)."""
        parts = [p.restrict(rows, spend=spend) for p in self.parts]
        voxels = parts[0].voxels
        for p in parts[1:]:  # one copy of the voxel indices
            p.voxels = voxels
        return SubsetOperator(parts=parts, scales=[gather(s, rows) for s in self.scales])


def split_bytes(op, n_subsets: int) -> int:
    """Device bytes of ``op``'s rows split by :func:`split` into ``n_subsets``: its entries again, and
    per subset and voxel a row offset and a scale (the unsplit rows are held beside them while they
    are split)."""
    return 8 * int(op.nnz) + int(n_subsets) * 12 * (int(op.n_voxels) + 1) + 4 * int(op.n_voxels)


def split(op, subset_of, n_subsets: int) -> SubsetOperator | None:
    """``op``'s rows split by the subsets of their pixels; None where ``op`` is not stored weights
    holding every row in CSR chunks (:class:`lfcore.weight_build.Weights`; the others keep the plain
    simultaneous form).

    Parameters
    ----------
    op
        An :class:`~lfcore.operator.Operator`.
    subset_of
        (n_pixels,) int32 Warp array on ``op``'s device: each pixel's subset (:func:`pixel_subsets`).
    n_subsets
        S.

    Returns
    -------
    SubsetOperator or None
        Its parts hold the same entries as ``op`` (``op`` may then be let go).
    """
    from lfcore._kernels import subsets as ks

    # stored rows, every one of them (the chunks of lfcore.weight_build.Weights); seen by what they hold
    if not dataclasses.is_dataclass(op) or not getattr(op, "stored", False) or not getattr(op, "chunks", ()):
        return None
    if op.n_voxels == 0:
        return None
    wp = warp()
    s, n, dev = int(n_subsets), op.n_voxels, op.device
    counts = np.zeros((n, s), dtype=np.int64)
    sums = np.zeros((n, s), dtype=np.float32)
    for c in op.chunks:
        cnt = wp.zeros(c.n * s, dtype=wp.int64, device=dev)
        sm = wp.zeros(c.n * s, dtype=float, device=dev)
        launch_rows(ks.count_subsets, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, subset_of, s, Rows(cnt, scale=s),
                                            Rows(sm, scale=s)], dev)
        counts[c.first:c.first + c.n] = cnt.numpy().reshape(c.n, s)
        sums[c.first:c.first + c.n] = sm.numpy().reshape(c.n, s)
    # per-voxel scale: the whole weight over the subset's, bounded
    whole = sums.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(sums > 0, np.minimum(whole / sums, MAX_SCALE * s), 0.0).astype(np.float32)
    parts: list[list] = [[] for _ in range(s)]
    totals = [0] * s
    for c in op.chunks:
        cnt = counts[c.first:c.first + c.n]
        offs = np.zeros((s, c.n + 1), dtype=np.int64)
        np.cumsum(cnt.T, axis=1, out=offs[:, 1:])
        nnz = offs[:, -1]
        base = np.concatenate([[0], np.cumsum(nnz)])
        # each row's cursor per subset in the joined output: the subset's base plus the row's offset
        cursor = wp.array((offs[:, :-1] + base[:-1, None]).T.ravel(), dtype=wp.int64, device=dev)
        out_pix = wp.empty(max(int(base[-1]), 1), dtype=wp.int32, device=dev)
        out_w = wp.empty(max(int(base[-1]), 1), dtype=float, device=dev)
        launch_rows(ks.split_rows, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, subset_of, s, Rows(cursor, scale=s),
                                         out_pix, out_w], dev)
        for k in range(s):
            lo, hi = int(base[k]), int(base[k + 1])
            parts[k].append(dataclasses.replace(c, offsets=wp.array(offs[k], dtype=wp.int64, device=dev),
                                                pix=out_pix[lo:hi] if hi > lo else out_pix[:1],
                                                w=out_w[lo:hi] if hi > lo else out_w[:1], nnz=hi - lo))
            totals[k] += hi - lo
    weights = [dataclasses.replace(op, chunks=parts[k], nnz=totals[k]) for k in range(s)]
    return SubsetOperator(parts=weights, scales=[wp.array(np.ascontiguousarray(scale[:, k]), dtype=float, device=dev)
                                                 for k in range(s)])


def _inverse(c: np.ndarray) -> np.ndarray:
    """1 / c where c > 0, else 0 (a voxel's share of its weight in a subset, from the subset's scale)."""
    with np.errstate(divide="ignore"):
        return np.where(c > 0, 1.0 / c, 0.0)


def groups_in_pass(n_subsets: int, halve_every: int, it: int) -> int:
    """The subsets (groups of the split ones) of pass ``it`` (1, 2, ...): ``n_subsets`` halved every
    ``halve_every`` passes, down to 1 (0: never halved)."""
    if halve_every <= 0:
        return n_subsets
    return max(1, n_subsets >> ((it - 1) // halve_every))


def ordered_pass(op: SubsetOperator, image, e, proj, ratio, floor: float, relaxation: float, *,
                 groups: int | None = None) -> None:
    """One pass of OS-SMART: for each subset in turn, its forward projection of ``e``, the log
    ratios of the measured ``image`` to it (:func:`lfcore.operator.log_ratio`; 0 on the other
    subsets' pixels, where it projects nothing) and its scaled update of ``e`` in place.

    Parameters
    ----------
    op
        The split weights (:func:`split`).
    image, proj, ratio
        (n_pixels,) float32 device arrays: the measured signal in counts, and scratch.
    e
        (n,) float32 intensities, updated in place.
    floor
        The least a pixel's measurement counts as, in counts.
    relaxation
        mu of each subset's update.
    groups
        Join the subsets into this many (:meth:`SubsetOperator.groups`; 1: the plain simultaneous
        update); None: every subset apart.
    """
    for members, scale in op.groups(op.n_subsets if groups is None else groups):
        op.subset_forward(members, e, out=proj)
        op.subset_update(members, log_ratio(image, proj, floor, ratio), e, relaxation, scale=scale)
