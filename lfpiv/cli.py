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
import os
import re
import sys
import warnings
from collections.abc import Sequence

from lfpiv import __version__
from lfpiv.commands import COMMANDS
from lfpiv.errors import UsageError

EXIT_USAGE = 2
EXIT_DEVICE = 3
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (no usage dump) raised as UsageError."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="lfpiv", description="Light-field particle image velocimetry: rigs, runs, "
                "synthetic images.")
    p.add_argument("--version", action="version", version=f"lfpiv {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        importlib.import_module(f"lfpiv.commands.{name}").register(sub)
    return p


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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfpiv`` command; returns the exit code."""
    try:
        from acquisition.pulse_generator import signals_call
        from calibration.store import CalibrationStoreError
        from lfcore.device import MemoryBudgetError
        from lfcore.errors import ComputeDeviceError, DeviceError
        from lfcore.rig import RigError
        from lfcore.runstore import RunStoreError
        from lfpiv.formats import FormatError
    except KeyboardInterrupt:  # Ctrl-C while starting: nothing was done yet
        print("lfpiv: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED

    warnings.filterwarnings("ignore", category=UserWarning, module="zarr")
    try:
        args = _build_parser().parse_args(_negative_lists(sys.argv[1:] if argv is None else list(argv)))
        # installed before any thread starts: a kill or a closed terminal disarms a laser armed
        # from any thread (the monitor arms from its recording thread, where no handler can be
        # set), then ends the command as Ctrl-C does (acquire and monitor refine this)
        with signals_call(_interrupted):
            return args.func(args)
    except (UsageError, RigError, RunStoreError, CalibrationStoreError, ComputeDeviceError, MemoryBudgetError,
            FormatError) as exc:
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
        where = f" {exc.filename}" if exc.filename else ""
        print(f"lfpiv: error: cannot use{where}: {exc.strerror or exc}; choose another path or fix its "
              "permissions and free space", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
