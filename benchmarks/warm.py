"""Warm starts along a series: frame B of each pair started from frame A carried by the last pair's
field, against the uniform start, in Q (against the truth), iterations and the vector error.

Run from the repository root::

    python benchmarks/warm.py --case S --pairs 4
    python benchmarks/warm.py --case Mc --pairs 3 --iterations 400 --counts 20,40,80    # minutes on a CPU
    python benchmarks/warm.py --case S --pairs 10 --reach 12     # issue 47's series goal

A series of ``--pairs`` double pulses of ``--flow`` (a fresh seeding per pair, as ``lfpiv synth``
and the simulated lab make them) is rendered on ``benchmarks/recon.py``'s case rig. Every frame A
and the first pair's B are reconstructed from the uniform start (``--iterations``); each later B
from its A carried along the previous pair's predictor field (:func:`lfcore.warm.predictor_field`,
what ``lfpiv reconstruct --warm-start`` does), at each of ``--counts`` iterations, and from the
uniform start at ``--iterations``. Per B: Q at each count against the cold Q, and the displacement
error of a correlation of (A, B) against the true flow, cold and warm at the default count
(``WARM_SHARE`` of ``--iterations``). The operator of each frame is built once for both starts.

``--reach N``: for every later B also the fewest warm iterations (1 to N) that reach the first pair's
B's Q (the cold start at ``--iterations``): issue 47's series goal ("pairs 2-10 reach the first
pair's Q in at most 1/4 of its iterations"); and those that reach the B's own cold Q (a pair whose
frames are harder than the first pair's may not reach the first's Q even cold).
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
from lfcore.correlate import CorrelationConfig, correlate  # noqa: E402
from lfcore.device import resolve_device, warp  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import WARM_SHARE, FrameReconstructor, ReconSettings, preprocess_images  # noqa: E402
from lfcore.render import LightFieldRenderer  # noqa: E402
from lfcore.warm import WARM_BLEND, WARM_BLUR, WarmStart, predictor_field  # noqa: E402
from lfcore.world import ParticleWorld  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S", help="a case of benchmarks/recon.py (S, S2, Mc, Mc2)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--flow", default="vortex-ring")
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=50, help="the cold frames' iterations")
    ap.add_argument("--counts", default="5,10,20", help="warm iteration counts, comma-separated")
    ap.add_argument("--blur", type=float, default=WARM_BLUR, help=f"voxels (default {WARM_BLUR})")
    ap.add_argument("--blend", type=float, default=WARM_BLEND, help=f"(default {WARM_BLEND})")
    ap.add_argument("--projector", choices=("stored", "auto", "matrix-free"), default="auto")
    ap.add_argument("--reach", type=int, default=0, metavar="N",
                    help="per later B, the fewest warm iterations (at most N) that reach the first pair's B's Q "
                    "(default: 0, not measured)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    wp = warp()
    counts = [int(c) for c in args.counts.split(",")]
    rb = _recon_bench()
    rig, _ = rb.case_rig(args.case)
    cams = rig.camera if args.case in ("S2", "Mc2") else rig.camera[:1]
    from lfcore.volume import VolumeGrid

    grid = VolumeGrid.from_rig(rig)
    world = ParticleWorld(rig, flow=args.flow, ppm=args.ppm, seed=3)
    render = rig.render.model_copy(update={"rays_per_particle": 5000})
    renderers = [LightFieldRenderer(c, render, wavelength_nm=rig.laser.wavelength_nm, device=device) for c in cams]
    proj = projector_for(cams, grid, device=device)
    settings = ReconSettings(projector=args.projector, iterations=args.iterations)
    frames = FrameReconstructor(proj, settings)
    warm = WarmStart(grid.shape, device=device, blur=args.blur, blend=args.blend)
    vox = np.asarray(grid.voxel_mm)
    config = CorrelationConfig(windows=rb_windows(grid.shape), overlap=0.75, deform_iterations=1)
    default = max(1, round(WARM_SHARE * args.iterations))
    print(f"case {args.case}: grid {grid.shape} (z, y, x), {world.n_particles} particles, flow {args.flow}, "
          f"cold {args.iterations} iterations, warm default {default}; correlation {config.windows}")
    predictor = None
    rows = []
    q_first = None  # the first pair's B's Q (cold, --iterations): the series goal's reference
    reached = []
    for k in range(args.pairs):
        particles, brightness = world.pair(k)
        imgs = [[r.frame(particles[f], brightness[f], seed=100 * k + 10 * f + c) for c, r in enumerate(renderers)]
                for f in (0, 1)]
        truth = [metrics.truth_volume(grid, particles[f]) for f in (0, 1)]
        ops, images, noises = [], [], []
        for f in (0, 1):
            sig, lits, _, noise = preprocess_images(proj, imgs[f], settings)
            images.append(wp.array(np.concatenate([s.ravel() for s in sig]), dtype=float, device=device))
            ops.append(frames.operator(frames.eliminate(lits)))
            noises.append(noise)

        def run(f, n, start=None, keep=False, ops=ops, images=images, noises=noises):
            t = time.perf_counter()
            d = frames.iterate(ops[f], images[f], noises[f], iterations=n, start=start)
            if keep:
                warm.keep(d.op, d.e)
            vol = frames.volume(d.op, d.e).numpy().copy()
            return vol, time.perf_counter() - t

        vol_a, t_a = run(0, args.iterations, keep=True)
        vol_b, t_b = run(1, args.iterations)
        q_a, q_b = metrics.q_recon(vol_a, truth[0]), metrics.q_recon(vol_b, truth[1])
        if q_first is None:
            q_first = q_b
        field_cold = correlate(vol_a, vol_b, config=config, device=device)
        true_d = true_displacement(world, field_cold, grid, k, vox)
        err_cold = rms(field_cold.displacement, true_d)
        line = (f"pair {k + 1}: A Q {q_a:.3f}; B cold {args.iterations}: Q {q_b:.3f} ({t_b:.2f} s), "
                f"vectors {err_cold:.3f}")
        if predictor is not None:
            qs = []
            for n in sorted(set(counts + [default])):
                vol_w, t_w = run(1, n, start=warm.start(ops[1], predictor))
                q = metrics.q_recon(vol_w, truth[1])
                qs.append(f"{n}: {q:.3f} ({t_w:.2f} s)")
                if n == default:
                    err_w = rms(correlate(vol_a, vol_w, config=config, device=device).displacement, true_d)
                    rows.append((q_b, q, err_cold, err_w))
            line += "; B warm " + ", ".join(qs) + f"; vectors at {default}: {err_w:.3f}"
            if args.reach:
                n_reach = reach(run, 1, q_first, args.reach, truth[1], warm, ops, predictor)
                n_own = reach(run, 1, q_b, args.reach, truth[1], warm, ops, predictor)
                reached.append((n_reach, n_own))
                line += (f"; reaches pair 1's Q {q_first:.3f} warm at {n_reach or f'more than {args.reach}'} "
                         f"iterations, its own cold Q at {n_own or f'more than {args.reach}'}")
        print(line, flush=True)
        predictor = predictor_field(vol_a, vol_b, device=device)
    if reached:
        for k, what in ((0, f"pair 1's Q {q_first:.3f}"), (1, "their own cold Q")):
            its = [r[k] for r in reached]
            print(f"series goal: {sum(n is not None for n in its)} of {len(its)} later B frames reach {what} within "
                  f"{args.reach} warm iterations (a quarter of {args.iterations} is {args.iterations / 4:g}); "
                  f"iterations {', '.join('-' if n is None else str(n) for n in its)}")
    if rows:
        r = np.array(rows)
        print(f"pairs 2-{args.pairs}, B at {default} warm iterations against {args.iterations} cold: "
              f"Q {r[:, 1].mean():.3f} vs {r[:, 0].mean():.3f}; "
              f"vector RMS error {r[:, 3].mean():.3f} vs {r[:, 2].mean():.3f} voxel")


def reach(run, f, q_target, most, truth, warm, ops, predictor):
    """The fewest iterations (1 to ``most``) from which frame ``f``, warm-started from ``warm``'s held
    frame along ``predictor``, reaches ``q_target``; None if it does not."""
    for n in range(1, most + 1):
        start = warm.start(ops[f], predictor)
        vol, _ = run(f, n, start=start)
        if metrics.q_recon(vol, truth) >= q_target:
            return n
    return None


def rb_windows(shape):
    """Two passes with windows about a third and a sixth of the box (multiples of 4, at least 8)."""
    def side(n, share):
        return max(8, int(n * share) // 4 * 4)
    nz, ny, nx = shape
    return ((side(nx, 0.34), side(ny, 0.34), side(nz, 0.34)), (side(nx, 0.17), side(ny, 0.17), side(nz, 0.17)))


def true_displacement(world, field, grid, k, vox):
    """The true displacement (x, y, z voxels) over dt at the field's window centres."""
    zc, yc, xc = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    centres = np.stack([xc, yc, zc], axis=-1).reshape(-1, 3)
    pts = np.asarray(grid.origin_mm) + centres * vox
    from lfcore.flows import advect

    moved = advect(world._field, pts, world.t0_s(k), world.dt_s)
    return ((moved - pts) / vox).reshape(field.displacement.shape)


def rms(measured, truth) -> float:
    ok = np.all(np.isfinite(measured), axis=-1)
    return float(np.sqrt(np.mean(np.sum((measured[ok] - truth[ok]) ** 2, axis=-1))))


if __name__ == "__main__":
    main()
