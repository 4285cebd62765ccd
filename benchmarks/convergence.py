"""Quality per unit of work: Q against the truth, iterations, voxels left and seconds, for DRT-MART
with every active voxel iterated to the end (the chapter's protocol) and with the dark voxels
leaving the operator (``ReconSettings.prune``, the default).

Run from the repository root::

    python benchmarks/convergence.py --case S
    python benchmarks/convergence.py --case Mc --counts 20,50,100,200,400     # minutes on a CPU
    python benchmarks/convergence.py --case Mc2 --counts 50,100,200 --device cuda

The cases are ``benchmarks/recon.py``'s (the same scene: rig, seeding and rendering). The
elimination and the operator (ray-traced stored weights; ``--projector auto`` or ``matrix-free``:
the templates' images where they pay or fit) are made once and timed; every reconstruction
starts from them (uniform start), so a row's total is the elimination and weights plus its own
iterations. Each row: the iteration count, Q against the true particles, the voxels left at the
end, ms per iteration and the total, and for the pruned rows the speed-up over the unpruned
reconstruction of the same count.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore import metrics  # noqa: E402
from lfcore.device import resolve_device, warp  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import PRUNE, FrameReconstructor, ReconSettings, preprocess_images  # noqa: E402


def _recon_bench():
    """benchmarks/recon.py as a module (its cases' scenes)."""
    spec = importlib.util.spec_from_file_location("recon_bench", ROOT / "benchmarks" / "recon.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S", help="a case of benchmarks/recon.py (S, S2, Mc, Mc2, ...)")
    ap.add_argument("--device", default=None, help="cpu or cuda (default: a GPU if there is one)")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--counts", default="10,20,50,100,200", help="iteration counts, comma-separated")
    ap.add_argument("--prune", type=float, default=PRUNE, help=f"the pruned rows' fraction (default {PRUNE})")
    ap.add_argument("--prune-every", type=int, default=10)
    ap.add_argument("--no-reference", action="store_true", help="skip the unpruned rows (the slow ones)")
    ap.add_argument("--projector", choices=("stored", "auto", "matrix-free"), default="stored",
                    help="what applies the operator (default: ray-traced stored weights; auto: the templates' images "
                    "where they cost less, as lfpiv reconstruct chooses)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    counts = [int(c) for c in args.counts.split(",")]
    wp = warp()
    _, _, cams, grid, pts, img = _recon_bench().scene(args.case, device, args.ppm)
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    settings = {"every voxel": ReconSettings.chapter(projector=args.projector),
                "pruned": ReconSettings(projector=args.projector, prune=args.prune, prune_every=args.prune_every)}
    if args.no_reference:
        del settings["every voxel"]
    frames = {k: FrameReconstructor(proj, s) for k, s in settings.items()}
    first = next(iter(frames.values()))
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
          f"{t1 - t0:.1f} s, weights {t2 - t1:.1f} s", flush=True)
    print("| settings | iterations | Q | voxels left | ms/iteration | total s | speed-up |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    totals: dict[int, float] = {}
    for name, fr in frames.items():
        for n in counts:
            done = fr.iterate(op, image, noise, iterations=n)
            q = metrics.q_recon(fr.volume(done.op, done.e).numpy(), truth)
            total = build + done.start_s + done.iterate_s
            if name == "every voxel":
                totals[n] = total
            speed = f"{totals[n] / total:.1f}x" if name != "every voxel" and n in totals else ""
            print(f"| {name} | {n} | {q:.3f} | {done.op.n_voxels:,} | {1e3 * done.iterate_s / n:.1f} | {total:.1f} | "
                  f"{speed} |", flush=True)


if __name__ == "__main__":
    main()
