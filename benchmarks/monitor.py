"""The demo's live monitor: pairs processed, trigger-to-display latency, and the live field's error.

Run from the repository root::

    python benchmarks/monitor.py timing --repeats 3                  # the demo's monitor step, plans alternated
    python benchmarks/monitor.py quality --run RUN.zarr              # each plan's live field against the truth

``timing`` runs the demo's live step (``lfpiv monitor --rig examples/demo.toml --sim-pool 2 --quiet
--pairs 30 --out ... --screenshot ... --after 1``, offscreen) once per plan (``--plans``: monitor
options after a name, ``drt`` for the plan before 2026-12 and ``fast`` for the default), the plans
alternated ``--repeats`` times in one run; per run it prints the pairs processed of those recorded,
the last trigger-to-display latency and the rate between the last pairs processed (the monitor's
own summary line), the wall time and the CPU time of the command (its process). The simulated lab
renders its pool of pairs before arming, so the figures measure the live path, not the simulated
cameras (the recording reports no drops).

``quality`` replays a run store's recorded pairs (a synthetic one, e.g. ``lfpiv acquire --rig
examples/demo.toml --pairs 10 --sim-pool 10``: a fresh seeding each pair) through the live pipeline
of each plan, pair after pair in order (warm starts follow the series), and compares each pair's
live velocity field with the truth flow at its window centres (RMS over all vectors, % of the peak
speed, as ``lfpiv evaluate``); it prints the per-pair error, the mean time of each stage and the
CPU time of the process (every thread) a pair, which a busy machine changes less than the wall time.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PLANS = {"drt": "--protocol drt", "fast": "--protocol fast"}


def plan_options(text: str) -> tuple[str, list[str]]:
    """``NAME=OPTIONS`` (or a name of :data:`PLANS`) as the name and the monitor options."""
    name, _, opts = text.partition("=")
    return name, shlex.split(opts if opts else PLANS[name])


def timing(args: argparse.Namespace) -> int:
    plans = [plan_options(p) for p in args.plans]
    rig = str(ROOT / "examples" / "demo.toml")
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": str(ROOT)}
    rows: dict[str, list[tuple[int, float, float, float, float]]] = {name: [] for name, _ in plans}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for name, opts in plans:
                cmd = [sys.executable, "-m", "lfpiv", "monitor", "--rig", rig, "--sim-pool", "2", "--quiet", "--pairs",
                       str(args.pairs), "--out", f"{tmp}/live.zarr", "--overwrite", "--screenshot",
                       f"{tmp}/monitor.png", "--after", "1", *opts]
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                t = time.perf_counter()
                done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp)
                wall = time.perf_counter() - t
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
                m = re.search(r"live: (\d+) pair\(s\) processed.*latency ([0-9.]+) s(?:, ([0-9.]+) pairs/s)?",
                              done.stdout)
                if done.returncode != 0 or m is None:
                    print(f"{name}: failed ({done.returncode}): {done.stderr.strip()[-500:]}")
                    return 1
                processed, lat, rate = int(m.group(1)), float(m.group(2)), float(m.group(3) or 0.0)
                rows[name].append((processed, lat, rate, wall, cpu))
                print(f"run {rep + 1} {name}: {processed} of {args.pairs} pairs processed, last latency {lat:.2f} s, "
                      f"{rate:.2f} pairs/s processed, wall {wall:.1f} s, CPU {cpu:.1f} s  [{shlex.join(opts)}]",
                      flush=True)
    for name, r in rows.items():
        a = np.array(r)
        print(f"{name}: processed {a[:, 0].mean():.1f} of {args.pairs} (mean), latency mean {a[:, 1].mean():.2f} s, "
              f"{a[:, 2].mean():.2f} pairs/s processed, wall {a[:, 3].mean():.1f} s, CPU {a[:, 4].mean():.1f} s over "
              f"{len(r)} runs")
    return 0


def quality(args: argparse.Namespace) -> int:
    from acquisition.ring import PairRing
    from lfcore import metrics
    from lfcore.correlate import CorrelationConfig
    from lfcore.runstore import RunStore
    from lfcore.volume import VolumeGrid
    from lfpiv.jobs.monitor import live_plan
    from lfpiv.rigfile import load_rig
    from realtime.pipeline import LivePipeline, LiveSettings, default_windows, monitoring_recon

    rig = load_rig(args.rig)
    store = RunStore.open(args.run)
    truth, flow = store.truth(), store.truth_flow()
    if truth is None or flow is None:
        print(f"{args.run} has no truth flow; record it on the simulated lab")
        return 1
    n = store.n_pairs if args.pairs is None else min(args.pairs, store.n_pairs)
    dt = rig.timing.dt_us * 1e-6
    for text in args.plans:
        name, opts = plan_options(text)
        p = argparse.ArgumentParser()
        p.add_argument("--protocol", default="fast")
        p.add_argument("--method", default=None)
        p.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None)
        p.add_argument("--iterations", type=int, default=5)
        p.add_argument("--pvr", default=None)
        o = p.parse_args(opts)
        method, warm = live_plan(rig, o.protocol, method=o.method, warm_start=o.warm_start)
        pvr = None if o.pvr is None else tuple(float(v) for v in o.pvr.split(","))
        grid = VolumeGrid.from_rig(rig, pvr=pvr)
        corr = CorrelationConfig(windows=default_windows(grid.shape, 2), overlap=0.5, deform_iterations=0)
        pipe = LivePipeline(rig, settings=LiveSettings(iterations=o.iterations),
                            recon=monitoring_recon(method=method, warm_start=warm), correlation=corr, pvr=pvr,
                            device=args.device, protocol=o.protocol)
        results = []
        pipe.subscribe(results.append)
        shapes = {c: store.read_frame(c, 0, 0).shape for c in store.cameras}
        ring = PairRing(shapes, slots=4)
        t0, c0 = time.perf_counter(), time.process_time()
        pipe.build()
        pipe.attach(ring)
        cpu_pair = []  # CPU seconds of the process (every thread) while each pair was processed
        with pipe:
            for k in range(n):  # one pair at a time, in order: each is processed, none skipped
                if ring.slot_of(k - ring.slots) is not None:
                    ring.release(k - ring.slots)
                for c in store.cameras:
                    for f in (0, 1):
                        ring.put(c, k, f, store.read_frame(c, k, f), 2 * k + f, time.time_ns())
                c1 = time.process_time()
                ring.publish(k)
                if not pipe.wait_processed(k + 1, 600.0):
                    print(f"{name}: pair {k} did not finish: {pipe.stats().error}")
                    return 1
                cpu_pair.append(time.process_time() - c1)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        errs = []
        for r in results:
            x, y, z = r.grid_mm
            ref = metrics.grid_velocity(flow, x, y, z, truth["t0_s"][r.pair] + 0.5 * dt)
            errs.append(100.0 * metrics.velocity_errors(r.velocity[None], ref[None]).of_peak)
        later = results[1:] or results
        stages = {k: np.mean([r.timings[k] for r in later]) for k in ("eliminate", "weights", "iterate", "volume",
                                                                        "correlate", "total")}
        print(f"{name} [{pipe.plan}, {o.iterations} iterations]: error % of peak per pair "
              f"{' '.join(f'{e:.1f}' for e in errs)}; mean {np.mean(errs):.2f}%; frame B warm in "
              f"{sum(r.warm for r in results)} of {len(results)}; first pair {results[0].timings['total']:.2f} s, "
              f"later pairs (s): " + ", ".join(f"{k} {v:.3f}" for k, v in stages.items())
              + f"; CPU a pair: first {cpu_pair[0]:.2f} s, later {np.mean(cpu_pair[1:] or cpu_pair):.2f} s; wall "
              f"{wall:.1f} s, CPU {cpu:.1f} s (build included)", flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    t = sub.add_parser("timing", help="the demo's monitor step, each plan in turn")
    t.add_argument("--plans", nargs="+", default=["drt", "fast"],
                   help="plans: drt, fast, or NAME='monitor options' (default: drt fast)")
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--pairs", type=int, default=30, help="pairs recorded (default: 30, as the demo)")
    q = sub.add_parser("quality", help="each plan's live field against the truth of a recorded synthetic run")
    q.add_argument("--run", required=True, help="a run store recorded on the simulated lab")
    q.add_argument("--rig", default=str(ROOT / "examples" / "demo.toml"))
    q.add_argument("--plans", nargs="+", default=["drt", "fast"],
                   help="plans: drt, fast, or NAME='--protocol P --method M --[no-]warm-start --iterations N "
                   "--pvr X,Y,Z'")
    q.add_argument("--pairs", type=int, default=None, help="the first N pairs (default: all)")
    q.add_argument("--device", default="cpu")
    args = ap.parse_args()
    return timing(args) if args.what == "timing" else quality(args)


if __name__ == "__main__":
    raise SystemExit(main())
