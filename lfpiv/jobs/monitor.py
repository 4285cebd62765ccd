"""The live monitor (``lfpiv monitor``): record in the background and watch the newest pair.

:func:`run_monitor` builds the live pipeline (:mod:`realtime.pipeline`) on one of its routes
(:data:`LIVE_ROUTES`: volumes and correlation, or particles and tracks) and the recorder, and
hands both to the monitor window's event loop (:func:`realtime.monitor.run_monitor_window`).

:class:`LiveRecorder` implements the monitor's :class:`realtime.monitor.Controls`: each
:meth:`~LiveRecorder.arm` records up to ``pairs`` pairs through :func:`lfpiv.jobs.acquire.record`, the
same path as ``lfpiv acquire`` (plan, program, configure, create the store, start the session,
arm; disarm first whatever happens), in a thread of its own, and attaches the live pipeline to
the session's ring before the laser is armed. :meth:`~LiveRecorder.disarm` ends the recording
the way Ctrl-C ends ``lfpiv acquire``: the laser is disarmed, every settled pair written, and
the run marked aborted if it stopped early. With ``record`` off the pairs go to a scratch run
store that is deleted afterwards: the live view still sees every pair.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.protocols import DeviceError
from acquisition.session import SessionStats
from lfcore.correlate import CorrelationConfig, CorrelationError
from lfcore.device import MemoryBudgetError, resolve_device
from lfcore.operator import MatrixFreeUnsupported
from lfcore.plan import PlanError
from lfcore.reconstruct import ReconSettings
from lfcore.rig import Rig
from lfcore.runstore import RunStore
from lfcore.volume import VolumeGrid
from lfpiv.errors import UsageError, os_error_line
from lfpiv.jobs.acquire import record
from realtime.pipeline import (
    LIVE_METHODS,
    LIVE_ROUTES,
    LivePipeline,
    LiveSettings,
    LiveStats,
    default_windows,
    monitoring_recon,
)
from realtime.settings import DEFAULT_LIVE_PROTOCOL, LIVE_PROTOCOLS, live_protocol

__all__ = ["DEFAULT_LIVE_PROTOCOL", "LIVE_METHODS", "LIVE_PROTOCOLS", "LIVE_ROUTES", "LiveRecorder", "MonitorOutcome",
           "Recording", "check_display", "live_plan", "live_recon", "live_settings", "require_gui", "run_monitor"]


@dataclass(frozen=True)
class Recording:
    """How one arming ended.

    Attributes
    ----------
    path
        The run store, or None for a scratch recording (record off).
    state
        ``"complete"``, ``"aborted"`` (disarmed early) or ``"failed"`` (a device fault).
    committed_pairs, frames_recorded, frames_dropped, overruns
        As the run store holds them at the end.
    message
        What happened, one line.
    """

    path: Path | None
    state: str
    committed_pairs: int
    frames_recorded: int
    frames_dropped: int
    overruns: int
    message: str


class LiveRecorder:
    """Arm and record in the background, feeding the live pipeline (see the module docstring).

    Parameters
    ----------
    rig
        The rig.
    pipeline
        The live pipeline to attach to each recording's ring.
    pairs
        Pairs per arming.
    out
        Run store of the first recording; later ones get ``-2``, ``-3``, ... before the suffix.
        None: nothing is recorded (record off) until :meth:`set_record` turns it on, which then
        names runs ``monitor-1.zarr``, ``monitor-2.zarr`` ... in the working directory.
    overwrite
        Replace an existing run store at ``out``.
    sim_options
        For ``hardware = "sim"``: as :func:`lfpiv.jobs.acquire.record`'s (``{"lab": lab}`` to reuse a
        started simulated lab for every arming).
    ring_slots
        Ring depth in pairs.
    """

    def __init__(self, rig: Rig, pipeline: LivePipeline, *, pairs: int, out: str | Path | None = None,
                 overwrite: bool = False, sim_options: dict[str, Any] | None = None, ring_slots: int = 32) -> None:
        self.rig = rig
        self.pipeline = pipeline
        self.pairs = int(pairs)
        self.out = Path(out) if out is not None else None
        self.overwrite = overwrite
        self.sim_options = sim_options
        self.ring_slots = ring_slots
        self._record = out is not None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stats: SessionStats | None = None
        self._armings = 0
        self.recordings: list[Recording] = []

    # --- Controls -------------------------------------------------------------------------------
    @property
    def armed(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def record(self) -> bool:
        return self._record

    def set_record(self, on: bool) -> None:
        """Record the next arming to a run store (on) or to a scratch store deleted afterwards."""
        self._record = bool(on)

    def arm(self) -> None:
        """Start a recording of ``pairs`` pairs in the background (nothing if one is running)."""
        with self._lock:
            if self.armed:
                return
            self._armings += 1
            self._stop.clear()
            self._stats = None
            path, scratch = self._next_path()
            self._thread = threading.Thread(target=self._run, args=(path, scratch), name="lfpiv-live-recorder",
                                            daemon=True)
            self._thread.start()

    def disarm(self) -> None:
        """Disarm and end the recording (returns at once; :meth:`wait` for the end)."""
        self._stop.set()

    def wait(self, timeout_s: float = 60.0) -> bool:
        """Wait for the recording to end; True if none is running."""
        t = self._thread
        if t is not None:
            t.join(timeout_s)
        return not self.armed

    def status(self) -> dict[str, float]:
        """The recorder's numbers for the status line (the last recording's once it ended)."""
        st = self._stats
        if self.armed or not self.recordings:
            if st is None:
                return {"committed_pairs": 0, "pair_rate_hz": 0.0, "frames_recorded": 0, "frames_dropped": 0,
                        "overruns": 0}
            return {"committed_pairs": st.committed_pairs, "pair_rate_hz": st.pair_rate_hz,
                    "frames_recorded": st.frames_recorded, "frames_dropped": st.frames_dropped,
                    "overruns": st.overruns}
        r = self.recordings[-1]
        return {"committed_pairs": r.committed_pairs, "pair_rate_hz": st.pair_rate_hz if st else 0.0,
                "frames_recorded": r.frames_recorded, "frames_dropped": r.frames_dropped, "overruns": r.overruns}

    # --- the recording thread ---------------------------------------------------------------
    def _next_path(self) -> tuple[Path, bool]:
        if not self._record:
            return Path(tempfile.mkdtemp(prefix="lfpiv-monitor-")) / "scratch.zarr", True
        base = self.out or Path("monitor.zarr")
        if self.out is not None and self._armings == 1:
            return base, False
        n = self._armings
        while True:
            p = base.with_name(f"{base.stem}-{n}{base.suffix}")
            if not p.exists():
                return p, False
            n += 1

    def _progress(self, stats: SessionStats) -> None:
        self._stats = stats
        if self._stop.is_set():
            raise KeyboardInterrupt  # record() disarms, writes what is settled, marks the run aborted

    def _attach(self, session) -> None:
        self.pipeline.attach(session.ring)
        if self._stop.is_set():
            raise KeyboardInterrupt  # disarmed before the laser was armed

    def _run(self, path: Path, scratch: bool) -> None:
        state, message = "failed", ""
        try:
            res = record(self.rig, path, self.pairs, overwrite=self.overwrite and not scratch,
                         sim_options=self.sim_options, ring_slots=self.ring_slots, progress=self._progress,
                         on_session=self._attach)
            self._stats = res.stats
            state, message = res.state, res.message
        except KeyboardInterrupt:
            state, message = "aborted", "disarmed from the monitor"
        except Exception as exc:  # noqa: BLE001 - shown in the monitor; the laser was disarmed by record()
            message = str(exc)
        try:
            summary = self._summary(path, state, message)
        except Exception as exc:  # noqa: BLE001 - no store was created (e.g. a bad path)
            summary = Recording(None if scratch else path, "failed", 0, 0, 0, 0, f"{message} ({exc})")
        if scratch:
            shutil.rmtree(path.parent, ignore_errors=True)
            summary = Recording(None, summary.state, summary.committed_pairs, summary.frames_recorded,
                                summary.frames_dropped, summary.overruns, summary.message)
        self.recordings.append(summary)

    def _summary(self, path: Path, state: str, message: str) -> Recording:
        store = RunStore.open(path)
        n = store.committed_pairs
        recorded = sum(int(np.count_nonzero(store.frame_ids(c)[:n] >= 0)) for c in store.cameras)
        drops = store.drops()
        overruns = sum(1 for d in drops if str(d["reason"]).startswith("ring overrun"))
        return Recording(path, state, n, recorded, len(drops), overruns, message)


def check_display(screenshot: bool) -> None:
    """Draw offscreen when only a screenshot is wanted and there is no display; without one and
    without a screenshot, a one-line :class:`UsageError`."""
    if os.environ.get("QT_QPA_PLATFORM") or not sys.platform.startswith("linux"):
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    if screenshot:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"  # nothing to show on: draw offscreen for the PNG
        return
    raise UsageError("no display to show the monitor on (DISPLAY is not set); run it on a desktop, or give "
                     "--screenshot out.png to draw offscreen")


def require_gui() -> None:
    """A one-line :class:`UsageError` naming the install command when pyqtgraph or its Qt binding
    is missing (checked before anything is built)."""
    from realtime.monitor import GuiUnavailable, require_qt

    try:
        require_qt()
    except GuiUnavailable as exc:
        raise UsageError(str(exc)) from None


def live_settings(*, iterations: int, relaxation: float, slice_axis: str) -> LiveSettings:
    """The live pipeline's run-time settings, or a one-line :class:`UsageError`."""
    try:
        return LiveSettings(iterations=iterations, relaxation=relaxation, slice_axis=slice_axis)
    except ValueError as exc:
        raise UsageError(f"--iterations/--relaxation: {exc}") from None


def live_recon(method: str, projector: str = "auto", *, warm_start: bool = False) -> ReconSettings:
    """The live path's fixed reconstruction settings (:func:`realtime.pipeline.monitoring_recon`)
    for ``method`` and ``projector``, or the one-line :class:`UsageError` ``lfpiv reconstruct``
    gives for the same pair (e.g. the matrix-free projector with a method other than drt-mart)."""
    try:
        return monitoring_recon(method=method, projector=projector, warm_start=warm_start)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def live_plan(rig: Rig, protocol: str = DEFAULT_LIVE_PROTOCOL, *, method: str | None = None,
              projector: str = "auto", warm_start: bool | None = None) -> tuple[str, bool]:
    """The live method and warm start of the named monitoring plan
    (:func:`realtime.settings.live_protocol`) on ``rig``'s cameras, the user's ``method``,
    ``projector`` and ``warm_start`` (None: the plan's) applied; an unknown plan is a one-line
    :class:`UsageError`."""
    from lfpiv.jobs.reconstruct import default_method

    try:
        return live_protocol(protocol, cameras_method=default_method(rig), method=method, projector=projector,
                             warm_start=warm_start)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


@dataclass(frozen=True)
class MonitorOutcome:
    """How ``lfpiv monitor`` ended.

    Attributes
    ----------
    recordings
        One per arming.
    numbers
        The status line's numbers when the window closed.
    stats
        The live pipeline's counters at the end.
    device
        The compute device of the live path.
    voxels
        (x, y, z) voxels of the live volume.
    projector
        What applied the operator to the last pair shown (``"stored"`` weights or the
        ``"matrix-free"`` templates; ``""`` if none was).
    plan
        The voxel route's plan, one line (:attr:`realtime.pipeline.LivePipeline.plan`); ``""`` on
        the particle route.
    screenshot, screenshot_error
        The screenshot written, or why it could not be.
    interrupted
        Ctrl-C or a signal closed the window.
    """

    recordings: list[Recording]
    numbers: dict[str, float]
    stats: LiveStats
    device: str
    voxels: tuple[int, int, int]
    projector: str
    screenshot: Path | None
    screenshot_error: OSError | None
    interrupted: bool
    plan: str = ""

    def raise_for_end(self) -> None:
        """Raise what ended the session badly: a device fault of a recording (the laser was
        disarmed), a screenshot that could not be written, or the interrupt."""
        failed = [r for r in self.recordings if r.state == "failed"]
        if failed:
            raise DeviceError(failed[-1].message)
        if self.screenshot_error is not None:
            err = self.screenshot_error
            line = os_error_line(err) if err.errno else str(err)  # the cause and the path
            raise UsageError(f"the screenshot was not written ({line}); what was recorded is kept")
        if self.interrupted:
            raise KeyboardInterrupt


def run_monitor(rig: Rig, *, pairs: int, settings: LiveSettings, method: str = "drt-mart", projector: str = "auto",
                passes: int = 2, pvr: Sequence[float] | None = None, device: str | None = None,
                out: str | Path | None = None, overwrite: bool = False, sim_options: dict[str, Any] | None = None,
                ring_slots: int = 32, title: str = "lfpiv monitor", screenshot: str | Path | None = None,
                after: int = 3, say: Callable[[str], None] = lambda text: None,
                warm_start: bool = False, flats: dict[str, Any] | None = None, route: str = "voxels",
                protocol: str | None = None) -> MonitorOutcome:
    """Arm the rig, record every pair (to ``out``, or to a scratch store) and show the newest live.

    Parameters
    ----------
    rig
        The rig, real or simulated.
    pairs
        Pairs to record per arming.
    settings
        The live path's run-time settings (iterations, relaxation, slice).
    method
        ``"drt-mart"`` or ``"mlos-mart"`` for light-field cameras (and mixed rigs), ``"mlos-smart"``
        for pinhole ones (see :data:`realtime.pipeline.LIVE_METHODS`).
    projector
        What applies DRT-MART's operator (:data:`lfcore.matrix_free.PROJECTORS`): ``"stored"`` weights, the
        ``"matrix-free"`` templates (built with the pipeline), or ``"auto"``: per pair the
        templates' images where they cost less to build than tracing the voxels the weight
        cache lacks, else stored weights (:meth:`lfcore.reconstruct.FrameReconstructor.templates_pay`).
    passes
        Correlation passes (1 or 2).
    pvr
        The live volume's pixel-voxel ratio (None: the rig's).
    device
        Compute device of the live path (None: a GPU if there is one).
    out, overwrite
        The run store the first arming records to (None: only shown), and whether it may replace
        an earlier one.
    sim_options
        For ``hardware = "sim"``: the simulated lab's options (:func:`lfpiv.rigging.sim_lab_options`).
    ring_slots
        The ring buffer's depth in pairs.
    title, screenshot, after
        The window's title; a PNG to save after ``after`` pairs were shown (works offscreen).
    say
        Called with progress messages.
    warm_start
        Start frame B of each pair from frame A carried along the last pair's field (:mod:`lfcore.warm`).
    flats
        Per camera, the flat field (:func:`lfpiv.jobs.calibrate.flat_fields`) the live path
        corrects every raw frame by; None: the raw frames.
    route
        ``"voxels"``: ``method`` and correlation; ``"particles"``: each frame's particles by
        iterative particle reconstruction (``method``'s weights model them) and their tracks
        binned on a grid, with the monitoring settings of
        :func:`realtime.settings.monitoring_ipr` and :func:`realtime.settings.monitoring_tracking`
        (:data:`LIVE_ROUTES`). What is recorded is the same either way.
    protocol
        The named plan ``method`` and ``warm_start`` came from (:func:`live_plan`), which the status
        line names; None: settings of one's own.

    Raises
    ------
    UsageError
        Windows that do not fit the live volume, a projector the method or the cameras cannot
        use (the matrix-free one: drt-mart on light-field cameras alone), or
        no Qt.
    """
    from realtime.monitor import GuiUnavailable, run_monitor_window

    recon = live_recon(method, projector, warm_start=warm_start)  # before the simulated lab renders anything
    device = resolve_device(device)
    with ExitStack() as stack:
        if sim_options is not None:
            from sim.lab import SimLab  # the application is the one layer that wires the simulated lab

            say(f"simulated lab: rendering {sim_options['pool_pairs']} pair(s) of '{sim_options['world'].flow}' "
                "per camera ...")
            sim_options = {"lab": stack.enter_context(SimLab(rig, **sim_options))}
        grid = VolumeGrid.from_rig(rig, pvr=None if pvr is None else tuple(pvr))
        try:
            corr = CorrelationConfig(windows=default_windows(grid.shape, passes), overlap=0.5, deform_iterations=0)
        except CorrelationError as exc:
            raise UsageError(str(exc)) from None
        pipe = LivePipeline(rig, settings=settings, recon=recon, correlation=corr, pvr=pvr, device=device, flats=flats,
                            route=route, protocol=protocol)
        what = "the particle reconstruction" if route == "particles" else "the reconstruction"
        then = "tracking" if route == "particles" else "correlation"
        say(f"building {what} ({'x'.join(map(str, pipe.grid.shape[::-1]))} voxels) and {then} on {device} ...")
        try:
            pipe.build()
        except (MatrixFreeUnsupported, MemoryBudgetError, PlanError) as exc:
            raise UsageError(str(exc)) from None
        stack.callback(pipe.stop)
        rec = LiveRecorder(rig, pipe, pairs=pairs, out=out, overwrite=overwrite, sim_options=sim_options,
                           ring_slots=ring_slots)

        def end_recording() -> None:
            rec.disarm()
            rec.wait(120.0)

        stack.callback(end_recording)  # the laser is disarmed whatever happens
        try:
            shown = run_monitor_window(pipe, rec, title=title, screenshot=screenshot, after=after, say=say)
        except GuiUnavailable as exc:
            raise UsageError(str(exc)) from None
        say(f"window closed; recording and live path stopped {shown.stop_s:.1f} s later")
    stats = pipe.stats()
    return MonitorOutcome(recordings=list(rec.recordings), numbers=shown.numbers, stats=stats, device=device,
                          voxels=tuple(pipe.grid.shape[::-1]), projector=stats.projector, screenshot=shown.screenshot,
                          screenshot_error=shown.screenshot_error, interrupted=shown.interrupted, plan=pipe.plan)
