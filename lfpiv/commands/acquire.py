"""``lfpiv acquire``: record double-frame pairs from the rig (real or simulated) into a run store."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import add_sim_options, positive_int, ring_slots, sim_lab_options, warn_optics


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("acquire", help="arm the laser and cameras and record double-frame pairs",
                       description="Program the pulse generator, arm the laser and the cameras (light-field or "
                       "pinhole) and record N double-frame pairs into a new run store. Every frame is recorded "
                       "or listed in drops with its reason; Ctrl-C or a device fault disarms the laser and keeps "
                       "what was recorded. With hardware = \"sim\" in the rig file it runs on the simulated lab.")
    s.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    s.add_argument("--pairs", required=True, type=positive_int, help="double-frame pairs to record")
    s.add_argument("--out", required=True, metavar="RUN", help="run store to create (a .zarr directory)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    s.add_argument("--ring", type=ring_slots, default=32, metavar="PAIRS",
                   help="ring-buffer depth in pairs (default: 32)")
    s.add_argument("--pairing", choices=("counter", "timestamps"), default="counter",
                   help="counter (default): frames A and B of one trigger, a camera's double-exposure mode; "
                   "timestamps: GenICam cameras without one take a frame per trigger, paired in software by their "
                   "time stamps (real hardware only)")
    add_sim_options(s)
    s.add_argument("--quiet", action="store_true", help="no progress line")
    s.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.acquire import check_plan, record
    from lfpiv.rigfile import load_rig
    from lfpiv.runs import check_new

    rig = load_rig(args.rig)
    warn_optics(rig)
    # refuse an impossible timing or a taken --out before the simulated lab renders
    check_plan(rig, args.pairs, pairing=args.pairing)
    check_new(args.out, args.overwrite)
    sim_options = sim_lab_options(rig, args)
    if sim_options is not None and not args.quiet:
        print(f"lfpiv: simulated lab: rendering {args.sim_pool} pair(s) of '{args.sim_flow}' per camera ...",
              file=sys.stderr)

    def show(st) -> None:
        if not args.quiet:
            print(f"\rpairs {st.committed_pairs}/{args.pairs}  {st.pair_rate_hz:5.1f} pairs/s  "
                  f"frames {st.frames_recorded}  drops {st.frames_dropped}  overruns {st.overruns}  "
                  f"{st.elapsed_s:6.1f} s", end="", file=sys.stderr, flush=True)

    def say(text: str) -> None:  # the laser's state and what is kept, as the recording ends: never quiet
        print(text, file=sys.stderr)

    res = record(rig, args.out, args.pairs, overwrite=args.overwrite, sim_options=sim_options, ring_slots=args.ring,
                 progress=show, pairing=args.pairing, say=say)
    show(res.stats)
    if not args.quiet:
        print(file=sys.stderr)
    st = res.stats
    print(f"wrote {res.store.path}: {st.committed_pairs} pair(s) x {len(rig.camera)} camera(s), "
          f"{st.frames_recorded} frames recorded, {res.drops} dropped (see drops/"
          + (f"; {st.missed_triggers} missed trigger(s)" if st.missed_triggers else "") + f"), state {res.state}"
          + (f", {st.pair_rate_hz:.1f} pairs/s" if st.committed_pairs > 1 else ""))
    return 0
