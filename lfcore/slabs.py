"""Reconstruction in depth slabs: volumes larger than memory, the same volume as in memory.

The in-memory path (:class:`lfcore.reconstruct.FrameReconstructor`) holds, besides the active
voxels' weights and intensities, buffers of the whole box: the elimination's masks (8 bytes per
voxel) and the dense result with its smoothing scratch (8 bytes per voxel). A box of 5e9 voxels
needs 80 GB for those alone. Here the box is cut along z into slabs and only one slab's buffers
(plus its smoothing halo) exist at a time, while the iterations still see the whole volume. The
plan is the in-memory path's, every stage of it (the ``fast`` protocol's included):

1. Coarse-to-fine elimination (:attr:`~lfcore.reconstruct.ReconSettings.coarse`, where
   :func:`lfcore.reconstruct.coarse_applies`): the coarse grid, ``coarse**3`` times fewer voxels,
   is reconstructed in memory as the in-memory path does it (:func:`lfcore.reconstruct.coarse_bright`);
   each slab's fine elimination then tests only the children of the bright coarse voxels that lie
   in the slab, and each of its voxels starts from its coarse parent's intensity (plus a share of
   the mean over all slabs, :func:`lfcore.warm.with_floor`).
2. Elimination, slab by slab. A voxel's test reads only its own sub-apertures' pixels, so
   testing the voxels of each slab in turn keeps exactly the voxels one pass over the box keeps.
   Each slab numbers its own voxels from its first plane (:meth:`lfcore.operator.Projector.planes`), so a box of
   more than 2**31 voxels (the chapter's dual-camera one: 1939 x 1455 x 1939) is numbered in
   int32 slab by slab, while each voxel's centre is the box's voxel's to the bit.
3. The operator of each slab's survivors, on its slab's projector: a voxel's weights depend on its
   centre and the cameras only, so they are the in-memory path's rows. The matrix-free templates
   are built once, over the whole box's depth planes, and serve every slab
   (:meth:`lfcore.matrix_free.DrtTemplates.on`). With line-of-sight first iterations
   (:attr:`~lfcore.reconstruct.ReconSettings.los_iterations`) these are line-of-sight weights; after
   those iterations the dark voxels leave at one threshold over all slabs, and each slab's
   line-of-sight weights are freed before the DRT weights of its survivors are built.
4. MART's ratio needs the projection of the whole volume. The slabs' operators are iterated as one
   (:class:`SlabOperators`) by the in-memory path's own loop (:func:`lfcore.reconstruct.smart_iterations`:
   the start, the pruning, the stopping rule): each projection is every slab's projected into an
   image-sized buffer and summed, and every slab is updated from that same projection's log ratios
   (computed once). SMART's update of a voxel reads only the projection and its own weights, so this
   is the in-memory iteration, reordered only in the sum over voxels (float round-off). With ordered
   subsets (:attr:`~lfcore.reconstruct.ReconSettings.subsets`) every slab's rows are split into the
   same pixel subsets (:func:`lfcore.subsets.split`), and each subset's step projects all slabs'
   rows of the subset, takes the log ratios and updates every slab (:func:`lfcore.subsets.ordered_pass`).
5. The result, slab by slab: the slab's intensities and those of the ``halo`` planes on either
   side (from the neighbouring slabs) scattered into a dense buffer, smoothed (the halo is the
   Gaussian's radius, so each of the slab's voxels sees what it sees in the whole volume; zero
   beyond the box as there), and the slab's planes handed to a writer (a chunked zarr array).

Memory: the active voxels' weights and intensities (as in memory) plus, per slab, about
:data:`BYTES_PER_SLAB_VOXEL` bytes per voxel of the slab and its halo, plus a few image-sized
buffers; with the coarse grid, for a while first, its elimination's buffers
(:data:`BYTES_PER_SLAB_VOXEL` per coarse voxel) and weights; with ordered subsets, one slab's rows
split beside its unsplit ones at a time. The warm start (a whole volume carried from frame to frame)
is not run in slabs. The sequential form (pixel by pixel, each update changing the projection) is
not split; it keeps the in-memory path.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from lfcore import coarse as coarse_grids
from lfcore.device import MemoryBudgetError, Rows, available_bytes, launch_rows, out_of_memory_is_budget_error, warp
from lfcore.device_ops import VolumeOps, gaussian_taps
from lfcore.operator import OPERATOR_KINDS, TEMPLATES, Operator, Projector, from_templates, max_planes
from lfcore.reconstruct import (
    CAPPED,
    CONVERGED,
    PRUNE,
    FrameReconstructor,
    ReconResult,
    ReconSettings,
    bright_voxels,
    coarse_applies,
    coarse_bright,
    coarse_reconstructor,
    preprocess_images,
    restrict_bytes,
    smart_iterations,
)
from lfcore.subsets import SubsetOperator, pixel_subsets, split, split_bytes
from lfcore.volume import VolumeGrid
from lfcore.warm import WARM_BLEND, with_floor

__all__ = ["BYTES_PER_SLAB_VOXEL", "Slab", "SlabOperators", "SlabReconstructor", "deepest_slab", "plan_slabs",
           "slab_halo", "slabs_for_budget"]

#: Bytes per voxel of a slab (and its halo) while it is eliminated and written: its voxel
#: indices, the elimination's mask and scan (int32 each), the dense buffer and its smoothing
#: scratch (float32 each).
BYTES_PER_SLAB_VOXEL = 20
#: Bytes per pixel of all cameras: the signal, the summed projection, one slab's projection, the
#: log ratio (float32 each) and the lit mask (uint8).
BYTES_PER_PIXEL = 17


@dataclass(frozen=True)
class Slab:
    """Planes ``z0 .. z1 - 1`` of the grid."""

    z0: int
    z1: int

    @property
    def nz(self) -> int:
        return self.z1 - self.z0


def slab_halo(settings: ReconSettings) -> int:
    """Planes on each side of a slab its smoothing reads: the Gaussian's radius (0 without)."""
    if settings.smooth <= 0:
        return 0
    return (len(gaussian_taps(settings.smooth)) - 1) // 2


def plan_slabs(nz: int, n_slabs: int) -> list[Slab]:
    """``n_slabs`` slabs of nearly equal depth covering ``nz`` planes, front to back.

    Raises
    ------
    ValueError
        If ``n_slabs`` is below 1 or above ``nz``.
    """
    if not 1 <= n_slabs <= nz:
        raise ValueError(f"the box is {nz} voxels deep: slabs must be from 1 to {nz}, got {n_slabs}")
    edges = np.linspace(0, nz, n_slabs + 1).round().astype(int)
    return [Slab(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def deepest_slab(grid: VolumeGrid, *, halo: int) -> int:
    """The most planes a slab of ``grid`` may have so that it and its ``halo`` planes on both sides
    are numbered in int32 (fewer than :data:`lfcore.projector.INDEX_LIMIT` voxels)."""
    return max_planes(grid) - 2 * halo


def slabs_for_budget(grid: VolumeGrid, budget_bytes: int, *, halo: int, n_pixels: int = 0, coarse: int = 1) -> int:
    """The fewest slabs whose buffers (:data:`BYTES_PER_SLAB_VOXEL` per voxel of a slab and its
    ``halo`` planes on both sides, and :data:`BYTES_PER_PIXEL` per pixel) fit in ``budget_bytes``,
    each slab with its halo numbered in int32 (:func:`deepest_slab`).

    ``coarse``: the factor of coarse-to-fine elimination where it runs (1: none). Its coarse grid is
    eliminated in memory before the slabs (:data:`BYTES_PER_SLAB_VOXEL` per coarse voxel, ``coarse**3``
    times fewer than the box's), so those buffers must fit in the budget as well.

    Raises
    ------
    MemoryBudgetError
        If even slabs one plane deep, or the coarse grid's buffers, do not fit.
    """
    nz, ny, nx = grid.shape
    plane = BYTES_PER_SLAB_VOXEL * ny * nx
    room = int(budget_bytes) - BYTES_PER_PIXEL * int(n_pixels)
    if coarse > 1:
        cz, cy, cx = (-(-n // int(coarse)) for n in grid.shape)
        need = BYTES_PER_SLAB_VOXEL * cz * cy * cx
        if need > room:
            raise MemoryBudgetError(f"the coarse grid of --coarse {coarse} ({cx * cy * cz:,} voxels) needs "
                                    f"{need / 2**20:.1f} MiB, more than the {budget_bytes / 2**20:.1f} MiB there is; "
                                    "use --coarse 1 or a coarser --pvr")
    planes = room // plane - 2 * halo  # the deepest slab that fits, halo apart
    if planes < 1:
        need = plane * (1 + 2 * halo) + BYTES_PER_PIXEL * n_pixels
        raise MemoryBudgetError(f"even a slab one plane deep needs {need / 2**20:.1f} MiB, more than the "
                                f"{budget_bytes / 2**20:.1f} MiB there is; use a coarser --pvr")
    planes = min(planes, deepest_slab(grid, halo=halo))
    if planes < 1:
        raise MemoryBudgetError(f"a plane of {ny * nx:,} voxels with its halo is more than int32 indices number; "
                                "use a coarser --pvr")
    return min(nz, -(-nz // int(planes)))


class SlabReconstructor:
    """Reconstruct frames slab by slab (see the module docstring): the volume of
    :class:`~lfcore.reconstruct.FrameReconstructor` without a buffer of the whole box.

    Parameters
    ----------
    projector
        Cameras and the WHOLE grid on a device (any :class:`~lfcore.operator.Projector`).
    settings
        As the in-memory path takes them; the simultaneous form only.
    slabs
        The slabs (:func:`plan_slabs`), covering the grid's planes in order.
    budget_bytes
        Memory the weights and buffers may take; None: what the device has free.

    Raises
    ------
    ValueError
        For the sequential form, slabs that do not cover the grid, or a slab that with its
        smoothing halo has too many voxels to number in int32 (:func:`deepest_slab`).
    """

    #: :meth:`reconstruct` hands the volume to a writer slab by slab.
    in_slabs = True

    def __init__(self, projector: Projector, settings: ReconSettings, *, slabs: Sequence[Slab],
                 budget_bytes: int | None = None) -> None:
        if settings.form != "simultaneous":
            raise ValueError("depth slabs need the simultaneous form (the sequential one changes the projection "
                             "after every pixel); use form 'simultaneous' or one slab")
        slabs = list(slabs)
        nz = projector.grid.shape[0]
        if not slabs or slabs[0].z0 != 0 or slabs[-1].z1 != nz or any(
                a.z1 != b.z0 for a, b in zip(slabs[:-1], slabs[1:], strict=True)) or any(s.nz < 1 for s in slabs):
            raise ValueError(f"the slabs must cover planes 0 to {nz} in order, got {[(s.z0, s.z1) for s in slabs]}")
        self.halo = slab_halo(settings)
        deepest = deepest_slab(projector.grid, halo=self.halo)
        too_deep = [s for s in slabs if s.nz > deepest]
        if too_deep:
            raise ValueError(f"slabs of {too_deep[0].nz} planes (with {self.halo} of halo each side) have more voxels "
                             f"than int32 indices number (at most {max(deepest, 0)} planes); use more slabs")
        self.projector = projector
        self.settings = settings
        self.slabs = slabs
        self.budget_bytes = budget_bytes
        self.wp = projector.wp
        self.device = projector.device
        # each slab on a projector of its own planes (its voxels numbered from its first plane)
        self._projectors = [projector.planes(s.z0, s.z1) for s in slabs]
        self._templates = None  # the matrix-free templates, once built: one set for every slab
        self._subset_of = None  # (n_pixels,) int32: each pixel's subset, for settings.subsets (made on first use)
        self._held = 0  # the bytes held while the iterations run (for the subsets' split and the writing)
        self.peak_bytes = 0  # the most bytes accounted at once in the last frame

    # --- one frame ---------------------------------------------------------------------------
    def reconstruct(self, images: Sequence[np.ndarray], *, write: Callable[[int, int, np.ndarray], None],
                    progress: Callable[[int], None] | None = None,
                    log: Callable[[str], None] | None = None) -> ReconResult:
        """Reconstruct one volume from one raw image per camera, handing it to ``write`` slab by slab.

        Parameters
        ----------
        images
            One raw (rows, columns) image per camera, in the projector's camera order, in counts.
        write
            Called as ``write(z0, z1, planes)`` once per slab, front to back, with ``planes`` the
            (z1 - z0, ny, nx) float32 host array of the volume's planes z0 .. z1 - 1 (e.g.
            ``lambda z0, z1, a: data[pair, frame, z0:z1] = a`` on a zarr array).
        progress
            Called with 1 after each iteration.
        log
            Called with one line per stage (each slab's elimination and operator, the start, each
            iteration, the writing) and the seconds it took: a frame of the chapter's 29 MP camera
            takes hours on a CPU, and this says where they go.

        Returns
        -------
        ReconResult
            Its ``volume`` is empty (0, 0, 0) (the planes went to ``write``); ``slabs`` and
            ``peak_bytes`` say how it was split and the most memory its buffers took at once.

        Raises
        ------
        MemoryBudgetError
            If the weights or a slab's buffers do not fit.
        """
        p, s = self.projector, self.settings
        signals, lits, backgrounds, noises = preprocess_images(p, images, s)
        what = f"{s.method} of a {p.grid.n_voxels:,}-voxel box in {len(self.slabs)} slabs"
        with out_of_memory_is_budget_error(p.device, what, "use more --slabs or a coarser --pvr"):
            return self._reconstruct(signals, lits, backgrounds, noises, write, progress, log or (lambda _: None))

    def _reconstruct(self, signals, lits, backgrounds, noises, write, progress, log) -> ReconResult:
        from lfcore._kernels import slabs as ks

        wp, p, s = self.wp, self.projector, self.settings
        dev = self.device
        budget = available_bytes(dev) if self.budget_bytes is None else int(self.budget_bytes)
        held = BYTES_PER_PIXEL * p.n_pixels
        self.peak_bytes = held
        t0 = time.perf_counter()
        lit_host = [np.asarray(m, dtype=np.uint8) for m in lits]
        image = wp.array(np.concatenate([x.ravel() for x in signals]), dtype=float, device=dev)
        bright = None
        if coarse_applies(p, s):  # the coarse grid (27x fewer voxels at 3) in memory, as the in-memory path runs it
            ta = time.perf_counter()
            coarse = coarse_reconstructor(p, s, budget_bytes=budget - held)
            bright = coarse_bright(coarse, lit_host, image, noises, factor=s.coarse)
            n_coarse = coarse.projector.grid.n_voxels
            # its elimination's buffers, operator (with its pruning's copy of one chunk), intensities and
            # projection buffers, all freed since
            self._peak(held + BYTES_PER_SLAB_VOXEL * n_coarse + bright.nbytes + bright.copy_bytes + 6 * bright.active
                       + 8 * p.n_pixels)
            del coarse
            t_coarse = time.perf_counter() - ta
            log(f"coarse grid ({s.coarse}x coarser, {n_coarse:,} voxels): {bright.active:,} active, "
                f"{bright.voxels.size:,} bright after {s.coarse_iterations} line-of-sight iterations, "
                f"{t_coarse:.1f} s")
        los_first = s.los_iterations > 0
        ops, own, starts = [], [], []
        t_elim = 0.0 if bright is None else t_coarse  # the coarse grid is the elimination's first stage
        for i, (slab, ps) in enumerate(zip(self.slabs, self._projectors, strict=True)):
            ta = time.perf_counter()
            frames = FrameReconstructor(ps, s, templates=self._templates)  # the slab's elimination and weights
            if bright is None:
                vox = frames.eliminate(lit_host)
            else:  # the fine voxels of its bright coarse ones in the slab, each started from its coarse one
                within = coarse_grids.children(bright.voxels, p.grid, s.coarse, z0=slab.z0, z1=slab.z1)
                vox = (ps.eliminate(lit_host, min_seen=s.min_seen, max_dark=s.max_dark,
                                    within=wp.array(within, dtype=wp.int32, device=dev)) if within.size else
                       wp.zeros(0, dtype=wp.int32, device=dev))
                starts.append(bright.inherited(vox.numpy(), p.grid, z0=slab.z0))
            wp.synchronize_device(dev)
            tb = time.perf_counter()
            t_elim += tb - ta
            self._peak(held + BYTES_PER_SLAB_VOXEL * slab.nz * _plane_voxels(p))
            first = not any(from_templates(x) for x in ops)
            self._budget(frames, slab, ps, int(vox.shape[0]), held, budget, first=first)
            w = frames.los_operator(vox) if los_first else frames.operator(vox)  # stored, or the templates
            if frames.templates is not None:
                self._templates = frames.templates
            own.append(self._own_bytes(w, first=first))
            held += own[-1] + 4 * w.n_voxels
            self._peak(held)
            wp.synchronize_device(dev)
            log(f"slab {i + 1}/{len(self.slabs)} (planes {slab.z0}-{slab.z1 - 1}): elimination {tb - ta:.1f} s, "
                f"{int(vox.shape[0]):,} active voxels; operator ({_operator_kind(w)}) "
                f"{time.perf_counter() - tb:.1f} s, {own[-1] / 2**20:.0f} MiB")
            ops.append(w)
        if s.method == "mart":
            t_elim = 0.0
        proj = wp.zeros(p.n_pixels, dtype=float, device=dev)
        ratio = wp.empty(p.n_pixels, dtype=float, device=dev)
        joint = SlabOperators(ops, scratch=wp.zeros(p.n_pixels, dtype=float, device=dev))
        n_total = joint.n_voxels
        los_first = los_first and n_total > 0
        first_kinds = joint.kind
        nnz, fly, operator_bytes = joint.nnz, joint.n_on_the_fly, sum(own)  # before any pruning
        del ops
        start = None
        if starts and n_total:  # a dark coarse voxel's children may still grow: a share of the mean over all slabs
            start = with_floor(wp.array(np.concatenate(starts), dtype=float, device=dev), WARM_BLEND, copy=False)
        held += 4 * n_total if start is not None else 0
        self._peak(held)
        del starts
        t1 = time.perf_counter()
        timing = _IterationLog(s.iterations, progress, log, dev)
        timing.voxels = n_total
        self._held = held
        # the pruning's threshold after the coarse grid (ReconSettings.coarse_prune), as in memory
        cut = (s.coarse_prune or None) if bright is not None and s.prune > 0 else None
        if (cut or s.prune) > 0:  # the pruning copies one chunk at a time beside what is held
            self._peak(held + restrict_bytes(joint, spend=True))
        done = smart_iterations(joint, wp.empty(max(n_total, 1), dtype=float, device=dev), image, proj, ratio, noises,
                                s, iterations=s.los_iterations if los_first else s.iterations,
                                stop_tolerance=0.0 if los_first else None, progress=timing.tick, start=start,
                                split=lambda op: self._split(op, budget), t0=t1, started=timing.started, prune=cut)
        del start, joint
        weights_s, iterate_s, ran = t1 - t0 + done.start_s, done.iterate_s, done.iterations
        kinds = first_kinds
        if los_first:
            # the cheap weights first; DRT's then for the voxels still bright (one threshold over all
            # slabs, as in memory), read without copying the line-of-sight weights, which all go before
            # the first slab's DRT weights are made
            t = time.perf_counter()
            joint = done.op
            bright, values = bright_voxels(joint.parts, joint.views(done.e), cut or s.prune or PRUNE)
            del done, joint
            # a dark voxel may still grow under the sharper weights
            start = with_floor(wp.array(np.concatenate(values), dtype=float, device=dev), WARM_BLEND, copy=False)
            del values
            drt, own = [], []
            # held: the pixel buffers and the start
            held = BYTES_PER_PIXEL * p.n_pixels + 4 * int(start.shape[0])
            for i, (slab, ps) in enumerate(zip(self.slabs, self._projectors, strict=True)):
                n = int(bright[i].size)
                vox = wp.array(bright[i], dtype=wp.int32, device=dev)
                bright[i] = None
                frames = FrameReconstructor(ps, s, templates=self._templates)
                first = not any(from_templates(x) for x in drt)
                self._budget(frames, slab, ps, n, held, budget, first=first)
                tb = time.perf_counter()
                w = frames.operator(vox)
                if frames.templates is not None:
                    self._templates = frames.templates
                own.append(self._own_bytes(w, first=first))
                held += own[-1]
                self._peak(held)
                wp.synchronize_device(dev)
                log(f"slab {i + 1}/{len(self.slabs)}: operator ({_operator_kind(w)}) of its {n:,} voxels still bright "
                    f"{time.perf_counter() - tb:.1f} s, {own[-1] / 2**20:.0f} MiB")
                drt.append(w)
            joint = SlabOperators(drt, scratch=wp.zeros(p.n_pixels, dtype=float, device=dev))
            del drt, bright
            nnz, fly, operator_bytes = joint.nnz, joint.n_on_the_fly, max(operator_bytes, sum(own))
            kinds = f"{first_kinds}, then {joint.kind}"
            weights_s += time.perf_counter() - t
            held += 4 * joint.n_voxels  # the intensities
            self._held = held
            self._peak(held + (restrict_bytes(joint, spend=True) if (cut or s.prune) > 0 else 0))
            timing.voxels = joint.n_voxels
            t2 = time.perf_counter()
            done = smart_iterations(joint, wp.empty(max(joint.n_voxels, 1), dtype=float, device=dev), image, proj,
                                    ratio, noises, s, iterations=s.iterations - s.los_iterations,
                                    progress=timing.tick, start=start, split=lambda op: self._split(op, budget),
                                    t0=t2, started=timing.started, prune=cut)
            del start, joint
            weights_s += done.start_s
            iterate_s += done.iterate_s
            ran = done.iterations + s.los_iterations
        if done.stopped in (CONVERGED, CAPPED):
            log(f"{ran} iterations ({done.stopped}), {done.op.n_voxels:,} voxels left")
        final = done.op
        es = final.views(done.e)
        t3 = time.perf_counter()
        nz, ny, nx = p.grid.shape
        plane = ny * nx
        # the result, slab by slab, each with the halo its smoothing reads
        for slab in self.slabs:
            lo, hi = max(0, slab.z0 - self.halo), min(nz, slab.z1 + self.halo)
            self._peak(self._held + BYTES_PER_SLAB_VOXEL * (hi - lo) * plane)
            ops_ = VolumeOps((hi - lo, ny, nx), device=dev)
            buf = wp.zeros((hi - lo, ny, nx), dtype=float, device=dev)
            flat = buf.reshape((hi - lo) * plane)
            for other, w, e in zip(self.slabs, final.parts, es, strict=True):
                if other.z1 > lo and other.z0 < hi and w.n_voxels:  # its voxels numbered from its plane z0
                    shift, n = wp.int64((other.z0 - lo) * plane), wp.int64((hi - lo) * plane)
                    launch_rows(ks.scatter_range, w.n_voxels, [Rows(w.voxels), Rows(e), shift, n, flat], dev)
            if s.smooth > 0:
                ops_.smooth(buf, s.smooth)
            planes = buf.numpy()[slab.z0 - lo: slab.z1 - lo]
            write(slab.z0, slab.z1, np.ascontiguousarray(planes, dtype=np.float32))
            del ops_, buf, flat
        log(f"volume smoothed and written, slab by slab, in {time.perf_counter() - t3:.1f} s")
        return ReconResult(volume=np.zeros((0, 0, 0), np.float32), active_voxels=n_total,
                           active_fraction=n_total / p.grid.n_voxels, nnz=nnz,
                           weight_bytes=operator_bytes, weights_s=weights_s,
                           iterate_s=iterate_s, iterations=ran, stopped=done.stopped, background=backgrounds,
                           noise=noises, eliminate_s=t_elim, on_the_fly_voxels=fly, final_voxels=final.n_voxels,
                           projector="matrix-free" if any(from_templates(w) for w in final.parts) else "stored",
                           slabs=len(self.slabs), peak_bytes=self.peak_bytes, operator=kinds)

    def _budget(self, frames: FrameReconstructor, slab: Slab, ps: Projector, n: int, held: int, budget: int, *,
                first: bool) -> None:
        """Set the budget of a slab's reconstructor ``frames`` so that the operator of its ``n`` voxels may
        take what the budget leaves beside the bytes ``held`` already, the slab's elimination buffers and
        its intensities."""
        # FrameReconstructor's weight budget sets aside the pixel buffers, the intensities and the slab's
        # dense volume (add them back), and the matrix-free templates, held already, which it sets aside itself
        room = budget - held - 4 * n - BYTES_PER_SLAB_VOXEL * slab.nz * _plane_voxels(ps)
        shared = 0 if first or self._templates is None else self._templates.nbytes
        frames.budget_bytes = room + 12 * self.projector.n_pixels + 4 * n + 8 * ps.grid.n_voxels + shared

    def _split(self, joint: SlabOperators, budget: int) -> SlabOperators:
        """Every slab's operator split into the same pixel subsets (:func:`lfcore.subsets.split`), one
        slab at a time (its unsplit rows then go); ``joint`` as it is (the plain form for every slab, as
        in memory) where a slab's operator is not stored weights held whole, or its split rows do not
        fit beside what is held."""
        wp, p, s = self.wp, self.projector, self.settings
        if self._subset_of is None:
            host = pixel_subsets(p.pixel_offsets, p.cameras, s.subsets)
            self._subset_of = wp.array(host, dtype=wp.int32, device=self.device)
        parts, held = joint.parts, self._held
        if any(w.n_voxels and split_bytes(w, s.subsets) + held > budget for w in parts):
            return joint
        out = []  # each slab's unsplit rows let go (joint's too: the loop holds only the split ones) as it is split
        for i, w in enumerate(parts):
            if not w.n_voxels:
                out.append(w)
                continue
            self._peak(held + split_bytes(w, s.subsets))
            cut = split(w, self._subset_of, s.subsets)
            if cut is None:  # not stored weights held whole: the plain form, every slab
                return SlabOperators(out + parts[i:], scratch=joint.scratch)
            held += int(cut.nbytes) - int(w.nbytes)
            parts[i] = None
            out.append(cut)
        self._held = held
        return SlabOperators(out, scratch=joint.scratch)

    def _own_bytes(self, w: Operator, *, first: bool) -> int:
        """Bytes of a slab's operator ``w``, the matrix-free templates (one set for all slabs)
        counted with the first slab that uses them only."""
        templates = self._templates
        own = int(w.nbytes)
        if w.kind == TEMPLATES:  # its nbytes holds the templates' too
            own -= templates.nbytes
        if first and from_templates(w):
            own += templates.nbytes
        return own

    def _peak(self, nbytes: int) -> None:
        self.peak_bytes = max(self.peak_bytes, int(nbytes))


def _operator_kind(w: Operator) -> str:
    """What applies a slab's operator, in words, for the stage log."""
    return OPERATOR_KINDS[w.kind] + (f"; {w.n_on_the_fly:,} voxels' made on the fly" if w.n_on_the_fly else "")


def _plane_voxels(p: Projector) -> int:
    """Voxels of one plane of ``p``'s grid."""
    return int(p.grid.shape[1]) * int(p.grid.shape[2])


class SlabOperators:
    """The operators of a volume's depth slabs as one :class:`~lfcore.operator.Operator` of their voxels
    in slab order (front to back: the box's voxel order), for the one SMART loop
    (:func:`lfcore.reconstruct.smart_iterations`): the intensities are one array, each slab's a view
    of it; the forward projection is the sum of the slabs' (each into ``scratch``, added pixel by
    pixel); the update reads that whole volume's projection and log ratios; :meth:`restrict` (the
    pruning) restricts each slab. Where every slab's operator is split into the same ordered subsets
    (:class:`lfcore.subsets.SubsetOperator`), a subset's projection is the sum of the slabs' and its
    update each slab's (:func:`lfcore.subsets.ordered_pass`).

    Parameters
    ----------
    parts
        One operator per slab, its voxels numbered from the slab's first plane.
    scratch
        (n_pixels,) float32 Warp array: one slab's projection.
    """

    def __init__(self, parts: Sequence[Operator], *, scratch) -> None:
        self.parts = list(parts)
        self.scratch = scratch
        self.offsets = np.concatenate([[0], np.cumsum([w.n_voxels for w in self.parts])]).astype(np.int64)
        lit = self._lit
        #: whether every slab with voxels runs the same ordered subsets
        self.ordered_subsets = bool(lit) and all(isinstance(w, SubsetOperator) for w in lit) and len(
            {w.n_subsets for w in lit}) == 1

    @property
    def _lit(self) -> list:
        """The slabs' operators that hold voxels."""
        return [w for w in self.parts if w is not None and w.n_voxels]

    @property
    def n_voxels(self) -> int:
        return int(self.offsets[-1])

    @property
    def nnz(self) -> int:
        return sum(int(w.nnz) for w in self.parts)

    @property
    def nbytes(self) -> int:
        return sum(int(w.nbytes) for w in self.parts)

    @property
    def n_on_the_fly(self) -> int:
        return sum(int(w.n_on_the_fly) for w in self.parts)

    @property
    def kind(self) -> str:
        return ", ".join(sorted({w.kind for w in self.parts}))

    @property
    def device(self):
        return self.scratch.device

    @property
    def n_subsets(self) -> int:
        return self._lit[0].n_subsets if self.ordered_subsets else 1

    def views(self, e) -> list:
        """Each slab's intensities: views of ``e`` (the volume's, in slab order)."""
        return [e[int(a):int(b)] for a, b in zip(self.offsets[:-1], self.offsets[1:], strict=True)]

    def _each(self, e):
        return [(w, v) for w, v in zip(self.parts, self.views(e), strict=True) if w.n_voxels]

    def forward(self, e, *, out=None):
        """The projection of the whole volume: the slabs' projections summed pixel by pixel."""
        from lfcore._kernels import slabs as ks

        wp = warp()
        if out is None:
            out = wp.zeros(self.scratch.shape[0], dtype=float, device=self.device)
        out.zero_()
        for w, v in self._each(e):
            w.forward(v, out=self.scratch)
            wp.launch(ks.accumulate, dim=int(out.shape[0]), inputs=[out, self.scratch], device=self.device)
        return out

    def update(self, ratio, e, relaxation: float) -> None:
        """Every slab's update from the whole volume's log ratios."""
        for w, v in self._each(e):
            w.update(ratio, v, relaxation)

    def restrict(self, rows, *, spend: bool = True) -> SlabOperators:
        """The slabs' operators of some of the voxels (``rows``: (m,) int32 Warp array of positions in
        slab order, ascending), each slab restricted to its own.

        This operator is spent by it (``spend`` is always so here): it lets go of each slab's operator
        as that slab's copy is made, and each slab's stored rows chunk by chunk as they are copied
        (:meth:`lfcore.weight_build.Weights.restrict`), so that beside the weights held stands one
        chunk's copy at a time, not a slab's or the whole box's (the frame's pruning goes on with the
        operator returned)."""
        wp = warp()
        host = np.asarray(rows.numpy(), dtype=np.int64)
        parts = []
        for i, (a, b) in enumerate(zip(self.offsets[:-1], self.offsets[1:], strict=True)):
            w, self.parts[i] = self.parts[i], None
            mine = host[(host >= a) & (host < b)] - a
            parts.append(w if mine.size == w.n_voxels else
                         w.restrict(wp.array(mine.astype(np.int32), dtype=wp.int32, device=w.device), spend=True))
            del w
        return SlabOperators(parts, scratch=self.scratch)

    def scatter(self, e, *, out=None):
        raise NotImplementedError("the slabs' volume is written slab by slab (SlabReconstructor)")

    # --- ordered subsets (every slab split alike) ---------------------------------------------
    def groups(self, n_groups: int) -> list[tuple[list[int], list]]:
        """As :meth:`lfcore.subsets.SubsetOperator.groups`, with each slab's per-voxel scales."""
        per = [w.groups(n_groups) for w in self._lit]
        return [(members, [g[j][1] for g in per]) for j, (members, _) in enumerate(per[0])]

    def subset_forward(self, k, e, *, out):
        """Subset ``k``'s (or a group's) projection of the whole volume: the slabs' summed."""
        from lfcore._kernels import slabs as ks

        wp = warp()
        out.zero_()
        for w, v in self._each(e):
            w.subset_forward(k, v, out=self.scratch)
            wp.launch(ks.accumulate, dim=int(out.shape[0]), inputs=[out, self.scratch], device=self.device)
        return out

    def subset_update(self, k, ratio, e, relaxation: float, *, scale=None) -> None:
        """Subset ``k``'s (or a group's) scaled update of every slab (``scale``: one per slab with voxels)."""
        scales = [None] * len(self._lit) if scale is None else scale
        for (w, v), sc in zip(self._each(e), scales, strict=True):
            w.subset_update(k, ratio, v, relaxation, scale=sc)


class _IterationLog:
    """Progress and the stage log of a frame's iterations in slabs, counted across its stages (the
    line-of-sight first iterations and DRT's): a line for each stage's start and its first three
    iterations, every tenth iteration and the last (a frame of L runs for hours: not 400 lines, nor
    none for an hour)."""

    def __init__(self, iterations: int, progress, log, device) -> None:
        self.iterations, self.progress, self.log, self.device = iterations, progress, log, device
        self.done = 0
        self.in_stage = 0  # iterations of the stage that started last
        self.voxels = 0  # of the stage that starts next
        self.since = time.perf_counter()

    def started(self, seconds: float) -> None:
        self.log(f"start (one projection of {self.voxels:,} voxels) {seconds:.1f} s")
        self.in_stage = 0
        self.since = time.perf_counter()

    def tick(self, k: int) -> None:
        if self.progress is not None:
            self.progress(k)
        if k != 1:  # the iterations the stopping rule left out
            return
        self.done += 1
        self.in_stage += 1
        if self.in_stage <= 3 or self.done % 10 == 0 or self.done == self.iterations:
            warp().synchronize_device(self.device)
            self.log(f"iteration {self.done}/{self.iterations} {time.perf_counter() - self.since:.1f} s")
        self.since = time.perf_counter()
