"""The ``lfpiv`` command.

Bad input never produces a traceback: it is reported as one line on stderr naming the problem
and the fix, with exit code 2. A device fault exits with 3, after the laser was disarmed. Ctrl-C
exits with 130 after marking an unfinished run aborted.
The subcommands live in :mod:`lfpiv.commands`.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import re
import sys
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from lfpiv import __version__
from lfpiv.commands import COMMANDS, module_of
from lfpiv.errors import UsageError, os_error_line

EXIT_USAGE = 2
EXIT_DEVICE = 3
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (no usage dump) raised as UsageError."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _logging_options(parser: argparse.ArgumentParser, *, top: bool) -> None:
    """``-v/--verbose`` and ``--log-file``, before the command or after it (``top`` False: the
    command's own copy, which leaves the values given before it alone)."""
    keep = {} if top else {"default": argparse.SUPPRESS}
    parser.add_argument("-v", "--verbose", action="count", help="say more on stderr: -v what each step does, "
                        "-vv every detail (devices, files)", **({"default": 0} if top else keep))
    parser.add_argument("--log-file", metavar="PATH", help="also write every detail, time-stamped, to PATH",
                        **({"default": None} if top else keep))


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every (sub)command parser below ``parser``."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for p in dict.fromkeys(action.choices.values()):
                out += [p, *_subparsers(p)]
    return out


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="lfpiv", description="Light-field particle image velocimetry: rigs, runs, "
                "synthetic images.")
    p.add_argument("--version", action="version", version=f"lfpiv {__version__}")
    _logging_options(p, top=True)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        importlib.import_module(f"lfpiv.commands.{module_of(name)}").register(sub)
    for command in _subparsers(p):
        _logging_options(command, top=False)
    return p


#: The packages whose loggers -v and --log-file show.
_LOGGERS = ("lfpiv", "lfcore", "acquisition", "calibration", "realtime", "sim")


class _LogFile(logging.FileHandler):
    """The ``--log-file`` handler: its first failure (a full disk, a file system gone) is kept,
    for one line when the command ends, instead of logging's traceback on stderr, and it stops
    writing there."""

    failed: OSError | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.failed is None:
            super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 - logging's name
        exc = sys.exc_info()[1]
        if self.failed is None:
            self.failed = exc if isinstance(exc, OSError) else OSError(0, f"{type(exc).__name__}: {exc}")

    def finish_line(self) -> OSError | None:
        """Flush what was written; the first failure so far, or None."""
        if self.failed is None:
            try:
                self.flush()
            except OSError as exc:
                self.failed = exc
        return self.failed

    def finish(self) -> OSError | None:
        """Flush and close the file; the first failure of the command's writes, or of these, or None."""
        try:
            self.flush()
            self.close()
        except OSError as exc:
            if self.failed is None:
                self.failed = exc
        return self.failed


class _Stderr(logging.StreamHandler):
    """The stderr handler: a closed or broken stderr drops the messages, silently (there is no one
    left to tell), and never changes what the command does."""

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 - logging's name
        pass


def _inside_store(path: str) -> str | None:
    """The zarr store (the outermost folder holding ``zarr.json``: a run or calibration store) that
    ``path`` lies inside, or is; None when it lies in none."""
    p = Path(os.path.abspath(path))
    found = str(p.parent) if p.name == "zarr.json" else None
    for folder in (p, *p.parents):  # the outermost: the store, not a group of it
        if (folder / "zarr.json").is_file():
            found = str(folder)
    return found


def _start_logging(verbose: int, log_file: str | None, *, command: str = "") -> _LogFile | None:
    """Our packages' loggers on stderr (warnings; -v steps; -vv details) and, with ``log_file``,
    every detail in that file, which starts with a line naming the ``command``; returns the
    file's handler.

    Raises
    ------
    UsageError
        ``log_file`` lies inside a zarr store (appending to its files would make it unreadable),
        or cannot be opened or written (a full disk).
    """
    level = {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    handlers: list[logging.Handler] = []
    err = _Stderr(sys.stderr)
    err.setLevel(level)
    err.setFormatter(logging.Formatter("lfpiv: %(levelname)s: %(message)s" if verbose else "lfpiv: %(message)s"))
    handlers.append(err)
    fh = None
    if log_file is not None:
        store = _inside_store(log_file)
        if store is not None:
            raise UsageError(f"--log-file {log_file} is inside the store {store}, whose files are its data and "
                             f"metadata (writing a log there would damage it); give a path outside it, e.g. "
                             f"{Path(store).parent / (Path(store).stem + '.log')}")
        try:
            fh = _LogFile(log_file, encoding="utf-8")
        except OSError as exc:
            raise UsageError(f"--log-file {log_file} cannot be written ({exc.strerror or exc}); give a writable "
                             "path") from None
        fh.setLevel(logging.DEBUG)
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        # the first line, written now: a log that cannot be written (a full disk) is said before
        # the command changes anything
        fh.emit(logging.LogRecord("lfpiv", logging.INFO, __file__, 0, "lfpiv %s: %s", (__version__, command), None))
        if fh.finish_line() is not None:
            with contextlib.suppress(OSError):  # its buffer flushed once more, failing again
                fh.close()
            raise UsageError(f"--log-file {log_file} cannot be written ({fh.failed.strerror or fh.failed}); give "
                             "a path on a disk with room, or leave it out")
        handlers.append(fh)
    for name in _LOGGERS:
        lg = logging.getLogger(name)
        for h in list(lg.handlers):  # a second main() in one process (the demo, tests) starts afresh
            if getattr(h, "_lfpiv", False):
                lg.removeHandler(h)
                with contextlib.suppress(OSError):  # a log file the last command could not write (said then)
                    h.close()
        lg.setLevel(logging.DEBUG if log_file is not None else level)
        for h in handlers:
            h._lfpiv = True  # type: ignore[attr-defined]
            lg.addHandler(h)
        lg.propagate = False
    return fh


class _Guarded:
    """stdout or stderr, whose reader may go away (``lfpiv check RUN | head -c 1``) or be closed:
    what cannot be written is dropped, the stream's file descriptor then points to /dev/null (so
    native code and the interpreter's last flush write nowhere, without an error), and the command
    goes on to its own end and exit code."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.lost = False

    def _lose(self) -> None:
        self.lost = True
        with contextlib.suppress(Exception):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)

    def write(self, text: str) -> int:
        if not self.lost:
            try:
                return self._stream.write(text)
            except (OSError, ValueError):  # EPIPE, EBADF, or a stream closed under us
                self._lose()
        return len(text)

    def flush(self) -> None:
        if not self.lost:
            try:
                self._stream.flush()
            except (OSError, ValueError):
                self._lose()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _standard_streams() -> None:
    """File descriptors 0, 1 and 2 open (on /dev/null where the caller closed them, ``2>&-``):
    otherwise the next file opened, a store's chunk, would get the number, and whatever native
    code writes to stderr would go into it. ``sys.stdin``, ``sys.stdout`` and ``sys.stderr`` are
    never None (Python's, for a stream closed at its start)."""
    for fd, name, mode in ((0, "stdin", "r"), (1, "stdout", "w"), (2, "stderr", "w")):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
        if getattr(sys, name) is None:
            setattr(sys, name, open(fd, mode, encoding="utf-8", errors="replace", closefd=False))  # noqa: SIM115


def _negative_lists(argv: list[str]) -> list[str]:
    """``--pvr -2,2,10`` as ``--pvr=-2,2,10``: argparse takes a value starting with a minus sign
    for an option unless it is a single number, and would answer "expected one argument"; joined,
    the value reaches the option's own check, which says what is wrong with it."""
    out: list[str] = []
    for tok in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and re.fullmatch(r"-[\d.][^,]*(,[^,]*)+", tok):
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def _interrupted() -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _one_ctrl_c(grace_s: float = 5.0) -> Iterator[None]:
    """Inside, the first Ctrl-C raises KeyboardInterrupt and those that follow it within
    ``grace_s`` seconds are ignored: the stop it began (notes of what is kept, a run marked
    aborted, buffers freed) runs to its end, without a second KeyboardInterrupt in the middle of
    it (people press Ctrl-C several times). One after that raises again, for a stop that hangs.
    Commands that hold signals themselves (acquire, monitor) put their handler inside this one."""
    import signal
    import threading
    import time

    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield  # not ours to change: ignored on purpose (nohup, a background job), or a caller's own
        return
    first: list[float] = []

    def in_finalizer(frame: Any) -> bool:
        # Python drops an exception raised in a __del__ ("Exception ignored"): the stop would be lost
        while frame is not None:
            if frame.f_code.co_name == "__del__":
                return True
            frame = frame.f_back
        return False

    def on_sigint(signum: int, frame: Any) -> None:
        if first and time.monotonic() - first[0] < grace_s:
            return
        if in_finalizer(frame):  # taken again a moment later, outside the finalizer
            threading.Timer(0.02, signal.raise_signal, (signal.SIGINT,)).start()
            return
        first[:] = [time.monotonic()]
        raise KeyboardInterrupt

    def unraisable(info: Any) -> None:
        # a Ctrl-C that still ended inside a finalizer or a weakref callback (one the frames above do
        # not show, e.g. a library's, collected during an import): Python would print it with a traceback
        # and drop it; taken again a moment later instead, as a first one
        if isinstance(info.exc_value, KeyboardInterrupt):
            first.clear()
            threading.Timer(0.02, signal.raise_signal, (signal.SIGINT,)).start()
            return
        previous_hook(info)

    previous_hook = sys.unraisablehook
    sys.unraisablehook = unraisable
    signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.unraisablehook = previous_hook


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfpiv`` command; returns the exit code.

    A reader of stdout that goes away (a pipe closed), or a closed stdout or stderr, changes
    neither what the command does nor its exit code: what cannot be written is dropped.
    """
    _standard_streams()
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Guarded(out), _Guarded(err)
    try:
        with _one_ctrl_c():
            return _main(argv)
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        sys.stdout, sys.stderr = out, err


def _written(args: argparse.Namespace | None) -> str | None:
    """What a command writes, for an I/O error that names no file: its --out, else its store."""
    for name in ("out", "run", "store"):
        value = getattr(args, name, None)
        if isinstance(value, str | os.PathLike):
            return str(value)
    return None


def _main(argv: Sequence[str] | None) -> int:
    args: argparse.Namespace | None = None
    try:
        from acquisition.pulse_generator import signals_call
        from calibration.store import CalibrationStoreError
        from lfcore.device import MemoryBudgetError
        from lfcore.errors import ComputeDeviceError, DeviceError
        from lfcore.rig import NotLightFieldError, RigError
        from lfcore.runstore import RunStoreError
        from lfpiv.formats import FormatError
    except KeyboardInterrupt:  # Ctrl-C while starting: nothing was done yet
        print("lfpiv: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED

    warnings.filterwarnings("ignore", category=UserWarning, module="zarr")
    try:
        args = _build_parser().parse_args(_negative_lists(sys.argv[1:] if argv is None else list(argv)))
        log = _start_logging(args.verbose or 0, args.log_file,
                             command=" ".join(sys.argv[1:] if argv is None else map(str, argv)))
        # installed before any thread starts: a kill or a closed terminal disarms a laser armed
        # from any thread (the monitor arms from its recording thread, where no handler can be
        # set), then ends the command as Ctrl-C does (acquire and monitor refine this)
        try:
            with signals_call(_interrupted):
                code = args.func(args)
        finally:
            failed = log.finish() if log is not None else None
        if failed is not None:
            why = (f"the --log-file {args.log_file} could not be written ({failed.strerror or failed}); the command "
                   f"itself ended {'without error' if code == 0 else f'with exit code {code}'}; give --log-file a "
                   "path on a disk with room, or leave it out")
            if code == 0:
                raise UsageError(why)
            print(f"lfpiv: warning: {why}", file=sys.stderr)
        return code
    except (UsageError, RigError, RunStoreError, CalibrationStoreError, ComputeDeviceError, MemoryBudgetError,
            FormatError, NotLightFieldError) as exc:
        print(f"lfpiv: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except DeviceError as exc:  # a hardware fault (a compute device that is not here is the user's choice, above)
        print(f"lfpiv: device error: {exc}", file=sys.stderr)
        return EXIT_DEVICE
    except KeyboardInterrupt:
        print("lfpiv: interrupted; what was recorded so far is kept", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError as exc:
        # what the memory checks did not foresee (NumPy says how much it wanted)
        print(f"lfpiv: error: out of memory{f' ({exc})' if str(exc) else ''}; make the job smaller (fewer pairs, a "
              "coarser --pvr, a smaller volume or sensor, a lower density) or run it on a machine with more memory",
              file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:
        # a path that cannot be written or read (read-only, missing folder, no space, ...); an
        # error naming no file (zarr's writes on a full disk) names what the command writes
        print(f"lfpiv: error: {os_error_line(exc, path=_written(args))}", file=sys.stderr)
        return EXIT_USAGE


def run() -> None:
    """The ``lfpiv`` program: :func:`main`, then exit with its code. Ctrl-Cs or kills that come
    once the code is decided (a second or third Ctrl-C while the interpreter shuts down) no
    longer change it: the command has said how it ended, and the laser was disarmed."""
    code = main()
    import signal

    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            with contextlib.suppress(ValueError, OSError):  # not in the main thread
                signal.signal(sig, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    run()
