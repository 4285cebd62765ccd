"""``lfpiv check``: is a run store whole? Every chunk against what the run says it holds."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("check", help="check that a run store is whole: every chunk there and intact",
                       description="Read every chunk of a run's committed pairs (frames, ids, time stamps), of "
                       "drops and truth, and of the volumes and vectors of the pairs they list as done, checking "
                       "each chunk's checksum; print every problem (a missing or damaged chunk, a wrong data type, "
                       "committed_pairs beyond the arrays, a damaged zarr.json), one line each. Exit code 0 when "
                       "the run is whole, 1 when it is not. Read-only: a run being written may be checked.")
    c.add_argument("run", metavar="RUN", help="run store (a .zarr directory)")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.check import check_run

    problems = check_run(args.run)
    for line in problems:
        print(line)
    if problems:
        print(f"{args.run}: {len(problems)} problem(s); restore the damaged parts from a copy of the run (what was "
              "made from the frames can be made again: lfpiv reconstruct / correlate)")
        return 1
    print(f"{args.run}: whole (every chunk there and intact)")
    return 0
