"""Live-pipeline benchmark: sustained pairs per second and trigger-to-result latency.

Run from the repository root::

    python benchmarks/live.py --case S --device cpu            # tiny rig, two cameras, seconds
    python benchmarks/live.py --case M --device cuda           # two 2048 x 2048 cameras (the goal)
    python benchmarks/live.py --case D --route particles       # the demo's rig, particles and tracks

Cases (two cameras at 90 degrees, 0.5 PPM, monitoring settings: DRT-MART, or MLOS-MART with
``--method mlos-mart``, with ``--iterations`` simultaneous iterations, two correlation passes at
50% overlap, no deformation):

S   examples/tiny.toml with a second camera: 192 x 160 pixels each, 82 x 68 x 29 voxels.
M   examples/one_camera.toml (the reconstruction benchmark's M case) with a second camera:
    2048 x 2048 pixels each.
D   examples/demo.toml (the demo's rig): two 256 x 256 light-field cameras at 90 degrees,
    73 x 73 x 73 voxels.

``--route particles`` runs the live particle route instead (``lfpiv monitor --route particles``:
iterative particle reconstruction of both frames with the monitoring settings, tracks binned on
a grid); ``--iterations`` and the per-iteration figures are then the voxel route's only.

A feeder thread plays the recorder: it puts a rendered pair into a :class:`PairRing` at
``--rate`` pairs per second (stamped with the host clock at its trigger time) and publishes it;
the pipeline takes the newest pair and skips the rest. Printed: pairs per second processed,
the mean and worst trigger-to-result latency, the time of every stage per pair, and from the
fixed and per-iteration costs the most iterations per pair that still keep up with 10 Hz
(``(0.1 s - fixed) / per-iteration``). Times exclude the build (projector, correlator, kernel
compilation), which happens once before the first pair.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquisition.ring import PairRing  # noqa: E402
from lfcore.device import resolve_device  # noqa: E402
from lfcore.matrix_free import PROJECTORS  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.render import LightFieldRenderer  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfpiv.commands import xyz_triple  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402
from realtime.pipeline import LIVE_METHODS, LIVE_ROUTES, LivePipeline, LiveSettings, monitoring_recon  # noqa: E402


def case_rig(case: str) -> Rig:
    if case == "D":
        return load_rig(ROOT / "examples" / "demo.toml")  # two cameras already
    path = ROOT / "examples" / ("tiny.toml" if case == "S" else "one_camera.toml")
    d = load_rig(path).to_dict()
    second = dict(d["camera"][0])
    second.update(name=f"{second['name']}_90", rotation_deg=[0.0, 90.0, 0.0])
    d["camera"] = [d["camera"][0], second]
    return Rig.from_dict(d)


def render_pair(rig: Rig, ppm: float, device: str, rays: int, seed: int = 1) -> dict[str, np.ndarray]:
    """One (2, rows, columns) uint16 pair per camera; frame B shifted 2 voxels along x."""
    n = particle_count(rig, ppm=ppm)
    pts = seed_particles(rig.volume, n, np.random.default_rng(seed))
    shift = np.array([2 * rig.volume.pvr[0] * rig.camera[0].object_pixel_mm, 0.0, 0.0])
    render = rig.render.model_copy(update={"rays_per_particle": rays})
    out = {}
    for cam in rig.camera:
        r = LightFieldRenderer(cam, render, wavelength_nm=rig.laser.wavelength_nm, device=device)
        frames = [r.frame(p, render.particle_counts, seed=2 * seed + k) for k, p in enumerate((pts, pts + shift))]
        out[cam.name] = np.stack([np.clip(f, 0, 65535).astype(np.uint16) for f in frames])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", choices=("S", "M", "D"), default="S")
    ap.add_argument("--route", choices=LIVE_ROUTES, default="voxels",
                    help="voxels: volumes and correlation; particles: IPR and tracks (default: voxels)")
    ap.add_argument("--device", default=None, help="cpu, cuda (default: a GPU if there is one)")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--method", choices=LIVE_METHODS, default="drt-mart",
                    help="the live reconstruction (default: drt-mart)")
    ap.add_argument("--projector", choices=PROJECTORS, default="auto",
                    help="what applies DRT-MART's operator (default: auto, as lfpiv monitor)")
    ap.add_argument("--pvr", type=xyz_triple, default=None, metavar="X,Y,Z",
                    help="pixel-voxel ratio of the live volume (default: the rig's, 2,2,10); a monitoring setting")
    ap.add_argument("--rate", type=float, default=10.0, help="pairs per second the feeder publishes (default: 10)")
    ap.add_argument("--seconds", type=float, default=20.0, help="how long to feed pairs (default: 20)")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--rays", type=int, default=2000, help="rays per particle when rendering the pair")
    ap.add_argument("--distinct", type=int, default=32,
                    help="distinct pairs (fresh seeding) the feeder cycles through (default: 32); the weight "
                    "cache only helps for voxels an earlier pair already activated")
    ap.add_argument("--warmup-limit", type=float, default=600.0,
                    help="give up if the first pair takes longer than this many seconds (default: 600)")
    args = ap.parse_args()
    pvr = args.pvr
    device = resolve_device(args.device)
    rig = case_rig(args.case)
    t = time.perf_counter()
    pairs = [render_pair(rig, args.ppm, device, args.rays, seed=1 + k) for k in range(max(1, args.distinct))]
    pair = pairs[0]
    cams = list(pair)
    rows_cols = {c: pair[c].shape[1:] for c in cams}
    what = ("particles (IPR) and tracks" if args.route == "particles"
            else f"{args.method} with {args.iterations} iterations")
    print(f"case {args.case}: {len(cams)} cameras of {rows_cols[cams[0]][1]} x {rows_cols[cams[0]][0]} px, "
          f"device {device}, {what}, feeder at {args.rate:g} Hz "
          f"cycling {len(pairs)} distinct pairs; rendered in "
          f"{time.perf_counter() - t:.1f} s")
    ring = PairRing(rows_cols, slots=8)
    try:
        recon = monitoring_recon(method=args.method, projector=args.projector)
    except ValueError as e:
        ap.error(str(e))
    pipe = LivePipeline(rig, settings=LiveSettings(iterations=args.iterations), recon=recon, pvr=pvr, device=device,
                        route=args.route)
    t = time.perf_counter()
    pipe.build()
    g = pipe.grid.shape
    print(f"  volume {g[2]} x {g[1]} x {g[0]} voxels (x, y, z) at PVR {pvr or rig.volume.pvr}, "
          + (f"bins {pipe.tracking.bin_voxels}, search {pipe.tracking.search_voxels}" if args.route == "particles"
             else f"windows {pipe.correlation.windows}") + f"; built in {time.perf_counter() - t:.1f} s")
    results = []
    pipe.subscribe(results.append)
    stop = threading.Event()

    def feed() -> None:
        period = 1.0 / args.rate
        start = time.monotonic()
        p = 0
        while not stop.is_set():
            due = start + p * period
            time.sleep(max(0.0, due - time.monotonic()))
            stamp = time.time_ns()
            s = ring.slot_of(p - ring.slots)
            if s is not None:
                ring.release(p - ring.slots)
            for c in cams:
                for f in range(2):
                    ring.put(c, p, f, pairs[p % len(pairs)][c][f], 2 * p + f, stamp)
            ring.publish(p)
            p += 1

    # warm-up: one pair through every stage (kernel compilation), not timed
    warm = PairRing(rows_cols, slots=2)
    for c in cams:
        for f in range(2):
            warm.put(c, 0, f, pair[c][f], f, time.time_ns())
    warm.publish(0)
    pipe.attach(warm)
    with pipe:
        t = time.perf_counter()
        while not pipe.wait_processed(1, 1.0):
            err = pipe.stats().error
            if err is not None or time.perf_counter() - t > args.warmup_limit:
                print(f"  the first pair did not finish: {err or f'still running after {args.warmup_limit:g} s, in:'}")
                if err is None:  # where the pipeline's thread is
                    live = next((th for th in threading.enumerate() if th.name == "lfpiv-live"), None)
                    frame = sys._current_frames().get(live.ident) if live is not None else None
                    print("".join(traceback.format_stack(frame)[-6:]) if frame is not None else "  (no live thread)")
                return 1
        print(f"  first pair (every weight traced, kernels compiled) in {time.perf_counter() - t:.1f} s")
        results.clear()
        pipe.attach(ring)
        feeder = threading.Thread(target=feed, daemon=True)
        t0 = time.monotonic()
        feeder.start()
        time.sleep(args.seconds)
        stop.set()
        feeder.join()
        fed_s = time.monotonic() - t0
    st = pipe.stats()
    if not results:
        print("  no pair finished within the run; give more --seconds")
        return 1
    n = len(results)
    lat = np.array([r.latency_s for r in results])
    stages = {k: np.mean([r.timings[k] for r in results]) for k in results[0].timings}
    print(f"  {n} pairs processed in {fed_s:.1f} s: {n / fed_s:.2f} pairs/s sustained; skipped {st.skipped}, "
          f"discarded {st.discarded}")
    print(f"  trigger-to-result latency: mean {lat.mean():.3f} s, worst {lat.max():.3f} s")
    print("  per pair (s): " + ", ".join(f"{k} {v:.4f}" for k, v in stages.items()))
    if args.route == "particles":
        found = np.array([r.particles for r in results], dtype=float)
        print(f"  particles per frame: mean {found.mean():.0f} (A, B); tracks kept per pair: mean "
              f"{np.mean([r.tracks for r in results]):.0f}; bins with a vector "
              f"{100 * np.mean([1 - r.outlier_fraction for r in results]):.0f}%")
        total = stages["total"]
        print(f"  10 Hz: {'reachable' if total <= 0.1 else 'not reachable'} on {device} (a pair takes {total:.3f} s)")
        return 0
    its = max(args.iterations, 1)
    per_it = stages["iterate"] / 2 / its  # two frames per pair
    fixed = stages["total"] - stages["iterate"]
    print(f"  fixed cost {fixed:.3f} s per pair, {1e3 * per_it:.2f} ms per iteration per frame; operator applied by "
          f"{', '.join(sorted({r.projector for r in results}))} (--projector {args.projector})")
    budget = 0.1 - fixed
    if budget <= 0:
        print(f"  10 Hz: not reachable on {device} at any iteration count (fixed cost {fixed:.3f} s > 0.1 s)")
    else:
        print(f"  10 Hz: at most {int(budget / (2 * per_it))} iteration(s) per frame keep up on {device}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
