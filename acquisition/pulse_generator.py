"""Driver for the Quantum Composers 9520 series pulse generator (and the BNC 575, same commands).

The generator's T0 clock runs at the double-pulse rate; each output channel fires a delay after
T0 (flashlamp and Q-switch of both laser cavities, the camera trigger). The driver programs a
:class:`~acquisition.protocols.TimingPlan` and implements the
:class:`~acquisition.protocols.PulseGenerator` protocol.

Protocol (SCPI-like, over RS-232 or the USB virtual serial port). Every command is one line,
``:KEYWORD:KEYWORD value`` ended by CR LF, and the instrument answers every command with one
line: ``ok``, the queried value, or ``?n`` where ``n`` is an error code (:data:`ERROR_CODES`).
Channel 0 is T0, 1 is channel A, 2 is B, and so on. Commands used here::

    *IDN?                       identification, "QC,9528,<serial>,<firmware>"
    :INST:CAT?                  channel list, "T0,CHA,CHB,..."
    :PULSE0:STATE ON|OFF        start / stop T0 (the RUN / STOP button)
    :PULSE0:PER <s>             T0 period, seconds
    :PULSE0:MODE NORM|BURS      continuous, or a burst of :PULSE0:BCO <n> periods then stop
    :PULSE0:TRIG:MODE DIS       T0 from the internal rate generator, no external trigger
    :PULSE0:GATE:MODE DIS       no external gate input holds pulses back
    :PULSEn:STATE ON|OFF        enable / disable output n
    :PULSEn:SYNC T0             output n is timed from T0
    :PULSEn:CMODE NORM          output n fires on every T0
    :PULSEn:MUX <2**(n-1)>      output n driven by timer n alone (the multiplexer can OR timers)
    :PULSEn:POL NORM|INV        active high / low
    :PULSEn:DELAY <s>           delay after T0, seconds
    :PULSEn:WIDT <s>            pulse width, seconds

Safety. A laser must never keep firing because software lost track of it:

- :meth:`QuantumComposers9520.program` stops T0 and disables every output before it loads a
  plan, and checks the reply of every command.
- Any failure inside a method (no reply, garbled reply, ``?n`` error, serial exception) first
  tries to stop T0 and disable every output, then raises a one-line
  :class:`~acquisition.protocols.DeviceError` that names the port, the command, what to do,
  and whether the outputs are confirmed off or the laser state is unknown.
- The driver is a context manager that disarms on exit, also when the body raises (Ctrl-C is a
  ``KeyboardInterrupt`` and unwinds through it).
- Every armed generator is registered; the registry disarms them all at interpreter exit
  (``atexit``) and on SIGTERM and SIGHUP, then hands the signal to the handler that was
  installed before (or, for the default handler, lets the process die of the signal as it
  would have). Install your own handlers for these signals before the first :meth:`arm`.
- With ``pulses > 0`` the plan runs in burst mode: the generator itself stops after that many
  periods, whatever happens to the computer.

What a hard kill cannot guarantee. SIGKILL, a kernel panic, a power cut of the computer or an
unplugged USB cable give the software no chance to run: a generator armed in continuous mode
then keeps firing the laser until someone presses STOP. Burst mode bounds the damage to the
planned number of pulses. Software is not a safety system: wire the laser's external
interlock (door switches, beam shutter, an emergency stop) so that it does not depend on this
program.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any, NoReturn

from .protocols import DeviceError, TimingPlan
from .serial_link import LinkClosed, LinkError, SerialLink

if TYPE_CHECKING:
    from lfcore.rig import PulseGeneratorConfig

    from .protocols import PulseGenerator

__all__ = ["ERROR_CODES", "MAX_BURST", "QuantumComposers9520", "disarm_all", "install_signal_handlers",
           "pulse_generator_for", "signals_call", "signals_held"]

log = logging.getLogger(__name__)

#: Meaning of the ``?n`` error replies (9500/9520 series and BNC 575 manuals; 8 on newer firmware).
ERROR_CODES = {
    1: "incorrect prefix (no colon or * to start the command)",
    2: "missing command keyword",
    3: "invalid command keyword",
    4: "missing parameter",
    5: "invalid parameter",
    6: "query only, the command needs a question mark",
    7: "invalid query, the command has no query form",
    8: "command unavailable in the current system state",
}

_FIX = {
    1: "the driver and the firmware disagree; check that this is a 9520-series or BNC 575 generator",
    2: "the driver and the firmware disagree; check that this is a 9520-series or BNC 575 generator",
    3: "the instrument lacks this command or channel; check the model, its channel count and firmware",
    4: "the driver and the firmware disagree; check that this is a 9520-series or BNC 575 generator",
    5: "the value is outside the instrument's range; check the timing plan (rate, delays, widths)",
    6: "the driver and the firmware disagree; check that this is a 9520-series or BNC 575 generator",
    7: "the driver and the firmware disagree; check that this is a 9520-series or BNC 575 generator",
    8: "press STOP on the generator, leave its menus and try again",
}

_CHANNEL_LETTERS = "ABCDEFGH"
_UNKNOWN = "laser state UNKNOWN: press STOP on the generator and check the laser interlock"


class QuantumComposers9520:
    """A Quantum Composers 9520-series (or BNC 575) pulse generator on a serial port.

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyUSB0``, ``COM3``) or pyserial URL.
    baud : int
        Baud rate; must match the instrument's interface setting (some units ship at 38400).
    timeout_s : float
        Time allowed for each reply, seconds.

    Examples
    --------
    >>> with QuantumComposers9520("/dev/ttyUSB0") as gen:   # doctest: +SKIP
    ...     gen.program(plan_timing(rig, pulses=100))
    ...     gen.arm()
    ...     record()
    """

    #: Most periods of one burst (``:PULSE0:BCO``); a plan of more pulses is answered ``?5``.
    MAX_BURST = 1_000_000

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 0.5) -> None:
        self._link = SerialLink(port, baud, timeout_s, eol=b"\r\n")
        self._idn = ""
        self._n_channels = 0
        self._plan: TimingPlan | None = None
        self._armed = False

    # --- life cycle ----------------------------------------------------------------------
    @property
    def port(self) -> str:
        return self._link.port

    @property
    def armed(self) -> bool:
        """True between :meth:`arm` and :meth:`disarm` (or the failure that disarmed it)."""
        return self._armed

    @property
    def n_channels(self) -> int:
        """Number of output channels (not counting T0), known after :meth:`open`."""
        return self._n_channels

    @property
    def plan(self) -> TimingPlan | None:
        """The plan last programmed."""
        return self._plan

    def open(self) -> None:
        """Open the port, check the identification and stop T0 with every output disabled.

        Raises
        ------
        DeviceError
            The port cannot be opened, or ``*IDN?`` gets no answer or one that is not a
            Quantum Composers / BNC identification.
        """
        if self._link.is_open:
            return
        try:
            self._link.open()
        except LinkError as exc:
            raise DeviceError(f"pulse generator on {self.port}: {exc}; check the port name and that no "
                              "other program holds it") from None
        try:
            idn = self._link.query("*IDN?")
        except LinkError as exc:
            self._link.close()
            raise DeviceError(
                f"pulse generator on {self.port}: '*IDN?': {exc}; check the cable, that the generator is on, "
                f"its baud rate ({self._link.baud}) and that this is the generator's port (nothing else was sent)"
            ) from None
        fields = [f.strip() for f in idn.split(",")]
        if len(fields) < 2 or not all(fields[:2]) or idn.startswith("?"):
            self._link.close()
            raise DeviceError(
                f"pulse generator on {self.port}: '*IDN?' answered {idn!r}, not a Quantum Composers 9520 / "
                "BNC 575 identification; check that this is the generator's port"
            )
        self._idn = idn
        self._n_channels = self._count_channels(fields)
        try:
            self._stop_everything("open")
        except DeviceError:
            self._link.close()
            raise

    def close(self) -> None:
        """Disarm (best effort) and release the port; safe in any state.

        Raises
        ------
        DeviceError
            Only when the generator was armed and did not confirm that it stopped; the port
            is released all the same.
        """
        if not self._link.is_open:
            self._mark_disarmed()
            return
        was_armed = self._armed
        problem, comm_failed = self._shutdown()
        self._mark_disarmed()
        self._link.close()
        if was_armed and comm_failed:
            raise DeviceError(f"pulse generator on {self.port}: closing: {problem}; {_UNKNOWN}")

    def __enter__(self) -> QuantumComposers9520:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # --- the PulseGenerator protocol -----------------------------------------------------
    def identify(self) -> str:
        """The instrument's identification string (``*IDN?``)."""
        return self._ask("*IDN?")

    def program(self, plan: TimingPlan) -> None:
        """Load a timing plan with T0 stopped and every output disabled.

        Parameters
        ----------
        plan : TimingPlan
            Period, channel delays and widths, and the number of pairs (0: continuous; more:
            burst mode, the generator stops by itself after that many periods).

        Raises
        ------
        DeviceError
            A channel the instrument does not have, or any command not acknowledged with
            ``ok``; the outputs are disabled first.
        """
        self._require_open("program")
        if self._armed:
            self.disarm()
        else:
            self._stop_everything("program")
        for c in plan.channels:
            if not 1 <= c.channel <= self._n_channels:
                self._fail(f":PULSE{c.channel}", f"the plan puts '{c.role}' on channel {c.channel} but the "
                           f"generator has {self._n_channels}",
                           "correct pulse_generator.channels in the rig file")
            if c.polarity not in ("NORM", "INV"):
                self._fail(f":PULSE{c.channel}:POL", f"polarity {c.polarity!r} of '{c.role}' is not NORM or INV",
                           "fix the timing plan")
        if plan.period_s <= 0 or plan.pulses < 0:
            self._fail(":PULSE0:PER", f"period {plan.period_s} s / pulses {plan.pulses} impossible",
                       "build the plan with acquisition.timing.plan_timing")
        self._plan = None
        self._cmd(":PULSE0:TRIG:MODE DIS")  # T0 from the internal rate generator
        self._cmd(":PULSE0:GATE:MODE DIS")  # no external gate may hold the pulses back
        self._cmd(f":PULSE0:PER {plan.period_s:.9f}")
        if plan.pulses > 0:
            self._cmd(":PULSE0:MODE BURS")
            self._cmd(f":PULSE0:BCO {plan.pulses}")
        else:
            self._cmd(":PULSE0:MODE NORM")
        for c in plan.channels:
            n = c.channel
            self._cmd(f":PULSE{n}:SYNC T0")
            self._cmd(f":PULSE{n}:CMODE NORM")
            # each output driven by its own timer alone: a multiplexer set from the front panel
            # could otherwise put, say, the Q-switch timer on a camera's output
            self._cmd(f":PULSE{n}:MUX {1 << (n - 1)}")
            self._cmd(f":PULSE{n}:POL {c.polarity}")
            self._cmd(f":PULSE{n}:DELAY {c.delay_s:.11f}")
            self._cmd(f":PULSE{n}:WIDT {c.width_s:.11f}")
        self._plan = plan

    def arm(self) -> None:
        """Enable the planned outputs and start T0: the laser fires from now on.

        Raises
        ------
        DeviceError
            No plan programmed, or a command failed (the outputs are disabled first).
        """
        self._require_open("arm")
        if self._plan is None:
            raise DeviceError(f"pulse generator on {self.port}: arm() before a plan was programmed; "
                              "call program(plan) first")
        if self._armed:
            return
        for c in self._plan.channels:
            self._cmd(f":PULSE{c.channel}:STATE ON")
        # Registered (and marked armed) before T0 starts, so a signal arriving from here on
        # finds the generator and stops it.
        self._armed = True
        _register(self)
        self._cmd(":PULSE0:STATE ON")

    def disarm(self) -> None:
        """Stop T0 and disable every output.

        Never raises for a device that answers, even with an error code; the driver counts as
        disarmed afterwards in every case.

        Raises
        ------
        DeviceError
            The generator did not answer (or the port failed), so the outputs could not be
            confirmed off: the laser state is unknown.
        """
        if not self._link.is_open:
            self._mark_disarmed()
            return
        problem, comm_failed = self._shutdown()
        self._mark_disarmed()
        if comm_failed:
            raise DeviceError(f"pulse generator on {self.port}: disarm: {problem}; {_UNKNOWN}")
        if problem:
            log.warning("pulse generator on %s: disarm: %s", self.port, problem)

    def is_running(self) -> bool:
        """Whether T0 runs now (False after a burst has completed), from ``:PULSE0:STATE?``."""
        return self._ask(":PULSE0:STATE?").strip() in ("1", "ON")

    # --- internals -----------------------------------------------------------------------
    def _count_channels(self, idn_fields: list[str]) -> int:
        try:
            reply = self._link.query(":INST:CAT?")
        except LinkError:
            reply = ""
        names = [n.strip().upper() for n in reply.split(",")] if reply and not reply.startswith("?") else []
        if names and names[0] == "T0":
            return len(names) - 1
        # Fall back on the model number: 9524 / 575-4 have 4 outputs, 9528 / 575-8 have 8.
        model = idn_fields[1] if len(idn_fields) > 1 else ""
        digits = re.findall(r"\d", model)
        return 4 if digits and digits[-1] == "4" else 8

    def _require_open(self, what: str) -> None:
        if not self._link.is_open:
            raise DeviceError(f"pulse generator on {self.port}: {what}() on a closed port; call open() first")

    def _mark_disarmed(self) -> None:
        self._armed = False
        _unregister(self)

    def _stop_everything(self, what: str) -> None:
        """Stop T0 and disable every output, raising (with the state) if that is not confirmed."""
        problem, comm_failed = self._shutdown()
        self._mark_disarmed()
        if problem:
            state = _UNKNOWN if comm_failed else "the outputs may not all be off"
            raise DeviceError(f"pulse generator on {self.port}: {what}: {problem}; {state}")

    def _shutdown(self) -> tuple[str, bool]:
        """Best effort: T0 off, then every output off. Never raises.

        Returns
        -------
        problem : str
            Empty when every command was acknowledged, else what went wrong.
        comm_failed : bool
            True when the instrument did not answer (or the port failed), so nothing is known.
        """
        cmds = [":PULSE0:STATE OFF"] + [f":PULSE{n}:STATE OFF" for n in range(1, max(self._n_channels, 1) + 1)]
        problems: list[str] = []
        comm_failed = False
        wait = True
        with self._link.lock:
            for cmd in cmds:
                try:
                    if not wait:
                        # The instrument stopped answering: send the rest anyway, without
                        # waiting a timeout for each, in case it still listens.
                        self._link.write_line(cmd)
                        continue
                    reply = self._link.query(cmd)
                    if reply.strip() == "?3" and cmd != cmds[0]:
                        continue  # no such channel on this model
                    if reply.strip().lower() != "ok":
                        problems.append(f"{cmd!r} answered {_describe(reply)}")
                except LinkClosed as exc:
                    problems.append(f"{cmd!r}: {exc}")
                    comm_failed = True
                    break
                except LinkError as exc:
                    problems.append(f"{cmd!r}: {exc}")
                    comm_failed = True
                    wait = False
                except Exception as exc:  # the shutdown path must not raise
                    problems.append(f"{cmd!r}: {exc!r}")
                    comm_failed = True
                    break
        return "; ".join(problems[:2]) + (f" (+{len(problems) - 2} more)" if len(problems) > 2 else ""), comm_failed

    def _emergency_disarm(self) -> None:
        """Disarm from atexit or a signal handler: never raises, logs what it could not do."""
        try:
            problem, comm_failed = self._shutdown()
            self._mark_disarmed()
            if problem:
                log.error("pulse generator on %s: emergency disarm: %s%s", self.port, problem,
                          f"; {_UNKNOWN}" if comm_failed else "")
        except Exception:
            log.exception("pulse generator on %s: emergency disarm failed; %s", self.port, _UNKNOWN)

    def _fail(self, cmd: str, what: str, fix: str) -> NoReturn:
        """Disarm (best effort) and raise one DeviceError line with the resulting laser state."""
        problem, comm_failed = self._shutdown()
        self._mark_disarmed()
        state = (_UNKNOWN if comm_failed else
                 "outputs switched off" if not problem else f"outputs may not all be off ({problem})")
        raise DeviceError(f"pulse generator on {self.port}: {cmd!r}: {what}; {fix}; {state}")

    def _ask(self, cmd: str) -> str:
        """Send a query or command and return the reply; any failure disarms and raises."""
        self._require_open(cmd)
        try:
            reply = self._link.query(cmd)
        except LinkClosed as exc:
            self._fail(cmd, str(exc), "check the USB/serial cable and the generator's power")
        except LinkError as exc:
            self._fail(cmd, str(exc), f"check the cable, the generator's power and baud rate ({self._link.baud})")
        m = re.fullmatch(r"\?(\d+)", reply.strip())
        if m:
            code = int(m.group(1))
            meaning = ERROR_CODES.get(code, "unknown error code")
            self._fail(cmd, f"rejected with ?{code} ({meaning})", _FIX.get(code, "see the instrument manual"))
        return reply

    def _cmd(self, cmd: str) -> None:
        """Send a setting command and require ``ok``."""
        reply = self._ask(cmd)
        if reply.strip().lower() != "ok":
            self._fail(cmd, f"unexpected reply {reply!r} instead of 'ok'",
                       "check that this is a 9520-series or BNC 575 generator and nothing else shares the port")


def _describe(reply: str) -> str:
    m = re.fullmatch(r"\?(\d+)", reply.strip())
    if m:
        code = int(m.group(1))
        return f"?{code} ({ERROR_CODES.get(code, 'unknown error code')})"
    return repr(reply)


# --- registry of armed generators: disarmed at exit and on SIGTERM / SIGHUP -------------------
_ARMED: set[QuantumComposers9520] = set()
_REGISTRY_LOCK = threading.RLock()
_ATEXIT_DONE = False
_PREVIOUS: dict[int, Any] = {}
_SIGNALS = tuple(s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None)


#: Most double pulses one burst fires (the generator then stops by itself): a longer recording is
#: several runs.
MAX_BURST = QuantumComposers9520.MAX_BURST


def pulse_generator_for(port: str, config: PulseGeneratorConfig) -> PulseGenerator:
    """The pulse-generator driver for ``port`` with a rig's ``[pulse_generator]`` settings, not
    yet open: the one place callers learn which driver that is."""
    return QuantumComposers9520(port, baud=config.baud)


def disarm_all() -> None:
    """Disarm every armed generator of this process (best effort, never raises)."""
    with _REGISTRY_LOCK:
        armed = list(_ARMED)
    for gen in armed:
        gen._emergency_disarm()


def _register(gen: QuantumComposers9520) -> None:
    global _ATEXIT_DONE
    with _REGISTRY_LOCK:
        _ARMED.add(gen)
        if not _ATEXIT_DONE:
            atexit.register(disarm_all)
            _ATEXIT_DONE = True
        install_signal_handlers()


def _unregister(gen: QuantumComposers9520) -> None:
    with _REGISTRY_LOCK:
        _ARMED.discard(gen)


def install_signal_handlers() -> None:
    """Make SIGTERM and SIGHUP disarm every armed generator, then do what they did before.

    Only the main thread may set signal handlers, so a program that arms from another thread
    (the live monitor does) must call this from its main thread first; :meth:`arm` calls it too,
    which covers programs that arm from the main thread. A handler someone replaced ours with
    since is chained to in turn; a signal the process ignores (``nohup`` ignores SIGHUP) stays
    ignored. atexit covers a normal exit; nothing covers SIGKILL.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in _SIGNALS:
        with contextlib.suppress(ValueError, OSError):
            current = signal.getsignal(sig)
            if current == signal.SIG_IGN:
                continue  # ignored on purpose (``nohup``): the recording is meant to go on
            if current is not _on_signal:
                _PREVIOUS[sig] = current
                signal.signal(sig, _on_signal)


@contextlib.contextmanager
def signals_call(handler: Callable[[], None]) -> Iterator[None]:
    """Inside, SIGTERM and SIGHUP disarm every armed generator and then call ``handler()`` in
    the main thread (to end a recording as Ctrl-C does, say, by raising or closing a window)
    instead of ending the process.

    Enter it from the main thread (only there do signals arrive in Python).
    """
    install_signal_handlers()
    _HOOKS.append(handler)
    try:
        yield
    finally:
        _HOOKS.remove(handler)


_HOOKS: list[Callable[[], None]] = []


@contextlib.contextmanager
def signals_held(note: Callable[[], None] | None = None, grace_s: float = 5.0) -> Iterator[list[int]]:
    """Inside, Ctrl-C (SIGINT), SIGTERM and SIGHUP disarm every armed generator and are then
    held, for cleanup that must finish (disarming, closing a run and writing its state) once a
    first Ctrl-C has started it. The first signal held calls ``note()`` (to say "one moment");
    every signal in the first ``grace_s`` seconds is held (people press Ctrl-C several times),
    and one after that raises KeyboardInterrupt after all, for cleanup that hangs.

    Yields the list of signal numbers held. Outside the main thread, where no handler can be
    set, it holds nothing.
    """
    held: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    since = time.monotonic()

    def hold(signum: int) -> None:
        held.append(signum)
        if len(held) > 1 and time.monotonic() - since > grace_s:
            raise KeyboardInterrupt
        if len(held) == 1 and note is not None:
            note()

    def on_sigint(signum: int, frame: FrameType | None) -> None:
        if _disarm_in_handler():
            hold(signum)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        with signals_call(lambda: hold(signal.SIGTERM)):
            yield held
    finally:
        signal.signal(signal.SIGINT, previous)


_IN_HANDLER = False


def _disarm_in_handler() -> bool:
    """Disarm every generator from a signal handler; False (and nothing done) when this
    interrupts a handler already disarming: that one goes on undisturbed, instead of meeting the
    second handler's exception or serial exchange in the middle of its own."""
    global _IN_HANDLER
    if _IN_HANDLER:
        return False
    _IN_HANDLER = True
    try:
        disarm_all()
    finally:
        _IN_HANDLER = False
    return True


def _on_signal(signum: int, frame: FrameType | None) -> None:
    if not _disarm_in_handler():
        return
    if _HOOKS:
        _HOOKS[-1]()
        return
    previous = _PREVIOUS.get(signum)
    if callable(previous):
        previous(signum, frame)
    elif previous == signal.SIG_IGN:
        return
    else:  # default action (terminate): do what it would have done
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
