"""Processing one pair: preprocess, reconstruct frames A and B, correlate (or particles and tracks).

:class:`PairProcessor` is the voxel route (:data:`realtime.settings.LIVE_ROUTES`); for each pair,
on the pipeline's thread:

1. preprocess on the device: the raw 16-bit frames (half the bytes of float signal) become the
   background-subtracted signal and the lit-pixel mask (:func:`lfcore.reconstruct.preprocess`'s
   rule, :class:`~lfcore.device_ops.ImagePreprocessor`); the background level and noise of each
   camera are estimated on the host on the first pair and refreshed every ``background_every``
   pairs, not per frame;
2. DRT-MART (or MLOS-MART: the same elimination, line-of-sight weights) of frames A and B with
   monitoring settings (few iterations; the iterations and the relaxation can be changed while
   it runs), by the batch path's :class:`~lfcore.reconstruct.FrameReconstructor` (one SMART
   loop for both), planned by the batch path's planner (:mod:`lfcore.plan`): the projector
   (geometry on the device), the pixel buffers and two volume buffers are built once and reused;
   the elimination is per frame, as the active voxels follow the particles, and a weight cache
   (where the plan has one) keeps the weights of every voxel already traced, so a frame traces
   only voxels no earlier frame activated (with line-of-sight weights the build traces every
   voxel a frame can keep, and no frame traces any); the volumes are scattered and smoothed on
   the device;
3. 3D multi-grid correlation (one or two passes, no deformation by default) with a
   :class:`~lfcore.correlate.Correlator` whose device buffers are allocated once, reading the
   volumes where they are.

:class:`ParticleProcessor` is the particle route, by the batch path's core functions too (those of
``lfpiv particles`` and ``lfpiv track``):

1. each camera's raw frames on the host (corrected by the flat field where one is given);
2. frames A's and B's particles by iterative particle reconstruction
   (:class:`lfcore.ipr.ParticleReconstructor`, its projector built once; monitoring settings,
   :func:`realtime.settings.monitoring_ipr`);
3. A's particles paired with B's into tracks and their field binned on a grid
   (:func:`lfcore.track.track_pair`), handed on as a :class:`~lfcore.correlate.VectorField` (the
   bins as windows) so that the view and the window draw it as they draw a correlation's;
4. frame A's particles drawn into a volume on the host (each particle's intensity spread over its
   8 nearest voxels), which the window's projections and slice show.

The result is a :class:`ProcessedPair`: volume A (on the device for the voxel route), the vector
field, and the time each stage took. What the window shows of it is :func:`realtime.view.derive`'s.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from acquisition.ring import PairView
from lfcore.correlate import CorrelationConfig, Correlator, VectorField, WindowGrid
from lfcore.device_ops import ImagePreprocessor, VolumeOps
from lfcore.flatfield import FlatField, correct
from lfcore.ipr import IprSettings, ParticleReconstructor, to_index
from lfcore.operator import applied_by
from lfcore.plan import build_reconstructor, plan_reconstruction, projector_for
from lfcore.reconstruct import ReconSettings, estimate_background, warm_count
from lfcore.rig import Rig
from lfcore.track import TrackResult, TrackSettings, track_pair
from lfcore.volume import VolumeGrid
from lfcore.warm import Predictor, WarmStart
from realtime.settings import LiveSettings
from realtime.staging import StagedPair, Staging

__all__ = ["PREFILL_MAX_VOXELS", "HostVolumeOps", "PairProcessor", "ParticleProcessor", "ProcessedPair",
           "particle_volume", "tracks_as_field"]

#: Most voxels whose weights the live build traces ahead (:meth:`_Reconstructor.prefill`): about 30 s
#: of line-of-sight tracing on two CPU cores (the demo's 389,017 took 7 CPU s).
PREFILL_MAX_VOXELS = 2_000_000


@dataclass(frozen=True)
class ProcessedPair:
    """One pair reconstructed and correlated, as :func:`realtime.view.derive` takes it.

    Attributes
    ----------
    view
        The pair as the ring held it (index, time stamps).
    raw
        Per camera, frame A (rows, columns) uint16, a copy.
    volume
        Volume A, (z, y, x) float32 on the device: the processor's buffer, valid until the
        next pair is processed.
    ops
        What cuts projections and planes of ``volume`` on the device and brings them to the
        host (:class:`~lfcore.device_ops.VolumeOps`).
    field
        The vector field of A to B, in voxels.
    grid
        The live volume's grid.
    dt_s
        Time between frames A and B in s.
    active_fraction
        Share of voxels that survived elimination (mean of A and B).
    projector
        What applied the operator to both frames: ``"stored"`` weights or the ``"matrix-free"``
        templates (``"matrix-free, stored"`` where ``auto`` used each for one frame).
    warm
        Whether frame B started from frame A carried along the last pair's field (a warm start).
    timings
        Seconds per stage: ``copy`` (out of the ring), ``preprocess``, ``eliminate``, ``weights``
        (from the cache or built), ``iterate``, ``volume``, ``correlate``; the particle route's:
        ``copy``, ``preprocess``, ``particles`` (both frames), ``track``, ``volume``.
    route
        ``"voxels"`` or ``"particles"`` (:data:`realtime.settings.LIVE_ROUTES`).
    particles
        The particle route's particles in frames A and B; None on the voxel route.
    tracks
        The particle route's tracks kept (not rejected as outliers); None on the voxel route.
    """

    view: PairView
    raw: dict[str, np.ndarray]
    volume: object
    ops: VolumeOps
    field: VectorField
    grid: VolumeGrid
    dt_s: float
    active_fraction: float
    projector: str
    timings: dict[str, float]
    warm: bool = False
    route: str = "voxels"
    particles: tuple[int, int] | None = None
    tracks: int | None = None


class _Reconstructor:
    """DRT-MART or MLOS-MART of one frame at a time with everything but the per-frame weights built once.

    Everything per pair stays on the device: the raw frames arrive there as uint16, are
    preprocessed there (:class:`~lfcore.device_ops.ImagePreprocessor`) into two signal and lit
    buffers, and reconstructed by the batch path's
    :class:`~lfcore.reconstruct.FrameReconstructor` (the same elimination, weights, SMART loop,
    scatter and smoothing, with its buffers kept) into two preallocated volumes, which the
    correlator reads where they are.
    """

    def __init__(self, rig: Rig, cameras: Sequence[str], grid: VolumeGrid, recon: ReconSettings,
                 device: str | None, flats: Mapping[str, FlatField] | None = None, *,
                 prefill: bool | None = None) -> None:
        self.cams = [rig.camera_named(n) for n in cameras]
        self.flats = [None if flats is None else flats.get(n) for n in cameras]
        self.recon = recon
        # the batch path's planner: the projector of the cameras' kind, its operator and whether a weight
        # cache traces each voxel once, on the first frame that keeps it
        self.plan = plan_reconstruction(self.cams, grid, recon, device=device, can_split=False)
        self.frames = build_reconstructor(self.plan, self.cams, grid, recon)
        self.projector = p = self.frames.projector
        self.cache = self.frames.cache
        self.wp = p.wp
        self.device = p.device
        # the matrix-free templates built now (kept by the reconstructor), not in the first pair's time;
        # a geometry without them (MatrixFreeUnsupported) or no room for them fails the build
        self.frames.prepare()
        # the weights of every voxel a frame can keep, traced now rather than in the first pairs' time
        if prefill is None:
            prefill = self.cache is not None and self.cache.method == "los"
        self.prefilled = self.prefill() if prefill and self.cache is not None else 0
        self.offsets = [int(o) for o in p.pixel_offsets]
        self.pre = ImagePreprocessor(self.cams, device=self.device, flats=self.flats)
        self.ops = self.frames.ops
        wp = self.wp
        self.signal = [wp.zeros(p.n_pixels, dtype=float, device=self.device) for _ in range(2)]
        self.lit = [wp.zeros(p.n_pixels, dtype=wp.uint8, device=self.device) for _ in range(2)]
        self.volumes = [self.ops.empty() for _ in range(2)]
        self.background: list[tuple[float, float] | None] = [None] * len(self.cams)
        # warm starts: frame A kept, frame B started from it along the last pair's field
        self.warm = WarmStart(grid.shape, device=self.device) if recon.warm_start else None
        self.predictor: Predictor | None = None
        self.warmed = False  # whether the last frame B started warm

    def camera_image(self, frames: np.ndarray, f: int, k: int) -> np.ndarray:
        """Camera ``k``'s (rows, columns) view of frame ``f`` of flat (2, n_pixels) host frames."""
        rows, cols = self.cams[k].sensor_px[1], self.cams[k].sensor_px[0]
        return frames[f, self.offsets[k]:self.offsets[k + 1]].reshape(rows, cols)

    def prefill(self) -> int:
        """Store in the weight cache the weights of every voxel that any frame's elimination can keep:
        the survivors of an all-lit frame (a lit pixel never drops a voxel, so every frame's survivors
        are among them); none where they are more than :data:`PREFILL_MAX_VOXELS` (over half a minute of
        tracing on a CPU), and no more than the first part where they would not all fit in the cache's
        budget.

        Returns
        -------
        int
            Voxels stored.
        """
        assert self.cache is not None
        every = self.frames.eliminate(self.wp.ones(self.projector.n_pixels, dtype=self.wp.uint8, device=self.device))
        if int(every.shape[0]) > PREFILL_MAX_VOXELS:
            return 0
        return self.cache.prefill(voxels=every.numpy(), whole=True)

    def estimate_background(self, frames: np.ndarray) -> None:
        """Each camera's background level and noise, from frame A of flat host frames."""
        for k in range(len(self.cams)):
            img = self.camera_image(frames, 0, k)
            flat = self.flats[k]
            # the level and noise of the frames as the device corrects them
            level, sigma = estimate_background(img if flat is None else correct(img, flat))
            if self.recon.background is not None:
                level = self.recon.background
            self.background[k] = (level, sigma)

    def preprocess(self, raw) -> None:
        """Signal and lit mask of both frames of the (2, n_pixels) uint16 device array ``raw``."""
        levels = [b[0] for b in self.background]  # type: ignore[index]
        thresholds = [self.recon.threshold_sigma * b[1] for b in self.background]  # type: ignore[index]
        for f in (0, 1):
            self.pre(raw[f], levels, thresholds, self.signal[f], self.lit[f], grow=self.recon.lit_grow)

    def eliminate(self, f: int):
        """The voxels that survive zero-voxel elimination in frame ``f``, (n,) int32 on the device."""
        return self.frames.eliminate(self.lit[f])

    def iterate(self, f: int, weights, iterations: int, relaxation: float):
        """Uniform start scaled to the measured signal, then ``iterations`` SMART updates (the
        dark voxels leaving the operator as the batch path's do): the
        :class:`~lfcore.reconstruct.Iterated` intensities and the operator they are of.

        With warm starts, frame A's intensities are kept and frame B, once a pair's field has been
        measured, starts from them carried along it, with :data:`~lfcore.reconstruct.WARM_SHARE` of
        ``iterations`` (the batch path's rule, :meth:`lfcore.reconstruct.FrameReconstructor.reconstruct`)."""
        noise = [sigma for _, sigma in self.background]  # type: ignore[misc]
        start = None
        self.warmed = False
        if self.warm is not None and f == 1 and self.predictor is not None and self.warm.held and iterations > 0:
            start = self.warm.start(weights, self.predictor)
            iterations = warm_count(iterations, self.recon.warm_iterations)
            self.warmed = True
        done = self.frames.iterate(weights, self.signal[f], noise, iterations=iterations, relaxation=relaxation,
                                   start=start)
        if self.warm is not None and f == 0:
            self.warm.keep(done.op, done.e)
        return done

    def volume(self, f: int, weights, e):
        """Frame ``f``'s (z, y, x) volume, smoothed, in its device buffer."""
        return self.frames.volume(weights, e, out=self.volumes[f])



class PairProcessor:
    """The live reconstruction and correlation, built once, and the processing of one pair.

    Parameters
    ----------
    rig
        The rig (cameras, timing).
    cameras
        Cameras to reconstruct from.
    grid
        The live volume.
    recon
        The fixed reconstruction settings (simultaneous form).
    correlation
        The correlation.
    device
        Warp device; None for the first GPU, else the CPU.
    flats
        Per camera name, the flat field its raw frames are corrected by on the device
        (:class:`lfcore.flatfield.FlatField`; None or a camera left out: uncorrected).
    prefill
        Trace the weights of every voxel a frame can keep while building, within the weight
        cache's budget, so that no pair traces any; None: where the cache holds line-of-sight
        weights (MLOS-MART: seconds for the demo's box; DRT weights would take minutes).

    Attributes
    ----------
    recon
        The live reconstructor (projector, weight cache, frame reconstructor, preprocessor and
        buffers).
    correlator
        The correlator, its device buffers allocated once.
    """

    def __init__(self, rig: Rig, cameras: Sequence[str], grid: VolumeGrid, recon: ReconSettings,
                 correlation: CorrelationConfig, device: str | None,
                 flats: Mapping[str, FlatField] | None = None, *, prefill: bool | None = None) -> None:
        self.cameras = list(cameras)
        self.grid = grid
        self.dt_s = rig.timing.dt_us * 1e-6
        self.recon = _Reconstructor(rig, self.cameras, grid, recon, device, flats, prefill=prefill)
        self.correlator = Correlator(grid.shape, config=correlation, device=self.recon.device)

    route = "voxels"

    @property
    def layout(self) -> _Reconstructor:
        """What the staging uploads the frames for (:meth:`realtime.staging.Staging.build`)."""
        return self.recon

    @property
    def device(self) -> str:
        """The Warp device the pair is processed on."""
        return self.recon.device

    def process(self, staged: StagedPair, settings: LiveSettings, *, staging: Staging,
                refresh_background: bool) -> ProcessedPair:
        """Preprocess, reconstruct and correlate the staged pair (on the pipeline's thread).

        The pair's host slot goes back to ``staging`` once its frames are on the device, and
        the next pair's upload starts between frame A's and frame B's kernels.

        Parameters
        ----------
        staged
            The pair, its upload started (:meth:`Staging.next_pair`).
        settings
            The run-time settings taken for this pair (iterations, relaxation, background).
        staging
            Where the pair came from.
        refresh_background
            Estimate each camera's background level and noise again from this pair (it is
            estimated on the first pair in any case).
        """
        rc = self.recon
        s = settings
        slot, view = staged.slot, staged.slot.view
        assert view is not None
        t: dict[str, float] = {"copy": slot.copy_s, "preprocess": 0.0, "eliminate": 0.0, "weights": 0.0,
                               "iterate": 0.0, "volume": 0.0}
        start = time.perf_counter()
        staging.device_waits_for_upload(staged)  # kernels wait for the upload on the device, not the host
        if rc.background[0] is None or refresh_background:
            rc.estimate_background(slot.frames)
        rc.preprocess(staged.raw)
        staging.consumed(staged)
        raw = {c: rc.camera_image(slot.frames, 0, k).copy() for k, c in enumerate(self.cameras)}
        staging.release(staged)
        t["preprocess"] = time.perf_counter() - start
        vols, active, projectors = [], [], set()
        for f in (0, 1):
            t0 = time.perf_counter()
            voxels = rc.eliminate(f)  # ends on the host (the count of survivors), so t1 is exact
            t1 = time.perf_counter()
            w = rc.frames.operator(voxels)  # from the cache where it has them
            t2 = time.perf_counter()
            done = rc.iterate(f, w, s.iterations, s.relaxation)
            t3 = time.perf_counter()
            vols.append(rc.volume(f, done.op, done.e))
            t4 = time.perf_counter()
            active.append(w.n_voxels / self.grid.n_voxels)
            projectors.add(applied_by(w))
            for k, a, b in (("eliminate", t0, t1), ("weights", t1, t2), ("iterate", t2, t3), ("volume", t3, t4)):
                t[k] += b - a
            del voxels, w, done  # frame A's weights go before frame B's are built (tens of GB for a large volume)
            staging.prefetch()
        t0 = time.perf_counter()
        vf = self.correlator(vols[0], vols[1])
        if rc.warm is not None:  # the next pair's predictor
            rc.predictor = Predictor.from_field(vf)
        t["correlate"] = time.perf_counter() - t0
        return ProcessedPair(view=view, raw=raw, volume=vols[0], ops=rc.ops, field=vf, grid=self.grid, dt_s=self.dt_s,
                             active_fraction=float(np.mean(active)), projector=", ".join(sorted(projectors)),
                             timings=t, warm=rc.warmed)


class HostVolumeOps:
    """:class:`~lfcore.device_ops.VolumeOps`' projections and planes of a volume on the host
    (the particle route's drawing of its particles)."""

    def projection(self, vol: np.ndarray, axis: int) -> np.ndarray:
        """Maximum-intensity projection along array ``axis`` (0 z, 1 y, 2 x)."""
        return np.asarray(vol).max(axis=axis)

    def plane(self, vol: np.ndarray, axis: int, index: int) -> np.ndarray:
        """The plane ``index`` normal to array ``axis``."""
        if not 0 <= index < vol.shape[axis]:
            raise IndexError(f"slice {index} is outside the volume's {vol.shape[axis]} planes along axis {axis}")
        return np.take(vol, index, axis=axis)


def particle_volume(grid: VolumeGrid, positions_mm: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """Particles drawn into a (z, y, x) float32 volume of ``grid``: each one's intensity spread
    over its 8 nearest voxel centres by trilinear weights (what a voxel reconstruction of a point
    would hold at best).

    Parameters
    ----------
    grid
        The volume.
    positions_mm
        (n, 3) world positions (x, y, z), mm.
    intensity
        (n,) intensities.
    """
    vol = np.zeros(grid.shape, np.float32)
    u = to_index(grid, positions_mm)
    if len(u) == 0:
        return vol
    base = np.floor(u).astype(np.int64)
    f = u - base
    shape = np.asarray(grid.shape)
    for corner in np.ndindex(2, 2, 2):
        c = np.asarray(corner)
        idx = base + c
        w = np.prod(np.where(c == 1, f, 1.0 - f), axis=1) * np.asarray(intensity, np.float64)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        np.add.at(vol, tuple(idx[inside].T), w[inside].astype(np.float32))
    return vol


def tracks_as_field(tracks: TrackResult, grid: VolumeGrid, bins: tuple[int, int, int]) -> VectorField:
    """A pair's tracks' binned field as a :class:`~lfcore.correlate.VectorField` in voxels (the
    bins as the windows of one pass, side by side), as the live view takes a correlation's.

    Parameters
    ----------
    tracks
        :func:`lfcore.track.track_pair`'s result: bin centres in mm and the (z, y, x, 3) mean
        displacement (x, y, z) in mm, NaN in bins with too few tracks.
    grid
        The voxel grid the tracks were binned on.
    bins
        (x, y, z) bin size, voxels.

    Returns
    -------
    VectorField
        Displacement in voxels; ``outlier`` True where a bin had too few tracks (NaN), peak ratio
        and height NaN (no correlation peak).
    """
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    origin = np.asarray(grid.origin_mm, dtype=np.float64)
    x, y, z = ((np.asarray(c, dtype=np.float64) - origin[a]) / voxel[a]
               for a, c in enumerate((tracks.x_mm, tracks.y_mm, tracks.z_mm)))
    disp = tracks.field_mm / voxel  # (z, y, x, 3) mm to voxels per component
    empty = ~np.all(np.isfinite(disp), axis=-1)
    nan = np.full(disp.shape[:3], np.nan)
    b = tuple(int(v) for v in bins)
    windows = WindowGrid(window=b, step=b, first=(0, 0, 0), counts=(len(x), len(y), len(z)))  # type: ignore[arg-type]
    return VectorField(x=x, y=y, z=z, displacement=disp, peak_ratio=nan, peak_height=nan.copy(), outlier=empty,
                       replaced=np.zeros_like(empty), grid=windows)


class _HostLayout:
    """Where each camera's pixels lie in the flat (2, n_pixels) host frames of the staging, for a
    route that reads its frames on the host (:meth:`realtime.staging.Staging.build`'s layout)."""

    def __init__(self, cams: Sequence, projector) -> None:
        self.cams = list(cams)
        self.projector = projector
        self.wp = projector.wp
        self.device = "cpu"  # the frames stay on the host: no upload stream
        self.offsets = [int(o) for o in projector.pixel_offsets]

    def camera_image(self, frames: np.ndarray, f: int, k: int) -> np.ndarray:
        """Camera ``k``'s (rows, columns) view of frame ``f`` of flat (2, n_pixels) host frames."""
        rows, cols = self.cams[k].sensor_px[1], self.cams[k].sensor_px[0]
        return frames[f, self.offsets[k]:self.offsets[k + 1]].reshape(rows, cols)


class ParticleProcessor:
    """The live particle route, built once, and the processing of one pair (see the module docstring).

    Parameters
    ----------
    rig
        The rig (cameras, timing).
    cameras
        Cameras to reconstruct from.
    grid
        The live volume: the particles' box and the tracks' bins.
    ipr
        How the particles are reconstructed (:func:`realtime.settings.monitoring_ipr`).
    tracking
        How they are tracked (:func:`realtime.settings.monitoring_tracking`).
    device
        Warp device of the quick reconstruction that gives the candidates; None for the first GPU,
        else the CPU. The fit runs on the host.
    flats
        Per camera name, the flat field its raw frames are corrected by (None or a camera left
        out: uncorrected).

    Attributes
    ----------
    particles
        The particle reconstructor (its projector built once).
    layout
        Where each camera's pixels lie in the staging's host frames.
    """

    route = "particles"

    def __init__(self, rig: Rig, cameras: Sequence[str], grid: VolumeGrid, ipr: IprSettings,
                 tracking: TrackSettings, device: str | None, flats: Mapping[str, FlatField] | None = None) -> None:
        self.cameras = list(cameras)
        self.grid = grid
        self.dt_s = rig.timing.dt_us * 1e-6
        self.tracking = tracking
        cams = [rig.camera_named(n) for n in self.cameras]
        self.flats = [None if flats is None else flats.get(n) for n in self.cameras]
        projector = projector_for(cams, grid, device=device)
        self.particles = ParticleReconstructor(projector, settings=ipr)
        self.layout = _HostLayout(cams, projector)
        self.device = projector.device
        self.ops = HostVolumeOps()

    def process(self, staged: StagedPair, settings: LiveSettings, *, staging: Staging,
                refresh_background: bool) -> ProcessedPair:
        """Both frames' particles, their tracks and field, and frame A's particles drawn into a
        volume (on the pipeline's thread). ``settings`` and ``refresh_background`` are the voxel
        route's: the particle reconstruction estimates each frame's background itself."""
        slot, view = staged.slot, staged.slot.view
        assert view is not None
        lay = self.layout
        t: dict[str, float] = {"copy": slot.copy_s}
        start = time.perf_counter()
        frames = []
        for f in (0, 1):
            images = []
            for k in range(len(self.cameras)):
                img = lay.camera_image(slot.frames, f, k)
                flat = self.flats[k]
                images.append(img.copy() if flat is None else correct(img, flat))  # as particles --flat-field does
            frames.append(images)
        raw = {c: lay.camera_image(slot.frames, 0, k).copy() for k, c in enumerate(self.cameras)}
        staging.consumed(staged)
        staging.release(staged)  # the host slot is free: the frames were copied out of it
        t["preprocess"] = time.perf_counter() - start
        t0 = time.perf_counter()
        found = []
        for images in frames:
            found.append(self.particles.reconstruct(images))
            staging.prefetch()
        t1 = time.perf_counter()
        tracks = track_pair(found[0].positions_mm, found[1].positions_mm, self.grid, settings=self.tracking)
        vf = tracks_as_field(tracks, self.grid, self.tracking.bin_voxels)
        t2 = time.perf_counter()
        volume = particle_volume(self.grid, found[0].positions_mm, found[0].intensity)
        t.update(particles=t1 - t0, track=t2 - t1, volume=time.perf_counter() - t2)
        kept = int(np.count_nonzero(~tracks.outlier))
        return ProcessedPair(view=view, raw=raw, volume=volume, ops=self.ops, field=vf,  # type: ignore[arg-type]
                             grid=self.grid, dt_s=self.dt_s, active_fraction=float("nan"), projector="", timings=t,
                             route=self.route, particles=(found[0].n, found[1].n), tracks=kept)
