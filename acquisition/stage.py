"""Driver for a Zaber motorised stage on the Zaber ASCII protocol (one axis, millimetres).

The stage carries the calibration target along the optical axis; the calibration runner moves
it through the 51 target planes with :meth:`ZaberStage.move_to`.

Protocol. A command is one line ``/<device> <axis> <command>`` ended by LF; the device answers
every command addressed to it with one line ``@<dd> <a> <flag> <status> <warning> <data>``
ended by CR LF, for example::

    /1 1 move abs 125000        ->  @01 1 OK BUSY -- 0
    /1 1 get pos                ->  @01 1 OK IDLE -- 125000
    /1 1 move abs 5             ->  @01 1 RJ IDLE WR BADDATA    (no reference position)
    /1 1 warnings               ->  @01 1 OK IDLE WR 01 WR

``flag`` is ``OK`` or ``RJ`` (rejected; ``data`` then gives the reason: BADDATA, BADCOMMAND,
BADAXIS, STATUSBUSY, PARKED, ...), ``status`` is ``BUSY`` while the axis moves and ``IDLE``
otherwise, ``warning`` is the highest-priority active warning flag or ``--``: ``WR`` no
reference position (not homed), ``WL`` a limit sensor stopped a move, ``FS`` stalled and
stopped, ``NI`` a move was interrupted by another command. Lines starting with ``#`` (info) or
``!`` (alerts) are skipped. Positions are in native steps (microsteps, 0.1 um by default on
Zaber linear stages; check the product's "microstep size").

Motion is polled: after ``move abs`` the driver reads ``get pos`` until the axis reports
``IDLE``, then checks the warning flags and the position against the target.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from types import TracebackType
from typing import NoReturn

from .protocols import DeviceError
from .serial_link import LinkClosed, LinkError, LinkTimeout, SerialLink

__all__ = ["ZaberReply", "ZaberStage", "parse_reply"]

_REPLY = re.compile(r"@(\d{2}) (\d) (OK|RJ) (IDLE|BUSY) (\S\S) ?(.*?)(?::[0-9A-Fa-f]{2})?")

#: What each rejection reason means and what to do.
_REJECTIONS = {
    "BADDATA": "the value is out of range or invalid",
    "BADCOMMAND": "the device does not know this command or setting (check its firmware)",
    "BADAXIS": "the device has no such axis (check the axis number)",
    "STATUSBUSY": "the device is busy; wait until it is idle",
    "PARKED": "the axis is parked; send 'tools parking unpark' or use the Zaber Console",
    "NOACCESS": "the command needs a higher access level",
    "LOCKSTEP": "the axis is part of a lockstep group; disable lockstep first",
    "DEVICEONLY": "the command applies to the whole device, not to an axis",
    "AGAIN": "the device asks to repeat the command",
}


@dataclass(frozen=True)
class ZaberReply:
    """A parsed ASCII reply line."""

    device: int
    axis: int
    flag: str       # "OK" or "RJ"
    status: str     # "IDLE" or "BUSY"
    warning: str    # highest-priority warning flag, "--" if none
    data: str

    @property
    def ok(self) -> bool:
        return self.flag == "OK"

    @property
    def idle(self) -> bool:
        return self.status == "IDLE"


def parse_reply(line: str) -> ZaberReply | None:
    """Parse one reply line; None if it is not a reply (an info ``#`` or alert ``!`` line)."""
    m = _REPLY.fullmatch(line.strip())
    if not m:
        return None
    dev, axis, flag, status, warn, data = m.groups()
    return ZaberReply(int(dev), int(axis), flag, status, warn, data.strip())


class ZaberStage:
    """A Zaber linear stage, one axis, positions in millimetres from the home sensor.

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyUSB0``, ``COM4``) or pyserial URL.
    baud : int
        Baud rate (115200 for the ASCII protocol by default).
    device, axis : int
        Address on the daisy chain and axis number.
    timeout_s : float
        Time allowed for each reply, seconds.
    microstep_um : float
        Size of one native step, micrometres.
    move_timeout_s : float
        Longest a move or homing may take before it counts as stalled.
    tolerance_um : float
        Largest accepted difference between a target and the position read back.
    poll_s : float
        Interval between status polls while the axis moves.
    """

    def __init__(self, port: str, baud: int = 115200, device: int = 1, axis: int = 1, timeout_s: float = 0.5,
                 microstep_um: float = 0.1, *, move_timeout_s: float = 60.0, tolerance_um: float = 1.0,
                 poll_s: float = 0.02) -> None:
        if microstep_um <= 0:
            raise ValueError("microstep_um must be positive")
        self._link = SerialLink(port, baud, timeout_s, eol=b"\n")
        self.device, self.axis = device, axis
        self.microstep_um = microstep_um
        self.move_timeout_s = move_timeout_s
        self.tolerance_um = tolerance_um
        self.poll_s = poll_s
        self._travel_mm: tuple[float, float] | None = None

    @property
    def port(self) -> str:
        return self._link.port

    @property
    def travel_mm(self) -> tuple[float, float]:
        """(min, max) positions the device accepts, read at :meth:`open`."""
        if self._travel_mm is None:
            raise DeviceError(f"stage on {self.port}: not open; call open() first")
        return self._travel_mm

    # --- life cycle ----------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, check that the device answers and read its travel limits.

        Raises
        ------
        DeviceError
            The port cannot be opened or the device does not answer as a Zaber device.
        """
        if self._link.is_open:
            return
        try:
            self._link.open()
        except LinkError as exc:
            raise DeviceError(f"stage on {self.port}: {exc}; check the port name and that no other program "
                              "(e.g. Zaber Launcher) holds it") from None
        try:
            lo = self._steps(self._command("get limit.min").data, "get limit.min")
            hi = self._steps(self._command("get limit.max").data, "get limit.max")
        except DeviceError:
            self._link.close()
            raise
        self._travel_mm = (self._mm(lo), self._mm(hi))

    def close(self) -> None:
        """Release the port (a move in progress is not stopped); safe in any state."""
        self._link.close()

    def __enter__(self) -> ZaberStage:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is not None and self._link.is_open:
            self._try_stop()  # whatever went wrong, do not leave the stage moving
        self.close()

    # --- the Stage protocol --------------------------------------------------------------
    def home(self) -> None:
        """Clear latched warnings, move to the home sensor and zero the position; blocks.

        Raises
        ------
        DeviceError
            The command is rejected, the device stops answering, or homing does not finish
            within ``move_timeout_s`` (the stage is then stopped).
        """
        self._command("warnings clear")
        self._command("home")
        reply = self._wait_idle("home", None)
        if reply.warning in ("WR", "FS", "FE", "WL"):
            self._fail("home", f"finished with warning {reply.warning} ({_flag_text(reply.warning)})",
                       "check the home sensor and that nothing blocks the carriage, then home again")

    def move_to(self, position_mm: float) -> float:
        """Move to an absolute position, block until idle and return the position read back.

        Raises
        ------
        DeviceError
            Target outside the travel, stage not homed, command rejected, limit sensor hit,
            stall (no arrival within ``move_timeout_s``; the stage is stopped), or readback
            further than ``tolerance_um`` from the target.
        """
        lo, hi = self.travel_mm
        steps = round(position_mm * 1000.0 / self.microstep_um)
        cmd = f"move abs {steps}"
        if not lo - 1e-9 <= position_mm <= hi + 1e-9:
            raise DeviceError(f"stage on {self.port}: {cmd!r}: target {position_mm:g} mm is outside the travel "
                              f"[{lo:g}, {hi:g}] mm; choose a position inside it")
        # 'warnings clear' lists the active flags and resets the latched ones (WL, FS, NI...),
        # so the flags after this move are this move's; WR stays until the stage is homed.
        flags = self._warnings(clear=True)
        if "WR" in flags:
            raise DeviceError(f"stage on {self.port}: {cmd!r}: the stage is not homed (flag WR, no reference "
                              "position); call home() first")
        self._command(cmd)
        reply = self._wait_idle(cmd, position_mm)
        reached = self._mm(self._steps(reply.data, cmd))
        if reply.warning in ("WL", "FS", "FE"):
            self._fail(cmd, f"stopped at {reached:.4f} mm with warning {reply.warning} "
                       f"({_flag_text(reply.warning)})",
                       "check for an obstruction and the limit settings, then home again")
        if abs(reached - position_mm) * 1000.0 > self.tolerance_um:
            self._fail(cmd, f"ended at {reached:.4f} mm, {abs(reached - position_mm) * 1000:.1f} um from the "
                       f"target {position_mm:.4f} mm (tolerance {self.tolerance_um:g} um)",
                       "the stage may slip or lose steps: check the load and current settings, then home again")
        return reached

    def position_mm(self) -> float:
        """Current position read back from the stage, millimetres."""
        return self._mm(self._steps(self._command("get pos").data, "get pos"))

    def stop(self) -> None:
        """Decelerate to a stop now.

        Raises
        ------
        DeviceError
            The device did not acknowledge the stop.
        """
        self._command("stop")

    # --- internals -----------------------------------------------------------------------
    def _mm(self, steps: int) -> float:
        return steps * self.microstep_um / 1000.0

    def _steps(self, data: str, cmd: str) -> int:
        try:
            return int(data.split()[0])
        except (ValueError, IndexError):
            self._fail(cmd, f"unexpected data {data!r} instead of a position", "check the device and firmware")

    def _warnings(self, clear: bool = False) -> set[str]:
        reply = self._command("warnings clear" if clear else "warnings")
        return set(reply.data.split()[1:])  # "NN F1 F2 ..."

    def _wait_idle(self, cmd: str, target_mm: float | None) -> ZaberReply:
        deadline = time.monotonic() + self.move_timeout_s
        while True:
            reply = self._command("get pos")
            if reply.idle:
                return reply
            if time.monotonic() > deadline:
                where = self._mm(self._steps(reply.data, cmd))
                self._try_stop()
                goal = f"{target_mm:.4f} mm" if target_mm is not None else "the home sensor"
                self._fail(cmd, f"did not reach {goal} within {self.move_timeout_s:g} s (still moving or stalled "
                           f"at {where:.4f} mm; stopped)",
                           "check for an obstruction or a stalled motor, then home again")
            time.sleep(self.poll_s)

    def _try_stop(self) -> None:
        try:
            self._link.query(self._line("stop"))
        except LinkError:
            pass

    def _line(self, cmd: str) -> str:
        return f"/{self.device} {self.axis} {cmd}"

    def _command(self, cmd: str) -> ZaberReply:
        """Send one command, return its reply; rejection or link failure raises DeviceError."""
        if not self._link.is_open:
            raise DeviceError(f"stage on {self.port}: {cmd!r} on a closed port; call open() first")
        line = self._line(cmd)
        try:
            with self._link.lock:
                self._link.discard_input()
                self._link.write_line(line)
                deadline = time.monotonic() + self._link.timeout_s
                while True:
                    text = self._link.read_line(max(deadline - time.monotonic(), 0.001))
                    reply = parse_reply(text)
                    if reply is None:
                        if text.startswith(("#", "!")):
                            continue  # info and alert messages
                        self._fail(cmd, f"unexpected reply {text!r}",
                                   "check the baud rate and that this port carries the Zaber ASCII protocol")
                    if reply.device == self.device and reply.axis in (self.axis, 0):
                        break
        except LinkClosed as exc:
            self._fail(cmd, str(exc), "check the USB/serial cable and the stage controller's power")
        except LinkTimeout:
            # read_line saw only the time left of the deadline; report the configured wait.
            self._fail(cmd, f"no reply within {self._link.timeout_s:g} s",
                       f"check the cable, the controller's power, baud rate ({self._link.baud}) "
                       f"and device number ({self.device})")
        except LinkError as exc:
            self._fail(cmd, str(exc), f"check the cable, the controller's power, baud rate ({self._link.baud}) "
                       f"and device number ({self.device})")
        if not reply.ok:
            reason = reply.data.split()[0] if reply.data else "?"
            if reply.warning == "WR" and cmd.startswith("move"):
                self._fail(cmd, "rejected: the stage is not homed (flag WR)", "call home() first")
            self._fail(cmd, f"rejected with {reason} ({_REJECTIONS.get(reason, 'see the Zaber ASCII manual')})",
                       "check the command's value against the stage's settings")
        return reply

    def _fail(self, cmd: str, what: str, fix: str) -> NoReturn:
        raise DeviceError(f"stage on {self.port}: {cmd!r}: {what}; {fix}")


_FLAG_TEXT = {
    "WR": "no reference position", "WL": "unexpected limit sensor", "FS": "stalled and stopped",
    "FE": "limit sensor fault", "WH": "not homed", "NI": "command interrupted", "NC": "manual control",
}


def _flag_text(flag: str) -> str:
    return _FLAG_TEXT.get(flag, "see the Zaber ASCII manual")
