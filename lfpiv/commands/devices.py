"""``lfpiv devices``: list the cameras, pulse generator and stage the rig can reach."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("devices", help="list the cameras, pulse generator and stage of a rig",
                       description="Look for every device the rig file names and print what answers: the "
                       "GenICam cameras the GenTL producers see (with serial numbers), the pulse generator's "
                       "identification and the stage's position. Nothing is armed or moved. With hardware = "
                       "\"sim\" it lists the simulated lab.")
    s.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    s.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.devices import list_devices
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    ok = True
    for line, found in list_devices(rig):
        print(line)
        ok &= found
    return 0 if ok else 3
