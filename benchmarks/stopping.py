"""Named protocols (``lfpiv reconstruct --protocol``) and the stopping rule against the MART baseline
at equal time: Q against the truth, iterations, why they stopped, voxels left and the whole frame's
time (elimination, operators, iterations), in one run.

Run from the repository root::

    python benchmarks/stopping.py --case S
    python benchmarks/stopping.py --case S --ppm 2            # a denser frame: the rule runs it longer
    python benchmarks/stopping.py --case Mc --protocols fixed,fast --no-mart     # minutes on a CPU
    python benchmarks/stopping.py --case S --subsets 1,4      # each protocol plain and by 4 ordered subsets
    python benchmarks/mcfast.py --case Mc                     # the stages' wall and CPU times against the chapter's

Each row reconstructs the case's frame (``benchmarks/recon.py``'s scene) from its image with
:meth:`lfcore.reconstruct.FrameReconstructor.reconstruct`, as ``lfpiv reconstruct`` does, with the
named protocol's settings (:data:`lfcore.reconstruct.PROTOCOLS`; one frame, so no warm start).
The MART baseline (line-of-sight weights on every voxel of the box, every voxel to the end) then
runs as many iterations as fit in each protocol's time (its per-iteration time measured on a short
run first), so its Q is at equal time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.convergence import _recon_bench  # noqa: E402  (benchmarks/recon.py's scenes)
from lfcore import metrics  # noqa: E402
from lfcore.device import resolve_device  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import FrameReconstructor, protocol_settings  # noqa: E402


def timed(proj, settings, img, truth):
    """One frame of ``settings``: its result, Q and seconds."""
    frames = FrameReconstructor(proj, settings)
    t = time.perf_counter()
    res = frames.reconstruct(img)
    total = time.perf_counter() - t
    return res, metrics.q_recon(res.volume, truth), total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S")
    ap.add_argument("--device", default=None)
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--protocols", default="fixed,fast", help="named protocols, comma-separated (chapter, fixed, fast)")
    ap.add_argument("--no-mart", action="store_true", help="skip the MART baseline at equal time")
    ap.add_argument("--subsets", default="0",
                    help="ordered subsets to run each protocol with, comma-separated (0: the protocol's own)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    _, _, cams, grid, pts, img = _recon_bench().scene(args.case, device, args.ppm)
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    print(f"case {args.case}: grid {grid.shape} (z, y, x), {len(pts)} particles ({args.ppm:g} PPM), device {device}")
    print("| protocol | iterations | stopped | Q | voxels left (of active) | elimination s | operators s | "
          "iterations s | total s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    # the kernels compiled (and the first-call costs paid) before anything is timed
    for method in ("drt-mart", "mlos-mart", "mart"):
        FrameReconstructor(proj, protocol_settings("fixed", method=method, iterations=2)).reconstruct(img)
    times = {}
    for name, n_sub in [(p, int(k)) for p in args.protocols.split(",") for k in args.subsets.split(",")]:
        settings = protocol_settings(name, n_cameras=len(cams), **({"subsets": n_sub} if n_sub else {}))
        res, q, total = timed(proj, settings, img, truth)
        if n_sub > 1:
            name = f"{name}, {n_sub} subsets"
        times[name] = total
        print(f"| {name} | {res.iterations} | {res.stopped} | {q:.3f} | {res.final_voxels:,} ({res.active_voxels:,}) | "
              f"{res.eliminate_s:.1f} | {res.weights_s - res.eliminate_s:.1f} | {res.iterate_s:.1f} | {total:.1f} |",
              flush=True)
    if args.no_mart:
        return
    probe = 5
    res, _, total = timed(proj, protocol_settings("chapter", method="mart", iterations=probe), img, truth)
    fixed_s, per_it = total - res.iterate_s, res.iterate_s / probe
    print(f"MART baseline: {res.active_voxels:,} voxels, {fixed_s:.1f} s before the iterations, "
          f"{1e3 * per_it:.1f} ms per iteration")
    for name, t in times.items():
        n = max(1, int((t - fixed_s) / per_it)) if t > fixed_s else 0
        if n == 0:
            print(f"| MART at {name}'s time ({t:.1f} s) | 0 | | (its weights alone take {fixed_s:.1f} s) | | | | | |")
            continue
        res, q, total = timed(proj, protocol_settings("chapter", method="mart", iterations=n), img, truth)
        print(f"| MART at {name}'s time | {n} | {res.stopped} | {q:.3f} | {res.final_voxels:,} | "
              f"{res.eliminate_s:.1f} | {res.weights_s - res.eliminate_s:.1f} | {res.iterate_s:.1f} | {total:.1f} |",
              flush=True)


if __name__ == "__main__":
    main()
