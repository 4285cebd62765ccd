"""The live pipeline: the newest recorded pair to a volume (or particles), vectors and vorticity, near real time.

It runs beside the recorder (the data flow of ``docs/development.md``) and never slows it. :class:`LivePipeline`
runs three rooms of one job each on a thread of its own, pair after pair:

1. staging (:mod:`realtime.staging`): a feeder thread copies the newest complete pair out of the
   session's :class:`~acquisition.ring.PairRing` into a host slot, checks the ring's seqlock,
   skips and counts the pairs in between, and starts the pair's upload to the device (on a GPU,
   on a stream of its own, overlapping the current pair's kernels);
2. processing (:mod:`realtime.processing`), by one of two routes
   (:data:`~realtime.settings.LIVE_ROUTES`): ``voxels``, preprocess, reconstruct frames A and B
   and correlate them on the device by the batch path's functions, buffers built once; or
   ``particles``, each frame's particles by iterative particle reconstruction and their tracks
   binned on a grid, by the functions of ``lfpiv particles`` and ``lfpiv track``;
3. the view (:mod:`realtime.view`): velocity in m/s, vorticity, maximum-intensity projections
   and one slice of volume A, the vector plane nearest that slice; a pure function of the
   processed pair and the settings.

Each result is a :class:`LiveResult`, built once every stage's time is known, and handed to
every subscriber on the pipeline's thread; subscribers must return quickly (the monitor puts it
on a Qt queued signal). The settings (:mod:`realtime.settings`) may change while it runs; each
pair takes them at its start.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from lfcore.correlate import CorrelationConfig
from lfcore.flatfield import FlatField
from lfcore.ipr import IprSettings
from lfcore.plan import default_method, unsupported_method
from lfcore.reconstruct import ReconSettings
from lfcore.rig import NotLightFieldError, Rig
from lfcore.track import TrackSettings
from lfcore.volume import VolumeGrid
from realtime.processing import PairProcessor, ParticleProcessor, ProcessedPair, _Reconstructor
from realtime.settings import (
    AXES,
    LIVE_METHODS,
    LIVE_ROUTES,
    LiveSettings,
    check_live_method,
    check_live_route,
    default_windows,
    describe_plan,
    monitoring_ipr,
    monitoring_recon,
    monitoring_tracking,
)
from realtime.staging import PairSource, StagedPair, Staging
from realtime.view import Derived, VectorSlice, derive

__all__ = ["AXES", "LIVE_METHODS", "LIVE_ROUTES", "LiveResult", "LiveSettings", "LiveStats", "LivePipeline",
           "PairSource", "VectorSlice", "default_windows", "monitoring_ipr", "monitoring_recon", "monitoring_tracking",
           "plausible_latency"]

#: Latencies beyond this are taken as a camera clock that is not the host's (reported as NaN).
_PLAUSIBLE_LATENCY_S = 3600.0


def plausible_latency(seconds: float) -> bool:
    """True for a latency that can be real (the camera clock is the host's)."""
    return 0.0 <= seconds < _PLAUSIBLE_LATENCY_S


@dataclass(frozen=True)
class LiveResult:
    """What the pipeline made of one pair.

    Attributes
    ----------
    pair
        Pair index in the run.
    sequence
        How many results were published before this one.
    raw
        Per camera, frame A (rows, columns) uint16, a copy.
    mip, slice_axis, slice_index, slice_image, extent_mm, vectors, velocity, vorticity, grid_mm, outlier_fraction
        What the window shows of the pair, as :class:`realtime.view.Derived` has them (the view's
        pure function, :func:`realtime.view.derive`, made them). On the particle route the
        "volume" is frame A's particles drawn into the live grid, and the vectors are the
        tracks' field in bins (NaN and counted as outliers where a bin had too few tracks).
    active_fraction
        Share of voxels that survived elimination (mean of A and B); NaN on the particle route.
    timings
        Seconds per stage: ``copy``, ``preprocess``, ``eliminate``, ``weights`` (from the cache or
        built), ``iterate``, ``volume``, ``correlate``, ``derive``, ``total``; on the particle
        route ``copy``, ``preprocess``, ``particles``, ``track``, ``volume``, ``derive``, ``total``.
    trigger_ns
        Frame A's time stamp (``time.time_ns`` scale for the simulated lab and for cameras
        without their own clock).
    latency_s
        From the trigger (``trigger_ns``) to the result; NaN when the camera's clock is not the
        host's.
    settings
        The settings used.
    skipped, discarded
        Pairs skipped, and pairs discarded because the ring reused their slot during the copy,
        up to this result.
    projector
        What applied the operator to both frames: ``"stored"`` weights or the ``"matrix-free"``
        templates (``"matrix-free, stored"`` where ``auto`` used each for one frame).
    warm
        Whether frame B started from frame A carried along the last pair's field
        (:func:`realtime.settings.monitoring_recon`'s ``warm_start``).
    route
        ``"voxels"`` or ``"particles"`` (:data:`realtime.settings.LIVE_ROUTES`).
    particles
        The particle route's particles found in frames A and B; None on the voxel route.
    tracks
        The particle route's tracks kept (outliers rejected); None on the voxel route.
    """

    pair: int
    sequence: int
    raw: dict[str, np.ndarray]
    mip: dict[str, np.ndarray]
    slice_axis: str
    slice_index: int
    slice_image: np.ndarray
    extent_mm: dict[str, tuple[float, float]]
    vectors: VectorSlice
    velocity: np.ndarray
    vorticity: np.ndarray
    grid_mm: tuple[np.ndarray, np.ndarray, np.ndarray]
    outlier_fraction: float
    active_fraction: float
    timings: dict[str, float]
    trigger_ns: int
    latency_s: float
    settings: LiveSettings
    skipped: int
    discarded: int
    projector: str = "stored"
    warm: bool = False
    route: str = "voxels"
    particles: tuple[int, int] | None = None
    tracks: int | None = None


@dataclass(frozen=True)
class LiveStats:
    """Counters of the pipeline, for the status line.

    Attributes
    ----------
    state
        ``"idle"`` (not started), ``"building"`` (projector and correlator), ``"waiting"`` (no
        new pair), ``"processing"``, ``"paused"``, ``"stopped"``.
    processed, skipped, discarded
        Pairs processed, skipped (newer ones were there) and discarded (overwritten during the
        copy). ``processed + skipped + discarded`` never exceeds the pairs the ring published.
    last_pair
        The newest pair taken, or -1.
    rate_hz
        Pairs processed per second over the last few.
    latency_s
        Trigger-to-result latency of the last result (NaN if unknown).
    error
        The last error of a stage (the pipeline keeps going), or None.
    projector
        What applied the operator to the last result (:attr:`LiveResult.projector`); ``""``
        before the first and on the particle route.
    route
        The pipeline's route (:data:`realtime.settings.LIVE_ROUTES`).
    particles, tracks
        The particle route's last result's particles (A, B) and tracks kept; None before the
        first and on the voxel route.
    plan
        The voxel route's plan (:func:`realtime.settings.describe_plan`: the named protocol, the
        method, how frame B starts); ``""`` on the particle route.
    """

    state: str
    processed: int
    skipped: int
    discarded: int
    last_pair: int
    rate_hz: float
    latency_s: float
    error: str | None
    projector: str = ""
    route: str = "voxels"
    particles: tuple[int, int] | None = None
    tracks: int | None = None
    plan: str = ""


class LivePipeline:
    """Reconstruct and correlate the newest pair of a recording (or track its particles), in a
    thread of its own.

    Parameters
    ----------
    rig
        The rig (cameras, volume, timing).
    source
        The session's ring; may be given later with :meth:`attach` (and changed for each
        recording).
    settings
        The run-time settings (see :meth:`update`).
    recon
        The fixed reconstruction settings (method: DRT-MART or MLOS-MART; thresholds, smoothing,
        sub-apertures); iterations and relaxation come from ``settings``. Only the simultaneous
        form is used; ``lit_hysteresis`` is refused (the device's lit mask has none).
    correlation
        The correlation; default: :func:`default_windows` at 50% overlap, no deformation.
    cameras
        Cameras to reconstruct from (default: all of the rig's).
    pvr
        Pixel-voxel ratio (x, y, z) of the live volume; default: the rig's ``volume.pvr``. A
        coarser one is a monitoring setting: the live path watches the flow on fewer, larger
        voxels (elimination, weights and correlation cost about in proportion to their number;
        iterations less, as a larger voxel has more line-of-sight weights), while the recording
        keeps the raw frames for full-resolution processing afterwards.
    device
        Warp device; None for the first GPU, else the CPU.
    poll_s
        How often to look for a new pair while waiting.
    flats
        Per camera name, the flat field its raw frames are corrected by
        (:class:`lfcore.flatfield.FlatField`, from a calibration's dark and white images); None:
        the raw frames, one background level per camera.
    route
        ``"voxels"`` (default): volumes and correlation; ``"particles"``: iterative particle
        reconstruction of both frames and tracks (:data:`realtime.settings.LIVE_ROUTES`). The
        particle route takes ``ipr`` and ``tracking``; ``recon``'s method still picks the
        volume route's weights where ``ipr`` has no method of its own, and ``correlation`` and the
        run-time iterations and relaxation are not used.
    ipr
        The particle route's reconstruction; default: :func:`realtime.settings.monitoring_ipr`
        with ``recon``'s method.
    tracking
        The particle route's tracking; default: :func:`realtime.settings.monitoring_tracking` of
        the live volume.
    protocol
        The named plan ``recon`` was made from (:data:`realtime.settings.LIVE_PROTOCOLS`), for the
        status line (:attr:`plan`); None: settings of one's own.
    prefill
        The voxel route's build traces the weights of every voxel a frame can keep (within the weight
        cache's budget), so that no pair traces any (:class:`realtime.processing.PairProcessor`); None:
        where the cache holds line-of-sight weights (MLOS-MART, the fast plan).

    Attributes
    ----------
    plan
        What the voxel route runs, one line (:func:`realtime.settings.describe_plan`); ``""`` on
        the particle route.
    """

    def __init__(self, rig: Rig, source: PairSource | None = None, *, settings: LiveSettings | None = None,
                 recon: ReconSettings | None = None, correlation: CorrelationConfig | None = None,
                 cameras: Sequence[str] | None = None, pvr: Sequence[float] | None = None, device: str | None = None,
                 poll_s: float = 0.005, flats: Mapping[str, FlatField] | None = None, route: str = "voxels",
                 ipr: IprSettings | None = None, tracking: TrackSettings | None = None,
                 protocol: str | None = None, prefill: bool | None = None) -> None:
        check_live_route(route)
        self.route = route
        self.rig = rig
        self.flats = flats
        self.cameras = list(cameras) if cameras else [c.name for c in rig.camera]
        cams = [rig.camera_named(n) for n in self.cameras]  # an unknown camera fails here
        self.grid = VolumeGrid.from_rig(rig, pvr=None if pvr is None else tuple(float(v) for v in pvr))
        self._settings = settings or LiveSettings()
        base = recon or monitoring_recon(method=default_method(cams))
        check_live_method(base.method)
        if base.lit_hysteresis is not None:  # the device's lit mask (ImagePreprocessor) would silently leave it out
            raise ValueError(f"lit_hysteresis {base.lit_hysteresis:g}: the live path's lit mask, made on the device, "
                             "has no hysteresis; leave it None (monitoring_recon's settings)")
        tomo = unsupported_method(cams, base.method)
        if tomo is not None:
            raise NotLightFieldError(f"camera '{tomo}' is a pinhole camera: the live {base.method} needs light-field "
                                     "cameras; use mlos-smart (the default for pinhole cameras)")
        self.recon = replace(base, form="simultaneous")
        self.plan = describe_plan(protocol, self.recon) if route == "voxels" else ""
        self.correlation = correlation or CorrelationConfig(windows=default_windows(self.grid.shape), overlap=0.5,
                                                            deform_iterations=0)
        self.ipr = ipr or monitoring_ipr(method=self.recon.method)
        self.tracking = tracking or monitoring_tracking(self.grid.shape)
        self.device_request = device
        self.prefill = prefill
        self.dt_s = rig.timing.dt_us * 1e-6
        self.poll_s = float(poll_s)
        self._lock = threading.Lock()
        self._subscribers: list[Callable[[LiveResult], None]] = []
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = "idle"
        self._processed = 0
        self._done_times: list[float] = []
        self._latency = float("nan")
        self._projector = ""
        self._error: str | None = None
        self._processor: PairProcessor | ParticleProcessor | None = None
        self._particles: tuple[int, int] | None = None
        self._tracks: int | None = None
        # the source, the pairs taken, skipped and discarded: the staging's, under this lock
        self._staging = Staging(self.cameras, lock=self._lock, stop=self._stop, paused=self._paused,
                                poll_s=self.poll_s)
        if source is not None:
            self.attach(source)

    # --- configuration ----------------------------------------------------------------------
    @property
    def settings(self) -> LiveSettings:
        return self._settings

    def update(self, **changes) -> LiveSettings:
        """Change run-time settings (validated; used from the next pair on)."""
        with self._lock:
            self._settings = replace(self._settings, **changes)
            return self._settings

    def attach(self, source: PairSource | None) -> None:
        """Take pairs from ``source`` from now on (a new recording's ring), or from nothing."""
        if source is not None:
            missing = [c for c in self.cameras if c not in source.cameras]
            if missing:
                raise ValueError(f"camera '{missing[0]}' is not in the ring (it has {source.cameras})")
        self._staging.attach(source)
        self._wake.set()

    def subscribe(self, callback: Callable[[LiveResult], None]) -> Callable[[], None]:
        """Call ``callback(result)`` for every result (on the pipeline's thread); returns an
        unsubscribe function."""
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    # --- life cycle ---------------------------------------------------------------------------
    def build(self) -> None:
        """Build the projector and the correlator (or the particle reconstructor) and their
        buffers (once; :meth:`start` does it on the pipeline's thread if not done before)."""
        if self._processor is None:
            processor: PairProcessor | ParticleProcessor
            if self.route == "particles":
                processor = ParticleProcessor(self.rig, self.cameras, self.grid, self.ipr, self.tracking,
                                              self.device_request, flats=self.flats)
            else:
                processor = PairProcessor(self.rig, self.cameras, self.grid, self.recon, self.correlation,
                                          self.device_request, flats=self.flats, prefill=self.prefill)
            self._staging.build(processor.layout)
            self._processor = processor

    @property
    def _recon(self) -> _Reconstructor | None:
        """The live reconstructor of the voxel route, once built."""
        p = self._processor
        return p.recon if isinstance(p, PairProcessor) else None

    @property
    def device(self) -> str | None:
        """The Warp device in use, once built."""
        return None if self._processor is None else self._processor.device

    def start(self) -> None:
        """Start the pipeline's thread (once)."""
        if self._thread is not None:
            raise RuntimeError("the live pipeline was already started")
        self._thread = threading.Thread(target=self._run, name="lfpiv-live", daemon=True)
        self._thread.start()

    def pause(self, paused: bool = True) -> None:
        """Stop taking pairs (``paused``) or take them again; the thread keeps its buffers."""
        if paused:
            self._paused.set()
        else:
            self._paused.clear()
        self._wake.set()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    def stop(self, timeout_s: float = 30.0) -> bool:
        """Stop the thread after the pair in hand (if any); safe in every state and more than once.

        Returns
        -------
        bool
            True if the thread ended (or never ran) within ``timeout_s``.
        """
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            return not self._thread.is_alive()
        with self._lock:
            self._state = "stopped"
        return True

    def __enter__(self) -> LivePipeline:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> LiveStats:
        with self._lock:
            t = self._done_times
            rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
            st = self._staging
            return LiveStats(self._state, self._processed, st.skipped, st.discarded, st.last_taken, rate,
                             self._latency, self._error, self._projector, route=self.route,
                             particles=self._particles, tracks=self._tracks, plan=self.plan)

    def wait_processed(self, n: int, timeout_s: float) -> bool:
        """Block until ``n`` pairs were processed or ``timeout_s`` passed (for scripts and tests)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._processed >= n:
                return True
            time.sleep(0.01)
        return self._processed >= n

    # --- the thread ---------------------------------------------------------------------------
    def _set_state(self, state: str) -> None:
        with self._lock:
            if self._state != "stopped":
                self._state = state

    def _run(self) -> None:
        try:
            self._set_state("building")
            self.build()
        except Exception as exc:  # noqa: BLE001 - reported in the stats; the recording goes on
            with self._lock:
                self._error = f"building the live pipeline failed: {type(exc).__name__}: {exc}"
                self._state = "stopped"
            return
        staging = self._staging
        staging.start()
        try:
            while not self._stop.is_set():
                if self._paused.is_set():
                    self._set_state("paused")
                    staging.drop_pending()
                    self._wake.wait(0.1)
                    self._wake.clear()
                    continue
                staged = staging.next_pair()
                if staged is None:
                    self._set_state("waiting")
                    staging.wait_for_ready()
                    continue
                self._set_state("processing")
                view = staged.slot.view
                try:
                    result = self._process(staged)
                except Exception as exc:  # noqa: BLE001 - a bad pair must not end the live view
                    staging.release(staged)
                    with self._lock:
                        self._error = f"pair {view.pair}: {type(exc).__name__}: {exc}"
                    continue
                self._publish(result)
        finally:
            self._stop.set()
            staging.stop(10.0)
            staging.drop_pending()  # taken but never processed: skipped
            with self._lock:
                self._state = "stopped"

    # --- one pair ----------------------------------------------------------------------------------
    def _process(self, staged: StagedPair) -> LiveResult:
        """Process the pair, derive what the window shows, and the result with every stage's time."""
        assert self._processor is not None
        s = self._settings
        start = time.perf_counter()
        refresh = s.background_every > 0 and self._processed % s.background_every == 0
        pair = self._processor.process(staged, s, staging=self._staging, refresh_background=refresh)
        t0 = time.perf_counter()
        shown = derive(pair, s)
        derive_s = time.perf_counter() - t0
        timings = {**pair.timings, "derive": derive_s, "total": time.perf_counter() - start + pair.timings["copy"]}
        return self._result(pair, shown, s, timings)

    def _result(self, pair: ProcessedPair, shown: Derived, s: LiveSettings, timings: dict[str, float]) -> LiveResult:
        """The frozen result of one pair: its view, its timings, its latency and the counters now."""
        stamp = int(pair.view.timestamp_ns[self.cameras[0]][0])
        latency = (time.time_ns() - stamp) * 1e-9 if stamp > 0 else float("nan")
        if not plausible_latency(latency):
            latency = float("nan")
        with self._lock:
            seq, skipped, discarded = self._processed, self._staging.skipped, self._staging.discarded
        return LiveResult(pair=pair.view.pair, sequence=seq, raw=pair.raw, mip=shown.mip, slice_axis=shown.slice_axis,
                          slice_index=shown.slice_index, slice_image=shown.slice_image, extent_mm=shown.extent_mm,
                          vectors=shown.vectors, velocity=shown.velocity, vorticity=shown.vorticity,
                          grid_mm=shown.grid_mm, outlier_fraction=shown.outlier_fraction,
                          active_fraction=pair.active_fraction, timings=timings, trigger_ns=stamp, latency_s=latency,
                          settings=s, skipped=skipped, discarded=discarded, projector=pair.projector,
                          warm=pair.warm, route=pair.route, particles=pair.particles, tracks=pair.tracks)

    def _publish(self, result: LiveResult) -> None:
        with self._lock:
            self._processed += 1
            self._latency = result.latency_s
            self._projector = result.projector
            self._particles, self._tracks = result.particles, result.tracks
            self._done_times = [*self._done_times[-9:], time.monotonic()]
            subs = list(self._subscribers)
        for cb in subs:
            try:
                cb(result)
            except Exception as exc:  # noqa: BLE001 - one bad subscriber must not stop the others
                with self._lock:
                    self._error = f"a subscriber failed: {type(exc).__name__}: {exc}"
