"""Emulators of the serial instruments on real pseudo-terminals.

Each emulator opens a pseudo-terminal pair (``os.openpty``), serves the master end on a daemon
thread and exposes the slave's path as :attr:`port`; the real drivers of ``acquisition`` open
that path with pyserial exactly as they open ``/dev/ttyUSB0`` in the lab, so the driver code
under test is the code that runs in the lab.

- :class:`PulseGeneratorEmulator`: a Quantum Composers 9520 / BNC 575 (``?n`` error codes,
  T0 period, normal/burst/single mode, per-channel enable, delay, width, sync, polarity). While
  T0 runs it ticks on a thread at the programmed period and calls its listeners, which is how
  simulated cameras learn that they were triggered and which laser cavities fired.
- :class:`StageEmulator`: a Zaber stage on the ASCII protocol (``@01 1 OK IDLE -- 0``), moving
  at a finite speed, with a home sensor, travel limits and warning flags.

Faults for tests (:meth:`inject`, :meth:`clear_faults`):

``"no_reply"``   commands are carried out but nothing is answered (broken receive line);
``"garbled"``    commands are carried out, replies come back as noise;
``"disconnect"`` the master end is closed (an unplugged USB adapter); the instrument keeps
                 its state, so an emulated generator whose T0 was running keeps firing;
``"error"``      (pulse generator) the next command is refused with ``?code``, one shot;
``"stall"``      (stage) the next move never progresses and the axis stays BUSY until stopped;
``"limit"``      (stage) the next move stops half way on a limit sensor, flag ``WL``;
``"slip"``       (stage) the next move ends IDLE 50 um away from its target;
``"flags"``      (stage) the next move or homing ends with the warning flags ``flags=(...)``
                 raised, e.g. ``("WT", "WM")`` (the reply then shows only the first);
``"again"``      (stage) the next ``count=n`` commands (default 1) are refused with
                 ``RJ ... AGAIN`` without being carried out;
``"bad_checksum"`` (stage) the next ``count=n`` replies (default 1) are corrupted on the way
                 back: one data character changes, the checksum of the original stays. The
                 command itself is carried out.

``after=n`` delays a fault until ``n`` more commands have been served normally.

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
import threading
import time
import tty
from collections.abc import Callable

from acquisition.stage import CorruptReply, checksum, verified

__all__ = ["ChannelState", "PulseGeneratorEmulator", "StageEmulator", "TickListener"]

log = logging.getLogger(__name__)

#: ``callback(tick, t0_ns, outputs)``: ``tick`` counts T0 periods from 0 since T0 was started,
#: ``t0_ns`` is the host wall-clock time (``time.time_ns`` scale) of that T0 edge, ``outputs``
#: maps each ENABLED channel number to its delay after T0 in seconds.
TickListener = Callable[[int, int, dict[int, float]], None]


class _PtyEmulator:
    """An instrument served on the master end of a pseudo-terminal, one line per command."""

    FAULTS: frozenset[str] = frozenset({"no_reply", "garbled", "disconnect"})
    name = "instrument"

    def __init__(self, latency_s: float = 0.002) -> None:
        #: Time between receiving a command and answering it, seconds.
        self.latency_s = latency_s
        #: Every command line received, in order (for tests).
        self.commands: list[str] = []
        self._lock = threading.RLock()
        self._faults: dict[str, int] = {}
        self._fault_args: dict[str, dict] = {}
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass through untouched
        #: Path of the slave end, to be opened by the driver.
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._disconnected = False
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

    @property
    def connected(self) -> bool:
        """False after a ``"disconnect"`` fault or :meth:`close`."""
        return not self._disconnected and not self._closed

    # --- faults --------------------------------------------------------------------------
    def inject(self, fault: str, *, after: int = 0, **options: object) -> None:
        """Make the emulator misbehave.

        Parameters
        ----------
        fault : str
            One of :attr:`FAULTS` (see the module docstring).
        after : int
            Serve this many more commands normally before the fault starts.
        **options
            ``code=n`` for ``"error"`` (default 5).
        """
        if fault not in self.FAULTS:
            raise ValueError(f"unknown fault {fault!r}; choose from {sorted(self.FAULTS)}")
        with self._lock:
            self._faults[fault] = after
            self._fault_args[fault] = dict(options)

    def clear_faults(self) -> None:
        """Back to normal behaviour (a disconnect cannot be undone)."""
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

    # --- serving -------------------------------------------------------------------------
    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except (OSError, ValueError):
                return  # master closed (disconnect or close)
            if not data:
                continue
            buf += data
            while b"\n" in buf or b"\r" in buf:
                cut = min(i for i in (buf.find(b"\n"), buf.find(b"\r")) if i >= 0)
                raw, buf = buf[:cut], buf[cut + 1:]
                if not raw.strip():
                    continue  # the other half of CR LF, or an empty line
                self._serve_line(raw.decode("ascii", errors="replace").strip())
                if self._disconnected:
                    return

    def _serve_line(self, line: str) -> None:
        faults = self._take_faults()
        with self._lock:
            self.commands.append(line)
        if "disconnect" in faults:
            self._disconnected = True
            self._close_master()
            return
        reply = self._respond(line, faults)
        if reply is None or "no_reply" in faults:
            return
        if self.latency_s > 0:
            time.sleep(self.latency_s)
        data = (reply + "\r\n").encode("ascii")
        if "garbled" in faults:
            data = bytes(random.randrange(128, 256) for _ in range(len(data) - 2)) + b"\r\n"
        try:
            os.write(self._master, data)
        except OSError:
            pass

    def _close_master(self) -> None:
        with self._lock:
            fd, self._master = self._master, -1
        if fd >= 0:
            with contextlib.suppress(OSError):
                os.close(fd)

    def _respond(self, line: str, faults: set[str]) -> str | None:  # pragma: no cover - abstract
        raise NotImplementedError


# ============================================================================================
# Pulse generator
# ============================================================================================


@dataclasses.dataclass
class ChannelState:
    """One output channel of the emulated pulse generator."""

    enabled: bool = False
    delay_s: float = 0.0
    width_s: float = 1e-6
    sync: str = "T0"
    polarity: str = "NORM"
    mode: str = "NORM"
    mux: int = 0  # the channel timers routed to this output, one bit each (timer A = 1)


class _ScpiError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


_ON = {"ON": True, "1": True, "OFF": False, "0": False}
_MODES = ("NORMal", "SINGle", "BURSt", "DCYCle")


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


class PulseGeneratorEmulator(_PtyEmulator):
    """An emulated Quantum Composers 9520-series pulse generator on a pseudo-terminal.

    Parameters
    ----------
    channels : int
        Number of outputs (4 for a 9524, 8 for a 9528).
    latency_s : float
        Reply latency, seconds (0 for fast tests).
    model, serial : str
        What ``*IDN?`` reports.

    Attributes
    ----------
    port : str
        Slave path for the driver.
    ticks_fired : int
        T0 periods fired since the emulator was created.
    commands : list of str
        Every command line received.
    """

    FAULTS = frozenset({"no_reply", "garbled", "disconnect", "error"})
    name = "pulse generator"

    def __init__(self, channels: int = 8, latency_s: float = 0.002, *, model: str = "9528",
                 serial: str = "EMU0001") -> None:
        self.n_channels = channels
        self.idn = f"QC,{model},{serial},3.0.0-emulator"
        self._channels = {n: ChannelState(mux=1 << (n - 1)) for n in range(1, channels + 1)}
        self.period_s = 1e-3
        self.mode = "NORM"
        self.burst_count = 1
        self.trigger_mode = "DIS"
        self.gate_mode = "DIS"
        self.ticks_fired = 0
        self._running = False
        self._run_stop: threading.Event | None = None
        self._ticker: threading.Thread | None = None
        self._listeners: list[TickListener] = []
        super().__init__(latency_s)

    # --- what the simulated world reads --------------------------------------------------
    @property
    def running(self) -> bool:
        """True while T0 runs (False after a burst completed or STATE OFF)."""
        return self._running

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

    def wait_stopped(self, timeout_s: float) -> bool:
        """Wait until T0 stops by itself (burst complete); True if it did."""
        deadline = time.monotonic() + timeout_s
        while self._running and time.monotonic() < deadline:
            time.sleep(0.002)
        return not self._running

    def close(self) -> None:
        self._set_running(False)
        super().close()

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
        if ticker is not None and ticker is not threading.current_thread():
            ticker.join(timeout=2.0)

    def _tick_loop(self, stop: threading.Event) -> None:
        # Absolute perf_counter schedule: tick k at start + sum of periods, no drift; a late
        # tick is fired at once (a real generator never skips a period).
        perf0 = time.perf_counter_ns()
        wall0 = time.time_ns()
        due = perf0
        k = 0
        while True:
            wait = (due - time.perf_counter_ns()) / 1e9
            if stop.wait(wait) if wait > 0 else stop.is_set():
                return
            with self._lock:
                if stop.is_set():
                    return
                # an output fires with the first of the timers its multiplexer routes to it
                outputs = {n: min(t.delay_s for m, t in self._channels.items() if c.mux >> (m - 1) & 1)
                           for n, c in self._channels.items() if c.enabled and c.mux}
                listeners = list(self._listeners)
                period, mode, count = self.period_s, self.mode, self.burst_count
            t0_ns = wall0 + (due - perf0)
            for cb in listeners:
                try:
                    cb(k, t0_ns, outputs)
                except Exception:
                    log.exception("pulse generator emulator: listener %r failed", cb)
            k += 1
            with self._lock:
                self.ticks_fired += 1
                limit = count if mode == "BURS" else 1 if mode == "SING" else 0
                if limit and k >= limit:
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
            return self._execute(line)
        except _ScpiError as e:
            return f"?{e.code}"

    def _execute(self, line: str) -> str:
        header, _, arg = line.partition(" ")
        arg = arg.strip()
        query = header.endswith("?")
        header = header.rstrip("?")
        if header.startswith("*"):
            common = header.upper()
            if common == "*IDN":
                if not query:
                    raise _ScpiError(6)
                return self.idn
            if common == "*RST":
                if query:
                    raise _ScpiError(7)
                self._reset()
                return "ok"
            raise _ScpiError(3)
        if not header.startswith(":"):
            raise _ScpiError(1)
        words = header[1:].split(":")
        if not words or not words[0]:
            raise _ScpiError(2)
        if _kw(words[0], "INSTrument"):
            if len(words) == 2 and _kw(words[1], "CATalog"):
                if not query:
                    raise _ScpiError(6)
                return ",".join(["T0"] + [f"CH{'ABCDEFGH'[n - 1]}" for n in self._channels])
            raise _ScpiError(3)
        m = re.fullmatch(r"(PULSE|PULS)(\d*)", words[0].upper())
        if not m or len(words) < 2:
            raise _ScpiError(3)
        n = int(m.group(2) or 1)
        if n == 0:
            return self._t0(words[1:], query, arg)
        if n not in self._channels:
            raise _ScpiError(3)
        return self._channel(n, words[1:], query, arg)

    def _t0(self, words: list[str], query: bool, arg: str) -> str:
        key = words[0]
        if len(words) == 2 and _kw(key, "TRIGger") and _kw(words[1], "MODe"):
            if query:
                return self.trigger_mode
            self.trigger_mode = _choice(_need(arg), ("DISabled", "TRIGgered", "DUAL"))
            return "ok"
        if len(words) == 2 and _kw(key, "GATe") and _kw(words[1], "MODe"):
            if query:
                return self.gate_mode
            self.gate_mode = _choice(_need(arg), ("DISabled", "PULSe", "OUTPut", "CHANnel"))
            return "ok"
        if len(words) != 1:
            raise _ScpiError(3)
        if _kw(key, "STATe"):
            if query:
                return "1" if self._running else "0"
            on = _ON.get(_need(arg).upper())
            if on is None:
                raise _ScpiError(5)
            self._set_running(on)
            return "ok"
        if _kw(key, "PERiod"):
            if query:
                return f"{self.period_s:.9f}"
            self.period_s = _number(arg, 100e-9, 5000.0)
            return "ok"
        if _kw(key, "MODe"):
            if query:
                return self.mode
            self.mode = _choice(_need(arg), _MODES)
            return "ok"
        if _kw(key, "BCOunter"):
            if query:
                return str(self.burst_count)
            value = _number(arg, 1, 1_000_000)
            if value != int(value):
                raise _ScpiError(5)
            self.burst_count = int(value)
            return "ok"
        raise _ScpiError(3)

    def _channel(self, n: int, words: list[str], query: bool, arg: str) -> str:
        if len(words) != 1:
            raise _ScpiError(3)
        key = words[0]
        with self._lock:
            c = self._channels[n]
            if _kw(key, "STATe"):
                if query:
                    return "1" if c.enabled else "0"
                on = _ON.get(_need(arg).upper())
                if on is None:
                    raise _ScpiError(5)
                c.enabled = on
            elif _kw(key, "DELay"):
                if query:
                    return f"{c.delay_s:.11f}"
                c.delay_s = _number(arg, -999.99999999975, 999.99999999975)
            elif _kw(key, "WIDTh"):
                if query:
                    return f"{c.width_s:.11f}"
                c.width_s = _number(arg, 10e-9, 999.99999999975)
            elif _kw(key, "SYNC"):
                if query:
                    return c.sync
                names = ["T0"] + [f"CH{'ABCDEFGH'[i - 1]}" for i in self._channels if i != n]
                value = _need(arg).upper()
                if value not in names:
                    raise _ScpiError(5)
                c.sync = value
            elif _kw(key, "POLarity"):
                if query:
                    return c.polarity
                c.polarity = _choice(_need(arg), ("NORMal", "COMPlement", "INVerted"))
            elif _kw(key, "CMODe"):
                if query:
                    return c.mode
                c.mode = _choice(_need(arg), _MODES)
            elif _kw(key, "MUX"):
                if query:
                    return str(c.mux)
                value = _number(arg, 0, 2 ** len(self._channels) - 1)
                if value != int(value):
                    raise _ScpiError(5)
                c.mux = int(value)
            else:
                raise _ScpiError(3)
        return "ok"

    def _reset(self) -> None:
        self._set_running(False)
        with self._lock:
            self._channels = {n: ChannelState(mux=1 << (n - 1)) for n in self._channels}
            self.period_s, self.mode, self.burst_count, self.trigger_mode = 1e-3, "NORM", 1, "DIS"
            self.gate_mode = "DIS"


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


# ============================================================================================
# Stage (Zaber ASCII protocol)
# ============================================================================================

#: Zaber warning flags in order of precedence (the reply shows the highest active one).
_FLAG_ORDER = ("FD", "FQ", "FS", "FT", "FB", "FP", "FE", "WH", "WL", "WP", "WV", "WT", "WM", "WR",
               "NC", "NI", "ND", "NU", "NJ")
_CLEARABLE = {"FQ", "FS", "FT", "FB", "FP", "FE", "WL", "NI"}


@dataclasses.dataclass
class _Motion:
    start: int          # true position, steps
    end: int            # where the motion stops, steps
    t0: float           # perf_counter at start
    speed: float        # steps per second
    stall: bool = False
    home: bool = False
    flags_on_arrival: tuple[str, ...] = ()


class StageEmulator(_PtyEmulator):
    """An emulated Zaber linear stage (one axis) on the ASCII protocol.

    The emulator keeps the TRUE carriage position (what the simulated world sees) and the
    position counter the device reports; they differ by an unknown offset until the stage is
    homed, as on a stage just powered up.

    Commands may end in a checksum (``/1 1 get pos:XX``); one that does not match is dropped
    unanswered, like any line the device cannot read.

    Parameters
    ----------
    device : int
        Device address on the daisy chain.
    axis : int
        The one axis this device has (the rig's ``stage.axis``).
    microstep_um : float
        Size of one native step (microstep), micrometres.
    travel_mm : float
        Travel between the home sensor (0) and ``limit.max``.
    speed_mm_s : float
        Speed of every motion (acceleration is not modelled).
    position_mm : float
        True carriage position at power-up.
    homed : bool
        Start homed (no ``WR`` flag) instead of freshly powered up.
    latency_s : float
        Reply latency, seconds.
    checksums : bool
        Append a checksum ``:XX`` to every reply (the device setting ``comm.checksum 1``).
    """

    FAULTS = frozenset({"no_reply", "garbled", "disconnect", "stall", "limit", "slip", "flags", "again",
                        "bad_checksum"})
    name = "stage"

    def __init__(self, *, device: int = 1, axis: int = 1, microstep_um: float = 0.1, travel_mm: float = 50.0,
                 speed_mm_s: float = 20.0, position_mm: float = 12.5, homed: bool = False,
                 latency_s: float = 0.002, checksums: bool = False) -> None:
        self.device = device
        self.axis = axis
        self.microstep_um = microstep_um
        self.limit_max = round(travel_mm * 1000 / microstep_um)
        self.speed_mm_s = speed_mm_s
        #: Append checksums to replies (may be changed at any time).
        self.checksums = checksums
        self._true = round(position_mm * 1000 / microstep_um)
        self._offset = 0 if homed else self._true  # the counter reads 0 at power-up
        self._flags: set[str] = set() if homed else {"WR"}
        self._motion: _Motion | None = None
        super().__init__(latency_s)

    # --- what the simulated world reads --------------------------------------------------
    @property
    def position_mm(self) -> float:
        """True carriage position, millimetres from the home sensor."""
        with self._lock:
            self._update()
            return self._true * self.microstep_um / 1000

    @property
    def homed(self) -> bool:
        with self._lock:
            self._update()
            return "WR" not in self._flags

    @property
    def busy(self) -> bool:
        with self._lock:
            self._update()
            return self._motion is not None

    @property
    def flags(self) -> frozenset[str]:
        with self._lock:
            self._update()
            return frozenset(self._flags)

    def set_flags(self, *flags: str) -> None:
        """Raise warning flags now (a standing condition, e.g. ``"FD"``, ``"WV"``).

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
            self._flags.update(flags)

    # --- faults that last for several commands -------------------------------------------
    def _count_down(self, fault: str) -> None:
        """Use one of the ``count=n`` occurrences of a fault; remove it after the last."""
        with self._lock:
            left = int(self._fault_args.get(fault, {}).get("count", 1)) - 1
            if left <= 0:
                self._consume_fault(fault)
            else:
                self._fault_args[fault]["count"] = left

    # --- motion model --------------------------------------------------------------------
    def _update(self) -> None:
        m = self._motion
        if m is None:
            return
        if m.stall:
            return  # stuck where it started, BUSY until stopped
        dist = abs(m.end - m.start)
        travelled = min(dist, m.speed * (time.perf_counter() - m.t0))
        self._true = m.start + int(math.copysign(round(travelled), m.end - m.start)) if dist else m.start
        if travelled >= dist:
            self._true = m.end
            self._motion = None
            if m.home:
                self._offset = 0
                self._flags.discard("WR")
            self._flags.update(m.flags_on_arrival)

    def _start(self, end: int, faults: set[str], *, home: bool = False) -> None:
        if self._motion is not None:
            self._flags.add("NI")  # a movement interrupted by another
        else:
            self._flags.discard("NI")
        speed = self.speed_mm_s * 1000 / self.microstep_um
        m = _Motion(start=self._true, end=end, t0=time.perf_counter(), speed=speed, home=home)
        if "stall" in faults:
            self._consume_fault("stall")
            m.stall = True
        elif "limit" in faults and not home:
            self._consume_fault("limit")
            m.end = m.start + (end - m.start) // 2
            m.flags_on_arrival = ("WL",)
        elif "slip" in faults and not home:
            self._consume_fault("slip")
            m.end = end + round(50.0 / self.microstep_um)
        if "flags" in faults:
            flags = tuple(self._consume_fault("flags").get("flags", ()))
            unknown = set(flags) - set(_FLAG_ORDER)
            if unknown:
                log.error("stage emulator: unknown flags %s ignored", sorted(unknown))
            m.flags_on_arrival += tuple(f for f in flags if f in _FLAG_ORDER)
        self._motion = m

    # --- ASCII protocol ------------------------------------------------------------------
    def _respond(self, line: str, faults: set[str]) -> str | None:
        if not line.startswith("/"):
            return None  # not a command: Zaber devices ignore it
        try:
            line = verified(line)
        except CorruptReply:
            return None  # corrupted on the way in: dropped
        parts = line[1:].split()
        try:
            dev = int(parts[0]) if parts else 0
            axis = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0
        except ValueError:
            return None
        if dev not in (0, self.device):
            return None  # for another device on the chain
        words = parts[2:] if len(parts) > 1 and parts[1].isdigit() else parts[1:]
        with self._lock:
            self._update()
            if axis not in (0, self.axis):
                reply = self._reply(axis, "RJ", "BADAXIS")
            elif "again" in faults:
                self._count_down("again")  # buffer busy: not carried out, asks for a repeat
                reply = self._reply(axis, "RJ", "AGAIN")
            else:
                reply = self._command(axis, [w.lower() for w in words], faults)
            return self._frame(reply, "bad_checksum" in faults)

    def _frame(self, reply: str, corrupt: bool) -> str:
        """Append the checksum; for the ``bad_checksum`` fault, corrupt the text after it."""
        body = reply[1:]
        if not (self.checksums or corrupt):
            return reply
        cs = checksum(body)
        if corrupt:
            self._count_down("bad_checksum")
            # One character flips on the line: the first digit of the data if there is one
            # (a position that silently changes), else the last character.
            fields = body.split(" ", 5)  # dd a flag status warning data
            data = fields[5] if len(fields) == 6 else ""
            i = next((k for k, ch in enumerate(data) if ch.isdigit()), None)
            if i is not None:
                fields[5] = data[:i] + str((int(data[i]) + 5) % 10) + data[i + 1:]
                body = " ".join(fields)
            else:
                body = body[:-1] + ("A" if body[-1] != "A" else "B")
        return f"@{body}:{cs}"

    def _reply(self, axis: int, flag: str, data: str) -> str:
        status = "BUSY" if self._motion is not None else "IDLE"
        warn = next((f for f in _FLAG_ORDER if f in self._flags), "--")
        return f"@{self.device:02d} {axis} {flag} {status} {warn} {data}"

    def _command(self, axis: int, words: list[str], faults: set[str]) -> str:
        if not words:
            return self._reply(axis, "OK", "0")
        cmd, args = words[0], words[1:]
        if cmd == "home":
            self._start(0, faults, home=True)
            return self._reply(axis, "OK", "0")
        if cmd == "move" and len(args) == 2 and args[0] == "abs":
            try:
                target = int(args[1])
            except ValueError:
                return self._reply(axis, "RJ", "BADDATA")
            if "WR" in self._flags:
                # No reference position: absolute moves are refused until the axis is homed.
                return self._reply(axis, "RJ", "BADDATA")
            if not 0 <= target <= self.limit_max:
                return self._reply(axis, "RJ", "BADDATA")
            self._start(target + self._offset, faults)
            return self._reply(axis, "OK", "0")
        if cmd in ("stop", "estop") and not args:
            if self._motion is not None:
                self._motion = None
                self._flags.add("NI")
            return self._reply(axis, "OK", "0")
        if cmd == "get" and len(args) == 1:
            values = {"pos": self._true - self._offset, "limit.min": 0, "limit.max": self.limit_max,
                      "maxspeed": round(self.speed_mm_s * 1000 / self.microstep_um * 1.6384),
                      "device.id": 50081}
            if args[0] not in values:
                return self._reply(axis, "RJ", "BADCOMMAND")
            return self._reply(axis, "OK", str(values[args[0]]))
        if cmd == "warnings" and args in ([], ["clear"]):
            active = [f for f in _FLAG_ORDER if f in self._flags]
            reply = self._reply(axis, "OK", " ".join([f"{len(active):02d}", *active]))
            if args:
                self._flags -= _CLEARABLE
            return reply
        return self._reply(axis, "RJ", "BADCOMMAND")
