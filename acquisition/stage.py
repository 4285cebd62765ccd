"""Driver for a Zaber motorised stage on the Zaber ASCII protocol (one axis, millimetres).

The stage carries the calibration target along the optical axis; the calibration runner moves
it through the 51 target planes with :meth:`ZaberStage.move_to`.

Protocol. A command is one line ``/<device> <axis> [<id>] <command>`` ended by LF; the device
answers every command addressed to it with ``@<dd> <a> [<id>] <flag> <status> <warning> <data>``
ended by CR LF, for example::

    /1 1 move abs 125000        ->  @01 1 OK BUSY -- 0
    /1 1 get pos                ->  @01 1 OK IDLE -- 125000
    /1 1 move abs 5             ->  @01 1 RJ IDLE WR BADDATA    (no reference position)
    /1 1 warnings               ->  @01 1 OK IDLE WR 01 WR

``<id>`` is an optional message id, 0-99, that the device copies into its reply; with
``message_ids=True`` (what :func:`stage_for` builds) every command carries the next id and only
the reply with that id is taken as its answer, so a late reply to an earlier command (after a
timeout, say) can never be mistaken for the answer to this one. ``flag`` is ``OK`` or ``RJ``
(rejected; ``data`` then gives the reason: BADDATA, BADCOMMAND,
BADAXIS, STATUSBUSY, PARKED, ...), ``status`` is ``BUSY`` while the axis moves and ``IDLE``
otherwise, ``warning`` is the highest-priority active warning flag or ``--``: ``WR`` no
reference position (not homed), ``WL`` a limit sensor stopped a move, ``FS`` stalled and
stopped, ``NI`` a move was interrupted by another command. A reply too long for one packet
(``comm.packet.size.max``) ends in a backslash and goes on in info messages ``#<dd> <a> [<id>] cont
...``, which are joined. Alerts (``!<dd> <a> <status> <warning>``, sent when ``comm.alert`` is 1)
are collected in :attr:`ZaberStage.alerts` and logged; other info lines are skipped.

Units. Positions are in native steps (microsteps). One microstep is the product's full step
divided by the axis' ``resolution`` (microsteps per full step, 64 by default), so
:meth:`ZaberStage.open` reads ``deviceid`` (and ``peripheral.id`` on a controller) and
``resolution`` from the device and takes the full step from :data:`ZABER_PRODUCTS`. A product
not in that table needs the rig's ``[stage] microstep_um`` (the size of one microstep as the
device is set up); for a known product that key is optional, and one that disagrees with the
device is reported in a warning and not used.

Motion is polled: after ``move abs`` the driver reads ``get pos`` until the axis reports
``IDLE``, then reads the full ``warnings`` list and checks the position against the target.

Checksums. A message may end in ``:XX``, a longitudinal redundancy check: the 8-bit sum of
the bytes after the leading ``/``, ``@``, ``#`` or ``!`` up to (not including) the ``:``,
negated (two's complement) and written as two hex digits. Devices append it to their replies
when the device setting ``comm.checksum`` is 1; a reply whose checksum does not match is
corrupt and is never used. With ``send_checksums=True`` the driver also appends one to its
commands so the device can refuse a corrupted command instead of carrying it out.

Retries. Every command this driver sends is safe to repeat: queries (``get``, ``warnings``),
``stop``, ``home`` (homing again just restarts it) and ``move abs`` (an absolute target, so a
second copy only restarts the same move; the device notes it with the ``NI`` notice, which is
ignored). So a command whose reply is corrupt is sent again, and so is one the device rejects
with ``AGAIN`` (it asks for the command to be repeated, e.g. while its command buffer is busy),
at most ``retries`` more times, ``retry_pause_s`` apart. ``warnings clear`` is repeated too:
the repeat may list fewer flags, which is why the flags are always read again afterwards.

Warning flags. The reply's warning field shows only the highest-priority active flag, so a
fatal flag can hide under a harmless one; after every move and homing the driver reads the
whole list (``warnings`` -> ``NN F1 F2 ...``). Faults (``F*``) and warnings (``W*``) fail the
move, except the health warnings ``WV`` (supply voltage out of range) and ``WT`` (temperature
high), which do not make a finished move wrong and are logged. Notices (``N*``: ``NI`` a move
was interrupted, e.g. by our own stop, ``NC`` manual control, ...) are ignored; the readback
against ``tolerance_um`` still catches a move that ended in the wrong place.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, NoReturn

from .protocols import DeviceError
from .serial_link import LinkClosed, LinkError, LinkGarbled, LinkTimeout, SerialLink

if TYPE_CHECKING:
    from lfcore.rig import StageConfig

    from .protocols import Stage

__all__ = ["ZABER_CONTROLLERS", "ZABER_PRODUCTS", "CorruptReply", "ZaberIdentity", "ZaberProduct", "ZaberReply",
           "ZaberStage", "checksum", "parse_reply", "stage_for", "verified"]

log = logging.getLogger(__name__)

_REPLY = re.compile(r"@(\d{2}) (\d+)(?: (\d{2}))? (OK|RJ) (IDLE|BUSY) (\S\S) ?(.*?)")
#: An info message that continues a reply split into packets: ``#01 1 [12] cont ...``.
_CONT = re.compile(r"#(\d{2}) (\d+)(?: (\d{2}))? cont ?(.*?)")
#: An alert: ``!01 1 IDLE --``.
_ALERT = re.compile(r"!(\d{2}) (\d+) (IDLE|BUSY) (\S\S)(?: (.*))?")
#: A message ending in a checksum: marker, body, two hex digits.
_CHECKED = re.compile(r"([/@#!])(.*):([0-9A-Fa-f]{2})")

#: Warnings that do not make a finished move wrong (logged, not fatal).
_HEALTH_WARNINGS = frozenset({"WV", "WT"})

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
    "BADMESSAGEID": "the message id is not 0-99",
    "BADSPLIT": "the command was split across packets wrongly",
    "NOTSUPPORTED": "the device does not support this command",
}


class CorruptReply(ValueError):
    """A message whose checksum does not match its content (corrupted on the line)."""


def checksum(body: str) -> str:
    """Checksum of a Zaber ASCII message, as two uppercase hex digits.

    Parameters
    ----------
    body
        The message between its leading ``/``, ``@``, ``#`` or ``!`` and the ``:`` that
        introduces the checksum, e.g. ``"01 1 OK IDLE -- 0"``.

    Returns
    -------
    str
        The 8-bit two's complement of the sum of the bytes of ``body``, so that the bytes and
        the checksum together sum to 0 modulo 256.
    """
    return f"{-sum(body.encode('ascii')) & 0xFF:02X}"


def verified(line: str) -> str:
    """``line`` (a command or a reply) without its checksum; unchanged if it has none.

    Raises
    ------
    CorruptReply
        The line ends in a checksum (``:XX``) that does not match its content.
    """
    m = _CHECKED.fullmatch(line)
    if m is None:
        return line
    marker, body, given = m.groups()
    if checksum(body) != given.upper():
        raise CorruptReply(f"reply {line!r} fails its checksum (computed {checksum(body)})")
    return marker + body


@dataclass(frozen=True)
class ZaberReply:
    """A parsed ASCII reply line."""

    device: int
    axis: int
    flag: str       # "OK" or "RJ"
    status: str     # "IDLE" or "BUSY"
    warning: str    # highest-priority warning flag, "--" if none
    data: str
    message_id: int | None = None  # the id of the command answered, where it carried one

    @property
    def ok(self) -> bool:
        return self.flag == "OK"

    @property
    def idle(self) -> bool:
        return self.status == "IDLE"


def parse_reply(line: str) -> ZaberReply | None:
    """Parse one reply line, verifying its checksum if it carries one.

    Parameters
    ----------
    line
        One line from the device, without or with its terminator.

    Returns
    -------
    ZaberReply or None
        The reply; None if the line is not a reply (an info ``#`` or alert ``!`` line, noise).

    Raises
    ------
    CorruptReply
        The line ends in a checksum (``:XX``) that does not match its content.
    """
    m = _REPLY.fullmatch(verified(line.strip()))
    if not m:
        return None
    dev, axis, mid, flag, status, warn, data = m.groups()
    return ZaberReply(int(dev), int(axis), flag, status, warn, data.strip(), None if mid is None else int(mid))


@dataclass(frozen=True)
class ZaberProduct:
    """A Zaber motion product: what turns its microsteps into millimetres.

    Attributes
    ----------
    name
        Product name.
    full_step_um
        Carriage travel of one full motor step, micrometres; one microstep is this divided by
        the axis' ``resolution``.
    travel_mm
        Travel between the home sensor and the far end.
    integrated
        True for a device with its own controller (found by ``deviceid``), False for a
        peripheral on a controller (found by the axis' ``peripheral.id``).
    """

    name: str
    full_step_um: float
    travel_mm: float
    integrated: bool = True


#: Products by ``deviceid`` (integrated devices) or ``peripheral.id`` (peripherals on a
#: controller). The entries are the products the simulated lab emulates, under ids no real
#: product uses; add a lab's stage here from the Zaber device database (Zaber Launcher shows
#: its deviceid, or peripheral id, and its microstep size at resolution 64) or set the rig's
#: ``[stage] microstep_um``.
ZABER_PRODUCTS: dict[int, ZaberProduct] = {
    59901: ZaberProduct("EMU-LS050 (emulated linear stage, 6.4 um full step)", 6.4, 50.0),
    59902: ZaberProduct("EMU-LSM050 (emulated lead-screw stage, 3.048 um full step)", 3.048, 50.0),
    69901: ZaberProduct("EMU-LRQ100 (emulated peripheral stage, 6.4 um full step)", 6.4, 100.0, integrated=False),
}

#: Controllers by ``deviceid``: their axes are peripherals, found by ``peripheral.id``.
ZABER_CONTROLLERS: dict[int, str] = {59950: "EMU-MCC2 (emulated two-axis controller)"}


@dataclass(frozen=True)
class ZaberIdentity:
    """What :meth:`ZaberStage.open` read from the device."""

    deviceid: int
    name: str
    serial: str
    firmware: str
    axes: int
    peripheral_id: int
    resolution: int
    microstep_um: float

    def describe(self) -> str:
        """``EMU-LS050 (...) deviceid 59901, serial 1234, firmware 7.38``."""
        periph = f", peripheral {self.peripheral_id}" if self.peripheral_id else ""
        return f"{self.name} deviceid {self.deviceid}{periph}, serial {self.serial}, firmware {self.firmware}"


class ZaberStage:
    """A Zaber linear stage, one axis, positions in millimetres from the home sensor.

    Parameters
    ----------
    port
        Serial device (``/dev/ttyUSB0``, ``COM4``) or pyserial URL.
    baud
        Baud rate (115200 for the ASCII protocol by default).
    device, axis
        Address on the daisy chain and axis number.
    timeout_s
        Time allowed for each reply, seconds.
    microstep_um
        Size of one native step as the device is set up, micrometres. Needed only for a
        product missing from :data:`ZABER_PRODUCTS`; for a known product the size follows from
        the device's ``resolution``, and a value that disagrees is reported and not used.
    move_timeout_s
        Longest a move or homing may take before it counts as stalled.
    tolerance_um
        Largest accepted difference between a target and the position read back.
    poll_s
        Interval between status polls while the axis moves.
    retries
        How many more times a command is sent when its reply is corrupt (bad checksum, a stray
        byte) or the device rejects it with ``AGAIN``.
    retry_pause_s
        Pause before each repeat, seconds.
    send_checksums
        Append a checksum to every command (the device then refuses corrupted commands).
    message_ids
        Put a message id (0-99, cycling) on every command and take only the reply with that id.
    reconnect_s
        After the port fails (an unplugged USB adapter), how long to try opening it again to
        stop the stage before reporting the failure.
    """

    def __init__(self, port: str, baud: int = 115200, device: int = 1, axis: int = 1, timeout_s: float = 0.5,
                 microstep_um: float | None = None, *, move_timeout_s: float = 60.0, tolerance_um: float = 1.0,
                 poll_s: float = 0.02, retries: int = 3, retry_pause_s: float = 0.05,
                 send_checksums: bool = False, message_ids: bool = False, reconnect_s: float = 0.5) -> None:
        if microstep_um is not None and microstep_um <= 0:
            raise ValueError("microstep_um must be positive")
        if retries < 0:
            raise ValueError("retries must be 0 or more")
        self._link = SerialLink(port, baud, timeout_s, eol=b"\n")
        self.device, self.axis = device, axis
        self._given_microstep_um = microstep_um
        self.microstep_um = microstep_um if microstep_um is not None else 0.1
        self.move_timeout_s = move_timeout_s
        self.tolerance_um = tolerance_um
        self.poll_s = poll_s
        self.retries = retries
        self.retry_pause_s = retry_pause_s
        self.send_checksums = send_checksums
        self.message_ids = message_ids
        self.reconnect_s = reconnect_s
        self._travel_mm: tuple[float, float] | None = None
        self._identity: ZaberIdentity | None = None
        self._next_id = 0
        self._echo_noted = False
        #: Alerts the device sent (``!01 1 IDLE --``), oldest first, at most 100.
        self.alerts: deque[str] = deque(maxlen=100)

    @property
    def port(self) -> str:
        return self._link.port

    @property
    def travel_mm(self) -> tuple[float, float]:
        """(min, max) positions the device accepts, read at :meth:`open`."""
        if self._travel_mm is None:
            raise DeviceError(f"stage on {self.port}: not open; call open() first")
        return self._travel_mm

    @property
    def identity(self) -> ZaberIdentity:
        """The product, serial number, firmware and microstep size read at :meth:`open`."""
        if self._identity is None:
            raise DeviceError(f"stage on {self.port}: not open; call open() first")
        return self._identity

    def describe(self) -> str:
        """One line naming the stage by its ``deviceid`` (what ``lfpiv devices`` prints)."""
        ident = self.identity
        lo, hi = self.travel_mm
        return (f"Zaber {ident.describe()}, device {self.device} axis {self.axis}, microstep {ident.microstep_um:g} um "
                f"(resolution {ident.resolution}), travel {lo:g}..{hi:g} mm")

    # --- life cycle ----------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, identify the device and read its resolution and travel limits.

        Raises
        ------
        DeviceError
            The port cannot be opened, the device does not answer as a Zaber device, has no
            such axis, or is a product whose microstep size is unknown and the rig gives none.
        """
        if self._link.is_open:
            return
        try:
            self._link.open()
        except LinkError as exc:
            raise DeviceError(f"stage on {self.port}: {exc}; check the port name and that no other program "
                              "(e.g. Zaber Launcher) holds it") from None
        try:
            self._identity = self._identify()
            self.microstep_um = self._identity.microstep_um
            lo = self._steps(self._command("get limit.min").data, "get limit.min")
            hi = self._steps(self._command("get limit.max").data, "get limit.max")
        except DeviceError:
            self._link.close()
            raise
        self._travel_mm = (self._mm(lo), self._mm(hi))

    def _identify(self) -> ZaberIdentity:
        deviceid = self._int(self._command("get deviceid", axis=0).data, "get deviceid")
        serial = self._command("get system.serial", axis=0).data
        firmware = self._command("get version", axis=0).data
        axes = self._int(self._command("get system.axiscount", axis=0).data, "get system.axiscount")
        if not 1 <= self.axis <= axes:
            self._fail("get system.axiscount", f"device {self.device} has {axes} axis(es), not axis {self.axis}",
                       "correct stage.axis in the rig file")
        peripheral = 0
        if deviceid in ZABER_CONTROLLERS:
            peripheral = self._int(self._command("get peripheral.id").data, "get peripheral.id")
        resolution = self._int(self._command("get resolution").data, "get resolution")
        product = ZABER_PRODUCTS.get(peripheral or deviceid)
        given = self._given_microstep_um
        if product is not None:
            microstep = product.full_step_um / resolution
            name = product.name
            if given is not None and not math.isclose(given, microstep, rel_tol=1e-6):
                log.warning("stage on %s: [stage] microstep_um = %g um, but the %s at resolution %d has %g um "
                            "microsteps; using %g um (remove microstep_um from the rig file)", self.port, given,
                            name, resolution, microstep, microstep)
        else:
            what = f"peripheral id {peripheral}" if peripheral else f"deviceid {deviceid}"
            name = ZABER_CONTROLLERS.get(deviceid, f"product {what}")
            if given is None:
                self._fail("get deviceid", f"{what} is not in lfpiv's Zaber product table, so its microstep size "
                           "is unknown", "set [stage] microstep_um in the rig file (Zaber Launcher shows it)")
            microstep = given
        return ZaberIdentity(deviceid, name, serial, firmware, axes, peripheral, resolution, microstep)

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
            The command is rejected, the device stops answering, homing does not finish
            within ``move_timeout_s`` (the stage is then stopped), or a fault or warning flag
            is active afterwards (``WR``: still no reference position).
        """
        self._command("warnings clear")
        self._command("home")
        reply = self._wait_idle("home", None)
        fatal = self._fatal_flags(self._warnings("home"))
        if fatal:
            where = self._mm(self._steps(reply.data, "home"))
            self._fail("home", f"finished at {where:.4f} mm with {_describe(fatal)}",
                       "check the home sensor and that nothing blocks the carriage, then home again")

    def move_to(self, position_mm: float) -> float:
        """Move to an absolute position, block until idle and return the position read back.

        Raises
        ------
        DeviceError
            Target outside the travel, stage not homed, a fault still active before the move,
            command rejected, a fault or warning flag after the move (limit sensor, stall, a
            reset that lost the reference position, ...), no arrival within ``move_timeout_s``
            (the stage is stopped), or readback further than ``tolerance_um`` from the target.
        """
        lo, hi = self.travel_mm
        steps = round(position_mm * 1000.0 / self.microstep_um)
        cmd = f"move abs {steps}"
        if not lo - 1e-9 <= position_mm <= hi + 1e-9:
            raise DeviceError(f"stage on {self.port}: {cmd!r}: target {position_mm:g} mm is outside the travel "
                              f"[{lo:g}, {hi:g}] mm; choose a position inside it")
        # 'warnings clear' resets the latched flags (WL, FS, NI...) so that the flags after this
        # move are this move's; what is still set after it (WR until homed, a driver fault) is
        # a standing condition that makes the move pointless.
        self._command("warnings clear")
        standing = self._warnings(cmd)
        if "WR" in standing:
            raise DeviceError(f"stage on {self.port}: {cmd!r}: the stage is not homed (flag WR, no reference "
                              "position); call home() first")
        fatal = self._fatal_flags(standing)
        if fatal:
            self._fail(cmd, f"refused to move: {_describe(fatal)} still active after 'warnings clear'",
                       "check its cause in the Zaber manual's warning-flag table, power-cycle the "
                       "controller if needed, then home again")
        self._command(cmd)
        reply = self._wait_idle(cmd, position_mm)
        reached = self._mm(self._steps(reply.data, cmd))
        flags = self._warnings(cmd)
        if "WR" in flags:
            self._fail(cmd, f"the stage lost its reference position during the move (flag WR: it was reset or "
                       f"power-cycled; it reads {reached:.4f} mm from where it restarted)",
                       "check the controller's power supply and cable, then home again")
        fatal = self._fatal_flags(flags)
        if fatal:
            self._fail(cmd, f"stopped at {reached:.4f} mm with {_describe(fatal)}",
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
        """Decelerate to a stop now and wait until the axis is at rest.

        Raises
        ------
        DeviceError
            The device did not acknowledge the stop, or is still moving ``move_timeout_s``
            later.
        """
        self._command("stop")
        deadline = time.monotonic() + self.move_timeout_s
        while not self._command("").idle:
            if time.monotonic() > deadline:
                self._fail("stop", f"still moving {self.move_timeout_s:g} s after the stop",
                           "check the stage; press its stop button or switch it off")
            time.sleep(self.poll_s)

    def warnings(self) -> list[tuple[str, str]]:
        """Every active warning flag with its meaning, highest priority first."""
        return [(f, _flag_text(f)) for f in self._warnings("warnings")]

    # --- internals -----------------------------------------------------------------------
    def _mm(self, steps: int) -> float:
        return steps * self.microstep_um / 1000.0

    def _steps(self, data: str, cmd: str) -> int:
        try:
            return int(data.split()[0])
        except (ValueError, IndexError):
            self._fail(cmd, f"unexpected data {data!r} instead of a position", "check the device and firmware")

    def _int(self, data: str, cmd: str) -> int:
        try:
            return int(data.split()[0])
        except (ValueError, IndexError):
            self._fail(cmd, f"unexpected data {data!r} instead of a number", "check the device and firmware")

    def _warnings(self, during: str) -> list[str]:
        """Every active warning flag, highest priority first (``warnings`` -> ``NN F1 F2 ...``)."""
        reply = self._command("warnings")
        words = reply.data.split()
        try:
            count = int(words[0])
        except (ValueError, IndexError):
            count = -1
        flags = words[1:]
        if count != len(flags) or not all(len(f) == 2 and f.isalpha() and f.isupper() for f in flags):
            self._fail(during, f"unexpected 'warnings' data {reply.data!r} (want a count and the flags)",
                       "check the device and firmware")
        return flags

    def _fatal_flags(self, flags: list[str]) -> list[str]:
        """The flags that make a move or homing fail; health warnings are logged, notices ignored."""
        fatal = [f for f in flags if f[0] == "F" or (f[0] == "W" and f not in _HEALTH_WARNINGS)]
        for f in flags:
            if f in _HEALTH_WARNINGS:
                log.warning("stage on %s: warning flag %s (%s)", self.port, f, _flag_text(f))
        return fatal

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
        """Stop the axis and wait briefly until it is at rest; never raises."""
        try:
            reply = self._exchange("stop", self.axis)
            deadline = time.monotonic() + 2.0
            while reply is not None and not reply.idle and time.monotonic() < deadline:
                time.sleep(self.poll_s)
                reply = self._exchange("", self.axis)
        except (DeviceError, LinkError):
            pass

    def _line(self, cmd: str, axis: int, msg_id: int | None) -> str:
        mid = "" if msg_id is None else f" {msg_id}"
        body = f"{self.device} {axis}{mid} {cmd}".rstrip()
        return f"/{body}:{checksum(body)}" if self.send_checksums else f"/{body}"

    def _command(self, cmd: str, axis: int | None = None) -> ZaberReply:
        """Send one command and return its reply, repeating it on a corrupt reply or AGAIN.

        A rejection, a link failure or running out of repeats raises DeviceError.
        """
        if not self._link.is_open:
            raise DeviceError(f"stage on {self.port}: {cmd!r} on a closed port; call open() first")
        axis = self.axis if axis is None else axis
        garbled = ""
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(self.retry_pause_s)
            try:
                reply = self._exchange(cmd, axis)
            except LinkGarbled as exc:
                reply, garbled = None, str(exc)  # a stray byte or noise: safe to send again
                log.warning("stage on %s: %r: %s; sending it again", self.port, cmd, exc)
            if reply is None:
                continue  # corrupt reply: the command is safe to send again (module docstring)
            if not reply.ok and reply.data.split()[:1] == ["AGAIN"]:
                continue  # the device asks for the command again
            break
        else:
            if reply is None and garbled:
                self._fail(cmd, f"{garbled} ({self.retries + 1} replies in a row unreadable)",
                           f"check the cable, the controller's power, baud rate ({self._link.baud}) "
                           f"and device number ({self.device})")
            if reply is None:
                self._fail(cmd, f"{self.retries + 1} replies in a row failed their checksum (corrupted on the line)",
                           "check the cable, its shielding and grounding, and the baud rate")
            self._fail(cmd, f"rejected with AGAIN ({_REJECTIONS['AGAIN']}) {self.retries + 1} times in a row",
                       "check that no other program or controller sends commands to the stage, then retry")
        if not reply.ok:
            reason = reply.data.split()[0] if reply.data else "?"
            if reply.warning == "WR" and cmd.startswith("move"):
                self._fail(cmd, "rejected: the stage is not homed (flag WR)", "call home() first")
            self._fail(cmd, f"rejected with {reason} ({_REJECTIONS.get(reason, 'see the Zaber ASCII manual')})",
                       "check the command's value against the stage's settings")
        return reply

    def _take_id(self) -> int | None:
        if not self.message_ids:
            return None
        msg_id, self._next_id = self._next_id, (self._next_id + 1) % 100
        return msg_id

    def _exchange(self, cmd: str, axis: int) -> ZaberReply | None:
        """Send ``cmd`` once and read its reply; None if the reply is corrupt (bad checksum).

        Raises LinkGarbled for an unreadable line (the caller may repeat the command) and
        DeviceError for everything else.
        """
        msg_id = self._take_id()
        line = self._line(cmd, axis, msg_id)
        try:
            with self._link.lock:
                self._link.discard_input()
                self._link.write_line(line)
                deadline = time.monotonic() + self._link.timeout_s
                while True:
                    text = self._link.read_line(max(deadline - time.monotonic(), 0.001))
                    try:
                        reply = parse_reply(text)
                    except CorruptReply as exc:
                        # Whose reply it was cannot be trusted either: count it as ours.
                        log.warning("stage on %s: %r: %s; sending it again", self.port, cmd, exc)
                        return None
                    if reply is None:
                        if self._aside(text, line):
                            continue
                        self._fail(cmd, f"unexpected reply {text!r}",
                                   "check the baud rate and that this port carries the Zaber ASCII protocol")
                    if reply.device != self.device or reply.axis not in (axis, 0):
                        continue  # another device's or axis' reply
                    if msg_id is not None and reply.message_id != msg_id:
                        continue  # a late reply to an earlier command
                    if reply.data.endswith("\\"):
                        reply = self._continued(reply, deadline)
                    return reply
        except LinkClosed as exc:
            self._lost_link(cmd, str(exc))
        except LinkTimeout:
            # read_line saw only the time left of the deadline; report the configured wait.
            self._fail(cmd, f"no reply within {self._link.timeout_s:g} s",
                       f"check the cable, the controller's power, baud rate ({self._link.baud}) "
                       f"and device number ({self.device})")

    def _aside(self, text: str, sent: str) -> bool:
        """Whether a line that is not a reply can be passed over: an alert (kept), an info
        message, or our own command echoed back (a terminal setting or a loopback adapter)."""
        if text.startswith("!"):
            try:
                alert = verified(text)
            except CorruptReply:
                return True
            if _ALERT.fullmatch(alert):
                self.alerts.append(alert)
                log.info("stage on %s: alert %s", self.port, alert)
            return True
        if text.startswith("#"):
            return True
        if text.startswith("/") and text.strip() == sent:
            if not self._echo_noted:
                self._echo_noted = True
                log.warning("stage on %s: the port echoes every command back (serial echo on, or a loopback "
                            "adapter); the echoes are skipped", self.port)
            return True
        return False

    def _continued(self, reply: ZaberReply, deadline: float) -> ZaberReply:
        """Join the ``#.. cont`` packets that continue a reply ending in a backslash."""
        data = reply.data
        while data.endswith("\\"):
            text = self._link.read_line(max(deadline - time.monotonic(), 0.001))
            m = _CONT.fullmatch(verified(text.strip()))
            if m is None:
                if self._aside(text, ""):
                    continue
                raise LinkGarbled(f"reply continued by {text[:24]!r}, not a 'cont' packet")
            data = data[:-1].rstrip() + " " + m.group(4).strip()
        return dataclasses.replace(reply, data=data.strip())

    def _lost_link(self, cmd: str, what: str) -> NoReturn:
        """The port failed: try to get it back (a re-plugged adapter) to stop the stage, then raise."""
        back = self._link.reopen(self.reconnect_s)
        if back:
            self._try_stop()
            self._fail(cmd, f"{what}; the port came back and the stage was told to stop",
                       "check the USB/serial cable, then home the stage again and retry")
        self._fail(cmd, what, "check the USB/serial cable and the stage controller's power")

    def _fail(self, cmd: str, what: str, fix: str) -> NoReturn:
        raise DeviceError(f"stage on {self.port}: {cmd!r}: {what}; {fix}")


#: Zaber warning flags: faults F*, warnings W*, notices N*.
_FLAG_TEXT = {
    "FF": "critical system error", "FN": "peripheral not supported", "FZ": "peripheral inactive",
    "FH": "hardware emergency stop, driver disabled", "FV": "over- or undervoltage, driver disabled",
    "FO": "driver disabled", "FC": "current inrush error", "FM": "motor temperature error",
    "FD": "driver temperature/current error", "FQ": "encoder error", "FS": "stalled and stopped",
    "FB": "stream bounds error", "FP": "interpolated path deviation", "FE": "limit error",
    "FT": "excessive twist",
    "WL": "unexpected limit trigger", "WV": "voltage out of range", "WT": "temperature high",
    "WS": "stalled with recovery", "WM": "displaced when stationary", "WP": "invalid calibration type",
    "WR": "no reference position", "WH": "device not homed",
    "NC": "manual control", "NI": "movement interrupted", "ND": "stream discontinuity", "NR": "value rounded",
}


def _flag_text(flag: str) -> str:
    return _FLAG_TEXT.get(flag, "see the Zaber ASCII manual")


def _describe(flags: list[str]) -> str:
    """``flag WL (unexpected limit trigger)`` or ``flags FS (...), WL (...)``."""
    items = ", ".join(f"{f} ({_flag_text(f)})" for f in flags)
    return f"flag{'s' if len(flags) > 1 else ''} {items}"


def stage_for(port: str, config: StageConfig) -> Stage:
    """The stage driver for ``port`` with a rig's ``[stage]`` settings (baud rate, Zaber
    address), not yet open: the one place callers learn which driver that is.

    The driver puts message ids on its commands and reads the microstep size from the device;
    the rig's ``microstep_um`` is passed on only where the rig file sets it (for a product
    missing from :data:`ZABER_PRODUCTS`).
    """
    given = config.microstep_um if "microstep_um" in config.model_fields_set else None
    return ZaberStage(port, baud=config.baud, device=config.device, axis=config.axis, microstep_um=given,
                      message_ids=True)
