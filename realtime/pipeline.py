"""The live pipeline: the newest recorded pair to a volume, vectors and vorticity, near real time.

It runs beside the recorder (DESIGN.md, "Data flow") and never slows it. A feeder thread
copies the newest complete pair out of the session's :class:`~acquisition.ring.PairRing` into
a host staging slot (pinned memory on a GPU machine; the only time it touches the ring, a
memcpy), checks the slot's generation (the ring's seqlock) and discards the copy if the
recorder's side reused the slot meanwhile. Pairs that arrived since the last one taken are
skipped and counted; a newer pair replaces a ready one not yet picked up. The copy of the next
pair thus overlaps the work on the current one, and on a GPU so does its upload: the pipeline
starts the next pair's upload on a CUDA stream of its own while the current pair's kernels
run, and the device waits for it with an event, not the host.

Stages, on the pipeline's own thread, for each pair:

1. preprocess on the device: the raw 16-bit frames (half the bytes of float signal) become the
   background-subtracted signal and the lit-pixel mask (:func:`lfcore.reconstruct.preprocess`'s
   rule, :class:`~lfcore.device_ops.ImagePreprocessor`); the background level and noise of each
   camera are estimated on the host on the first pair and refreshed every ``background_every``
   pairs, not per frame;
2. DRT-MART (or MLOS-MART: the same elimination, line-of-sight weights) of frames A and B with
   monitoring settings (few iterations; the iterations and the relaxation can be changed while
   it runs), by the batch path's :class:`~lfcore.reconstruct.FrameReconstructor` (one SMART
   loop for both): the projector (geometry on the device), the pixel buffers and two volume
   buffers are built once and reused; the elimination is per frame, as the active voxels
   follow the particles, and a :class:`~lfcore.weight_cache.WeightCache` keeps the weights of
   every voxel already traced, so a frame traces only voxels no earlier frame activated; the
   volumes are scattered and smoothed on the device;
3. 3D multi-grid correlation (one or two passes, no deformation by default) with a
   :class:`~lfcore.correlate.Correlator` whose device buffers are allocated once, reading the
   volumes where they are;
4. derived quantities: velocity in m/s, vorticity; maximum-intensity projections and one slice
   of volume A (computed on the device: only these planes come to the host), and the in-plane
   vectors and out-of-plane vorticity of the vector plane nearest that slice.

Each result is a :class:`LiveResult` handed to every subscriber on the pipeline's thread;
subscribers must return quickly (the monitor puts it on a Qt queued signal).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from acquisition.ring import PairView
from lfcore.correlate import CorrelationConfig, Correlator, VectorField
from lfcore.device_ops import ImagePreprocessor
from lfcore.operator import applied_by
from lfcore.plan import build_reconstructor, default_method, plan_reconstruction, unsupported_method
from lfcore.reconstruct import ReconSettings, estimate_background
from lfcore.rig import NotLightFieldError, Rig
from lfcore.vectors import centres_mm, displacement_to_velocity, vorticity
from lfcore.volume import VolumeGrid

__all__ = ["AXES", "LIVE_METHODS", "LiveResult", "LiveSettings", "LiveStats", "LivePipeline", "PairSource",
           "VectorSlice", "default_windows", "monitoring_recon", "plausible_latency"]

#: Slice axes: the axis normal to the slice.
AXES = ("x", "y", "z")
#: Latencies beyond this are taken as a camera clock that is not the host's (reported as NaN).
_PLAUSIBLE_LATENCY_S = 3600.0


def plausible_latency(seconds: float) -> bool:
    """True for a latency that can be real (the camera clock is the host's)."""
    return 0.0 <= seconds < _PLAUSIBLE_LATENCY_S


class PairSource(Protocol):
    """Where pairs come from: :class:`acquisition.ring.PairRing` (or anything like it)."""

    cameras: list[str]

    def latest(self) -> PairView | None: ...

    def still_valid(self, view: PairView) -> bool: ...


#: Reconstruction methods the live path runs: all eliminate zero voxels, so their weights
#: follow the particles and can be cached. ``mlos-smart`` is for pinhole (Tomo-PIV) cameras.
LIVE_METHODS = ("drt-mart", "mlos-mart", "mlos-smart")


def monitoring_recon(iterations: int = 5, relaxation: float = 1.0, method: str = "drt-mart", *,
                     projector: str = "auto") -> ReconSettings:
    """Settings for monitoring: few simultaneous iterations, the default thresholds.

    ``method`` is one of :data:`LIVE_METHODS`; ``projector`` one of
    :data:`lfcore.matrix_free.PROJECTORS` (what applies DRT-MART's operator, as in
    :class:`~lfcore.reconstruct.ReconSettings`).

    Raises
    ------
    ValueError
        A method the live path does not run, or a projector the method cannot use.
    """
    _check_live_method(method)
    return ReconSettings(method=method, iterations=iterations, relaxation=relaxation, form="simultaneous",
                         projector=projector)


def _check_live_method(method: str) -> None:
    if method not in LIVE_METHODS:
        raise ValueError(f"the live path runs {', '.join(LIVE_METHODS[:-1])} or {LIVE_METHODS[-1]}, not '{method}'")


def default_windows(shape: tuple[int, int, int], passes: int = 2) -> tuple[tuple[int, int, int], ...]:
    """Monitoring windows (x, y, z) for volumes of ``shape`` (z, y, x): ``passes`` sizes, halving.

    The first is the largest power of two no more than 0.6 of the volume along each axis (at
    most 64 voxels, at least 4); each further pass halves it (at least 4).
    """
    if passes not in (1, 2):
        raise ValueError(f"the live pipeline correlates in 1 or 2 passes, got {passes}")
    nz, ny, nx = shape
    first = []
    for n in (nx, ny, nz):
        w = 4
        while w * 2 <= min(64, 0.6 * n):
            w *= 2
        first.append(min(w, n))
    out = [tuple(first)]
    if passes == 2:
        out.append(tuple(max(4, w // 2) for w in first))
    return tuple(out)  # type: ignore[return-value]


@dataclass(frozen=True)
class LiveSettings:
    """What may change while the pipeline runs (taken at the start of each pair).

    Attributes
    ----------
    iterations
        DRT-MART iterations per frame (0: the elimination's uniform start only).
    relaxation
        DRT-MART relaxation (simultaneous form: at most 2).
    slice_axis
        ``"x"``, ``"y"`` or ``"z"``: the axis normal to the slice shown.
    slice_index
        Voxel index of the slice along ``slice_axis``; None for the middle. Clipped to the grid.
    background_every
        Re-estimate each camera's background level and noise every this many processed pairs
        (0: only on the first).
    """

    iterations: int = 5
    relaxation: float = 1.0
    slice_axis: str = "z"
    slice_index: int | None = None
    background_every: int = 50

    def __post_init__(self) -> None:
        monitoring_recon(self.iterations, self.relaxation)  # the reconstruction's own checks
        if self.slice_axis not in AXES:
            raise ValueError(f"slice_axis must be one of x, y, z, got '{self.slice_axis}'")
        if self.background_every < 0:
            raise ValueError(f"background_every must be 0 or more, got {self.background_every}")


@dataclass(frozen=True)
class VectorSlice:
    """The vectors of one plane of the vector grid, in that plane.

    Attributes
    ----------
    axis
        Axis normal to the plane.
    index
        Index of the plane in the vector grid along ``axis``.
    position_mm
        World coordinate of the plane along ``axis``.
    h_mm, v_mm
        1-D world coordinates of the plane's horizontal and vertical axes (for axis z: x and y;
        for y: x and z; for x: y and z).
    uv
        (len(v_mm), len(h_mm), 2) in-plane velocity (horizontal, vertical) in m/s.
    normal_vorticity
        (len(v_mm), len(h_mm)) the vorticity component along ``axis`` in 1/s.
    """

    axis: str
    index: int
    position_mm: float
    h_mm: np.ndarray
    v_mm: np.ndarray
    uv: np.ndarray
    normal_vorticity: np.ndarray


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
    mip
        Maximum-intensity projections of volume A along each axis: ``"z"`` (ny, nx),
        ``"y"`` (nz, nx), ``"x"`` (nz, ny).
    slice_axis, slice_index, slice_image
        The slice of volume A shown: (ny, nx) for z, (nz, nx) for y, (nz, ny) for x.
    extent_mm
        Per axis name, the (min, max) world coordinates of the voxel centres.
    vectors
        The vector plane nearest the slice.
    velocity
        (nz, ny, nx, 3) velocity (u, v, w) in m/s on the vector grid.
    vorticity
        (nz, ny, nx, 3) vorticity (x, y, z) in 1/s.
    grid_mm
        1-D world coordinates (x, y, z) of the vector grid.
    outlier_fraction
        Share of the vectors the median test flagged.
    active_fraction
        Share of voxels that survived elimination (mean of A and B).
    timings
        Seconds per stage: ``copy``, ``preprocess``, ``eliminate``, ``weights`` (from the cache or
        built), ``iterate``, ``volume``, ``correlate``, ``derive``, ``total``.
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
        before the first.
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
                 device: str | None) -> None:
        self.cams = [rig.camera_named(n) for n in cameras]
        self.recon = recon
        # the batch path's planner: the projector of the cameras' kind, its operator and whether a weight
        # cache traces each voxel once, on the first frame that keeps it
        self.plan = plan_reconstruction(self.cams, grid, recon, device=device)
        self.frames = build_reconstructor(self.plan, self.cams, grid, recon)
        self.projector = p = self.frames.projector
        self.cache = self.frames.cache
        self.wp = p.wp
        self.device = p.device
        # the matrix-free templates built now (kept by the reconstructor), not in the first pair's time;
        # a geometry without them (MatrixFreeUnsupported) or no room for them fails the build
        self.frames.prepare()
        self.offsets = [int(o) for o in p.pixel_offsets]
        self.pre = ImagePreprocessor(self.cams, device=self.device)
        self.ops = self.frames.ops
        wp = self.wp
        self.signal = [wp.zeros(p.n_pixels, dtype=float, device=self.device) for _ in range(2)]
        self.lit = [wp.zeros(p.n_pixels, dtype=wp.uint8, device=self.device) for _ in range(2)]
        self.volumes = [self.ops.empty() for _ in range(2)]
        self.background: list[tuple[float, float] | None] = [None] * len(self.cams)

    def camera_image(self, frames: np.ndarray, f: int, k: int) -> np.ndarray:
        """Camera ``k``'s (rows, columns) view of frame ``f`` of flat (2, n_pixels) host frames."""
        rows, cols = self.cams[k].sensor_px[1], self.cams[k].sensor_px[0]
        return frames[f, self.offsets[k]:self.offsets[k + 1]].reshape(rows, cols)

    def estimate_background(self, frames: np.ndarray) -> None:
        """Each camera's background level and noise, from frame A of flat host frames."""
        for k in range(len(self.cams)):
            level, sigma = estimate_background(self.camera_image(frames, 0, k))
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
        """Uniform start scaled to the measured signal, then ``iterations`` SMART updates."""
        noise = [sigma for _, sigma in self.background]  # type: ignore[misc]
        return self.frames.iterate(weights, self.signal[f], noise, iterations=iterations, relaxation=relaxation).e

    def volume(self, f: int, weights, e):
        """Frame ``f``'s (z, y, x) volume, smoothed, in its device buffer."""
        return self.frames.volume(weights, e, out=self.volumes[f])


@dataclass(eq=False)
class _Slot:
    """Host staging for one pair: (2, n_pixels) uint16 frames, pinned on a GPU machine."""

    host: object  # warp.array on the CPU
    frames: np.ndarray  # its NumPy view
    view: PairView | None = None
    source: object = None
    copy_s: float = 0.0


@dataclass(eq=False)
class _Job:
    """A pair on its way to the device: the slot, the device frames, the upload's event."""

    slot: _Slot
    raw: object  # (2, n_pixels) uint16 warp.array on the device
    buffer: int  # which device buffer (-1 on the CPU, where the slot itself is used)
    uploaded: object = None  # warp.Event on a GPU
    released: bool = False  # the host slot was given back


class LivePipeline:
    """Reconstruct and correlate the newest pair of a recording, in a thread of its own.

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
        form is used.
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
    """

    def __init__(self, rig: Rig, source: PairSource | None = None, *, settings: LiveSettings | None = None,
                 recon: ReconSettings | None = None, correlation: CorrelationConfig | None = None,
                 cameras: Sequence[str] | None = None, pvr: Sequence[float] | None = None, device: str | None = None,
                 poll_s: float = 0.005) -> None:
        self.rig = rig
        self.cameras = list(cameras) if cameras else [c.name for c in rig.camera]
        cams = [rig.camera_named(n) for n in self.cameras]  # an unknown camera fails here
        self.grid = VolumeGrid.from_rig(rig, pvr=None if pvr is None else tuple(float(v) for v in pvr))
        self._settings = settings or LiveSettings()
        base = recon or monitoring_recon(method=default_method(cams))
        _check_live_method(base.method)
        tomo = unsupported_method(cams, base.method)
        if tomo is not None:
            raise NotLightFieldError(f"camera '{tomo}' is a pinhole camera: the live {base.method} needs light-field "
                                     "cameras; use mlos-smart (the default for pinhole cameras)")
        self.recon = replace(base, form="simultaneous")
        self.correlation = correlation or CorrelationConfig(windows=default_windows(self.grid.shape), overlap=0.5,
                                                            deform_iterations=0)
        self.device_request = device
        self.dt_s = rig.timing.dt_us * 1e-6
        self.poll_s = float(poll_s)
        self._source: PairSource | None = None
        self._last_taken = -1
        self._lock = threading.Lock()
        self._subscribers: list[Callable[[LiveResult], None]] = []
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = "idle"
        self._processed = self._skipped = self._discarded = 0
        self._done_times: list[float] = []
        self._latency = float("nan")
        self._projector = ""
        self._error: str | None = None
        self._recon: _Reconstructor | None = None
        self._correlator: Correlator | None = None
        # Staging (see _feed and _next_job): host slots the feeder thread fills with the newest
        # pair, the one pair ready for the pipeline, and the one already on its way to the device.
        self._slots_cv = threading.Condition()
        self._free: list[_Slot] = []
        self._ready: _Slot | None = None
        self._prefetched: _Job | None = None
        self._feeder: threading.Thread | None = None
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
        with self._lock:
            self._source = source
            self._last_taken = -1
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
        """Build the projector and the correlator and their buffers (once; :meth:`start` does it
        on the pipeline's thread if not done before)."""
        if self._recon is None:
            rc = _Reconstructor(self.rig, self.cameras, self.grid, self.recon, self.device_request)
            self._correlator = Correlator(self.grid.shape, config=self.correlation, device=rc.device)
            wp, n = rc.wp, rc.projector.n_pixels
            gpu = rc.device != "cpu"
            # Four host slots: one being filled, one ready, one prefetched, one being preprocessed.
            for _ in range(4):
                host = wp.empty((2, n), dtype=wp.uint16, device="cpu", pinned=gpu)
                self._free.append(_Slot(host=host, frames=host.numpy()))
            if gpu:
                # Uploads run on a stream of their own so that the next pair's copy overlaps the
                # kernels of the current one; two device buffers alternate between them.
                self._copy_stream = wp.Stream(rc.device)
                self._dev_raw = [wp.empty((2, n), dtype=wp.uint16, device=rc.device) for _ in range(2)]
                self._uploaded = [wp.Event(rc.device) for _ in range(2)]
                self._consumed = [wp.Event(rc.device) for _ in range(2)]
                self._next_buffer = 0
            self._recon = rc

    @property
    def device(self) -> str | None:
        """The Warp device in use, once built."""
        return None if self._recon is None else self._recon.device

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
            return LiveStats(self._state, self._processed, self._skipped, self._discarded, self._last_taken, rate,
                             self._latency, self._error, self._projector)

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
        self._feeder = threading.Thread(target=self._feed, name="lfpiv-live-feed", daemon=True)
        self._feeder.start()
        try:
            while not self._stop.is_set():
                if self._paused.is_set():
                    self._set_state("paused")
                    self._drop_pending()
                    self._wake.wait(0.1)
                    self._wake.clear()
                    continue
                job = self._next_job()
                if job is None:
                    self._set_state("waiting")
                    with self._slots_cv:
                        if self._ready is None and not self._stop.is_set():
                            self._slots_cv.wait(self.poll_s)
                    continue
                self._set_state("processing")
                view = job.slot.view
                try:
                    result = self._process(job)
                except Exception as exc:  # noqa: BLE001 - a bad pair must not end the live view
                    self._release(job)
                    with self._lock:
                        self._error = f"pair {view.pair}: {type(exc).__name__}: {exc}"
                    continue
                self._publish(result)
        finally:
            self._stop.set()
            with self._slots_cv:
                self._slots_cv.notify_all()
            self._feeder.join(10.0)
            self._drop_pending()  # taken but never processed: skipped
            with self._lock:
                self._state = "stopped"

    # --- staging: the feeder thread and the hand-over ---------------------------------------------
    def _feed(self) -> None:
        """Copy the newest pair not yet taken into a free host slot and make it the ready one.

        Runs on a thread of its own with host work only (a memcpy out of the ring), so the copy
        of the next pair overlaps the processing of the current one. A newer pair replaces a
        ready one that the pipeline has not yet picked up (that one counts as skipped): the
        pipeline always starts on the newest complete pair.
        """
        while not self._stop.is_set():
            if self._paused.is_set():
                self._stop.wait(0.05)
                continue
            with self._lock:
                src, last = self._source, self._last_taken
            view = src.latest() if src is not None else None
            if view is None or view.pair <= last:
                self._stop.wait(self.poll_s)
                continue
            with self._slots_cv:
                slot = self._free.pop() if self._free else None
                if slot is None:
                    self._slots_cv.wait(self.poll_s)
                    continue
            t0 = time.perf_counter()
            rc = self._recon
            for k, c in enumerate(self.cameras):
                for f in (0, 1):
                    np.copyto(rc.camera_image(slot.frames, f, k), view.frames[c][f])  # type: ignore[union-attr]
            ok = src.still_valid(view)
            slot.view, slot.source, slot.copy_s = view, src, time.perf_counter() - t0
            with self._lock:
                current = self._source is src
                if current:
                    self._skipped += view.pair - last - 1
                    self._last_taken = view.pair
                    if not ok:
                        self._discarded += 1
            if not (current and ok):
                self._free_slot(slot)
                continue
            with self._slots_cv:
                replaced, self._ready = self._ready, slot
                if replaced is not None:
                    self._free.append(replaced)
                self._slots_cv.notify_all()
            if replaced is not None:
                with self._lock:
                    self._skipped += 1

    def _free_slot(self, slot: _Slot) -> None:
        slot.view = slot.source = None
        with self._slots_cv:
            self._free.append(slot)
            self._slots_cv.notify_all()

    def _upload(self, slot: _Slot) -> _Job:
        """Start the slot's frames on their way to the device (on the GPU: the copy stream)."""
        rc = self._recon
        assert rc is not None
        if rc.device == "cpu":
            return _Job(slot=slot, raw=slot.host, buffer=-1)
        i = self._next_buffer
        self._next_buffer ^= 1
        s = self._copy_stream
        s.wait_event(self._consumed[i])  # the pair before last has been preprocessed out of buffer i
        rc.wp.copy(self._dev_raw[i], slot.host, stream=s)
        s.record_event(self._uploaded[i])
        return _Job(slot=slot, raw=self._dev_raw[i], buffer=i, uploaded=self._uploaded[i])

    def _release(self, job: _Job) -> None:
        """The job's host slot is free once its upload is done (once only)."""
        if job.released:
            return
        job.released = True
        if job.uploaded is not None:
            self._recon.wp.synchronize_event(job.uploaded)  # type: ignore[union-attr]
        self._free_slot(job.slot)

    def _claim_ready(self) -> _Slot | None:
        with self._slots_cv:
            slot, self._ready = self._ready, None
        if slot is not None and slot.source is not self._source:  # from a recording since detached
            self._free_slot(slot)
            return None
        return slot

    def _next_job(self) -> _Job | None:
        """The newest pair: the prefetched one unless a newer one is ready."""
        pre, self._prefetched = self._prefetched, None
        if pre is not None and pre.slot.source is not self._source:  # from a recording since detached
            self._release(pre)
            pre = None
        slot = self._claim_ready()
        if pre is None:
            return None if slot is None else self._upload(slot)
        if slot is None:
            return pre
        self._release(pre)  # a newer pair came in since the prefetch: take that one instead
        with self._lock:
            self._skipped += 1
        return self._upload(slot)

    def _prefetch(self) -> None:
        """If a pair is ready and none is prefetched, start its upload now (overlapping the
        current pair's kernels on the GPU)."""
        if self._prefetched is None:
            slot = self._claim_ready()
            if slot is not None:
                self._prefetched = self._upload(slot)

    def _drop_pending(self) -> None:
        """Give back the ready and the prefetched pair, counting them as skipped."""
        dropped = 0
        pre, self._prefetched = self._prefetched, None
        if pre is not None:
            self._release(pre)
            dropped += 1
        with self._slots_cv:
            slot, self._ready = self._ready, None
        if slot is not None:
            self._free_slot(slot)
            dropped += 1
        if dropped:
            with self._lock:
                self._skipped += dropped

    # --- one pair ----------------------------------------------------------------------------------
    def _process(self, job: _Job) -> LiveResult:
        assert self._recon is not None and self._correlator is not None
        rc = self._recon
        s = self._settings
        slot, view = job.slot, job.slot.view
        assert view is not None
        t: dict[str, float] = {"copy": slot.copy_s, "preprocess": 0.0, "eliminate": 0.0, "weights": 0.0,
                               "iterate": 0.0, "volume": 0.0}
        start = time.perf_counter()
        if job.uploaded is not None:  # kernels wait for the upload on the device, not the host
            rc.wp.get_stream(rc.device).wait_event(job.uploaded)
        if rc.background[0] is None or (s.background_every > 0 and self._processed % s.background_every == 0):
            rc.estimate_background(slot.frames)
        rc.preprocess(job.raw)
        if job.buffer >= 0:
            rc.wp.get_stream(rc.device).record_event(self._consumed[job.buffer])
        raw = {c: rc.camera_image(slot.frames, 0, k).copy() for k, c in enumerate(self.cameras)}
        self._release(job)
        t["preprocess"] = time.perf_counter() - start
        vols, active, projectors = [], [], set()
        for f in (0, 1):
            t0 = time.perf_counter()
            voxels = rc.eliminate(f)  # ends on the host (the count of survivors), so t1 is exact
            t1 = time.perf_counter()
            w = rc.frames.operator(voxels)  # from the cache where it has them
            t2 = time.perf_counter()
            e = rc.iterate(f, w, s.iterations, s.relaxation)
            t3 = time.perf_counter()
            vols.append(rc.volume(f, w, e))
            t4 = time.perf_counter()
            active.append(w.n_voxels / self.grid.n_voxels)
            projectors.add(applied_by(w))
            for k, a, b in (("eliminate", t0, t1), ("weights", t1, t2), ("iterate", t2, t3), ("volume", t3, t4)):
                t[k] += b - a
            del voxels, w, e  # frame A's weights go before frame B's are built (tens of GB for a large volume)
            self._prefetch()
        t0 = time.perf_counter()
        vf = self._correlator(vols[0], vols[1])
        t1 = time.perf_counter()
        result = replace(self._derive(view, raw, vols[0], vf, s, float(np.mean(active)), t),
                         projector=", ".join(sorted(projectors)))
        t["correlate"] = t1 - t0
        t["derive"] = time.perf_counter() - t1
        t["total"] = time.perf_counter() - start + slot.copy_s
        return result

    def _derive(self, view: PairView, raw: dict[str, np.ndarray], vol, vf: VectorField, s: LiveSettings,
                active: float, t: dict[str, float]) -> LiveResult:
        """Velocity, vorticity and what the monitor shows; ``vol`` is volume A on the device."""
        g = self.grid
        vel = displacement_to_velocity(vf.displacement, g.voxel_mm, self.dt_s)
        x_mm, y_mm, z_mm = centres_mm((vf.x, vf.y, vf.z), g.origin_mm, g.voxel_mm)
        vort = vorticity(np.nan_to_num(vel), x_mm, y_mm, z_mm)
        ops = self._recon.ops  # type: ignore[union-attr]
        mip = {a: ops.projection(vol, ax) for ax, a in enumerate("zyx")}  # only these come to the host
        ax = "zyx".index(s.slice_axis)  # array axis of the volume
        n = g.shape[ax]
        idx = n // 2 if s.slice_index is None else int(np.clip(s.slice_index, 0, n - 1))
        sl = ops.plane(vol, ax, idx)
        # the vector plane nearest the voxel slice
        centres_vox = {"x": vf.x, "y": vf.y, "z": vf.z}[s.slice_axis]
        vi = int(np.argmin(np.abs(np.asarray(centres_vox) - idx)))
        coords = {"x": x_mm, "y": y_mm, "z": z_mm}
        h, v = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}[s.slice_axis]
        comp = {"x": 0, "y": 1, "z": 2}
        plane = np.take(vel, vi, axis=ax)  # (v, h, 3) in array order
        wplane = np.take(vort, vi, axis=ax)[..., comp[s.slice_axis]]
        uv = np.stack([plane[..., comp[h]], plane[..., comp[v]]], axis=-1)
        vs = VectorSlice(axis=s.slice_axis, index=vi, position_mm=float(coords[s.slice_axis][vi]),
                         h_mm=coords[h], v_mm=coords[v], uv=uv, normal_vorticity=wplane)
        extent = {a: (float(g.axis_mm(a)[0]), float(g.axis_mm(a)[-1])) for a in AXES}
        stamp = int(view.timestamp_ns[self.cameras[0]][0])
        latency = (time.time_ns() - stamp) * 1e-9 if stamp > 0 else float("nan")
        if not plausible_latency(latency):
            latency = float("nan")
        with self._lock:
            seq, skipped, discarded = self._processed, self._skipped, self._discarded
        return LiveResult(pair=view.pair, sequence=seq, raw=raw,
                          mip=mip, slice_axis=s.slice_axis, slice_index=idx, slice_image=sl, extent_mm=extent,
                          vectors=vs, velocity=vel, vorticity=vort, grid_mm=(x_mm, y_mm, z_mm),
                          outlier_fraction=float(np.mean(vf.outlier)), active_fraction=active, timings=t,
                          trigger_ns=stamp, latency_s=latency, settings=s, skipped=skipped, discarded=discarded)

    def _publish(self, result: LiveResult) -> None:
        with self._lock:
            self._processed += 1
            self._latency = result.latency_s
            self._projector = result.projector
            self._done_times = [*self._done_times[-9:], time.monotonic()]
            subs = list(self._subscribers)
        for cb in subs:
            try:
                cb(result)
            except Exception as exc:  # noqa: BLE001 - one bad subscriber must not stop the others
                with self._lock:
                    self._error = f"a subscriber failed: {type(exc).__name__}: {exc}"

