"""``lfpiv check-camera``: the checks before recording, per camera, against the chapter's ranges."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import add_sim_options, by_camera, camera_names, png_path, sim_lab_options


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("check-camera", help="check seeding, saturation and focus of each camera before recording",
                       description="Grab one double-frame pair from the rig (the laser fires one pulse pair and is "
                       "disarmed, as lfpiv acquire does; on the simulated lab with hardware = \"sim\") and check "
                       "frame A of every camera: the seeding density estimated from the raw image (particles per "
                       "microlens, PPM, for a light-field camera; particles per pixel, PPP, for a pinhole one), the "
                       "share of saturated pixels, the micro-image fill, the histogram and a refocused plane "
                       "through the middle of the volume, each against the range the chapter recommends (0.5 "
                       "PPM; nothing saturated). Nothing is kept. --run or --image check recorded frames instead. "
                       "Exit code 0 when every figure is in its range, 1 when one is not.")
    c.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    c.add_argument("--camera", type=camera_names, default=None, metavar="NAMES",
                   help="only these cameras, comma-separated (default: every one)")
    c.add_argument("--calibration", default=None, metavar="STORE",
                   help="calibration store with the fitted microlens grids (default: the rig file's nominal MLA)")
    c.add_argument("--run", default=None, metavar="RUN", help="check frame A of a recorded run's pair instead")
    c.add_argument("--pair", type=int, default=0, metavar="N", help="the run's pair (default: 0)")
    c.add_argument("--image", action="append", default=[], metavar="CAM=FILE",
                   help="check a raw image file of camera CAM instead (repeatable; CAM= may be left out with one "
                   "camera)")
    c.add_argument("--plot", type=png_path, default=None, metavar="PNG",
                   help="draw the checks (histogram, seeding against its range, refocused plane) into a PNG")
    add_sim_options(c)
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.check_camera import check_cameras
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    images = by_camera(args.image, "--image", [c.name for c in rig.camera]) if args.image else None
    grab = args.run is None and not images
    sim = sim_lab_options(rig, args) if grab else None
    if sim is not None:
        sim["pool_pairs"] = 1
        print("lfpiv: simulated lab: rendering one pair per camera ...", file=sys.stderr)
    checks, notes = check_cameras(rig, run=args.run, pair=args.pair, images=images, calibration=args.calibration,
                                  sim_options=sim, cameras=args.camera, out=args.plot)
    for note in notes:
        print(f"lfpiv: note: {note}")
    ok = True
    for c in checks:
        print(f"camera {c.camera}: background {c.background:.0f} counts, noise {c.noise:.1f} counts")
        for line, good in c.verdicts():
            print(f"  {'ok  ' if good else 'FIX '} {line}")
            ok &= good
    if args.plot:
        print(f"wrote {args.plot}")
    return 0 if ok else 1
