"""``lfpiv study``: the chapter's studies reproduced, on the default rigs or the user's own."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import add_device, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    from lfpiv.jobs.study import SCALES, STUDY_NAMES

    s = sub.add_parser("study", help="reproduce the chapter's studies (or ask them of your own rig): tables, "
                       "figures, reports",
                       description="Run one of the chapter's studies (or all) on synthetic pairs of known truth: "
                       "each writes DIR/NAME/table.csv, figure.png (laid out like the chapter's) and report.md "
                       "(the chapter's claim, ours, reproduced or not and by how much). With --rig, the same "
                       "study on your own rig: which PPM, which separation angle, how many iterations, what "
                       "error at which depth. Studies: " + ", ".join(STUDY_NAMES) + ".")
    s.add_argument("name", metavar="NAME", choices=(*STUDY_NAMES, "all"),
                   help=f"{', '.join(STUDY_NAMES)} or all")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder (a sub-folder per study)")
    s.add_argument("--rig", default=None, metavar="RIG",
                   help="your rig file (default: the scale's example rigs); at --scale quick its sensors are "
                   "cropped to 192 x 160 pixels and its volume to what they see")
    s.add_argument("--scale", choices=SCALES, default="quick",
                   help="tiny: seconds, a check that the study runs; quick: minutes on a laptop CPU (smaller "
                   "optics, fewer pairs); chapter: the chapter's optics and protocol, for a GPU workstation or "
                   "a cluster (default: quick)")
    add_device(s)
    g = s.add_mutually_exclusive_group()
    g.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="run the cases in N worker processes on this machine (default: in this process)")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the cases on the workers of a running Dask cluster, e.g. tcp://head:8786")
    d = s.add_mutually_exclusive_group()
    d.add_argument("--skip-done", action="store_true",
                   help="keep the cases an earlier run finished with the same scale and rig (to resume)")
    d.add_argument("--overwrite", action="store_true", help="do every case again, replacing earlier results")
    s.add_argument("--quiet", action="store_true", help="no line per finished case")
    s.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.study import run_studies, study_setup

    setup = study_setup(scale=args.scale, rig=args.rig, device=args.device)

    def line(text: str) -> None:
        print(f"lfpiv: {text}", file=sys.stderr, flush=True)

    outcomes = run_studies([args.name], setup, args.out, skip_done=args.skip_done, overwrite=args.overwrite,
                           workers=args.workers, scheduler=args.scheduler, progress=None if args.quiet else line)
    for o in outcomes:
        kept = o.cases - o.done_now
        print(f"study {o.name}: {o.cases} cases ({o.done_now} run now{f', {kept} kept' if kept else ''}) in "
              f"{o.seconds:.0f} s; wrote {o.table}, {o.figure}, {o.report}")
        for f in o.findings:
            print(f"  {f.figure}: {f.verdict}{f' ({f.by})' if f.by else ''}: {f.ours}")
    if len(outcomes) > 1:
        print(f"index of the studies: {outcomes[0].folder.parent / 'README.md'}")
    return 0
