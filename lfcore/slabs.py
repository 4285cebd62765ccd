"""Reconstruction in depth slabs: volumes larger than memory, the same volume as in memory.

The in-memory path (:class:`lfcore.reconstruct.FrameReconstructor`) holds, besides the active
voxels' weights and intensities, buffers of the whole box: the elimination's masks (8 bytes per
voxel) and the dense result with its smoothing scratch (8 bytes per voxel). A box of 5e9 voxels
needs 80 GB for those alone. Here the box is cut along z into slabs and only one slab's buffers
(plus its smoothing halo) exist at a time, while the iterations still see the whole volume:

1. Elimination, slab by slab. A voxel's test reads only its own sub-apertures' pixels, so
   testing the voxels of each slab in turn keeps exactly the voxels one pass over the box keeps.
   Each slab numbers its own voxels from its first plane (:meth:`lfcore.operator.Projector.planes`), so a box of
   more than 2**31 voxels (the chapter's dual-camera one: 1939 x 1455 x 1939) is numbered in
   int32 slab by slab, while each voxel's centre is the box's voxel's to the bit.
2. The weights of each slab's survivors, on its slab's projector: a voxel's weights depend on its
   centre and the cameras only, so they are the in-memory path's rows. The matrix-free templates
   are built once, over the whole box's depth planes, and serve every slab
   (:meth:`lfcore.matrix_free.DrtTemplates.on`).
3. MART's ratio needs the projection of the whole volume. Each iteration therefore projects every
   slab into an image-sized buffer and sums them into one projection, then updates every slab
   from that same projection's log ratios (computed once): SMART's update of a voxel reads only
   the projection and its own weights, so this is the in-memory iteration, reordered only in the
   sum over voxels (float round-off). The uniform start is scaled by the same summed projection.
4. The result, slab by slab: the slab's intensities and those of the ``halo`` planes on either
   side (from the neighbouring slabs) scattered into a dense buffer, smoothed (the halo is the
   Gaussian's radius, so each of the slab's voxels sees what it sees in the whole volume; zero
   beyond the box as there), and the slab's planes handed to a writer (a chunked zarr array).

Memory: the active voxels' weights and intensities (as in memory) plus, per slab, about
:data:`BYTES_PER_SLAB_VOXEL` bytes per voxel of the slab and its halo, plus a few image-sized
buffers. The sequential form (pixel by pixel, each update changing the projection) is not
split; it keeps the in-memory path.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from lfcore.device import MemoryBudgetError, Rows, available_bytes, launch_rows, out_of_memory_is_budget_error
from lfcore.device_ops import VolumeOps, gaussian_taps
from lfcore.operator import OPERATOR_KINDS, TEMPLATES, Operator, Projector, from_templates, log_ratio, max_planes
from lfcore.reconstruct import (
    CAPPED,
    CONVERGED,
    FIXED,
    NO_VOXELS,
    FrameReconstructor,
    ReconResult,
    ReconSettings,
    StoppingRule,
    _total,
    _total_measured,
    preprocess_images,
    prune_dark,
    relative_residual,
    stop_interval,
)
from lfcore.volume import VolumeGrid

__all__ = ["BYTES_PER_SLAB_VOXEL", "Slab", "SlabReconstructor", "deepest_slab", "plan_slabs", "slab_halo",
           "slabs_for_budget"]

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


def slabs_for_budget(grid: VolumeGrid, budget_bytes: int, *, halo: int, n_pixels: int = 0) -> int:
    """The fewest slabs whose buffers (:data:`BYTES_PER_SLAB_VOXEL` per voxel of a slab and its
    ``halo`` planes on both sides, and :data:`BYTES_PER_PIXEL` per pixel) fit in ``budget_bytes``,
    each slab with its halo numbered in int32 (:func:`deepest_slab`).

    Raises
    ------
    MemoryBudgetError
        If even slabs one plane deep do not fit.
    """
    nz, ny, nx = grid.shape
    plane = BYTES_PER_SLAB_VOXEL * ny * nx
    room = int(budget_bytes) - BYTES_PER_PIXEL * int(n_pixels)
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
        nz, ny, nx = p.grid.shape
        plane = ny * nx
        budget = available_bytes(dev) if self.budget_bytes is None else int(self.budget_bytes)
        held = BYTES_PER_PIXEL * p.n_pixels
        self.peak_bytes = held
        t0 = time.perf_counter()
        lit_host = [np.asarray(m, dtype=np.uint8) for m in lits]
        voxels, weights = [], []
        t_elim = 0.0
        operator_bytes = 0
        for i, (slab, ps) in enumerate(zip(self.slabs, self._projectors, strict=True)):
            ta = time.perf_counter()
            frames = FrameReconstructor(ps, s, templates=self._templates)  # the slab's elimination and weights
            vox = frames.eliminate(lit_host)
            wp.synchronize_device(dev)
            tb = time.perf_counter()
            t_elim += tb - ta
            self._peak(held + BYTES_PER_SLAB_VOXEL * slab.nz * plane)
            # the weights may take what the budget leaves beside those held already and this slab's
            # intensities (FrameReconstructor's weight budget sets the slab's dense volume aside: add it back)
            room = budget - held - 4 * int(vox.shape[0]) - BYTES_PER_SLAB_VOXEL * slab.nz * plane
            # and the matrix-free templates, held already, which it sets aside itself
            first = not any(from_templates(x) for x in weights)
            shared = 0 if first or self._templates is None else self._templates.nbytes
            frames.budget_bytes = room + 12 * p.n_pixels + 4 * int(vox.shape[0]) + 8 * ps.grid.n_voxels + shared
            w = frames.operator(vox)  # stored, or the templates
            if frames.templates is not None:
                self._templates = frames.templates
            own = self._own_bytes(w, first=first)
            operator_bytes += own
            held += own + 4 * w.n_voxels
            self._peak(held)
            wp.synchronize_device(dev)
            log(f"slab {i + 1}/{len(self.slabs)} (planes {slab.z0}-{slab.z1 - 1}): elimination {tb - ta:.1f} s, "
                f"{int(vox.shape[0]):,} active voxels; operator ({_operator_kind(w)}) "
                f"{time.perf_counter() - tb:.1f} s, {own / 2**20:.0f} MiB")
            voxels.append(vox)
            weights.append(w)
        if s.method == "mart":
            t_elim = 0.0
        image = wp.array(np.concatenate([x.ravel() for x in signals]), dtype=float, device=dev)
        proj = wp.zeros(p.n_pixels, dtype=float, device=dev)
        part = wp.zeros(p.n_pixels, dtype=float, device=dev)
        ratio = wp.empty(p.n_pixels, dtype=float, device=dev)
        es = [wp.empty(max(w.n_voxels, 1), dtype=float, device=dev) for w in weights]
        n_total = sum(w.n_voxels for w in weights)
        nnz, fly = sum(w.nnz for w in weights), sum(w.n_on_the_fly for w in weights)  # before any pruning

        def project() -> None:
            # the projection of the whole volume: the slabs' images summed pixel by pixel
            proj.zero_()
            for w, e in zip(weights, es, strict=True):
                if w.n_voxels:
                    w.forward(e, out=part)
                    wp.launch(ks.accumulate, dim=p.n_pixels, inputs=[proj, part], device=dev)

        t1 = time.perf_counter()
        start_s = iterate_s = 0.0
        rule = StoppingRule(s.stop_tolerance, voxels=s.stop_voxels, every=stop_interval(s, prune=s.prune > 0))
        ran, stopped = (0, NO_VOXELS) if n_total == 0 else (s.iterations, CAPPED if rule.on else FIXED)
        if n_total == 0:
            for e in es:
                e.fill_(0.0)
        else:
            for e in es:
                e.fill_(1.0)
            project()
            total_proj = _total(proj)
            scale = _total_measured(image) / total_proj if total_proj > 0 else 0.0
            for e in es:
                e.fill_(scale)
            wp.synchronize_device(dev)
            t2 = time.perf_counter()
            start_s = t2 - t1
            log(f"start (one projection of {n_total:,} voxels) {start_s:.1f} s")
            floor = max(s.floor * s.threshold_sigma * float(np.mean(noises)), 1e-6)
            for it in range(s.iterations):
                ti = time.perf_counter()
                project()
                left = sum(w.n_voxels for w in weights)
                if rule.due(it) and rule.converged(it, relative_residual(image, proj), left):
                    ran, stopped = it, CONVERGED  # the stopping rule (ReconSettings.stop_tolerance)
                    if progress is not None:
                        progress(s.iterations - it)
                    break
                log_ratio(image, proj, floor, ratio)  # every slab's update reads the whole volume's
                for w, e in zip(weights, es, strict=True):
                    if w.n_voxels:
                        w.update(ratio, e, s.relaxation)
                if s.prune > 0 and (it + 1) % s.prune_every == 0 and it + 1 < s.iterations:
                    # the dark voxels leave every slab's operator, at one threshold for the whole volume
                    weights, es = prune_dark(weights, es, s.prune)
                if progress is not None:
                    progress(1)
                if it < 3 or it == s.iterations - 1:  # the first few and the last: not 400 lines
                    wp.synchronize_device(dev)
                    log(f"iteration {it + 1}/{s.iterations} {time.perf_counter() - ti:.1f} s")
            wp.synchronize_device(dev)
            iterate_s = time.perf_counter() - t2
        t3 = time.perf_counter()
        # the result, slab by slab, each with the halo its smoothing reads
        for slab in self.slabs:
            lo, hi = max(0, slab.z0 - self.halo), min(nz, slab.z1 + self.halo)
            self._peak(held + BYTES_PER_SLAB_VOXEL * (hi - lo) * plane)
            ops = VolumeOps((hi - lo, ny, nx), device=dev)
            buf = wp.zeros((hi - lo, ny, nx), dtype=float, device=dev)
            flat = buf.reshape((hi - lo) * plane)
            for other, w, e in zip(self.slabs, weights, es, strict=True):
                if other.z1 > lo and other.z0 < hi and w.n_voxels:  # its voxels numbered from its plane z0
                    shift, n = wp.int64((other.z0 - lo) * plane), wp.int64((hi - lo) * plane)
                    launch_rows(ks.scatter_range, w.n_voxels, [Rows(w.voxels), Rows(e), shift, n, flat], dev)
            if s.smooth > 0:
                ops.smooth(buf, s.smooth)
            planes = buf.numpy()[slab.z0 - lo: slab.z1 - lo]
            write(slab.z0, slab.z1, np.ascontiguousarray(planes, dtype=np.float32))
            del ops, buf, flat
        log(f"volume smoothed and written, slab by slab, in {time.perf_counter() - t3:.1f} s")
        return ReconResult(volume=np.zeros((0, 0, 0), np.float32), active_voxels=n_total,
                           active_fraction=n_total / p.grid.n_voxels, nnz=nnz,
                           weight_bytes=operator_bytes, weights_s=t1 - t0 + start_s,
                           iterate_s=iterate_s, iterations=ran, stopped=stopped, background=backgrounds,
                           noise=noises,
                           eliminate_s=t_elim, on_the_fly_voxels=fly, final_voxels=sum(w.n_voxels for w in weights),
                           projector="matrix-free" if any(from_templates(w) for w in weights) else "stored",
                           slabs=len(self.slabs), peak_bytes=self.peak_bytes,
                           operator=", ".join(sorted({w.kind for w in weights})))

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
