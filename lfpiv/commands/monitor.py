"""``lfpiv monitor``: arm the rig, record every pair and watch the newest reconstructed live."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from lfpiv.commands import (
    add_device,
    add_sim_options,
    check_pvr,
    iterations,
    png_path,
    positive_float,
    positive_int,
    ring_slots,
    run_flat_fields,
    sim_lab_options,
    warn_optics,
    xyz_triple,
)
from lfpiv.commands.reconstruct import add_projector
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("monitor", help="arm the rig, record, and watch the newest pair reconstructed live",
                       description="Arm the rig (real or simulated) exactly as 'lfpiv acquire' does, record every "
                       "pair to --out, and show the newest pair live: the raw light-field images, projections "
                       "and a slice of the reconstructed volume, the in-plane vectors of the slice over their "
                       "vorticity, and a status line. The live path never slows the recorder: it skips to the "
                       "newest pair and says how many it skipped. Needs the gui extra: pip install 'lfpiv[gui]'.")
    m.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    m.add_argument("--pairs", type=positive_int, default=1000,
                   help="double-frame pairs to record per arming (default: 1000)")
    m.add_argument("--out", default=None, metavar="RUN",
                   help="run store to record to (a .zarr directory); without it the pairs are only shown "
                   "(the 'record' box turns recording on for the next arming)")
    m.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    m.add_argument("--screenshot", type=png_path, default=None, metavar="PNG",
                   help="save the window as PNG after --after pairs were shown, then end when the recording "
                   "does (works without a display)")
    m.add_argument("--after", type=positive_int, default=None, metavar="N",
                   help="pairs shown before the screenshot (default: 3, or --pairs when fewer)")
    m.add_argument("--protocol", choices=("fast", "drt"), default=None,
                   help="the live plan, which --method, --projector and --warm-start change: fast (default) "
                   "reconstructs light-field cameras by mlos-mart and starts frame B of each pair warm from frame A; "
                   "drt by drt-mart from uniform starts (the plan before 2026-12); pinhole cameras by mlos-smart in "
                   "either; the voxel route's. The status line names the plan")
    m.add_argument("--method", choices=("drt-mart", "mlos-mart", "mlos-smart"), default=None,
                   help="reconstruction: drt-mart (dense ray-traced weights) or mlos-mart (the same elimination, "
                   "line-of-sight weights; several times faster to build) for light-field cameras, mlos-smart for "
                   "pinhole (Tomo-PIV) ones (default: the protocol's: mlos-mart for fast, drt-mart for drt, and "
                   "drt-mart where --projector is stored or matrix-free; mlos-smart where every camera is a pinhole "
                   "camera)")
    add_projector(m)
    m.add_argument("--route", choices=("voxels", "particles"), default="voxels",
                   help="how the live path goes from a pair's images to its vectors: voxels (the volumes reconstructed "
                   "by --method and cross-correlated, as 'lfpiv reconstruct' and 'lfpiv correlate') or particles "
                   "(each frame's particles by iterative particle reconstruction and A's paired with B's into "
                   "tracks binned on a grid, as 'lfpiv particles' and 'lfpiv track'; --iterations, --relaxation, "
                   "--projector, --warm-start and --passes are the voxel route's) (default: voxels); the "
                   "recording is the same either way")
    m.add_argument("--iterations", type=iterations, default=5,
                   help="MART iterations per frame (default: 5; changeable in the window)")
    m.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                   help="start frame B of each pair from frame A carried along the last pair's field, with a fifth "
                   "of the iterations (the first pair's B starts uniform); --no-warm-start starts every frame "
                   "uniform (default: the protocol's: on for fast, off for drt)")
    m.add_argument("--relaxation", type=positive_float, default=1.0,
                   help="MART relaxation, at most 2 (default: 1; changeable in the window)")
    m.add_argument("--pvr", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="pixel-voxel ratio per axis of the live volume (default: the rig's volume.pvr); a "
                   "coarser one, e.g. twice the rig's, watches the flow on 8x fewer voxels, several times faster. "
                   "The recording keeps the raw frames whatever it is")
    m.add_argument("--flat-field", default=None, metavar="CALIB",
                   help="calibration store with white (and dark) images (lfpiv calibrate mla): the live path "
                   "corrects every raw frame per pixel by them and leaves the pixels they show unlit or dead out "
                   "(default: the raw frames; the recording keeps the raw frames either way)")
    m.add_argument("--slice", choices=("x", "y", "z"), default="z", help="axis normal to the slice (default: z)")
    m.add_argument("--passes", type=int, choices=(1, 2), default=2, help="correlation passes (default: 2)")
    m.add_argument("--ring", type=ring_slots, default=32, metavar="PAIRS",
                   help="ring-buffer depth in pairs (default: 32)")
    add_device(m)
    add_sim_options(m)
    m.add_argument("--quiet", action="store_true", help="no progress messages")
    m.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.acquire import check_plan
    from lfpiv.jobs.monitor import (
        DEFAULT_LIVE_PROTOCOL,
        check_display,
        live_plan,
        live_settings,
        require_gui,
        run_monitor,
    )
    from lfpiv.jobs.reconstruct import default_method
    from lfpiv.rigfile import load_rig
    from lfpiv.runs import check_new

    rig = load_rig(args.rig)
    warn_optics(rig)
    check_plan(rig, args.pairs)
    if args.route == "particles":
        if args.protocol is not None:
            raise UsageError(f"--protocol {args.protocol} is the voxel route's plan; leave it out with --route "
                             "particles")
        method, warm = args.method or default_method(rig), bool(args.warm_start)
    else:
        args.protocol = args.protocol or DEFAULT_LIVE_PROTOCOL
        method, warm = live_plan(rig, args.protocol, method=args.method, projector=args.projector,
                                 warm_start=args.warm_start)
    if args.after is None:  # the default never refuses what was asked: a short run's screenshot after its last pair
        args.after = min(3, args.pairs)
    elif args.screenshot is not None and args.after > args.pairs:
        raise UsageError(f"--after {args.after} is more pairs than --pairs {args.pairs} shows; the screenshot "
                         f"comes after at most {args.pairs}")
    if args.screenshot is not None:
        folder = Path(args.screenshot).parent
        if folder.exists() and not (folder.is_dir() and os.access(folder, os.W_OK)):
            raise UsageError(f"cannot write the screenshot into {folder}; give a writable --screenshot path")
    check_display(args.screenshot is not None)
    require_gui()
    check_pvr(args.pvr)
    if args.out is not None:
        check_new(args.out, args.overwrite)
    settings = live_settings(iterations=args.iterations, relaxation=args.relaxation, slice_axis=args.slice)

    def say(text: str) -> None:
        if not args.quiet:
            print(f"lfpiv monitor: {text}", file=sys.stderr)

    flats, _ = run_flat_fields(rig, args.flat_field)
    end = run_monitor(rig, pairs=args.pairs, settings=settings, method=method, projector=args.projector,
                      passes=args.passes, pvr=args.pvr,
                      device=args.device, out=args.out, overwrite=args.overwrite,
                      sim_options=sim_lab_options(rig, args), ring_slots=args.ring,
                      title=f"lfpiv monitor: {args.rig}", screenshot=args.screenshot, after=args.after, say=say,
                      warm_start=warm, flats=flats, route=args.route, protocol=args.protocol)
    for r in end.recordings:
        where = str(r.path) if r.path is not None else "not recorded (no --out)"
        print(f"recording: {where}: {r.committed_pairs} pair(s) x {len(rig.camera)} camera(s), {r.frames_recorded} "
              f"frames recorded, {r.frames_dropped} dropped, {r.overruns} overruns, state {r.state}")
    numbers = end.numbers
    lat = numbers["latency_s"]
    rate = float(numbers.get("processed_hz", 0.0))
    st = end.stats
    if args.route == "particles":
        found = (f", last pair {st.particles[0]}/{st.particles[1]} particles (A/B) and {st.tracks} tracks"
                 if st.particles is not None else "")
        route = f"particles (IPR with {method}'s weights) and tracks{found}"
    else:
        route = f"{method}, {args.iterations} iteration(s)"
    print(f"live: {int(numbers['processed'])} pair(s) processed, {int(numbers['skipped'])} skipped, "
          f"{int(numbers['discarded'])} discarded, {int(numbers['displayed'])} shown; last trigger-to-display "
          f"latency {f'{lat:.2f} s' if math.isfinite(lat) else 'n/a'}"
          # the rate between the last pairs processed (the status line's): it needs two of them
          + (f", {rate:.2f} pairs/s processed" if rate > 0 else "") + f"; {route} "
          f"on {end.device}, {'x'.join(map(str, end.voxels))} voxels at PVR "
          f"{','.join(f'{v:g}' for v in args.pvr or rig.volume.pvr)}"
          + (f", projector {end.projector}" if end.projector else "")
          + (f"; plan {end.plan}" if end.plan else ""))
    if end.stats.error:
        print(f"lfpiv monitor: warning: the live path reported: {end.stats.error}", file=sys.stderr)
    if end.screenshot is not None:
        print(f"screenshot: {end.screenshot}")
    end.raise_for_end()
    return 0
