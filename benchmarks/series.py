"""The series goal under the defaults (issue 47, part 3): ``lfpiv reconstruct --no-warm-start`` (``cold``),
``--warm-predictor last`` (``warm``: frame B from frame A carried along the last pair's field) and
``--warm-predictor own`` (``own``, the default: along the pair's own predictor) as the command runs them
(the ``fast`` protocol and its stopping rule), on copies of one synthetic run, in one process; per pair
the iterations, Q against the truth (as ``lfpiv evaluate``) and CPU seconds (``time.process_time``) of
each frame, and of the last pair's predictor measured between pairs.

Run from the repository root::

    python benchmarks/series.py                              # the tiny rig, 10 pairs of the vortex ring
    python benchmarks/series.py --pairs 4 --modes own        # fewer pairs, the own-pair warm start only

The synthetic run is made once (``lfpiv synth --rig RIG --flow FLOW --pairs N``, seed 1, in a temporary
folder unless ``--run`` names one to keep). The goal: pairs 2-N's frames B reach the first pair's B's Q
in at most a quarter of its iterations; the warm frames' CPU against the cold ones' in the same run.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore.reconstruct import FrameReconstructor  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_run  # noqa: E402
from lfpiv.jobs.reconstruct import (  # noqa: E402
    DEFAULT_PROTOCOL,
    Series,
    camera_count,
    cameras_kind,
    protocol_run_settings,
    reconstruct_run,
    run_method,
)
from lfpiv.runs import open_run  # noqa: E402

#: cold: every frame uniform; warm: frame B from frame A carried along the last pair's field; own: along
#: the pair's own predictor (frame A against a few line-of-sight iterations of B)
MODES = {"cold": {"warm_start": False}, "warm": {"warm_start": True, "warm_predictor": "last"},
         "own": {"warm_start": True, "warm_predictor": "own"}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(ROOT / "examples" / "tiny.toml"))
    ap.add_argument("--flow", default="vortex-ring")
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--run", default=None, help="the synthetic run to use (made there if missing)")
    ap.add_argument("--modes", default="cold,warm,own", help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--protocol", default=DEFAULT_PROTOCOL)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--vectors", action="store_true",
                    help="also correlate each mode's volumes (lfpiv correlate's defaults) and give the vector error "
                    "of pairs 2-N against the true flow")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="lfpiv-series-"))
    try:
        run = Path(args.run) if args.run else tmp / "run.zarr"
        if not run.exists():
            subprocess.run([sys.executable, "-m", "lfpiv", "synth", "--rig", args.rig, "--flow", args.flow, "--pairs",
                            str(args.pairs), "--out", str(run), "--quiet"], check=True, cwd=ROOT)
        rows = {}
        for mode in args.modes.split(","):
            copy = tmp / f"{mode}.zarr"
            shutil.copytree(run, copy, ignore=shutil.ignore_patterns("volumes*"))
            rows[mode] = one_mode(copy, args, MODES[mode])
            if args.vectors:
                rows[mode]["vectors"] = vectors(copy)
        report(rows, args.pairs)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def one_mode(path: Path, args, options: dict) -> dict:
    """Reconstruct the run at ``path`` as ``lfpiv reconstruct`` does with ``options``; per frame
    (pair, frame): iterations, why it stopped, voxels, warm, CPU s; and Q."""
    store = open_run(str(path), mode="r+")
    settings = protocol_run_settings(args.protocol, n_cameras=camera_count(store.rig),
                                     camera_kind=cameras_kind(store.rig), method=run_method(store.rig), **options)
    cpu: list[float] = []
    original = FrameReconstructor.reconstruct

    def timed(self, *a, **k):
        c0 = time.process_time()
        try:
            return original(self, *a, **k)
        finally:
            cpu.append(time.process_time() - c0)

    measured = Series.measured
    predictor_cpu: list[float] = []

    def timed_measured(self, *a, **k):  # the last pair's predictor, measured between pairs
        c0 = time.process_time()
        try:
            return measured(self, *a, **k)
        finally:
            predictor_cpu.append(time.process_time() - c0)

    FrameReconstructor.reconstruct = timed
    Series.measured = timed_measured
    c0 = time.process_time()
    try:
        results = reconstruct_run(store, settings, device=args.device, progress=False, protocol=args.protocol,
                                  warm_optional=not options.get("warm_start"))
    finally:
        FrameReconstructor.reconstruct = original
        Series.measured = measured
    total = time.process_time() - c0
    q = {(e.pair, e.frame): e.q for e in evaluate_run(store)}
    frames = [dict(pair=i // 2, frame=i % 2, iterations=r.iterations, stopped=r.stopped, active=r.active_voxels,
                   final=r.final_voxels, warm=r.warm, cpu=c, q=q[(i // 2, i % 2)], elim=r.eliminate_s,
                   weights=r.weights_s - r.eliminate_s, iterate=r.iterate_s, predictor=r.predictor_s)
              for i, (r, c) in enumerate(zip(results, cpu, strict=True))]
    return {"frames": frames, "cpu": total, "between": sum(predictor_cpu) / max(len(predictor_cpu), 1)}


def vectors(path: Path) -> str:
    """``lfpiv correlate`` of the run's volumes (in a process of its own, windows of a third and a sixth of
    the box, its other defaults), and the RMS
    vector error of pairs 2-N in voxels (x, y, z) against the true flow."""
    from lfpiv.jobs.evaluate import evaluate_vector_fields

    nz, ny, nx = open_run(str(path)).volume_grid().shape
    # two passes of windows about a third and a sixth of the box (benchmarks/warm.py's)
    windows = ",".join("x".join(str(max(8, int(n * share) // 4 * 4)) for n in (nx, ny, nz)) for share in (0.34, 0.17))
    subprocess.run([sys.executable, "-m", "lfpiv", "correlate", str(path), "--windows", windows, "--quiet"],
                   check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    ev = evaluate_vector_fields(open_run(str(path)), slice(1, None))
    if isinstance(ev, str):
        return ev
    rms = ev.rms_voxels
    return f"vector RMS error of pairs 2-N {', '.join(f'{v:.3f}' for v in rms)} voxel (x, y, z)"


def report(rows: dict, n_pairs: int) -> None:
    for mode, row in rows.items():
        print(f"\n## {mode}: {row['cpu']:.1f} CPU s in all")
        print("| pair | frame | iterations | stopped | active voxels | left | warm | Q | CPU s | wall s: elimination, "
              "operators, iterations, own predictor |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for f in row["frames"]:
            print(f"| {f['pair'] + 1} | {'AB'[f['frame']]} | {f['iterations']} | {f['stopped']} | {f['active']:,} | "
                  f"{f['final']:,} | {'yes' if f['warm'] else ''} | {f['q']:.3f} | {f['cpu']:.2f} | "
                  f"{f['elim']:.2f}, {f['weights']:.2f}, {f['iterate']:.2f}, {f['predictor']:.2f} |")
        bs = [f for f in row["frames"] if f["frame"] == 1]
        first, later = bs[0], bs[1:]
        if first["warm"] and "cold" in rows:  # the goal is against a uniform start's first B
            first = [f for f in rows["cold"]["frames"] if f["frame"] == 1][0]
        if later:
            quarter = first["iterations"] / 4
            reach = sum(f["q"] >= first["q"] and f["iterations"] <= quarter for f in later)
            reach_q = sum(f["q"] >= first["q"] for f in later)

            def mean(k: str, later: list = later) -> float:
                return sum(f[k] for f in later) / len(later)

            frames_a = [f for f in row["frames"] if f["frame"] == 0]
            print(f"{mode}: the first B {first['iterations']} iterations, Q {first['q']:.3f}"
                  f"{' (cold)' if first is not bs[0] else ''}; pairs 2-{n_pairs} B: "
                  f"iterations {min(f['iterations'] for f in later)}-{max(f['iterations'] for f in later)} "
                  f"(mean {mean('iterations'):.1f}; a quarter: {quarter:.1f}), Q mean {mean('q'):.3f}, "
                  f"reach the first's Q in {reach_q} of {len(later)}, within a quarter of its iterations in "
                  f"{reach} of {len(later)}; CPU a later B {mean('cpu'):.2f} s, a frame A "
                  f"{sum(f['cpu'] for f in frames_a) / len(frames_a):.2f} s, the last pair's predictor between "
                  f"pairs {row['between']:.2f} s a pair; frames B of all pairs: Q mean "
                  f"{sum(f['q'] for f in bs) / len(bs):.3f}, CPU mean {sum(f['cpu'] for f in bs) / len(bs):.2f} s")
        if "vectors" in row:
            print(f"{mode}: {row['vectors']}")


if __name__ == "__main__":
    main()
