"""Recording double-frame runs from the rig, real or simulated (``lfpiv acquire``).

The order of operations is what keeps the laser safe and the data whole:

1. Plan the timing and check the output path before touching any device.
2. Open the pulse generator, program it with outputs disabled; open and configure the cameras.
3. Create the run store, start the cameras and the recorder, then arm: the generator fires
   exactly ``pairs`` double pulses (burst mode) and stops by itself.
4. Watch: progress, camera stalls, recorder errors, the generator still answering.
5. Whatever happens (done, Ctrl-C, SIGTERM, a device fault), disarm first, then stop the
   cameras, let the recorder write every settled pair, and mark the run ``complete`` or
   ``aborted``. Frames that never came are listed in ``drops``.

Steps 2, 3 and 5 are the context manager :func:`armed` (the devices and the store) and
:class:`ArmedRecording` (arming, and on every way out disarming, closing and marking);
:func:`record` plans, then watches inside it. Nothing here prints: the lines a user must read
at once while a recording ends go to the caller's ``say`` (standard error by default), and
:class:`AcquireResult` holds the rest.

With ``hardware = "sim"`` the same code runs against :class:`sim.lab.SimLab`: the real serial
driver talks to the emulated generator on a pseudo-terminal and the simulated cameras are
triggered by it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acquisition.protocols import DeviceError, PulseGenerator, TimingPlan
from acquisition.pulse_generator import MAX_BURST, signals_call, signals_held
from acquisition.session import RecordingSession, SessionStats
from acquisition.timing import TimingError, plan_timing
from lfcore.rig import Rig
from lfcore.runstore import RunStore, RunStoreError
from lfpiv import __version__
from lfpiv.errors import UsageError
from lfpiv.rigging import Rigging, open_rig

__all__ = ["PAIRINGS", "AcquireResult", "ArmedRecording", "armed", "check_plan", "record"]

#: How frames A and B are paired (``lfpiv acquire --pairing``).
PAIRINGS = ("counter", "timestamps")


class Terminated(Exception):
    """SIGTERM or SIGHUP arrived while recording."""


def _terminated() -> None:
    raise Terminated()


@dataclass(frozen=True)
class AcquireResult:
    """What a recording did."""

    store: RunStore
    state: str
    stats: SessionStats
    drops: int
    message: str


def check_plan(rig: Rig, pairs: int, *, pairing: str = "counter") -> TimingPlan:
    """The timing plan for ``pairs`` double pulses, or a one-line :class:`UsageError` saying why
    the rig's timing (or the ``pairing``, see :func:`record`) is impossible."""
    if pairs < 1:
        raise UsageError(f"--pairs must be at least 1, got {pairs}")
    if pairs > MAX_BURST:
        # the generator stops by itself after a burst of that many periods
        raise UsageError(f"--pairs {pairs} is more than one burst of the pulse generator fires "
                         f"({MAX_BURST:,}); record the experiment as several runs")
    if pairing not in PAIRINGS:
        raise UsageError(f"--pairing must be one of {', '.join(PAIRINGS)}, got '{pairing}'")
    if pairing == "timestamps" and rig.hardware == "sim":
        raise UsageError("--pairing timestamps is for real GenICam cameras without a double-exposure mode; the "
                         "simulated cameras expose both frames of each trigger (leave it out)")
    try:
        return plan_timing(rig, pulses=pairs)
    except TimingError as exc:
        raise UsageError(str(exc)) from None


def record(rig: Rig, out: str | Path, pairs: int, *, overwrite: bool = False,
           sim_options: dict[str, Any] | None = None, ring_slots: int = 32, writer_threads: int = 4,
           stall_s: float = 3.0, progress: Callable[[SessionStats], None] | None = None,
           on_session: Callable[[RecordingSession], None] | None = None,
           pairing: str = "counter", say: Callable[[str], None] | None = None) -> AcquireResult:
    """Record ``pairs`` double-frame pairs from every camera of ``rig`` into a new run store.

    Parameters
    ----------
    rig
        The rig (devices, timing, laser rate).
    out
        Path of the run store to create.
    pairs
        Double pulses to fire and pairs to record.
    overwrite
        Replace an existing run store at ``out``.
    sim_options
        For ``hardware = "sim"``: keyword arguments of :class:`sim.lab.SimLab`.
    ring_slots, writer_threads
        Ring-buffer depth in pairs, and parallel frame writers.
    stall_s
        A camera that delivers nothing for this long (beyond the trigger period) while
        triggers are due is taken as failed and the recording stops.
    progress
        Called about five times a second with the session's statistics.
    on_session
        Called with the recording session once it started and before the laser is armed (the
        live pipeline attaches to ``session.ring`` here); it must return quickly.
    pairing
        ``"counter"`` (frames A and B of one trigger, by frame counter) or ``"timestamps"``: real
        GenICam cameras without a double-exposure mode take one frame per trigger, paired in
        software by their time stamps (the simulated cameras expose both frames of a trigger).
    say
        Called with each line the user must read at once while the recording ends (the laser's
        state, what is kept, a run that could not be marked); default: standard error.

    Returns
    -------
    AcquireResult
        The store, its final state ("complete" or "aborted") and statistics.

    Raises
    ------
    UsageError
        For an impossible timing plan or an existing output.
    DeviceError
        A device fault; the laser was disarmed and what was recorded is kept, marked aborted.
    KeyboardInterrupt
        Ctrl-C; the laser was disarmed and the run marked aborted.
    """
    plan = check_plan(rig, pairs, pairing=pairing)
    RunStore.check_new(out, overwrite=overwrite)
    with armed(rig, out, pairs, plan=plan, overwrite=overwrite, sim_options=sim_options, ring_slots=ring_slots,
               writer_threads=writer_threads, pairing=pairing, on_session=on_session, say=say) as rec:
        _watch(rec, stall_s=stall_s, progress=progress)
    return AcquireResult(rec.store, rec.state, rec.stats, rec.drops, rec.message)


def _watch(rec: ArmedRecording, *, stall_s: float, progress: Callable[[SessionStats], None] | None) -> None:
    """Watch an armed recording until every pair is in: progress, camera stalls, recorder errors,
    the generator still answering. Raises what stops it early (ArmedRecording disarms)."""
    session, period = rec.session, rec.period_s
    last_trigger_due = rec.armed_at + rec.pairs * period
    grace = 1.0 + 2 * period
    drained = False
    next_ping = rec.armed_at + 1.0
    while not session.done:
        session.wait(0.2)
        now = time.monotonic()
        if progress is not None:
            progress(session.stats())
        if session.error is not None:
            raise session.error
        if not drained and now > last_trigger_due + grace:
            session.drop_undelivered(f"not delivered within {grace:.1f} s after the last trigger")
            drained = True
        if not drained:
            for cam in rec.cameras:
                if session.seconds_since_frame(cam.name) > stall_s + period:
                    raise DeviceError(f"camera '{cam.name}' delivered no frame for {stall_s + period:.1f} s "
                                      "while triggered; check its trigger cable, power and link")
        if now > next_ping:
            # a generator that stops answering, was reset or was changed from its front panel
            # stops the recording (the driver disarms first)
            rec.generator.verify()
            next_ping = now + 1.0


@contextmanager
def armed(rig: Rig, out: str | Path, pairs: int, *, plan: TimingPlan, overwrite: bool = False,
          sim_options: dict[str, Any] | None = None, ring_slots: int = 32, writer_threads: int = 4,
          pairing: str = "counter", on_session: Callable[[RecordingSession], None] | None = None,
          say: Callable[[str], None] | None = None) -> Iterator[ArmedRecording]:
    """Open the rig, create the run store, start recording and arm the laser; disarm, close and mark
    on the way out, whatever ends the block.

    In order: open the pulse generator and the cameras, program the generator with its outputs
    disabled, check and configure the cameras, create the run store, start the recording
    session, call ``on_session``, arm. The block watches the recording (:func:`record` waits
    for every pair); leaving it normally means the recording is done. Then, and on every other
    way out (an exception, Ctrl-C, SIGTERM or SIGHUP, a device fault), :class:`ArmedRecording`
    disarms the laser first, stops the session, marks the run ``complete`` or ``aborted``, and
    the devices are closed last. Parameters as :func:`record`'s; ``plan`` is
    :func:`check_plan`'s.

    Yields
    ------
    ArmedRecording
        The session, the generator and the cameras while armed; its ``state``, ``message``,
        ``stats`` and ``drops`` once the block has ended.

    Raises
    ------
    UsageError
        A camera whose sensor disagrees with the rig file (before the store is created).
    DeviceError
        A device fault that ended the block (the laser's state and what was kept in the
        message), or a laser whose disarm could not be confirmed.
    RunStoreError
        A recording that completed but could not be marked so.
    KeyboardInterrupt
        Ctrl-C, SIGTERM or SIGHUP; the laser was disarmed and the run marked aborted.
    """
    with open_rig(rig, sim_options=sim_options, software_pairing=pairing == "timestamps") as rg:
        gen = rg.pulse_generator
        gen.program(plan)
        for cam in rg.cameras:
            cols, rows = cam.sensor_px
            want = rig.camera_named(cam.name).sensor_px
            if (cols, rows) != tuple(want):
                raise UsageError(f"camera '{cam.name}' delivers {cols} x {rows} pixels but the rig file says "
                                 f"sensor_px = {list(want)}; correct the rig file")
            cam.configure(triggered=True, frames_per_trigger=2, exposure_us=rig.timing.camera_exposure_us,
                          dt_us=rig.timing.dt_us)
        # the timing as the instrument holds it (every time rounded to its resolution), not as asked
        held = getattr(gen, "programmed", None) or plan
        timing = {"dt_s": held.dt_s, "rate_hz": 1.0 / held.period_s, "pulses": pairs,
                  "channels": [{"channel": c.channel, "role": c.role, "delay_s": c.delay_s, "width_s": c.width_s,
                                "polarity": c.polarity} for c in held.channels],
                  "planned": {"dt_s": plan.dt_s, "rate_hz": 1.0 / plan.period_s}}
        store = RunStore.create(out, rig, pairs, timing=timing, software_version=__version__, overwrite=overwrite)
        say = say or _to_stderr
        try:
            store.group.attrs.update({"hardware": rig.hardware})
            session = RecordingSession(rg.cameras, store, pairs, ring_slots=ring_slots,
                                       writer_threads=writer_threads, trigger_period_s=plan.period_s)
        except BaseException as exc:  # a Ctrl-C or a fault before recording: the run is not left "recording"
            _close_run(store, "aborted", f"stopped before recording began ({type(exc).__name__})", None, 0, say)
            raise
        with ArmedRecording(rg, store, session, pairs=pairs, period_s=plan.period_s, out=out, on_session=on_session,
                            say=say) as rec:
            yield rec


class ArmedRecording:
    """The laser armed over a started recording session; disarmed, the session closed and the run
    marked on every way out.

    Entering starts the session, calls ``on_session`` and arms the generator. Leaving, however
    the block ends:

    1. disarm the laser (at once on a device fault; held Ctrl-Cs and kills meanwhile disarm it
       too, and say that the run is being closed);
    2. close the session: the cameras stop and the recorder writes every settled pair;
    3. mark the run ``complete`` (the block ended normally and every pair was written) or
       ``aborted`` (with its reason: the fault, or how it was stopped and after how many
       committed pairs), and write a simulated lab's truth;
    4. raise what ended it badly: a device fault as a :class:`DeviceError` that says what became
       of the laser and what was kept, SIGTERM or SIGHUP as KeyboardInterrupt, a laser whose
       disarm was not confirmed or a run that could not be marked as errors of their own; Ctrl-C
       and other exceptions go on as they came.

    Parameters
    ----------
    rigging
        The opened devices (:func:`lfpiv.rigging.open_rig`); they are closed by their owner after this.
    store
        The new run store, state ``recording``.
    session
        The recording session into ``store``, not yet started.
    pairs
        Pairs the generator fires.
    period_s
        The trigger period in s.
    out
        The run store's path as the user gave it (in the messages).
    on_session
        Called with the started session before the laser is armed.
    say
        Called with each line the user must read at once (default: standard error).

    Attributes
    ----------
    state, message
        ``"complete"`` or ``"aborted"`` and the reason, once the block has ended.
    stats, drops
        The session's statistics and the number of frames listed in ``drops``, once the block
        ended without an error.
    armed_at
        ``time.monotonic()`` when the laser was armed.
    """

    def __init__(self, rigging: Rigging, store: RunStore, session: RecordingSession, *, pairs: int, period_s: float,
                 out: str | Path, on_session: Callable[[RecordingSession], None] | None = None,
                 say: Callable[[str], None] | None = None) -> None:
        self.generator: PulseGenerator = rigging.pulse_generator
        self.cameras = rigging.cameras
        self.lab = rigging.lab
        self.store = store
        self.session = session
        self.pairs = pairs
        self.period_s = period_s
        self.out = out
        self.say = say or _to_stderr
        self._on_session = on_session
        self.state, self.message = "aborted", ""
        self.stats: SessionStats | None = None
        self.drops = 0
        self.armed_at = float("nan")
        # SIGTERM / SIGHUP (a kill, a closed terminal) disarm and then end the recording as
        # Ctrl-C does, so the run is closed and marked; signals reach only the main thread
        self._signals = ExitStack()

    def __enter__(self) -> ArmedRecording:
        if _is_main_thread():
            self._signals.enter_context(signals_call(_terminated))
        try:
            self.session.start()
            if self._on_session is not None:
                self._on_session(self.session)
            self.generator.arm()
        except BaseException as exc:
            self._end(exc)
            raise
        self.armed_at = time.monotonic()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> bool:
        self._end(exc)
        return False  # what ended the block goes on (or _end raised what replaces it)

    def _end(self, exc: BaseException | None) -> None:
        """Disarm, close and mark (see the class); raise what replaces ``exc``, or return to let it go on."""
        # how the recording was stopped, when the reason ends with the pairs committed by the end
        stopped_by = ""
        # a device fault that stopped the recording: what became of the laser
        fault: str | None = None
        # None until disarmed, then "" or what could not be confirmed
        undisarmed: str | None = None
        if exc is None:
            self.state, self.message = "complete", f"recorded {self.pairs} pair(s)"
        elif isinstance(exc, KeyboardInterrupt):
            stopped_by = "interrupted"
        elif isinstance(exc, Terminated):
            stopped_by = "terminated by a signal"
        elif isinstance(exc, (DeviceError, RuntimeError)):
            self.message = str(exc)
            undisarmed = _disarm(self.generator)
            # reported once the run is closed, with the state it could be marked
            fault = "the laser was disarmed" if not undisarmed else _unconfirmed(undisarmed)
        undisarmed, unclosed = self._close(undisarmed, stopped_by)
        committed = self.session.committed_pairs
        if isinstance(exc, Terminated):
            raise KeyboardInterrupt from None
        if fault is not None:
            marked = (f"state '{self.state}'" if not unclosed else
                      f"it could not be marked '{self.state}', so it still says 'recording'")
            raise DeviceError(f"{self.message}; {fault}; the {committed} pair(s) recorded so far are kept "
                              f"in {self.out} ({marked})") from None
        if exc is not None:
            return
        if undisarmed:
            raise DeviceError(f"{self.message}: the run is kept in {self.out} (state '{self.state}'), but "
                              f"{_unconfirmed(undisarmed)}")
        if unclosed:
            raise RunStoreError(f"recorded {committed} pair(s) into {self.out}, but {unclosed}")
        self.stats = self.session.stats()
        self.drops = len(self.store.drops())

    def _close(self, undisarmed: str | None, stopped_by: str) -> tuple[str, str]:
        """Disarm (unless done), close the session, mark the run; (why the disarm was not
        confirmed, why the run could not be marked), each "" when all went well."""
        session = self.session
        # Ctrl-Cs or kills while the run is closed wait for it (one after the grace time
        # does not); every signal disarms the laser at once in any case
        try:
            with signals_held(self._closing, grace_s=CLOSE_GRACE_S):
                if undisarmed is None:
                    undisarmed = _disarm(self.generator)
                    if undisarmed and self.state != "complete":  # leaving on Ctrl-C or a signal
                        self.say(f"lfpiv: warning: {_unconfirmed(undisarmed)}")
                self._signals.close()
                session.close()
                if self.state == "complete" and session.committed_pairs < self.pairs:
                    self.state = "aborted"
                    self.message = f"only {session.committed_pairs} of {self.pairs} pairs could be written"
                if stopped_by:  # counted once the recorder has written what was settled
                    self.message = f"{stopped_by} after {session.committed_pairs} committed pair(s)"
                unclosed = _close_run(self.store, self.state, self.message, self.lab, session.committed_pairs,
                                      self.say)
                if stopped_by and not undisarmed and _is_main_thread():  # Ctrl-C or a kill: say so at once
                    kept = f"state '{self.state}'" if not unclosed else "still saying 'recording'"
                    self.say(f"lfpiv: the laser is disarmed; {session.committed_pairs} pair(s) are kept in "
                             f"{self.out} ({kept})")
        except KeyboardInterrupt:
            self.say(f"lfpiv: warning: left before the run was closed: {self.out} may still say 'recording'; its "
                     "committed pairs read back whole")
            raise
        return undisarmed, unclosed

    def _closing(self) -> None:
        self.say(f"\nlfpiv: the laser is disarmed; closing the run, one moment (Ctrl-C after {CLOSE_GRACE_S:g} s "
                 "leaves at once)")


def _to_stderr(text: str) -> None:
    """Where the lines a caller must read at once go when it passes no ``say`` (a Python user, a
    test): standard error. What became of the laser must never go unsaid."""
    print(text, file=sys.stderr)


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _disarm(gen: PulseGenerator) -> str:
    """Disarm ``gen``; "" when confirmed, else why not (never raises: it must not mask the error
    that ended the recording)."""
    try:
        gen.disarm()
    except Exception as exc:  # noqa: BLE001
        return str(exc) or type(exc).__name__
    return ""


def _unconfirmed(problem: str) -> str:
    return (f"the laser could NOT be confirmed disarmed ({problem}): press STOP on the pulse generator or close "
            "the laser shutter, then check the generator's cable and power")


#: Seconds after a recording stops during which further Ctrl-Cs and kills wait for the run to be
#: closed; one after that leaves at once (for a close that hangs).
CLOSE_GRACE_S = 5.0


def _close_run(store: RunStore, state: str, message: str, lab: Any, committed: int,
               say: Callable[[str], None]) -> str:
    """Write the run's final state (and a simulated lab's truth); "" when done, else what could
    not be written, also said as a warning. Never raises OSError: a full disk must not hide
    the fault that ended the recording, nor that the laser was disarmed."""
    try:
        store.group.attrs.update({"abort_reason": message} if state == "aborted" else {})
        store.set_state(state)
    except OSError as exc:
        why = (f"the run could not be marked '{state}' ({exc.strerror or exc}), so it still says 'recording'; its "
               f"{committed} committed pair(s) read back whole")
    else:
        if lab is None or committed == 0:
            return ""
        try:
            _write_sim_truth(store, lab, committed)
            return ""
        except OSError as exc:
            why = f"the simulated lab's truth could not be written ({exc.strerror or exc}); the frames are whole"
    say(f"lfpiv: warning: {why}")
    return why


def _write_sim_truth(store: RunStore, lab: Any, pairs: int) -> None:
    # A simulated recording knows exactly what the cameras saw: keep it, as synth does, so that
    # reconstruction and vectors of a recorded run can be checked against the truth.
    import numpy as np

    particles, brightness = lab.truth(pairs)
    full = np.zeros((store.n_pairs, *particles.shape[1:]))
    full[:pairs] = particles
    bright = np.zeros((store.n_pairs, *brightness.shape[1:]))
    bright[:pairs] = brightness
    world = lab.world
    t0 = lab.truth_times_s(store.n_pairs)  # the lab shows its pool of pairs over and over
    density = {"ppm": world.ppm} if world.ppp is None else {"ppm": None, "ppp": world.ppp}
    store.write_truth(full, bright, world.flow_params, t0_s=t0, **density, seed=world.seed, source="simulated lab",
                      pairs_with_truth=pairs)
