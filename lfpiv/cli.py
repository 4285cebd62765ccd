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


def _start_logging(verbose: int, log_file: str | None) -> None:
    """Our packages' loggers on stderr (warnings; -v steps; -vv details) and, with ``log_file``,
    every detail in that file."""
    level = {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    handlers: list[logging.Handler] = []
    err = logging.StreamHandler(sys.stderr)
    err.setLevel(level)
    err.setFormatter(logging.Formatter("lfpiv: %(levelname)s: %(message)s" if verbose else "lfpiv: %(message)s"))
    handlers.append(err)
    if log_file is not None:
        try:
            fh = logging.FileHandler(log_file, encoding="utf-8")
        except OSError as exc:
            raise UsageError(f"--log-file {log_file} cannot be written ({exc.strerror or exc}); give a writable "
                             "path") from None
        fh.setLevel(logging.DEBUG)
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handlers.append(fh)
    for name in _LOGGERS:
        lg = logging.getLogger(name)
        for h in list(lg.handlers):  # a second main() in one process (the demo, tests) starts afresh
            if getattr(h, "_lfpiv", False):
                lg.removeHandler(h)
                h.close()
        lg.setLevel(logging.DEBUG if log_file is not None else level)
        for h in handlers:
            h._lfpiv = True  # type: ignore[attr-defined]
            lg.addHandler(h)
        lg.propagate = False


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

    def on_sigint(signum: int, frame: object) -> None:
        if first and time.monotonic() - first[0] < grace_s:
            return
        first[:] = [time.monotonic()]
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfpiv`` command; returns the exit code."""
    with _one_ctrl_c():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
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
        _start_logging(args.verbose or 0, args.log_file)
        # installed before any thread starts: a kill or a closed terminal disarms a laser armed
        # from any thread (the monitor arms from its recording thread, where no handler can be
        # set), then ends the command as Ctrl-C does (acquire and monitor refine this)
        with signals_call(_interrupted):
            return args.func(args)
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
    except BrokenPipeError:
        # the reader went away (``lfpiv info run.zarr | head``): nothing left to say
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        # a path that cannot be written or read (read-only, missing folder, no space, ...)
        print(f"lfpiv: error: {os_error_line(exc)}", file=sys.stderr)
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
