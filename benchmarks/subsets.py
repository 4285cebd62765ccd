"""Ordered subsets (OS-SMART, ``ReconSettings.subsets``, ``--subsets``) against the plain simultaneous
form: Q against the truth per pass through the data and per second, in one run.

Run from the repository root::

    python benchmarks/subsets.py --case S --subsets 2,4,9 --counts 5,10,20,50,100 --halving 0,10
    python benchmarks/subsets.py --case Mc --subsets 4,9 --counts 10,25,50 --plain 25,50,100,200,400 --reference 400

The cases are ``benchmarks/recon.py``'s scenes. The elimination and the operator (ray-traced
stored weights) are made once and timed; each row iterates from them (uniform start): with S
subsets the rows are split once by pixel subset (timed with the row: its ``start+split s``), then
each iteration is one pass through the subsets, the subsets halved every ``--halving`` passes
(``ReconSettings.subset_halving``; 0: never). The ``plain`` rows are today's default (the plain
simultaneous form, with pruning) at ``--plain`` counts; ``--reference`` adds the chapter's protocol
at those counts (the plain form, every active voxel to the end), the uniform-start reference of
issue 47. A row's
``total s`` is the elimination and weights plus its own split and iterations, so rows of equal
total compare at equal time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.convergence import _recon_bench  # noqa: E402  (benchmarks/recon.py's scenes)
from lfcore import metrics  # noqa: E402
from lfcore.device import resolve_device, warp  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import FrameReconstructor, ReconSettings, preprocess_images  # noqa: E402
from lfcore.subsets import SUBSET_HALVING  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S", help="a case of benchmarks/recon.py (S, S2, Mc, Mc2, ...)")
    ap.add_argument("--device", default=None, help="cpu or cuda (default: a GPU if there is one)")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--subsets", default="2,4,9", help="numbers of subsets, comma-separated")
    ap.add_argument("--counts", default="5,10,20,50", help="the subsets' passes, comma-separated")
    ap.add_argument("--halving", default=str(SUBSET_HALVING),
                    help=f"passes between the subsets' halvings, comma-separated (0: never; default {SUBSET_HALVING})")
    ap.add_argument("--plain", default="5,10,20,50,100",
                    help="the plain form's iterations, comma-separated (none: skip)")
    ap.add_argument("--relaxation", type=float, default=1.0)
    ap.add_argument("--reference", default="", help="the chapter's protocol's counts, comma-separated (none: skip)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    counts = [int(c) for c in args.counts.split(",")]
    wp = warp()
    _, _, cams, grid, pts, img = _recon_bench().scene(args.case, device, args.ppm)
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    rows = [("plain", ReconSettings(projector="stored", relaxation=args.relaxation),
             [int(c) for c in args.plain.split(",")])] if args.plain else []
    rows += [(f"{s} subsets, halved every {h}" if int(h) else f"{s} subsets",
              ReconSettings(projector="stored", subsets=int(s), subset_halving=int(h), relaxation=args.relaxation),
              counts)
             for s in args.subsets.split(",") for h in args.halving.split(",")]
    if args.reference:
        rows.append(("chapter (reference)", ReconSettings.chapter(projector="stored"),
                     [int(c) for c in args.reference.split(",")]))
    first = FrameReconstructor(proj, ReconSettings(projector="stored"))
    signals, lits, _, noise = preprocess_images(proj, img, first.settings)
    image = wp.array(np.concatenate([s.ravel() for s in signals]), dtype=float, device=device)
    t0 = time.perf_counter()
    voxels = first.eliminate(lits)
    t1 = time.perf_counter()
    op = first.operator(voxels)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    build = t2 - t0
    print(f"case {args.case}: {len(pts)} particles, {grid.n_voxels:,} voxels, {op.n_voxels:,} active "
          f"({op.n_voxels / grid.n_voxels:.2%}), {op.nnz:,} weights ({op.kind}) on {device}; elimination "
          f"{t1 - t0:.1f} s, weights {t2 - t1:.1f} s; relaxation {args.relaxation:g}", flush=True)
    print("| settings | passes | Q | voxels left | start+split s | ms/pass | total s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, settings, ns in rows:
        fr = FrameReconstructor(proj, settings)
        for n in ns:
            done = fr.iterate(op, image, noise, iterations=n)
            q = metrics.q_recon(fr.volume(done.op, done.e).numpy(), truth)
            total = build + done.start_s + done.iterate_s
            print(f"| {name} | {n} | {q:.3f} | {done.op.n_voxels:,} | {done.start_s:.2f} | "
                  f"{1e3 * done.iterate_s / max(n, 1):.1f} | {total:.1f} |", flush=True)


if __name__ == "__main__":
    main()
