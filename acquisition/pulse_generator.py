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

Read-back. After loading a plan, :meth:`QuantumComposers9520.program` reads every setting
back: the instrument rounds each time to its resolution (:data:`PULSE_GENERATOR_MODELS`: 250 ps
on a 9520 or BNC 575, 1 ns on a 9500 Plus), and a read-back further from the plan than that
resolution (or any other setting that does not read back as sent) refuses the plan, so
:meth:`~QuantumComposers9520.arm` cannot fire it. :attr:`~QuantumComposers9520.programmed` is
the plan as the instrument holds it (rounded), which is what a run records.
:meth:`~QuantumComposers9520.verify` reads the state back during a run: a generator that was
power-cycled, reset or changed from its front panel is disarmed and reported.

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
- A port that fails (an unplugged USB adapter) is opened again for up to ``reconnect_s``; if
  the adapter comes back in that time, the outputs are switched off through it.
- A generator that echoes commands (serial echo switched on) is noticed: the echoes are
  skipped, the echo is switched off at :meth:`~QuantumComposers9520.open`, and one that starts
  echoing while armed is disarmed and reported.

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
import math
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any, NoReturn

from .protocols import DeviceError, TimingPlan
from .serial_link import LinkClosed, LinkError, SerialLink

if TYPE_CHECKING:
    from lfcore.rig import PulseGeneratorConfig

    from .protocols import PulseGenerator

__all__ = ["ERROR_CODES", "MAX_BURST", "PULSE_GENERATOR_MODELS", "PulseGeneratorModel", "QuantumComposers9520",
           "disarm_all", "install_signal_handlers", "pulse_generator_for", "signals_call", "signals_held"]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class PulseGeneratorModel:
    """What sets one model apart: maker, outputs and time resolutions.

    Attributes
    ----------
    maker
        First field of ``*IDN?`` ("QC" or "BNC").
    channels
        Outputs, not counting T0.
    resolution_s
        Resolution of channel delays and widths, seconds (read-backs show values rounded to it).
    period_resolution_s
        Resolution of the T0 period, seconds.
    """

    maker: str
    channels: int
    resolution_s: float
    period_resolution_s: float

    @property
    def decimals(self) -> int:
        """Decimal places of a delay or width in the instrument's replies (seconds)."""
        return 11 if self.resolution_s < 1e-9 else 9  # to 10 ps, or to 1 ns


#: Models by the second field of ``*IDN?``: the Quantum Composers 9520 series and the BNC 575
#: (250 ps delay and width resolution, 10 ns period resolution) and the older 9500 Plus series
#: (1 ns), which share the SCPI command set.
PULSE_GENERATOR_MODELS: dict[str, PulseGeneratorModel] = {
    "9524": PulseGeneratorModel("QC", 4, 250e-12, 10e-9),
    "9528": PulseGeneratorModel("QC", 8, 250e-12, 10e-9),
    "575-4": PulseGeneratorModel("BNC", 4, 250e-12, 10e-9),
    "575-8": PulseGeneratorModel("BNC", 8, 250e-12, 10e-9),
    "9514": PulseGeneratorModel("QC", 4, 1e-9, 10e-9),
    "9518": PulseGeneratorModel("QC", 8, 1e-9, 10e-9),
}

#: Meaning of the ``?n`` error replies (9500/9520 series, BNC 575 / 577 manuals; 8 and 9 on newer firmware).
ERROR_CODES = {
    1: "incorrect prefix (no colon or * to start the command)",
    2: "missing command keyword",
    3: "invalid command keyword",
    4: "missing parameter",
    5: "invalid parameter",
    6: "query only, the command needs a question mark",
    7: "invalid query, the command has no query form",
    8: "command unavailable in the current system state",
    9: "parameter out of bounds for the channel",
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
    9: "the value conflicts with another channel's settings; check the timing plan",
}

_CHANNEL_LETTERS = "ABCDEFGH"
_UNKNOWN = "laser state UNKNOWN: press STOP on the generator and check the laser interlock"


class QuantumComposers9520:
    """A Quantum Composers 9520-series (or BNC 575) pulse generator on a serial port.

    Parameters
    ----------
    port
        Serial device (``/dev/ttyUSB0``, ``COM3``) or pyserial URL.
    baud
        Baud rate; must match the instrument's interface setting (some units ship at 38400).
    timeout_s
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

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 0.5, *, reconnect_s: float = 1.0) -> None:
        self._link = SerialLink(port, baud, timeout_s, eol=b"\r\n")
        self._idn = ""
        self._n_channels = 0
        self._model = PULSE_GENERATOR_MODELS["9528"]
        self._plan: TimingPlan | None = None
        self._programmed: TimingPlan | None = None
        self._armed = False
        self._reconnected = False
        self.reconnect_s = reconnect_s

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

    @property
    def model(self) -> PulseGeneratorModel:
        """The model found at :meth:`open` (its resolutions)."""
        return self._model

    @property
    def programmed(self) -> TimingPlan | None:
        """The plan as the instrument holds it: every time as read back (rounded to the
        instrument's resolution); None until :meth:`program` succeeded. This is the timing a
        run records."""
        return self._programmed

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
            idn = self._link.query("*IDN?", skip_echo=True)
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
        model = PULSE_GENERATOR_MODELS.get(fields[1].upper())
        if model is None:
            log.warning("pulse generator on %s: model %r is not in lfpiv's table; assuming 250 ps resolution",
                        self.port, fields[1])
            model = PULSE_GENERATOR_MODELS["9528"]
        self._model = model
        self._n_channels = self._count_channels(fields)
        try:
            if self._link.echo_seen:
                # serial echo switched on (front panel): off, so every reply is the answer
                log.warning("pulse generator on %s: serial echo was on; switching it off", self.port)
                self._link.query(":SYST:COMM:SER:ECHO OFF", skip_echo=True)
                self._link.echo_seen = False
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
        plan
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
        self._plan = self._programmed = None
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
        self._programmed = self._read_back(plan)
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

    def verify(self) -> None:
        """Read the programmed settings and, when armed, the outputs back; call it during a run.

        Raises
        ------
        DeviceError
            A setting differs from what was programmed, or an armed generator's outputs are
            off or its T0 stopped before its burst was due to end: it was power-cycled, reset
            or changed from its front panel. The generator is disarmed first.
        """
        self._require_open("verify")
        if self._programmed is None:
            return
        self._read_back(self._programmed, during="verify")
        if not self._armed:
            return
        off = [c.channel for c in self._programmed.channels
               if self._ask(f":PULSE{c.channel}:STATE?").strip() not in ("1", "ON")]
        if off:
            self._fail(f":PULSE{off[0]}:STATE?", f"output {off[0]} is off although armed (the generator was "
                       "reset, power-cycled or stopped from its front panel)",
                       "check the generator and program the plan again")
        if self._programmed.pulses == 0 and not self.is_running():
            self._fail(":PULSE0:STATE?", "T0 stopped although armed in continuous mode (the generator was reset, "
                       "power-cycled or stopped from its front panel)",
                       "check the generator and program the plan again")

    def _read_back(self, plan: TimingPlan, during: str = "program") -> TimingPlan:
        """Query every setting of ``plan``; the plan with the times as read back.

        Any read-back that differs from the plan (a time by more than the instrument's
        resolution) disarms and raises DeviceError.
        """
        res, per_res = self._model.resolution_s, self._model.period_resolution_s
        period = self._read_time(":PULSE0:PER?", plan.period_s, per_res, during)
        expect = {":PULSE0:TRIG:MODE?": "DIS", ":PULSE0:GATE:MODE?": "DIS",
                  ":PULSE0:MODE?": "BURS" if plan.pulses > 0 else "NORM"}
        if plan.pulses > 0:
            expect[":PULSE0:BCO?"] = str(plan.pulses)
        channels = []
        for c in plan.channels:
            n = c.channel
            expect.update({f":PULSE{n}:SYNC?": "T0", f":PULSE{n}:CMODE?": "NORM", f":PULSE{n}:MUX?": str(1 << (n - 1)),
                           f":PULSE{n}:POL?": c.polarity})
            delay = self._read_time(f":PULSE{n}:DELAY?", c.delay_s, res, during)
            width = self._read_time(f":PULSE{n}:WIDT?", c.width_s, res, during)
            channels.append(replace(c, delay_s=delay, width_s=width))
        for cmd, want in expect.items():
            got = self._ask(cmd).strip()
            if got.upper() != want.upper():
                self._fail(cmd, f"reads back {got!r}, programmed {want!r} ({self._changed(during)})",
                           "check that nothing else (front panel, another program) changes the generator")
        return replace(plan, period_s=period, channels=tuple(channels))

    def _read_time(self, cmd: str, planned: float, resolution: float, during: str) -> float:
        reply = self._ask(cmd)
        try:
            value = float(reply)
        except ValueError:
            self._fail(cmd, f"unexpected reply {reply!r} instead of a time", "check that this is a 9520-series or BNC "
                       "575 generator and nothing else shares the port")
        if not math.isfinite(value) or abs(value - planned) > resolution * (1 + 1e-6):
            self._fail(cmd, f"reads back {value:.12g} s, planned {planned:.12g} s, more than the instrument's "
                       f"{resolution * 1e12:g} ps resolution apart ({self._changed(during)})",
                       "check the timing plan against the generator's ranges, and that nothing else changes it")
        return value

    @staticmethod
    def _changed(during: str) -> str:
        return ("refused before arming" if during == "program"
                else "changed since programming: power cycle, reset or front panel")

    # --- internals -----------------------------------------------------------------------
    def _count_channels(self, idn_fields: list[str]) -> int:
        try:
            reply = self._link.query(":INST:CAT?", skip_echo=True)
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

        When the port has failed (an unplugged USB adapter), it is opened again for up to
        ``reconnect_s`` seconds and, if it came back, the outputs are switched off through it.

        Returns
        -------
        problem : str
            Empty when every command was acknowledged, else what went wrong.
        comm_failed : bool
            True when the instrument did not answer (or the port failed), so nothing is known.
        """
        self._reconnected = False
        problem, comm_failed, port_lost = self._shutdown_commands()
        if port_lost and self.reconnect_s > 0 and self._link.reopen(self.reconnect_s):
            again, failed_again, _ = self._shutdown_commands()
            if not failed_again:
                self._reconnected = True  # the adapter came back: switched off through it
                return again, False
        return problem, comm_failed

    def _shutdown_commands(self) -> tuple[str, bool, bool]:
        """Send the shutdown once: (problem, comm_failed, port_lost). Never raises."""
        cmds = [":PULSE0:STATE OFF"] + [f":PULSE{n}:STATE OFF" for n in range(1, max(self._n_channels, 1) + 1)]
        problems: list[str] = []
        comm_failed = port_lost = False
        wait = True
        with self._link.lock:
            for cmd in cmds:
                try:
                    if not wait:
                        # The instrument stopped answering: send the rest anyway, without
                        # waiting a timeout for each, in case it still listens.
                        self._link.write_line(cmd)
                        continue
                    reply = self._link.query(cmd, skip_echo=True)
                    if reply.strip() == "?3" and cmd != cmds[0]:
                        continue  # no such channel on this model
                    if reply.strip().lower() != "ok":
                        problems.append(f"{cmd!r} answered {_describe(reply)}")
                except LinkClosed as exc:
                    problems.append(f"{cmd!r}: {exc}")
                    comm_failed = port_lost = True
                    break
                except LinkError as exc:
                    problems.append(f"{cmd!r}: {exc}")
                    comm_failed = True
                    wait = False
                except Exception as exc:  # the shutdown path must not raise
                    problems.append(f"{cmd!r}: {exc!r}")
                    comm_failed = True
                    break
        problem = "; ".join(problems[:2]) + (f" (+{len(problems) - 2} more)" if len(problems) > 2 else "")
        return problem, comm_failed, port_lost

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
        if self._reconnected and not comm_failed:
            state = f"the port came back and {state}"
        raise DeviceError(f"pulse generator on {self.port}: {cmd!r}: {what}; {fix}; {state}")

    def _ask(self, cmd: str) -> str:
        """Send a query or command and return the reply; any failure disarms and raises."""
        self._require_open(cmd)
        try:
            reply = self._link.query(cmd, skip_echo=True)
        except LinkClosed as exc:
            self._fail(cmd, str(exc), "check the USB/serial cable and the generator's power")
        except LinkError as exc:
            self._fail(cmd, str(exc), f"check the cable, the generator's power and baud rate ({self._link.baud})")
        if self._link.echo_seen:
            # someone switched the serial echo on (front panel): the generator is not in the
            # state this program set up
            self._link.echo_seen = False
            self._fail(cmd, "the generator started echoing every command (serial echo switched on from its "
                       "front panel?)", "switch its serial echo off (:SYST:COMM:SER:ECHO OFF) and check its settings")
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
