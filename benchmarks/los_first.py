"""DRT-MART with its first iterations on line-of-sight weights (``--los-iterations``) against DRT
weights from the start: Q against the truth and the whole frame's time (elimination, operators,
iterations), in one run.

Run from the repository root::

    python benchmarks/los_first.py --case S --iterations 100 --los 10,20
    python benchmarks/los_first.py --case Mc --iterations 200,400 --los 30      # minutes on a CPU

Each row reconstructs the case's frame (``benchmarks/recon.py``'s scene) from its image with
:meth:`lfcore.reconstruct.FrameReconstructor.reconstruct`, as ``lfpiv reconstruct`` does (the
default operator, ``--projector auto``, and pruning), with ``los_iterations`` 0 (DRT weights from
the start) or each of ``--los``.
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
from lfcore.reconstruct import FrameReconstructor, ReconSettings  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S")
    ap.add_argument("--device", default=None)
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--iterations", default="100", help="iteration counts, comma-separated")
    ap.add_argument("--los", default="10,20", help="line-of-sight first iterations, comma-separated")
    args = ap.parse_args()
    device = resolve_device(args.device)
    _, _, cams, grid, pts, img = _recon_bench().scene(args.case, device, args.ppm)
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    print(f"case {args.case}: grid {grid.shape} (z, y, x), {len(pts)} particles, device {device}")
    print("| iterations | line-of-sight first | Q | elimination s | operators s | iterations s | total s | operator |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for its in (int(n) for n in args.iterations.split(",")):
        for los in [0, *(int(n) for n in args.los.split(","))]:
            frames = FrameReconstructor(proj, ReconSettings(iterations=its, los_iterations=los))
            t = time.perf_counter()
            res = frames.reconstruct(img)
            total = time.perf_counter() - t
            q = metrics.q_recon(res.volume, truth)
            print(f"| {its} | {los} | {q:.3f} | {res.eliminate_s:.1f} | {res.weights_s - res.eliminate_s:.1f} | "
                  f"{res.iterate_s:.1f} | {total:.1f} | {res.operator} |", flush=True)


if __name__ == "__main__":
    main()
