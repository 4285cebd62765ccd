"""``lfpiv info``: describe a run store, or a calibration store."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    i = sub.add_parser("info", help="describe a run store or a calibration store",
                       description="Print a run's cameras, pairs, flow and state; given a calibration store, "
                       "what it holds (as 'lfpiv calibrate report').")
    i.add_argument("run", metavar="STORE", help="run store or calibration store (a .zarr directory)")
    i.add_argument("--check", action="store_true",
                   help="also check every chunk of a run (as 'lfpiv check'); exit code 1 if anything is damaged")
    i.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.info import describe

    for line in describe(args.run):
        print(line)
    if args.check:
        from lfpiv.commands.check import run as check

        return check(args)
    return 0
