"""Recording in the background for the live monitor (``lfpiv monitor``).

:class:`LiveRecorder` implements the monitor's :class:`realtime.monitor.Controls`: each
:meth:`~LiveRecorder.arm` records up to ``pairs`` pairs through :func:`lfpiv.acquire.record`, the
same path as ``lfpiv acquire`` (plan, program, configure, create the store, start the session,
arm; disarm first whatever happens), in a thread of its own, and attaches the live pipeline to
the session's ring before the laser is armed. :meth:`~LiveRecorder.disarm` ends the recording
the way Ctrl-C ends ``lfpiv acquire``: the laser is disarmed, every settled pair written, and
the run marked aborted if it stopped early. With ``record`` off the pairs go to a scratch run
store that is deleted afterwards: the live view still sees every pair.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.session import SessionStats
from lfcore.rig import Rig
from lfcore.runstore import RunStore
from lfpiv.acquire import record
from realtime.pipeline import LivePipeline

__all__ = ["LiveRecorder", "Recording"]


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
        For ``hardware = "sim"``: as :func:`lfpiv.acquire.record`'s (``{"lab": lab}`` to reuse a
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
