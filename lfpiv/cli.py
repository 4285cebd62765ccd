"""The ``lfpiv`` command.

Bad input never produces a traceback: it is reported as one line on stderr naming the problem
and the fix, with exit code 2. A device fault exits with 3, after the laser was disarmed. Ctrl-C
exits with 130 after marking an unfinished run aborted.
The subcommands live in :mod:`lfpiv.commands`.
"""

from __future__ import annotations

import argparse
import importlib
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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfpiv`` command; returns the exit code."""
    from acquisition.protocols import DeviceError as HardwareError
    from acquisition.pulse_generator import install_signal_handlers
    from lfcore.device import DeviceError
    from lfcore.rig import RigError
    from lfcore.runstore import RunStoreError

    warnings.filterwarnings("ignore", category=UserWarning, module="zarr")
    # before any thread starts: a kill or a closed terminal disarms a laser armed from any
    # thread (the monitor arms from its recording thread, where no handler can be set)
    install_signal_handlers()
    try:
        args = _build_parser().parse_args(argv)
        return args.func(args)
    except (UsageError, RigError, RunStoreError, DeviceError) as exc:
        print(f"lfpiv: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except HardwareError as exc:
        print(f"lfpiv: device error: {exc}", file=sys.stderr)
        return EXIT_DEVICE
    except KeyboardInterrupt:
        print("lfpiv: interrupted; what was recorded so far is kept", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    raise SystemExit(main())
