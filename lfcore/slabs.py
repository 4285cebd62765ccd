"""Reconstruction in depth slabs: volumes larger than memory, the same volume as in memory.

The in-memory path (:class:`lfcore.reconstruct.FrameReconstructor`) holds, besides the active
voxels' weights and intensities, buffers of the whole box: the elimination's masks (8 bytes per
voxel) and the dense result with its smoothing scratch (8 bytes per voxel). A box of 5e9 voxels
needs 80 GB for those alone. Here the box is cut along z into slabs and only one slab's buffers
(plus its smoothing halo) exist at a time, while the iterations still see the whole volume:

1. Elimination, slab by slab. A voxel's test reads only its own sub-apertures' pixels, so
   testing the voxels of each slab in turn keeps exactly the voxels one pass over the box keeps
   (the same kernel on the same voxel indices of the whole grid, so the same voxel centres).
2. The weights of each slab's survivors, on the projector of the WHOLE grid (a voxel's weights
   depend on its centre and the cameras only), so they are the in-memory path's rows.
3. MART's ratio needs the projection of the whole volume. Each iteration therefore projects every
   slab into an image-sized buffer and sums them into one projection, then updates every slab
   from that same projection: SMART's update of a voxel reads only the projection and its own
   weights, so this is the in-memory iteration, reordered only in the sum over voxels (float
   round-off). The uniform start is scaled by the same summed projection.
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
from lfcore.matrix_free import applied_by
from lfcore.projector import PREFILTER_CHECKS, Projector
from lfcore.reconstruct import FrameReconstructor, ReconResult, ReconSettings, _total, preprocess_images
from lfcore.volume import VolumeGrid

__all__ = ["BYTES_PER_SLAB_VOXEL", "Slab", "SlabReconstructor", "plan_slabs", "slab_halo", "slabs_for_budget"]

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


def slabs_for_budget(grid: VolumeGrid, budget_bytes: int, *, halo: int, n_pixels: int = 0) -> int:
    """The fewest slabs whose buffers (:data:`BYTES_PER_SLAB_VOXEL` per voxel of a slab and its
    ``halo`` planes on both sides, and :data:`BYTES_PER_PIXEL` per pixel) fit in ``budget_bytes``.

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
    return min(nz, -(-nz // int(planes)))


class SlabReconstructor:
    """Reconstruct frames slab by slab (see the module docstring): the volume of
    :class:`~lfcore.reconstruct.FrameReconstructor` without a buffer of the whole box.

    Parameters
    ----------
    projector
        Cameras and the WHOLE grid on a device (a light-field :class:`~lfcore.projector.Projector`,
        a :class:`~lfcore.pinhole_projector.PinholeProjector` or a
        :class:`~lfcore.pinhole_projector.JointProjector`).
    settings
        As the in-memory path takes them; the simultaneous form only.
    slabs
        The slabs (:func:`plan_slabs`), covering the grid's planes in order.
    budget_bytes
        Memory the weights and buffers may take; None: what the device has free.

    Raises
    ------
    ValueError
        For the sequential form, or slabs that do not cover the grid.
    """

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
        self.projector = projector
        self.settings = settings
        self.slabs = slabs
        self.budget_bytes = budget_bytes
        self.halo = slab_halo(settings)
        self.wp = projector.wp
        self.device = projector.device
        self._frames = FrameReconstructor(projector, settings)  # its weights() (stored or matrix-free)
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
        for i, slab in enumerate(self.slabs):
            ta = time.perf_counter()
            vox = self._eliminate(lit_host, slab)
            wp.synchronize_device(dev)
            tb = time.perf_counter()
            t_elim += tb - ta
            self._peak(held + BYTES_PER_SLAB_VOXEL * slab.nz * plane)
            # the weights may take what the budget leaves beside those held already and this slab's
            # intensities (FrameReconstructor's weight budget sets the box's dense volume aside: add it back)
            room = budget - held - 4 * int(vox.shape[0]) - BYTES_PER_SLAB_VOXEL * slab.nz * plane
            # and the matrix-free templates, held already, which it sets aside itself
            first = not any(applied_by(x) == "matrix-free" for x in weights)
            shared = 0 if first or self._frames._templates is None else self._frames._templates.nbytes
            self._frames.budget_bytes = (room + 12 * p.n_pixels + 4 * int(vox.shape[0]) + 8 * p.grid.n_voxels
                                         + shared)
            w = self._frames.weights(vox)
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
        es = [wp.empty(max(w.n_voxels, 1), dtype=float, device=dev) for w in weights]
        n_total = sum(w.n_voxels for w in weights)

        def project() -> None:
            # the projection of the whole volume: the slabs' images summed pixel by pixel
            proj.zero_()
            for w, e in zip(weights, es, strict=True):
                if w.n_voxels:
                    p.forward(w, e, part)
                    wp.launch(ks.accumulate, dim=p.n_pixels, inputs=[proj, part], device=dev)

        t1 = time.perf_counter()
        start_s = iterate_s = 0.0
        if n_total == 0:
            for e in es:
                e.fill_(0.0)
        else:
            for e in es:
                e.fill_(1.0)
            project()
            total_proj = _total(proj)
            scale = _total(image) / total_proj if total_proj > 0 else 0.0
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
                for w, e in zip(weights, es, strict=True):
                    if w.n_voxels:
                        p.smart_update(w, image, proj, e, s.relaxation, floor)
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
            ops = VolumeOps((hi - lo, ny, nx), dev)
            buf = wp.zeros((hi - lo, ny, nx), dtype=float, device=dev)
            flat = buf.reshape((hi - lo) * plane)
            for other, w, e in zip(self.slabs, weights, es, strict=True):
                if other.z1 > lo and other.z0 < hi and w.n_voxels:
                    launch_rows(ks.scatter_range, w.n_voxels, [Rows(w.voxels), Rows(e), lo * plane, hi * plane, flat],
                                dev)
            if s.smooth > 0:
                ops.smooth(buf, s.smooth)
            planes = buf.numpy()[slab.z0 - lo: slab.z1 - lo]
            write(slab.z0, slab.z1, np.ascontiguousarray(planes, dtype=np.float32))
            del ops, buf, flat
        log(f"volume smoothed and written, slab by slab, in {time.perf_counter() - t3:.1f} s")
        return ReconResult(volume=np.zeros((0, 0, 0), np.float32), active_voxels=n_total,
                           active_fraction=n_total / p.grid.n_voxels, nnz=sum(w.nnz for w in weights),
                           weight_bytes=operator_bytes, weights_s=t1 - t0 + start_s,
                           iterate_s=iterate_s, iterations=s.iterations, background=backgrounds, noise=noises,
                           eliminate_s=t_elim, on_the_fly_voxels=sum(w.n_on_the_fly for w in weights),
                           projector=("matrix-free" if any(applied_by(w) == "matrix-free" for w in weights)
                                      else "stored"),
                           slabs=len(self.slabs), peak_bytes=self.peak_bytes)

    def _own_bytes(self, w, *, first: bool) -> int:
        """Bytes of a slab's operator ``w``, the matrix-free templates (one set for all slabs)
        counted with the first slab that uses them only."""
        templates = self._frames._templates
        own = int(w.nbytes)
        if getattr(w, "matrix_free", False):  # its nbytes holds the templates' too
            own -= templates.nbytes
        if first and applied_by(w) == "matrix-free":
            own += templates.nbytes
        return own

    def _peak(self, nbytes: int) -> None:
        self.peak_bytes = max(self.peak_bytes, int(nbytes))

    # --- a slab's voxels -----------------------------------------------------------------------
    def _eliminate(self, lits: list[np.ndarray], slab: Slab) -> object:
        """The slab's voxels to reconstruct ((n,) int32 flat indices of the whole grid, ascending):
        the survivors of the projector's elimination, or all of them for the MART baseline."""
        from lfcore._kernels import slabs as ks
        from lfcore.pinhole_projector import JointProjector, PinholeProjector

        p, s, wp = self.projector, self.settings, self.wp
        plane = p.grid.shape[1] * p.grid.shape[2]
        first, n = slab.z0 * plane, slab.nz * plane
        if s.method == "mart":
            out = wp.empty(n, dtype=wp.int32, device=self.device)
            wp.launch(ks.voxel_range, dim=n, inputs=[first, out], device=self.device)
            return out
        if isinstance(p, JointProjector):
            lf_lit, ph_lit = p._split(lits)
            kept = np.intersect1d(_eliminate_range(p.lf, lf_lit, first, n, s).numpy(),
                                  _eliminate_range(p.ph, ph_lit, first, n, s).numpy())
            return wp.array(kept.astype(np.int32), dtype=wp.int32, device=self.device)
        if isinstance(p, PinholeProjector) or type(p) is Projector:
            return _eliminate_range(p, lits, first, n, s)
        raise TypeError(f"depth slabs do not know the projector {type(p).__name__}")


def _operator_kind(w) -> str:
    """What applies a slab's operator, in words, for the stage log."""
    if getattr(w, "matrix_free", False):
        return "matrix-free templates, applied in every iteration"
    if getattr(w, "from_templates", False):
        return "matrix-free templates' images, stored"
    return "stored weights" + (f", {w.n_on_the_fly:,} voxels' made on the fly" if w.n_on_the_fly else "")


def _eliminate_range(p: Projector, lits: list[np.ndarray], first: int, n: int, s: ReconSettings) -> object:
    """The voxels ``first .. first + n - 1`` of the grid that the projector's elimination keeps
    (the kernels of :meth:`Projector.eliminate` and :meth:`PinholeProjector.eliminate`, run on
    that range of voxels only), as (k,) int32 flat indices, ascending."""
    from lfcore._kernels import slabs as ks
    from lfcore.device import RowOffset
    from lfcore.pinhole_projector import PinholeProjector

    wp = p.wp
    lit = p._lit_on_device(lits)
    mask = p._scratch("mask", n, wp.int32)
    mask.zero_()
    ids = p._scratch("slab_ids", n, wp.int32)
    wp.launch(ks.voxel_range, dim=n, inputs=[first, ids], device=p.device)
    if isinstance(p, PinholeProjector):
        launch_rows(p._kp.mlos_eliminate, n, [p._grid, p.views, len(p.cameras), lit, RowOffset(first), Rows(mask)],
                    p.device)
        return p._compact(mask, ids)
    kw = p._kw
    common = [p._grid, p.views, len(p.cameras), p.sub_a, p.check_order, lit, float(s.min_seen), float(s.max_dark),
              p._checks, p._n_checks]
    # as Projector.eliminate: a few checks on every voxel of the range, then all of them on the candidates
    launch_rows(kw.eliminate, n, [*common, ids, PREFILTER_CHECKS, RowOffset(0), mask], p.device)
    candidates = p._compact(mask, ids, scratch="candidates")
    k = int(candidates.shape[0])
    mask = mask[:max(k, 1)]
    mask.zero_()
    launch_rows(kw.eliminate, k, [*common, candidates, 2**30, RowOffset(0), mask], p.device)
    return p._compact(mask[:k], candidates)

