"""Emulators of the serial instruments on real pseudo-terminals, built from the vendors' manuals.

Each emulator opens a pseudo-terminal pair (``os.openpty``), serves the master end on a daemon
thread and exposes a stable path as :attr:`port` (a symbolic link to the slave end, as
``/dev/serial/by-id/...`` is to ``/dev/ttyUSB0``); the real drivers of ``acquisition`` open that
path with pyserial exactly as they open a USB adapter in the lab, so the driver code under test
is the code that runs in the lab. An unplugged and re-plugged adapter is a new pseudo-terminal
behind the same path.

- :class:`PulseGeneratorEmulator`: a Quantum Composers 9520 (9524 / 9528) or BNC 575 (575-4 /
  575-8) pulse generator, its SCPI command set as the manuals give it (:data:`QC_COMMANDS`):
  system and channel modes NORM / SING / BURS / DCYC with their counters, trigger and gate
  inputs, clocks, outputs, multiplexer, stored settings, ``?1`` to ``?9`` errors, and every
  time quantised to the model's resolution (:data:`PULSE_GENERATOR_MODELS`). While T0 runs it
  ticks on a thread at the programmed period and calls its listeners, which is how simulated
  cameras learn that they were triggered and which laser cavities fired.
- :class:`StageEmulator`: a chain of Zaber devices on the ASCII protocol
  (:data:`ZABER_COMMANDS`): message ids, checksums, info (``#``) and alert (``!``) messages,
  replies split into packets, device and axis addressing, broadcast and ``renumber``, the
  settings drivers and the official library read, moves with acceleration (``stop``
  decelerates), travel limits, a home sensor and the real warning flags.

Faults for tests (:meth:`inject`, :meth:`clear_faults`), common to both:

``"no_reply"``   commands are carried out but nothing is answered (broken receive line);
``"garbled"``    commands are carried out, replies come back as noise;
``"split"``      every reply is written in two pieces ``gap_s`` (0.02 s) apart, as a USB
                 adapter delivers a line across two reads;
``"stray"``      the next ``count=n`` (1) replies are preceded by one stray byte ``byte``
                 (0xFE): line noise, or a device that glitched while sending;
``"echo"``       every received byte is echoed back before the reply (a terminal setting, or
                 the generator's own serial echo switched on from its front panel);
``"reset"``      the device power-cycles on receiving the next command (which is lost):
                 motion and position lost, settings back to their power-up values, T0 stopped;
``"disconnect"`` the USB adapter is unplugged: the master end is closed; the instrument keeps
                 its state, so an emulated generator whose T0 was running keeps firing;
``"reconnect"``  as ``"disconnect"``, then the adapter comes back ``down_s`` (0.2 s) later as a
                 new pseudo-terminal behind the same :attr:`port` path (also :meth:`reconnect`).

and per instrument (see each class). ``after=n`` delays a fault until ``n`` more commands have
been served normally.

Example
-------
>>> with PulseGeneratorEmulator(latency_s=0) as emu:          # doctest: +SKIP
...     emu.add_listener(lambda tick, t0_ns, outputs: print(tick, outputs))
...     with QuantumComposers9520(emu.port) as gen:
...         gen.program(plan); gen.arm()
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import random
import re
import select
import shutil
import tempfile
import threading
import time
import tty
from collections.abc import Callable

from acquisition.stage import ZABER_PRODUCTS, ZaberProduct, checksum

__all__ = ["QC_COMMANDS", "ZABER_COMMANDS", "ChannelState", "PulseGeneratorEmulator", "StageEmulator", "TickListener",
           "ZaberAxis", "ZaberDevice"]

log = logging.getLogger(__name__)

#: ``callback(tick, t0_ns, outputs)``: ``tick`` counts T0 periods from 0 since T0 was started,
#: ``t0_ns`` is the host wall-clock time (``time.time_ns`` scale) of that T0 edge, ``outputs``
#: maps each channel that fired on this tick to its delay after T0 in seconds.
TickListener = Callable[[int, int, dict[int, float]], None]


class _PtyEmulator:
    """An instrument served on the master end of a pseudo-terminal, one line per command."""

    FAULTS: frozenset[str] = frozenset({"no_reply", "garbled", "disconnect", "reconnect", "split", "stray", "echo",
                                        "reset"})
    name = "instrument"

    def __init__(self, latency_s: float = 0.002) -> None:
        #: Time between receiving a command and answering it, seconds.
        self.latency_s = latency_s
        #: Every command line received, in order (for tests).
        self.commands: list[str] = []
        self._lock = threading.RLock()
        self._faults: dict[str, int] = {}
        self._fault_args: dict[str, dict] = {}
        self._dir = tempfile.mkdtemp(prefix="lfpiv-emu-")
        #: Stable path of the port, to be opened by the driver (a link to the current slave end).
        self.port = os.path.join(self._dir, "ttyUSB0")
        self._master = self._slave = -1
        self._plug_in()
        self._stop = threading.Event()
        self._disconnected = False
        self._reconnect_at: float | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._serve, name=f"{self.name} emulator", daemon=True)
        self._thread.start()

    # --- life cycle ----------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop serving and close both ends; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_master()
        with contextlib.suppress(OSError):
            os.close(self._slave)
        shutil.rmtree(self._dir, ignore_errors=True)

    @property
    def connected(self) -> bool:
        """False while unplugged (``"disconnect"``, ``"reconnect"``) and after :meth:`close`."""
        return not self._disconnected and not self._closed

    def _plug_in(self) -> None:
        """A new pseudo-terminal behind :attr:`port` (the adapter plugged in)."""
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: bytes pass through untouched
        link = self.port + ".new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(link)
        os.symlink(os.ttyname(slave), link)
        os.replace(link, self.port)
        old_slave = self._slave
        with self._lock:
            self._master, self._slave = master, slave
        if old_slave >= 0:
            with contextlib.suppress(OSError):
                os.close(old_slave)

    def disconnect(self) -> None:
        """Unplug the USB adapter now (the instrument keeps running); its device node vanishes."""
        self._disconnected = True
        self._close_master()
        with self._lock:
            slave, self._slave = self._slave, -1
        with contextlib.suppress(OSError):
            os.unlink(self.port)
        if slave >= 0:
            with contextlib.suppress(OSError):
                os.close(slave)

    def reconnect(self) -> None:
        """Plug the adapter back in: a new pseudo-terminal behind the same :attr:`port`."""
        with self._lock:
            if self._closed or not self._disconnected:
                return
            self._reconnect_at = None
            self._plug_in()
            self._disconnected = False

    def power_cycle(self) -> None:
        """Switch the instrument off and on again now (see the ``"reset"`` fault)."""
        with self._lock:
            self._power_cycle()

    def _power_cycle(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # --- faults --------------------------------------------------------------------------
    def inject(self, fault: str, *, after: int = 0, **options: object) -> None:
        """Make the emulator misbehave.

        Parameters
        ----------
        fault
            One of :attr:`FAULTS` (see the module docstring).
        after
            Serve this many more commands normally before the fault starts.
        **options
            The fault's options (``code=``, ``count=``, ``gap_s=``, ``byte=``, ``down_s=``, ...).
        """
        if fault not in self.FAULTS:
            raise ValueError(f"unknown fault {fault!r}; choose from {sorted(self.FAULTS)}")
        with self._lock:
            self._faults[fault] = after
            self._fault_args[fault] = dict(options)

    def clear_faults(self) -> None:
        """Back to normal behaviour (an unplugged adapter stays unplugged: :meth:`reconnect`)."""
        with self._lock:
            self._faults.clear()
            self._fault_args.clear()

    def _take_faults(self) -> set[str]:
        """Faults active for the command being served; counts down delayed ones."""
        with self._lock:
            active = {f for f, n in self._faults.items() if n <= 0}
            for f, n in self._faults.items():
                if n > 0:
                    self._faults[f] = n - 1
            return active

    def _consume_fault(self, fault: str) -> dict:
        """Remove a one-shot fault and return its options."""
        with self._lock:
            self._faults.pop(fault, None)
            return self._fault_args.pop(fault, {})

    def _count_down(self, fault: str) -> dict:
        """Use one of the ``count=n`` occurrences of a fault (removed after the last); its options."""
        with self._lock:
            args = dict(self._fault_args.get(fault, {}))
            left = int(args.get("count", 1)) - 1
            if left <= 0:
                self._consume_fault(fault)
            else:
                self._fault_args[fault]["count"] = left
            return args

    # --- serving -------------------------------------------------------------------------
    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            if self._disconnected:
                at = self._reconnect_at
                if at is not None and time.monotonic() >= at:
                    self.reconnect()
                    buf = b""
                else:
                    self._stop.wait(0.01)
                self._idle()
                continue
            try:
                ready, _, _ = select.select([self._master], [], [], 0.01)
                data = os.read(self._master, 4096) if ready else b""
            except (OSError, ValueError):
                if not self._disconnected and not self._stop.is_set():
                    self._disconnected = True  # master closed under us
                continue
            self._idle()
            if not data:
                continue
            buf += data
            while b"\n" in buf or b"\r" in buf:
                cut = min(i for i in (buf.find(b"\n"), buf.find(b"\r")) if i >= 0)
                raw, buf = buf[:cut], buf[cut + 1:]
                if not raw.strip():
                    continue  # the other half of CR LF, or an empty line
                self._serve_line(raw)
                if self._disconnected:
                    buf = b""
                    break

    def _idle(self) -> None:
        """Called every few milliseconds on the serving thread (spontaneous messages)."""

    def _echoing(self) -> bool:
        """Whether the instrument itself echoes what it receives (a setting of its own)."""
        return False

    def _serve_line(self, raw: bytes) -> None:
        faults = self._take_faults()
        line = raw.decode("ascii", errors="replace").strip()
        with self._lock:
            self.commands.append(line)
        if "disconnect" in faults or "reconnect" in faults:
            args = self._consume_fault("reconnect") if "reconnect" in faults else {}
            self._consume_fault("disconnect")
            if "reconnect" in faults:
                self._reconnect_at = time.monotonic() + float(args.get("down_s", 0.2))
            self.disconnect()
            return
        if "echo" in faults or self._echoing():
            self._write(raw + b"\r\n")
        if "reset" in faults:
            self._consume_fault("reset")
            self.power_cycle()
            return  # the command was lost with the power
        replies = self._respond(line, faults)
        if replies is None or "no_reply" in faults:
            return
        if isinstance(replies, str):
            replies = [replies]
        if self.latency_s > 0:
            time.sleep(self.latency_s)
        for reply in replies:
            self._send(reply, faults)

    def _send(self, reply: str, faults: set[str]) -> None:
        """Write one message with its terminator, as the faults in force deform it."""
        data = (reply + "\r\n").encode("ascii")
        if "garbled" in faults:
            data = bytes(random.randrange(128, 256) for _ in range(len(data) - 2)) + b"\r\n"
        if "stray" in faults:
            data = bytes(self._count_down("stray").get("byte", b"\xfe"))[:1] + data
            faults.discard("stray")
        if "split" in faults:
            gap = float(self._fault_args.get("split", {}).get("gap_s", 0.02))
            half = max(1, len(data) // 2)
            self._write(data[:half])
            time.sleep(gap)
            data = data[half:]
        self._write(data)

    def _write(self, data: bytes) -> None:
        with self._lock:
            fd = self._master
        if fd < 0:
            return
        with contextlib.suppress(OSError):
            os.write(fd, data)

    def _close_master(self) -> None:
        with self._lock:
            fd, self._master = self._master, -1
        if fd >= 0:
            with contextlib.suppress(OSError):
                os.close(fd)

    def _respond(self, line: str, faults: set[str]) -> str | list[str] | None:  # pragma: no cover - abstract
        raise NotImplementedError


# ============================================================================================
# Pulse generator (Quantum Composers 9520 / BNC 575 SCPI)
# ============================================================================================

#: The SCPI command set as the emulator implements it, from the Quantum Composers 9500 Plus /
#: 9520 and BNC 575 / 577 manuals: ``(manual section, command, what it does)``. ``n`` is a
#: channel (0 = T0, 1 = A, ...). Every row is exercised by the tests, one test per row.
QC_COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("IEEE 488.2 common commands", "*IDN?", "identification: maker,model,serial,firmware"),
    ("IEEE 488.2 common commands", "*RST", "every setting to its default, T0 stopped"),
    ("IEEE 488.2 common commands", "*SAV 3", "store the settings in memory 1-12"),
    ("IEEE 488.2 common commands", "*RCL 3", "recall memory 1-12 (0: factory defaults)"),
    ("Instrument subsystem", ":INST:CAT?", "the channel list T0,CHA,CHB,..."),
    ("Instrument subsystem", ":INST:FULL?", "the channel list with numbers T0,0,CHA,1,..."),
    ("Instrument subsystem", ":INST:STAT OFF", "enable or disable every output at once"),
    ("Instrument subsystem", ":INST:NSEL 2", "select the implied channel by number"),
    ("Instrument subsystem", ":INST:SEL CHB", "select the implied channel by name"),
    ("System (T0) commands", ":PULSE0:STATE ON", "start / stop T0 (RUN / STOP)"),
    ("System (T0) commands", ":PULSE0:PER 0.001", "T0 period, 100 ns to 5000 s, quantised"),
    ("System (T0) commands", ":PULSE0:MODE BURS", "system mode NORMal, SINGle, BURSt, DCYCle"),
    ("System (T0) commands", ":PULSE0:BCO 10", "burst count, 1 to 1,000,000"),
    ("System (T0) commands", ":PULSE0:PCO 3", "duty cycle: periods on, 1 to 1,000,000"),
    ("System (T0) commands", ":PULSE0:OCO 2", "duty cycle: periods off, 1 to 1,000,000"),
    ("System (T0) commands", ":PULSE0:ICL EXT10", "clock source SYS or EXT10..EXT100 (MHz reference)"),
    ("System (T0) commands", ":PULSE0:OCL T0", "clock out: T0 or a 10-100 MHz reference"),
    ("System (T0) commands", ":PULSE0:TRIG:MOD TRIG", "trigger mode DISabled, TRIGgered, DUAL"),
    ("System (T0) commands", ":PULSE0:TRIG:EDGE FALL", "trigger edge RISing or FALLing"),
    ("System (T0) commands", ":PULSE0:TRIG:LEV 2.5", "trigger threshold, 0.2 to 15 V"),
    ("System (T0) commands", ":PULSE0:GATE:MOD PULS", "gate mode DISabled, PULSe inhibit, OUTPut inhibit, CHANnel"),
    ("System (T0) commands", ":PULSE0:GATE:LOG LOW", "gate logic LOW or HIGH active"),
    ("System (T0) commands", ":PULSE0:GATE:LEV 2.5", "gate threshold, 0.2 to 15 V"),
    ("System (T0) commands", ":PULSE0:COUN:STAT ON", "T0 pulse counter on / off"),
    ("System (T0) commands", ":PULSE0:COUN:COUN?", "T0 pulses counted since cleared (query only)"),
    ("System (T0) commands", ":PULSE0:COUN:CLE", "clear the T0 pulse counter (no query form)"),
    ("Channel commands", ":PULSE1:STATE ON", "enable / disable the output"),
    ("Channel commands", ":PULSE1:WIDT 0.00001", "pulse width, 10 ns to 999.99999999975 s, quantised"),
    ("Channel commands", ":PULSE1:DEL 0.0001", "delay after its sync source, +-999.99999999975 s, quantised"),
    ("Channel commands", ":PULSE1:SYNC CHB", "sync source T0 or another channel"),
    ("Channel commands", ":PULSE1:MUX 3", "the timers ORed onto this output, one bit each"),
    ("Channel commands", ":PULSE1:POL INV", "polarity NORMal, COMPlement, INVerted"),
    ("Channel commands", ":PULSE1:OUTP:MODE ADJ", "output TTL or ADJustable amplitude"),
    ("Channel commands", ":PULSE1:OUTP:AMPL 5.0", "adjustable amplitude, 2 to 20 V"),
    ("Channel commands", ":PULSE1:CMOD DCYC", "channel mode NORMal, SINGle, BURSt, DCYCle"),
    ("Channel commands", ":PULSE1:BCO 4", "channel burst count"),
    ("Channel commands", ":PULSE1:PCO 2", "channel duty cycle on count"),
    ("Channel commands", ":PULSE1:OCO 2", "channel duty cycle off count"),
    ("Channel commands", ":PULSE1:WCO 5", "wait count: T0 pulses skipped before the channel starts"),
    ("Channel commands", ":PULSE1:CGAT HIGH", "channel gate DISabled, LOW, HIGH"),
    ("Display subsystem", ":DISP:ENAB OFF", "front-panel display updates on / off"),
    ("System subsystem", ":SYST:COMM:SER:ECHO ON", "echo every received character"),
    ("System subsystem", ":SYST:KLOC ON", "lock the front-panel keys"),
    ("System subsystem", ":SYST:VERS?", "SCPI version (query only)"),
    ("System subsystem", ":SYST:SERN?", "serial number (query only)"),
    ("Error codes", ":PULSE1:FOO 1", "?1 prefix, ?2 keyword missing, ?3 invalid keyword, ?4 parameter missing, "
     "?5 invalid parameter, ?6 query only, ?7 no query form, ?8 unavailable now, ?9 out of bounds"),
)

_MODES = ("NORMal", "SINGle", "BURSt", "DCYCle")
_ON = {"ON": True, "1": True, "OFF": False, "0": False}
_LETTERS = "ABCDEFGH"


@dataclasses.dataclass
class ChannelState:
    """One output channel (and its timer) of the emulated pulse generator."""

    enabled: bool = False
    delay_s: float = 0.0
    width_s: float = 1e-5
    sync: str = "T0"
    polarity: str = "NORM"
    mode: str = "NORM"
    mux: int = 0  # the channel timers routed to this output, one bit each (timer A = 1)
    burst: int = 1
    on_count: int = 1
    off_count: int = 1
    wait: int = 0
    gate: str = "DIS"
    out_mode: str = "TTL"
    amplitude_v: float = 4.0


@dataclasses.dataclass
class _System:
    """The T0 timer and the instrument-wide settings."""

    period_s: float = 1e-3
    mode: str = "NORM"
    burst: int = 1
    on_count: int = 1
    off_count: int = 1
    clock_in: str = "SYS"
    clock_out: str = "T0"
    trigger_mode: str = "DIS"
    trigger_edge: str = "RIS"
    trigger_level_v: float = 2.5
    gate_mode: str = "DIS"
    gate_logic: str = "HIGH"
    gate_level_v: float = 2.5
    counter_on: bool = False
    display: bool = True
    echo: bool = False
    keylock: bool = False


class _ScpiError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _kw(word: str, spec: str) -> bool:
    """SCPI keyword match: ``spec`` like "STATe" accepts STAT and STATE, any case."""
    short = "".join(ch for ch in spec if ch.isupper() or ch.isdigit())
    return word.upper() in (short, spec.upper())


def _choice(value: str, specs: tuple[str, ...]) -> str:
    """Match an SCPI enumeration (specs like "BURSt"); return its short form."""
    for spec in specs:
        if _kw(value, spec):
            return "".join(ch for ch in spec if ch.isupper() or ch.isdigit())
    raise _ScpiError(5)


def _need(arg: str) -> str:
    if not arg:
        raise _ScpiError(4)
    return arg


def _number(arg: str, lo: float, hi: float) -> float:
    try:
        value = float(_need(arg))
    except ValueError:
        raise _ScpiError(5) from None
    if not math.isfinite(value) or not lo <= value <= hi:
        raise _ScpiError(5)
    return value


def _count(arg: str, lo: int, hi: int) -> int:
    value = _number(arg, lo, hi)
    if value != int(value):
        raise _ScpiError(5)
    return int(value)


def _flag(arg: str) -> bool:
    on = _ON.get(_need(arg).upper())
    if on is None:
        raise _ScpiError(5)
    return on


def _quantise(value: float, step: float) -> float:
    """``value`` rounded to the instrument's resolution ``step`` (read-backs show this)."""
    return round(round(value / step) * step, 13)


def _fires(tick: int, mode: str, burst: int, on: int, off: int) -> bool:
    """Whether a timer in ``mode`` fires on the ``tick``-th T0 pulse it sees (from 0)."""
    if mode == "SING":
        return tick == 0
    if mode == "BURS":
        return tick < burst
    if mode == "DCYC":
        return tick % (on + off) < on
    return True


class PulseGeneratorEmulator(_PtyEmulator):
    """An emulated Quantum Composers 9520-series or BNC 575 pulse generator on a pseudo-terminal.

    Parameters
    ----------
    channels
        Number of outputs; by default the model's (8 for a 9528, 4 for a 9524).
    latency_s
        Reply latency, seconds (0 for fast tests).
    model
        A key of :data:`~acquisition.pulse_generator.PULSE_GENERATOR_MODELS` ("9528", "9524",
        "575-8", "575-4", ...): its maker, channels and time resolutions.
    serial
        What ``*IDN?`` reports as the serial number.

    Attributes
    ----------
    port
        Path for the driver.
    ticks_fired
        T0 periods fired since the emulator was created.
    commands
        Every command line received.

    Besides the common faults: ``"error"`` the next command is refused with ``?code`` (5).
    A power cycle (``"reset"``) stops T0 and brings every setting back to its defaults (the
    stored memories survive). In ``TRIGgered`` mode T0 waits for :meth:`external_trigger`.
    """

    FAULTS = _PtyEmulator.FAULTS | {"error"}
    name = "pulse generator"

    def __init__(self, channels: int | None = None, latency_s: float = 0.002, *, model: str = "9528",
                 serial: str = "EMU0001") -> None:
        from acquisition.pulse_generator import PULSE_GENERATOR_MODELS

        if model not in PULSE_GENERATOR_MODELS:
            raise ValueError(f"unknown model {model!r}; choose from {sorted(PULSE_GENERATOR_MODELS)}")
        self.model = PULSE_GENERATOR_MODELS[model]
        self.n_channels = channels if channels is not None else self.model.channels
        self.idn = f"{self.model.maker},{model},{serial},3.0.0-emulator"
        self.serial = serial
        self._sys = _System()
        self._channels = self._default_channels()
        self._memories: dict[int, tuple[_System, dict[int, ChannelState]]] = {}
        self._implied = 1
        self.ticks_fired = 0
        self.counter = 0
        self._running = False
        self._run_stop: threading.Event | None = None
        self._ticker: threading.Thread | None = None
        self._stopped_ticker: threading.Thread | None = None  # joined once the lock is let go
        self._triggers = threading.Semaphore(0)
        self._listeners: list[TickListener] = []
        super().__init__(latency_s)

    def _default_channels(self) -> dict[int, ChannelState]:
        return {n: ChannelState(mux=1 << (n - 1)) for n in range(1, self.n_channels + 1)}

    # --- what the simulated world reads --------------------------------------------------
    @property
    def running(self) -> bool:
        """True while T0 runs (False after a burst or single shot completed, or STATE OFF)."""
        return self._running

    @property
    def period_s(self) -> float:
        return self._sys.period_s

    @property
    def mode(self) -> str:
        return self._sys.mode

    @property
    def burst_count(self) -> int:
        return self._sys.burst

    @property
    def trigger_mode(self) -> str:
        return self._sys.trigger_mode

    @property
    def gate_mode(self) -> str:
        return self._sys.gate_mode

    @property
    def echo(self) -> bool:
        """Whether the generator echoes what it receives (``:SYST:COMM:SER:ECHO``)."""
        return self._sys.echo

    def channel_state(self, n: int) -> ChannelState:
        """A copy of channel ``n``'s settings (1-based)."""
        with self._lock:
            return dataclasses.replace(self._channels[n])

    def enabled_channels(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(n for n, c in self._channels.items() if c.enabled)

    def outputs_enabled(self) -> bool:
        """Whether any output is enabled (with T0 running, that means the laser fires)."""
        return bool(self.enabled_channels())

    @property
    def firing(self) -> bool:
        """T0 running with at least one output enabled."""
        return self._running and self.outputs_enabled()

    def add_listener(self, callback: TickListener) -> None:
        """Call ``callback(tick, t0_ns, outputs)`` on the ticker thread at every T0 edge."""
        with self._lock:
            self._listeners.append(callback)

    def remove_listener(self, callback: TickListener) -> None:
        with self._lock:
            if callback in self._listeners:
                self._listeners.remove(callback)

    def external_trigger(self) -> None:
        """A pulse on the TRIGGER input (starts one T0 cycle in TRIGgered mode)."""
        self._triggers.release()

    def wait_stopped(self, timeout_s: float) -> bool:
        """Wait until T0 stops by itself (burst complete); True if it did."""
        deadline = time.monotonic() + timeout_s
        while self._running and time.monotonic() < deadline:
            time.sleep(0.002)
        return not self._running

    def close(self) -> None:
        self._set_running(False)
        self._join_stopped_ticker()
        super().close()

    def _power_cycle(self) -> None:
        self._set_running(False)
        self._join_stopped_ticker()
        with self._lock:
            self._sys = _System()
            self._channels = self._default_channels()
            self._implied = 1

    def _echoing(self) -> bool:
        return self._sys.echo

    # --- T0 ticker -----------------------------------------------------------------------
    def _set_running(self, on: bool) -> None:
        with self._lock:
            if on == self._running:
                return
            self._running = on
            if on:
                stop = threading.Event()
                self._run_stop = stop
                self._ticker = threading.Thread(target=self._tick_loop, args=(stop,), daemon=True,
                                                name="pulse generator T0")
                self._ticker.start()
                return
            stop, ticker = self._run_stop, self._ticker
            self._run_stop = self._ticker = None
        if stop is not None:
            stop.set()
        # Joined by the caller once it lets go of the lock: a command (STATE OFF, *RST) runs under
        # the lock, which the ticker may be waiting for; joining here would stall the reply.
        self._stopped_ticker = ticker

    def _join_stopped_ticker(self) -> None:
        """Wait for a stopped T0 ticker to end (its last tick delivered), outside the lock."""
        ticker, self._stopped_ticker = self._stopped_ticker, None
        if ticker is not None and ticker is not threading.current_thread():
            ticker.join(timeout=2.0)

    def _timer_delay(self, n: int, seen: tuple[int, ...] = ()) -> float:
        """Delay of timer ``n`` after T0, following its sync chain."""
        c = self._channels[n]
        if c.sync == "T0" or n in seen:
            return c.delay_s
        return c.delay_s + self._timer_delay(_LETTERS.index(c.sync[2]) + 1, (*seen, n))

    def _tick_loop(self, stop: threading.Event) -> None:
        # Absolute perf_counter schedule: tick k at start + k periods, no drift; a late tick is
        # fired at once (a real generator never skips a period).
        perf0 = time.perf_counter_ns()
        wall0 = time.time_ns()
        due = perf0
        k = 0  # T0 pulses produced by the rate generator
        fired = 0  # T0 pulses let through by the system mode
        while True:
            with self._lock:
                triggered = self._sys.trigger_mode == "TRIG"
            if triggered:
                while not self._triggers.acquire(timeout=0.01):
                    if stop.is_set():
                        return
                due = time.perf_counter_ns()
            else:
                wait = (due - time.perf_counter_ns()) / 1e9
                # a late tick fires at once, but after a pause that lets the serial thread have the
                # lock: catching up on a busy CPU must not starve the commands (STATE OFF among them)
                if stop.wait(wait if wait > 0 else 0.0002):
                    return
            with self._lock:
                if stop.is_set():
                    return
                s = self._sys
                t0_out = _fires(k, s.mode, s.burst, s.on_count, s.off_count)
                outputs: dict[int, float] = {}
                if t0_out and s.gate_mode == "DIS":
                    # each timer fires by its channel mode, counted over the T0 pulses it saw
                    # after its wait count; an output fires with the first timer its mux routes
                    timers = {m: self._timer_delay(m) for m, t in self._channels.items()
                              if fired >= t.wait and _fires(fired - t.wait, t.mode, t.burst, t.on_count, t.off_count)}
                    outputs = {n: min(timers[m] for m in timers if c.mux >> (m - 1) & 1)
                               for n, c in self._channels.items()
                               if c.enabled and c.gate == "DIS" and any(c.mux >> (m - 1) & 1 for m in timers)}
                listeners = list(self._listeners) if t0_out else []
                period = s.period_s
                done = (s.mode == "BURS" and k + 1 >= s.burst) or (s.mode == "SING" and k + 1 >= 1)
            t0_ns = wall0 + (due - perf0)
            for cb in listeners:
                try:
                    cb(fired, t0_ns, outputs)
                except Exception:
                    log.exception("pulse generator emulator: listener %r failed", cb)
            k += 1
            with self._lock:
                if t0_out:
                    fired += 1
                    self.ticks_fired += 1
                    if s.counter_on:
                        self.counter += 1
                if done:
                    if self._run_stop is stop:
                        self._running = False
                        self._run_stop = self._ticker = None
                    return
            due += max(1, round(period * 1e9))

    # --- SCPI ----------------------------------------------------------------------------
    def _respond(self, line: str, faults: set[str]) -> str | None:
        if "error" in faults:
            return f"?{int(self._consume_fault('error').get('code', 5))}"
        try:
            with self._lock:
                reply = self._execute(line)
        except _ScpiError as e:
            reply = f"?{e.code}"
        self._join_stopped_ticker()  # T0 switched off: its last tick delivered before the reply
        return reply

    def _execute(self, line: str) -> str:
        header, _, arg = line.strip().partition(" ")
        arg = arg.strip()
        query = header.endswith("?")
        header = header[:-1] if query else header
        if header.startswith("*"):
            return self._common(header.upper(), query, arg)
        if not header.startswith(":"):
            raise _ScpiError(1)
        words = header[1:].split(":")
        if not words or not words[0]:
            raise _ScpiError(2)
        if _kw(words[0], "INSTrument"):
            return self._instrument(words[1:], query, arg)
        if _kw(words[0], "DISPlay"):
            if len(words) == 2 and _kw(words[1], "ENABle"):
                return self._bool_setting(self._sys, "display", query, arg)
            raise _ScpiError(3)
        if _kw(words[0], "SYSTem"):
            return self._system(words[1:], query, arg)
        m = re.fullmatch(r"(PULSE|PULS)(\d*)", words[0].upper())
        if not m:
            raise _ScpiError(3)
        if len(words) < 2:
            raise _ScpiError(2)
        n = int(m.group(2)) if m.group(2) else self._implied
        if n == 0:
            return self._t0(words[1:], query, arg)
        if n not in self._channels:
            raise _ScpiError(3)
        self._implied = n  # the last channel referenced is the implied one
        return self._channel(n, words[1:], query, arg)

    def _common(self, header: str, query: bool, arg: str) -> str:
        if header == "*IDN":
            if not query:
                raise _ScpiError(6)
            return self.idn
        if query:
            if header in ("*RST", "*SAV", "*RCL"):
                raise _ScpiError(7)
            raise _ScpiError(3)
        if header == "*RST":
            self._power_cycle_settings()
            return "ok"
        if header == "*SAV":
            slot = _count(arg, 1, 12)
            self._memories[slot] = (dataclasses.replace(self._sys),
                                    {n: dataclasses.replace(c) for n, c in self._channels.items()})
            return "ok"
        if header == "*RCL":
            slot = _count(arg, 0, 12)
            if self._running:
                raise _ScpiError(8)  # not while T0 runs: stop first
            if slot == 0:
                self._power_cycle_settings()
            elif slot not in self._memories:
                raise _ScpiError(5)
            else:
                sys_, chans = self._memories[slot]
                self._sys = dataclasses.replace(sys_)
                self._channels = {n: dataclasses.replace(c) for n, c in chans.items()}
            return "ok"
        raise _ScpiError(3)

    def _power_cycle_settings(self) -> None:
        self._set_running(False)
        self._sys = _System(echo=self._sys.echo)
        self._channels = self._default_channels()
        self._implied = 1

    def _names(self) -> list[str]:
        return ["T0"] + [f"CH{_LETTERS[n - 1]}" for n in self._channels]

    def _instrument(self, words: list[str], query: bool, arg: str) -> str:
        if len(words) != 1:
            raise _ScpiError(3 if words else 2)
        key = words[0]
        if _kw(key, "CATalog") or _kw(key, "FULL"):
            if not query:
                raise _ScpiError(6)
            if _kw(key, "CATalog"):
                return ",".join(self._names())
            return ",".join(f"{name},{i}" for i, name in enumerate(self._names()))
        if _kw(key, "STATe"):
            if query:
                return "1" if any(c.enabled for c in self._channels.values()) else "0"
            on = _flag(arg)
            for c in self._channels.values():
                c.enabled = on
            return "ok"
        if _kw(key, "NSELect"):
            if query:
                return str(self._implied)
            self._implied = _count(arg, 1, len(self._channels))
            return "ok"
        if _kw(key, "SELect"):
            if query:
                return self._names()[self._implied]
            names = self._names()
            if _need(arg).upper() not in names[1:]:
                raise _ScpiError(5)
            self._implied = names.index(arg.upper())
            return "ok"
        raise _ScpiError(3)

    def _system(self, words: list[str], query: bool, arg: str) -> str:
        if len(words) == 3 and _kw(words[0], "COMMunicate") and _kw(words[1], "SERial") and _kw(words[2], "ECHo"):
            return self._bool_setting(self._sys, "echo", query, arg)
        if len(words) == 1 and _kw(words[0], "KLOCk"):
            return self._bool_setting(self._sys, "keylock", query, arg)
        if len(words) == 1 and (_kw(words[0], "VERSion") or _kw(words[0], "SERNumber")):
            if not query:
                raise _ScpiError(6)
            return "1999.0" if _kw(words[0], "VERSion") else self.serial
        raise _ScpiError(3)

    @staticmethod
    def _bool_setting(obj: object, attr: str, query: bool, arg: str) -> str:
        if query:
            return "1" if getattr(obj, attr) else "0"
        setattr(obj, attr, _flag(arg))
        return "ok"

    def _setting(self, obj: object, attr: str, query: bool, arg: str, kind: str, *limits: object) -> str:
        """Query or set one setting: ``kind`` "time" (quantised), "period", "count", "volts",
        "choice" (limits are the SCPI spellings) or "bool"."""
        value = getattr(obj, attr)
        if query:
            if kind == "time":
                return f"{value:.{self.model.decimals}f}"
            if kind == "period":
                return f"{value:.9f}"
            if kind == "volts":
                return f"{value:.2f}"
            if kind == "bool":
                return "1" if value else "0"
            return str(value)
        if kind == "time":
            lo, hi = limits
            new: object = _quantise(_number(arg, lo, hi), self.model.resolution_s)
        elif kind == "period":
            new = max(100e-9, _quantise(_number(arg, 100e-9, 5000.0), self.model.period_resolution_s))
        elif kind == "count":
            new = _count(arg, *limits)
        elif kind == "volts":
            new = round(_number(arg, *limits), 2)
        elif kind == "bool":
            new = _flag(arg)
        else:
            new = _choice(_need(arg), limits)
        setattr(obj, attr, new)
        return "ok"

    def _t0(self, words: list[str], query: bool, arg: str) -> str:
        s, key = self._sys, words[0]
        if len(words) == 2:
            sub = words[1]
            if _kw(key, "TRIGger"):
                if _kw(sub, "MODe"):
                    return self._setting(s, "trigger_mode", query, arg, "choice", "DISabled", "TRIGgered", "DUAL")
                if _kw(sub, "EDGe"):
                    return self._setting(s, "trigger_edge", query, arg, "choice", "RISing", "FALLing")
                if _kw(sub, "LEVel"):
                    return self._setting(s, "trigger_level_v", query, arg, "volts", 0.2, 15.0)
            if _kw(key, "GATe"):
                if _kw(sub, "MODe"):
                    return self._setting(s, "gate_mode", query, arg, "choice", "DISabled", "PULSe", "OUTPut",
                                         "CHANnel")
                if _kw(sub, "LOGic"):
                    return self._setting(s, "gate_logic", query, arg, "choice", "LOW", "HIGH")
                if _kw(sub, "LEVel"):
                    return self._setting(s, "gate_level_v", query, arg, "volts", 0.2, 15.0)
            if _kw(key, "COUNter"):
                if _kw(sub, "STATe"):
                    return self._setting(s, "counter_on", query, arg, "bool")
                if _kw(sub, "COUNts"):
                    if not query:
                        raise _ScpiError(6)
                    return str(self.counter)
                if _kw(sub, "CLEar"):
                    if query:
                        raise _ScpiError(7)
                    self.counter = 0
                    return "ok"
            raise _ScpiError(3)
        if len(words) != 1:
            raise _ScpiError(3)
        if _kw(key, "STATe"):
            if query:
                return "1" if self._running else "0"
            self._set_running(_flag(arg))
            return "ok"
        if _kw(key, "PERiod"):
            return self._setting(s, "period_s", query, arg, "period")
        if _kw(key, "MODe"):
            return self._setting(s, "mode", query, arg, "choice", *_MODES)
        if _kw(key, "BCOunter"):
            return self._setting(s, "burst", query, arg, "count", 1, 1_000_000)
        if _kw(key, "PCOunter"):
            return self._setting(s, "on_count", query, arg, "count", 1, 1_000_000)
        if _kw(key, "OCOunter"):
            return self._setting(s, "off_count", query, arg, "count", 1, 1_000_000)
        if _kw(key, "ICLock"):
            return self._setting(s, "clock_in", query, arg, "choice", "SYS", "EXT10", "EXT20", "EXT25", "EXT40",
                                 "EXT50", "EXT80", "EXT100")
        if _kw(key, "OCLock"):
            return self._setting(s, "clock_out", query, arg, "choice", "T0", "10", "20", "25", "40", "50", "80",
                                 "100")
        raise _ScpiError(3)

    def _channel(self, n: int, words: list[str], query: bool, arg: str) -> str:
        c, key = self._channels[n], words[0]
        if len(words) == 2 and _kw(key, "OUTPut"):
            if _kw(words[1], "MODe"):
                return self._setting(c, "out_mode", query, arg, "choice", "TTL", "ADJustable")
            if _kw(words[1], "AMPLitude"):
                return self._setting(c, "amplitude_v", query, arg, "volts", 2.0, 20.0)
            raise _ScpiError(3)
        if len(words) != 1:
            raise _ScpiError(3)
        if _kw(key, "STATe"):
            return self._setting(c, "enabled", query, arg, "bool")
        if _kw(key, "DELay"):
            return self._setting(c, "delay_s", query, arg, "time", -999.99999999975, 999.99999999975)
        if _kw(key, "WIDTh"):
            return self._setting(c, "width_s", query, arg, "time", 10e-9, 999.99999999975)
        if _kw(key, "SYNC"):
            if query:
                return c.sync
            names = ["T0"] + [f"CH{_LETTERS[i - 1]}" for i in self._channels]
            value = _need(arg).upper()
            if value not in names:
                raise _ScpiError(5)
            if value == f"CH{_LETTERS[n - 1]}" or self._sync_cycle(n, value):
                raise _ScpiError(9)  # a channel timed from itself, directly or through others
            c.sync = value
            return "ok"
        if _kw(key, "POLarity"):
            return self._setting(c, "polarity", query, arg, "choice", "NORMal", "COMPlement", "INVerted")
        if _kw(key, "CMODe"):
            return self._setting(c, "mode", query, arg, "choice", *_MODES)
        if _kw(key, "MUX"):
            return self._setting(c, "mux", query, arg, "count", 0, 2 ** len(self._channels) - 1)
        if _kw(key, "BCOunter"):
            return self._setting(c, "burst", query, arg, "count", 1, 1_000_000)
        if _kw(key, "PCOunter"):
            return self._setting(c, "on_count", query, arg, "count", 1, 1_000_000)
        if _kw(key, "OCOunter"):
            return self._setting(c, "off_count", query, arg, "count", 1, 1_000_000)
        if _kw(key, "WCOunter"):
            return self._setting(c, "wait", query, arg, "count", 0, 1_000_000)
        if _kw(key, "CGATe"):
            return self._setting(c, "gate", query, arg, "choice", "DISabled", "LOW", "HIGH")
        raise _ScpiError(3)

    def _sync_cycle(self, n: int, source: str) -> bool:
        seen = {n}
        while source != "T0":
            m = _LETTERS.index(source[2]) + 1
            if m in seen:
                return True
            seen.add(m)
            source = self._channels[m].sync
        return False

# ============================================================================================
# Stage (Zaber ASCII protocol)
# ============================================================================================

#: The Zaber ASCII protocol as the emulator speaks it: ``(section of the protocol manual,
#: example command, what the device does)``. The tests exercise every row (one test per row).
ZABER_COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("Message format: empty command", "/1 1", "status reply, data 0"),
    ("Message format: message id", "/1 1 42 get pos", "the reply carries the same id (0-99)"),
    ("Message format: checksum", "/1 1 get pos:XX", "verified; a wrong checksum is dropped unanswered"),
    ("Message format: broadcast", "/get deviceid", "every device on the chain replies, in address order"),
    ("Replies: packets", "/1 tools echo <long text>", "a reply longer than comm.packet.size.max ends in \\ "
     "and continues in #.. cont info messages"),
    ("Alerts", "/1 set comm.alert 1", "!dd a IDLE ff sent when an axis comes to rest"),
    ("Commands: home", "/1 1 home", "moves to the home sensor, zeroes pos, clears WR"),
    ("Commands: move abs", "/1 1 move abs 1000", "absolute move in microsteps; BADDATA outside the limits"),
    ("Commands: move rel", "/1 1 move rel -500", "relative move; BADDATA if it would leave the limits"),
    ("Commands: move vel", "/1 1 move vel 16384", "moves at a velocity until stopped or at a limit"),
    ("Commands: move min", "/1 1 move min", "moves to limit.min"),
    ("Commands: move max", "/1 1 move max", "moves to limit.max"),
    ("Commands: stop", "/1 1 stop", "decelerates at accel; BUSY until at rest; NI if a move was cut short"),
    ("Commands: estop", "/1 1 estop", "stops at once; NI"),
    ("Commands: warnings", "/1 1 warnings", "NN F1 F2 ... every active flag"),
    ("Commands: warnings clear", "/1 1 warnings clear", "lists the flags, then clears the latched ones"),
    ("Commands: get", "/1 1 get maxspeed", "the setting's value; axis 0: one value per axis"),
    ("Commands: set", "/1 1 set maxspeed 100000", "BADDATA out of range, BADCOMMAND read-only or unknown"),
    ("Commands: renumber", "/renumber", "devices numbered 1, 2, ... in chain order (or /1 renumber 5)"),
    ("Commands: system reset", "/1 system reset", "OK, then the device restarts (position lost, WR)"),
    ("Commands: system restore", "/1 system restore", "settings back to their defaults"),
    ("Commands: tools echo", "/1 tools echo hello", "replies with the text"),
    ("Rejections: BADCOMMAND", "/1 1 frobnicate", "unknown command or setting"),
    ("Rejections: BADAXIS", "/1 5 get pos", "no such axis"),
    ("Rejections: BADDATA", "/1 1 move abs -5", "value out of range or not a number"),
    ("Rejections: BADMESSAGEID", "/1 1 123 get pos", "a message id that is not 0-99"),
    ("Rejections: DEVICEONLY", "/1 1 get deviceid", "a device setting or command addressed to an axis"),
)

#: Zaber warning flags in order of precedence (the reply shows the highest active one).
_FLAG_ORDER = ("FD", "FQ", "FS", "FT", "FB", "FP", "FE", "WH", "WL", "WP", "WV", "WT", "WM", "WR",
               "NC", "NI", "ND", "NU", "NJ")
_CLEARABLE = {"FQ", "FS", "FT", "FB", "FP", "FE", "WL", "NI"}

#: Native units of the ASCII protocol: a velocity of ``v`` microsteps/s reads ``v * 1.6384``, an
#: acceleration of ``a`` microsteps/s^2 reads ``a * 1.6384 / 10000``.
_VEL_UNIT = 1.6384
_ACCEL_UNIT = 1.6384 / 10000


@dataclasses.dataclass
class ZaberAxis:
    """One axis of an emulated Zaber device. Positions are kept in micrometres from the home
    sensor (the TRUE carriage position); the device counts microsteps from where it was
    switched on, or from the home sensor once homed."""

    product: ZaberProduct
    peripheral_id: int = 0
    resolution: int = 64
    speed_mm_s: float = 20.0
    accel_mm_s2: float = 1000.0
    true_um: float = 0.0
    offset_um: float = 0.0
    v_um_s: float = 0.0
    target_um: float | None = None
    vel_um_s: float | None = None       # "move vel": the velocity to hold
    moving: bool = False
    stall: bool = False
    home: bool = False
    arrival_flags: tuple[str, ...] = ()
    flags: set[str] = dataclasses.field(default_factory=set)
    limit_min_um: float = 0.0
    limit_max_um: float = 0.0
    t_last: float = 0.0

    def __post_init__(self) -> None:
        if not self.limit_max_um:
            self.limit_max_um = self.product.travel_mm * 1000.0

    @property
    def microstep_um(self) -> float:
        return self.product.full_step_um / self.resolution

    def steps(self, um: float) -> int:
        return round(um / self.microstep_um)

    @property
    def pos(self) -> int:
        """The position counter, microsteps."""
        return self.steps(self.true_um - self.offset_um)


@dataclasses.dataclass
class ZaberDevice:
    """One device of the daisy chain: an integrated stage (one axis) or a controller."""

    address: int
    deviceid: int
    axes: list[ZaberAxis]
    serial: int = 1234
    version: str = "7.38"
    build: int = 17000
    alert: bool = False
    checksums: bool = False
    packet_size: int = 80
    access: int = 1


def _zaber_defaults(dev: ZaberDevice) -> None:
    """The settings a device powers up with after ``system restore``."""
    dev.alert, dev.checksums, dev.packet_size, dev.access = False, False, 80, 1
    for ax in dev.axes:
        ax.resolution = 64
        ax.limit_min_um, ax.limit_max_um = 0.0, ax.product.travel_mm * 1000.0


class _Rejected(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class StageEmulator(_PtyEmulator):
    """A chain of emulated Zaber devices on the ASCII protocol, on one pseudo-terminal.

    By default one integrated linear stage (one axis), the product whose native step at the
    default resolution (64) is ``microstep_um``. The emulator keeps the TRUE carriage position
    of each axis (what the simulated world sees) and the position counter each device reports;
    they differ by an unknown offset until the axis is homed, as on a stage just powered up.

    Commands may carry message ids and checksums (``/1 1 12 get pos:XX``); a checksum that does
    not match drops the line unanswered, like any line the device cannot read.

    Parameters
    ----------
    device
        Address of the (first) device on the daisy chain.
    axis
        The axis the simulated world and :attr:`position_mm` follow.
    microstep_um
        Native step at resolution 64 of the stage emulated (a product of
        :data:`~acquisition.stage.ZABER_PRODUCTS`).
    travel_mm
        Travel between the home sensor (0) and ``limit.max`` (default: the product's).
    speed_mm_s
        ``maxspeed`` of every axis, mm/s (settable later as :attr:`speed_mm_s`).
    accel_mm_s2
        ``accel`` of every axis, mm/s^2 (``stop`` decelerates at it).
    position_mm
        True carriage position at power-up.
    homed
        Start homed (no ``WR`` flag) instead of freshly powered up.
    latency_s
        Reply latency, seconds.
    checksums
        Append a checksum ``:XX`` to every reply (the device setting ``comm.checksum 1``).
    chain
        The whole chain instead (addresses, products, axes), for several devices on one port.

    Notes
    -----
    Faults (besides the common ones): ``"stall"`` the next move never progresses and the axis
    stays BUSY until stopped; ``"limit"`` the next move stops half way on a limit sensor, flag
    ``WL``; ``"slip"`` the next move ends IDLE 50 um away from its target; ``"flags"`` the next
    move or homing ends with the warning flags ``flags=(...)`` raised (the reply then shows only
    the first); ``"again"`` the next ``count=n`` commands (1) are refused with ``RJ ... AGAIN``
    without being carried out; ``"bad_checksum"`` the next ``count=n`` replies (1) are
    corrupted on the way back: one data character changes, the checksum of the original stays
    (the command itself is carried out).
    """

    FAULTS = _PtyEmulator.FAULTS | {"stall", "limit", "slip", "flags", "again", "bad_checksum"}
    name = "stage"

    def __init__(self, *, device: int = 1, axis: int = 1, microstep_um: float = 0.1, travel_mm: float | None = None,
                 speed_mm_s: float = 20.0, accel_mm_s2: float = 1000.0, position_mm: float = 12.5,
                 homed: bool = False, latency_s: float = 0.002, checksums: bool = False,
                 chain: list[ZaberDevice] | None = None) -> None:
        if chain is None:
            product_id = _product_for_microstep(microstep_um)
            product = ZABER_PRODUCTS[product_id]
            if travel_mm is not None:
                product = dataclasses.replace(product, travel_mm=travel_mm)
            axes = [ZaberAxis(product) for _ in range(max(1, axis))]
            chain = [ZaberDevice(address=device, deviceid=product_id, axes=axes)]
        self.chain = chain
        self.device = device
        self.axis = axis
        now = time.perf_counter()
        for dev in chain:
            dev.checksums = dev.checksums or checksums
            for ax in dev.axes:
                ax.speed_mm_s, ax.accel_mm_s2, ax.t_last = speed_mm_s, accel_mm_s2, now
                ax.true_um = position_mm * 1000.0
                ax.offset_um = 0.0 if homed else ax.true_um  # the counter reads 0 at power-up
                if not homed:
                    ax.flags.add("WR")
        self._alerts: list[str] = []
        super().__init__(latency_s)

    # --- what the simulated world reads --------------------------------------------------
    def _axis(self) -> ZaberAxis:
        dev = next((d for d in self.chain if d.address == self.device), self.chain[0])
        return dev.axes[self.axis - 1]

    @property
    def microstep_um(self) -> float:
        """Native step of the followed axis at its current resolution, micrometres."""
        return self._axis().microstep_um

    @property
    def limit_max(self) -> int:
        """``limit.max`` of the followed axis, microsteps."""
        return self._axis().steps(self._axis().limit_max_um)

    @property
    def checksums(self) -> bool:
        """Whether the devices append checksums to their replies (``comm.checksum``)."""
        return self.chain[0].checksums

    @checksums.setter
    def checksums(self, on: bool) -> None:
        with self._lock:
            for dev in self.chain:
                dev.checksums = bool(on)

    @property
    def speed_mm_s(self) -> float:
        """``maxspeed`` of the followed axis, mm/s (settable: moves started later use it)."""
        return self._axis().speed_mm_s

    @speed_mm_s.setter
    def speed_mm_s(self, value: float) -> None:
        with self._lock:
            self._axis().speed_mm_s = float(value)

    @property
    def position_mm(self) -> float:
        """True carriage position of the followed axis, millimetres from the home sensor."""
        with self._lock:
            self._update()
            return self._axis().true_um / 1000.0

    @property
    def homed(self) -> bool:
        with self._lock:
            self._update()
            return "WR" not in self._axis().flags

    @property
    def busy(self) -> bool:
        with self._lock:
            self._update()
            return self._axis().moving

    @property
    def flags(self) -> frozenset[str]:
        with self._lock:
            self._update()
            return frozenset(self._axis().flags)

    @property
    def alerts(self) -> list[str]:
        """Every alert message sent (for tests)."""
        with self._lock:
            return list(self._alerts)

    def set_flags(self, *flags: str) -> None:
        """Raise warning flags on the followed axis now (a standing condition, e.g. ``"FD"``).

        Raises
        ------
        ValueError
            A flag this emulator does not know.
        """
        unknown = set(flags) - set(_FLAG_ORDER)
        if unknown:
            raise ValueError(f"unknown flags {sorted(unknown)}; choose from {list(_FLAG_ORDER)}")
        with self._lock:
            self._update()
            self._axis().flags.update(flags)

    def _power_cycle(self) -> None:
        # Power lost: motion stops where it is, the counter restarts at 0 with no reference
        # position (WR) and an interrupted move leaves NI. Settings live in non-volatile memory
        # and survive (``system restore`` resets them).
        self._update()
        for dev in self.chain:
            for ax in dev.axes:
                if ax.moving:
                    ax.flags.add("NI")
                ax.moving, ax.v_um_s, ax.target_um, ax.vel_um_s, ax.stall = False, 0.0, None, None, False
                ax.flags -= {"WL", "FS"}
                ax.flags.add("WR")
                ax.offset_um = ax.true_um

    # --- motion model --------------------------------------------------------------------
    def _update(self) -> None:
        now = time.perf_counter()
        for dev in self.chain:
            for number, ax in enumerate(dev.axes, start=1):
                was = ax.moving
                _advance(ax, now)
                if was and not ax.moving and dev.alert:
                    self._alert(dev, number)

    def _idle(self) -> None:
        with self._lock:
            self._update()

    def _alert(self, dev: ZaberDevice, axis: int) -> None:
        ax = dev.axes[axis - 1]
        warn = next((f for f in _FLAG_ORDER if f in ax.flags), "--")
        body = f"{dev.address:02d} {axis} {'BUSY' if ax.moving else 'IDLE'} {warn}"
        message = f"!{body}:{checksum(body)}" if dev.checksums else f"!{body}"
        self._alerts.append(message)
        self._write((message + "\r\n").encode("ascii"))

    def _start(self, ax: ZaberAxis, target_um: float | None, faults: set[str], *, home: bool = False,
               vel_um_s: float | None = None) -> None:
        if ax.moving:
            ax.flags.add("NI")  # a movement interrupted by another
        else:
            ax.flags.discard("NI")
        ax.target_um, ax.vel_um_s, ax.home, ax.stall, ax.arrival_flags = target_um, vel_um_s, home, False, ()
        ax.moving = True
        ax.t_last = time.perf_counter()
        if "stall" in faults:
            self._consume_fault("stall")
            ax.stall = True
        elif "limit" in faults and not home and target_um is not None:
            self._consume_fault("limit")
            ax.target_um = ax.true_um + (target_um - ax.true_um) / 2
            ax.arrival_flags = ("WL",)
        elif "slip" in faults and not home and target_um is not None:
            self._consume_fault("slip")
            ax.target_um = target_um + 50.0
        if "flags" in faults:
            flags = tuple(self._consume_fault("flags").get("flags", ()))
            unknown = set(flags) - set(_FLAG_ORDER)
            if unknown:
                log.error("stage emulator: unknown flags %s ignored", sorted(unknown))
            ax.arrival_flags += tuple(f for f in flags if f in _FLAG_ORDER)

    # --- ASCII protocol ------------------------------------------------------------------
    def _respond(self, line: str, faults: set[str]) -> list[str] | None:
        if not line.startswith("/"):
            return None  # not a command: Zaber devices ignore it
        m = re.fullmatch(r"/(.*):([0-9A-Fa-f]{2})", line)
        if m is not None:
            if checksum(m.group(1)) != m.group(2).upper():
                return None  # corrupted on the way in: dropped
            line = "/" + m.group(1)
        words = line[1:].split()
        dev_no = axis = 0
        msg_id: int | None = None
        if words and words[0].isdigit():
            dev_no = int(words.pop(0))
            if words and words[0].isdigit():
                axis = int(words.pop(0))
                if words and (words[0].isdigit() or words[0] == "--"):
                    token = words.pop(0)
                    if token != "--":
                        msg_id = int(token) if len(token) <= 2 else -1
        replies: list[str] = []
        with self._lock:
            self._update()
            targets = [d for d in self.chain if dev_no in (0, d.address)]
            if words[:1] == ["renumber"] and not dev_no:
                targets = list(self.chain)  # renumbered in chain order, each replies from its new address
            for dev in targets:
                replies += self._device_reply(dev, axis, msg_id, words, faults, broadcast=dev_no == 0)
            if "again" in faults and targets:
                self._count_down("again")
        return replies or None

    def _device_reply(self, dev: ZaberDevice, axis: int, msg_id: int | None, words: list[str], faults: set[str],
                      *, broadcast: bool) -> list[str]:
        flag, data = "OK", "0"
        if msg_id == -1:
            flag, data, msg_id = "RJ", "BADMESSAGEID", None
        elif axis > len(dev.axes):
            flag, data = "RJ", "BADAXIS"
        elif "again" in faults:
            flag, data = "RJ", "AGAIN"  # command buffer busy: not carried out, asks for a repeat
        else:
            try:
                data = self._command(dev, axis, [w.lower() for w in words], faults, broadcast=broadcast)
            except _Rejected as rj:
                flag, data = "RJ", rj.reason
        return self._packets(dev, axis, msg_id, flag, data, "bad_checksum" in faults)

    def _header(self, dev: ZaberDevice, axis: int, msg_id: int | None) -> str:
        mid = "" if msg_id is None else f" {msg_id:02d}"
        return f"{dev.address:02d} {axis}{mid}"

    def _packets(self, dev: ZaberDevice, axis: int, msg_id: int | None, flag: str, data: str,
                 corrupt: bool) -> list[str]:
        """The reply as the packets the device sends: ``@...`` then ``#... cont`` continuations."""
        axes = dev.axes if axis == 0 else dev.axes[axis - 1:axis]  # none for an axis it lacks
        status = "BUSY" if any(a.moving for a in axes) else "IDLE"
        active: set[str] = set().union(*(a.flags for a in axes))
        warn = next((f for f in _FLAG_ORDER if f in active), "--")
        head = f"{self._header(dev, axis, msg_id)} {flag} {status} {warn}"
        room = dev.packet_size - 1 - (3 if dev.checksums else 0)  # marker and ":XX"
        bodies, cont = [], f"{self._header(dev, axis, msg_id)} cont"
        words, current = data.split(" "), head
        for w in words:
            if len(current) + 1 + len(w) + 2 > room and current not in (head, cont):
                bodies.append(current + " \\")
                current = cont
            current += " " + w
        bodies.append(current)
        out = [("@" if i == 0 else "#") + self._frame(dev, b, corrupt and i == 0) for i, b in enumerate(bodies)]
        return out

    def _frame(self, dev: ZaberDevice, body: str, corrupt: bool) -> str:
        """Append the checksum; for the ``bad_checksum`` fault, corrupt the text after it."""
        if not (dev.checksums or corrupt):
            return body
        cs = checksum(body)
        if corrupt:
            self._count_down("bad_checksum")
            # One character flips on the line: the first digit of the data if there is one
            # (a position that silently changes), else the last character.
            m = re.match(r"(\d\d \d+(?: \d\d)? \S+ \S+ \S+ )(.*)", body)
            head, data = (m.group(1), m.group(2)) if m else ("", body)
            i = next((k for k, ch in enumerate(data) if ch.isdigit()), None)
            if i is not None:
                body = head + data[:i] + str((int(data[i]) + 5) % 10) + data[i + 1:]
            else:
                body = body[:-1] + ("A" if body[-1] != "A" else "B")
        return f"{body}:{cs}"

    def _command(self, dev: ZaberDevice, axis: int, words: list[str], faults: set[str], *, broadcast: bool) -> str:
        if not words:
            return "0"
        cmd, args = words[0], words[1:]
        axes = list(range(1, len(dev.axes) + 1)) if axis == 0 else [axis]
        if cmd == "home" and not args:
            for n in axes:
                self._start(dev.axes[n - 1], 0.0, faults, home=True)
            return "0"
        if cmd == "move" and args:
            for n in axes:
                self._move(dev.axes[n - 1], args, faults)
            return "0"
        if cmd in ("stop", "estop") and not args:
            for n in axes:
                _stop(dev.axes[n - 1], at_once=cmd == "estop")
            return "0"
        if cmd == "warnings" and args in ([], ["clear"]):
            active = set().union(*(dev.axes[n - 1].flags for n in axes))
            listed = [f for f in _FLAG_ORDER if f in active]
            if args:
                for n in axes:
                    dev.axes[n - 1].flags -= _CLEARABLE
            return " ".join([f"{len(listed):02d}", *listed])
        if cmd == "get" and len(args) == 1:
            return self._get(dev, axis, args[0])
        if cmd == "set" and len(args) == 2:
            self._set(dev, axis, args[0], args[1])
            return "0"
        if cmd == "tools" and args[:1] == ["echo"]:
            return " ".join(args[1:]) or "0"
        device_only = {"renumber", "system"}
        if cmd in device_only and axis:
            raise _Rejected("DEVICEONLY")
        if cmd == "renumber" and len(args) <= 1:
            if args:
                number = _integer(args[0], 1, 99)
            elif broadcast:
                number = self.chain.index(dev) + 1
            else:
                raise _Rejected("BADDATA")
            dev.address = number
            return "0"
        if cmd == "system" and args == ["reset"]:
            threading.Timer(0.01, self.power_cycle).start()  # after the reply has gone out
            return "0"
        if cmd == "system" and args == ["restore"]:
            _zaber_defaults(dev)
            for ax in dev.axes:
                ax.flags.add("WR")  # the resolution (and so the counter) was reset
            return "0"
        raise _Rejected("BADCOMMAND")

    def _move(self, ax: ZaberAxis, args: list[str], faults: set[str]) -> None:
        kind, rest = args[0], args[1:]
        if kind in ("abs", "rel") and len(rest) == 1:
            steps = _integer(rest[0], -(2 ** 31), 2 ** 31 - 1)
            if kind == "abs" and "WR" in ax.flags:
                # No reference position: absolute moves are refused until the axis is homed.
                raise _Rejected("BADDATA")
            counter = steps if kind == "abs" else ax.pos + steps
            lo, hi = ax.steps(ax.limit_min_um), ax.steps(ax.limit_max_um)
            if not lo <= counter <= hi:
                raise _Rejected("BADDATA")
            self._start(ax, counter * ax.microstep_um + ax.offset_um, faults)
        elif kind == "vel" and len(rest) == 1:
            native = _integer(rest[0], -(2 ** 31), 2 ** 31 - 1)
            v = native / _VEL_UNIT * ax.microstep_um
            if abs(v) > ax.speed_mm_s * 1000.0 * 1.000001:
                raise _Rejected("BADDATA")
            self._start(ax, None, faults, vel_um_s=v)
        elif kind in ("min", "max") and not rest:
            if "WR" in ax.flags:
                raise _Rejected("BADDATA")
            edge = ax.limit_min_um if kind == "min" else ax.limit_max_um
            self._start(ax, edge + ax.offset_um, faults)
        else:
            raise _Rejected("BADCOMMAND")

    # --- settings ------------------------------------------------------------------------
    def _get(self, dev: ZaberDevice, axis: int, name: str) -> str:
        device_settings = {
            "deviceid": lambda: dev.deviceid,
            "system.serial": lambda: dev.serial,
            "version": lambda: dev.version,
            "version.build": lambda: dev.build,
            "system.axiscount": lambda: len(dev.axes),
            "comm.packet.size.max": lambda: dev.packet_size,
            "comm.command.packets.max": lambda: 5,
            "comm.word.size.max": lambda: 20,
            "get.settings.max": lambda: 1,
            "comm.alert": lambda: int(dev.alert),
            "comm.checksum": lambda: int(dev.checksums),
            "comm.address": lambda: dev.address,
            "system.access": lambda: dev.access,
            "device.hw.modified": lambda: 0,
            "system.voltage": lambda: "48.1",
            "system.temperature": lambda: "31.5",
        }
        axis_settings: dict[str, Callable[[ZaberAxis], object]] = {
            "pos": lambda a: a.pos,
            "resolution": lambda a: a.resolution,
            "limit.min": lambda a: a.steps(a.limit_min_um),
            "limit.max": lambda a: a.steps(a.limit_max_um),
            "maxspeed": lambda a: round(a.speed_mm_s * 1000.0 / a.microstep_um * _VEL_UNIT),
            "accel": lambda a: round(a.accel_mm_s2 * 1000.0 / a.microstep_um * _ACCEL_UNIT),
            "peripheral.id": lambda a: a.peripheral_id,
            "peripheral.serial": lambda a: 0,
            "peripheral.hw.modified": lambda a: 0,
            "driver.temperature": lambda a: "35.2",
        }
        if name in device_settings:
            if axis:
                raise _Rejected("DEVICEONLY")
            return str(device_settings[name]())
        if name in axis_settings:
            if name.startswith("peripheral.") and not any(a.peripheral_id for a in dev.axes):
                raise _Rejected("BADCOMMAND")  # integrated devices have no peripherals
            axes = dev.axes if axis == 0 else [dev.axes[axis - 1]]
            return " ".join(str(axis_settings[name](a)) for a in axes)
        raise _Rejected("BADCOMMAND")

    def _set(self, dev: ZaberDevice, axis: int, name: str, value: str) -> None:
        device_settings = {"comm.alert": (0, 1), "comm.checksum": (0, 1), "comm.packet.size.max": (20, 2000),
                           "system.access": (1, 2), "comm.address": (1, 99)}
        if name in device_settings:
            if axis:
                raise _Rejected("DEVICEONLY")
            v = _integer(value, *device_settings[name])
            if name == "comm.alert":
                dev.alert = bool(v)
            elif name == "comm.checksum":
                dev.checksums = bool(v)
            elif name == "comm.packet.size.max":
                dev.packet_size = v
            elif name == "system.access":
                dev.access = v
            else:
                dev.address = v
            return
        axes = dev.axes if axis == 0 else [dev.axes[axis - 1]]
        for ax in axes:
            if name == "pos":
                ax.offset_um = ax.true_um - _integer(value, -(2 ** 31), 2 ** 31 - 1) * ax.microstep_um
            elif name == "resolution":
                ax.resolution = _integer(value, 1, 256)
                ax.flags.add("WR")  # the counter no longer means the same distance
                ax.offset_um = ax.true_um
            elif name == "maxspeed":
                v = _integer(value, 1, 2 ** 31 - 1)
                ax.speed_mm_s = v / _VEL_UNIT * ax.microstep_um / 1000.0
            elif name == "accel":
                v = _integer(value, 1, 2 ** 31 - 1)
                ax.accel_mm_s2 = v / _ACCEL_UNIT * ax.microstep_um / 1000.0
            elif name in ("limit.min", "limit.max"):
                if dev.access < 2:
                    raise _Rejected("NOACCESS")
                um = _integer(value, -(2 ** 31), 2 ** 31 - 1) * ax.microstep_um
                if not 0.0 <= um <= ax.product.travel_mm * 1000.0:
                    raise _Rejected("BADDATA")
                if name == "limit.min":
                    ax.limit_min_um = um
                else:
                    ax.limit_max_um = um
            elif name in ("deviceid", "system.serial", "version", "system.axiscount", "peripheral.id",
                          "limit.home.pos"):
                raise _Rejected("BADCOMMAND")  # read-only
            else:
                raise _Rejected("BADCOMMAND")


def _integer(text: str, lo: int, hi: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise _Rejected("BADDATA") from None
    if not lo <= value <= hi:
        raise _Rejected("BADDATA")
    return value


def _product_for_microstep(microstep_um: float) -> int:
    """The emulated product whose native step at resolution 64 is ``microstep_um``."""
    for pid, p in ZABER_PRODUCTS.items():
        if p.integrated and math.isclose(p.full_step_um / 64, microstep_um, rel_tol=1e-9):
            return pid
    sizes = sorted({p.full_step_um / 64 for p in ZABER_PRODUCTS.values() if p.integrated})
    raise ValueError(f"no emulated Zaber stage has a {microstep_um} um microstep; choose one of {sizes}")


def _advance(ax: ZaberAxis, now: float) -> None:
    """Integrate the axis' motion up to ``now``: accelerate at ``accel`` to ``maxspeed`` (or the
    ``move vel`` velocity) and brake so as to stop on the target; a stall does not move."""
    if not ax.moving:
        ax.t_last = now
        return
    if ax.stall:
        ax.t_last = now
        return
    a = ax.accel_mm_s2 * 1000.0
    vmax = ax.speed_mm_s * 1000.0
    lo, hi = ax.limit_min_um + ax.offset_um, ax.limit_max_um + ax.offset_um
    t = ax.t_last
    while t < now and ax.moving:
        h = min(1e-3, now - t)
        if ax.vel_um_s is not None:  # a velocity move ends at the travel limit ahead
            target, cap = (hi if ax.vel_um_s > 0 else lo), min(vmax, abs(ax.vel_um_s))
        else:
            target, cap = ax.target_um, vmax
        rem = target - ax.true_um
        desired = math.copysign(min(cap, math.sqrt(2 * a * abs(rem))), rem) if rem else 0.0
        v_new = ax.v_um_s + max(-a * h, min(a * h, desired - ax.v_um_s))
        x_new = ax.true_um + (ax.v_um_s + v_new) / 2 * h
        after = target - x_new
        if rem == 0 or rem * after <= 0 or (abs(after) < 1e-3 and abs(v_new) <= 2 * a * h):
            ax.true_um, ax.v_um_s = target, 0.0
            _arrive(ax)
            break
        ax.true_um, ax.v_um_s = x_new, v_new
        t += h
    ax.t_last = now


def _arrive(ax: ZaberAxis) -> None:
    ax.moving, ax.target_um, ax.vel_um_s = False, None, None
    if ax.home:
        ax.offset_um = ax.true_um
        ax.flags.discard("WR")
        ax.home = False
    ax.flags.update(ax.arrival_flags)
    ax.arrival_flags = ()


def _stop(ax: ZaberAxis, *, at_once: bool) -> None:
    """``stop``: brake at ``accel`` to rest (BUSY until then); ``estop``: stop where it is."""
    if not ax.moving:
        return
    ax.flags.add("NI")
    ax.home, ax.arrival_flags = False, ()
    if at_once or ax.stall or ax.v_um_s == 0.0:
        ax.moving, ax.v_um_s, ax.target_um, ax.vel_um_s, ax.stall = False, 0.0, None, None, False
        return
    a = ax.accel_mm_s2 * 1000.0
    ax.vel_um_s = None
    ax.target_um = ax.true_um + math.copysign(ax.v_um_s ** 2 / (2 * a), ax.v_um_s)
