"""A line-oriented serial link shared by the pulse-generator and stage drivers.

Both instruments speak ASCII, one command line out and (at most) one reply line back, so the
transport is the same: write a terminated command, read one ``\\n``-terminated reply within a
timeout, and tell apart the three ways that can fail:

- :class:`LinkTimeout`: nothing came back in time (cable, power, wrong baud or port);
- :class:`LinkGarbled`: bytes came back that are not a complete printable ASCII line (wrong
  baud rate, noise, another device on the port);
- :class:`LinkClosed`: the port itself failed (unplugged USB adapter, closed port).

The drivers turn these into :class:`~acquisition.protocols.DeviceError` messages that name the
instrument and the command. ``port`` is a device path (``/dev/ttyUSB0``, ``COM3``, a
pseudo-terminal) or any pyserial URL (``socket://host:port``, ``loop://``).
"""

from __future__ import annotations

import threading
import time

import serial

try:  # POSIX: pyserial lets termios errors through when a port vanishes under it
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # pragma: no cover - Windows
    _PORT_ERRORS = (serial.SerialException, OSError)

__all__ = ["LinkClosed", "LinkError", "LinkGarbled", "LinkTimeout", "SerialLink"]


class LinkError(Exception):
    """A command/reply exchange that failed; the message says how, without the port."""


class LinkTimeout(LinkError):
    """No reply (or no complete reply) arrived within the timeout."""


class LinkGarbled(LinkError):
    """A reply that is not a printable ASCII line."""


class LinkClosed(LinkError):
    """The port is closed, unplugged or failed at the operating-system level."""


class SerialLink:
    """One serial port carrying an ASCII command/reply protocol.

    Parameters
    ----------
    port
        Device path or pyserial URL.
    baud
        Baud rate (8 data bits, no parity, 1 stop bit, no flow control).
    timeout_s
        Default time allowed for a reply, seconds.
    eol
        Terminator appended to every command line.

    Notes
    -----
    Every exchange holds a re-entrant lock, so threads never interleave their commands, and
    a signal handler that runs in the thread that holds the lock can still send its own.
    Stale input is discarded before each command so that a late reply to an earlier command
    is never taken for the answer to this one.
    """

    def __init__(self, port: str, baud: int, timeout_s: float, *, eol: bytes = b"\r\n") -> None:
        self.port = port
        self.baud = baud
        self.timeout_s = timeout_s
        self.eol = eol
        self.lock = threading.RLock()
        #: Set when :meth:`query` passed over an echo of the command (see ``skip_echo``).
        self.echo_seen = False
        self._ser: serial.Serial | None = None

    @property
    def is_open(self) -> bool:
        return self._ser is not None and self._ser.is_open

    def open(self) -> None:
        """Open the port.

        Raises
        ------
        LinkClosed
            The port does not exist, is busy or cannot be configured.
        """
        if self.is_open:
            return
        kwargs = dict(baudrate=self.baud, timeout=self.timeout_s, write_timeout=self.timeout_s)
        try:
            if "://" in self.port:
                self._ser = serial.serial_for_url(self.port, **kwargs)
            else:
                # exclusive: a second program (or a second driver object) cannot open the same
                # port and interleave commands to a laser trigger.
                self._ser = serial.Serial(self.port, exclusive=True, **kwargs)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._ser = None
            raise LinkClosed(f"cannot open the port ({_short(exc)})") from exc

    def close(self) -> None:
        """Close the port; safe to call in any state."""
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def reopen(self, wait_s: float, poll_s: float = 0.05) -> bool:
        """Close the port and open it again, trying for up to ``wait_s`` seconds.

        A USB serial adapter that was unplugged and plugged back in is a new device behind
        the same name: the old handle stays dead, a new one works. Returns True once the port
        is open again, False if it did not come back in time (it is then closed).
        """
        with self.lock:
            self.close()
            deadline = time.monotonic() + max(0.0, wait_s)
            while True:
                try:
                    self.open()
                    return True
                except LinkClosed:
                    if time.monotonic() >= deadline:
                        return False
                    time.sleep(poll_s)

    def write_line(self, line: str) -> None:
        """Send one command line without waiting for a reply."""
        with self.lock:
            ser = self._require()
            try:
                ser.write(line.encode("ascii") + self.eol)
            except serial.SerialTimeoutException as exc:
                raise LinkTimeout(f"the port did not accept the command within {self.timeout_s:g} s") from exc
            except _PORT_ERRORS as exc:
                raise LinkClosed(f"the port failed while writing ({_short(exc)})") from exc

    def read_line(self, timeout_s: float | None = None) -> str:
        """Read one reply line and return it without its terminator.

        Raises
        ------
        LinkTimeout
            Nothing arrived within the timeout.
        LinkGarbled
            A partial line, or bytes that are not printable ASCII.
        LinkClosed
            The port failed.
        """
        with self.lock:
            ser = self._require()
            timeout = self.timeout_s if timeout_s is None else timeout_s
            try:
                if ser.timeout != timeout:
                    ser.timeout = timeout
                # pyserial's read_until applies the timeout to the whole call.
                buf = ser.read_until(b"\n")
            except _PORT_ERRORS as exc:
                raise LinkClosed(f"the port failed while reading ({_short(exc)})") from exc
            if not buf:
                raise LinkTimeout(f"no reply within {timeout:g} s")
            if not buf.endswith(b"\n"):
                raise LinkGarbled(f"incomplete reply {bytes(buf)[:16]!r} (no line end within {timeout:g} s)")
            text = bytes(buf).rstrip(b"\r\n")
            if not all(32 <= b < 127 for b in text):
                raise LinkGarbled(f"garbled reply {text[:16]!r}")
            return text.decode("ascii")

    def query(self, line: str, timeout_s: float | None = None, *, skip_echo: bool = False) -> str:
        """Discard stale input, send ``line`` and return the reply line.

        With ``skip_echo``, a first line that repeats ``line`` (a device or terminal echoing
        what it receives) is passed over and :attr:`echo_seen` is set.
        """
        with self.lock:
            self.discard_input()
            self.write_line(line)
            reply = self.read_line(timeout_s)
            if skip_echo and reply.strip() == line.strip():
                self.echo_seen = True
                reply = self.read_line(timeout_s)
            return reply

    def discard_input(self) -> None:
        """Throw away whatever the device sent that nobody read yet."""
        with self.lock:
            ser = self._require()
            try:
                ser.reset_input_buffer()
            except _PORT_ERRORS as exc:
                raise LinkClosed(f"the port failed ({_short(exc)})") from exc

    def _require(self) -> serial.Serial:
        if self._ser is None or not self._ser.is_open:
            raise LinkClosed("the port is not open")
        return self._ser


def _short(exc: BaseException) -> str:
    """One line of an exception's message."""
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    # pyserial's words for a port whose other end vanished: "returned no data" from a read,
    # EIO from reconfiguring or writing to a pseudo-terminal or USB adapter that went away.
    if "returned no data" in line or "Input/output error" in line:
        return "device disconnected"
    return line
