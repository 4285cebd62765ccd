"""Depth slabs (:mod:`lfcore.slabs`, :mod:`lfcore.slab_correlate`) against the in-memory reconstruction
and correlation: peak memory, time, the volume or the vectors.

Run from the repository root::

    python benchmarks/slabs.py                       # tiny rig at PVR (0.5, 0.5, 2): 12.9 M voxels
    python benchmarks/slabs.py --pvr 1,1,2 --slabs 3
    python benchmarks/slabs.py --device cuda --pvr 0.25,0.25,2 --slabs 8   # on a GPU (benchmarks/gpu.sh slabs)
    python benchmarks/slabs.py --plans               # slabs with fast's plan against slabs with the plain one
    python benchmarks/slabs.py --correlate           # a 128 x 128 x 384 blob pair in 8 slabs
    python benchmarks/slabs.py --correlate --shape 512,256,256 --slabs 8

With ``--correlate`` the pair is a blob pair moved by a flow that varies along z, stored in a zarr
array chunked as a run store's volumes; in memory both volumes are read whole and correlated, in
slabs each slab is read with its halo (:class:`lfcore.slab_correlate.SlabCorrelator`). Printed per
mode as for the reconstruction, then the largest difference between the two vector fields (voxels)
and whether their flags agree. The correlation's batch buffers are capped (``--batch-mib``) so that
the volumes, not the FFT batch, set the memory.

Each mode runs in a process of its own (so that its peak resident memory is its own): one frame of
the tiny rig's camera (0.05 PPM), DRT-MART, written into a zarr array chunked as a run store's
volumes are, in memory (the whole volume at once) and in slabs (slab by slab). Printed per mode: the
process's peak resident memory, its rise over the memory held once the projector is built, the
memory the slab path accounts for its weights and buffers, and the seconds; then the largest
difference between the two volumes relative to the volume's maximum. On a GPU the resident memory
is the host's, the accounted figure the device's.

With ``--plans`` the frame is reconstructed in slabs by the plain plan (``--protocol fixed``: elimination,
one operator, ``--iterations`` with the pruning) and by the ``fast`` protocol's (coarse-to-fine elimination,
20 line-of-sight first iterations, 6 ordered subsets, the stopping rule at most 400; no warm start), and
in memory by ``fast``'s: per run the CPU seconds (:func:`time.process_time`), the wall seconds, the
iterations, the active voxels, Q against the truth and the peak memory; then the largest difference
between ``fast``'s volumes in slabs and in memory.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _rss_bytes(field: str = "VmRSS") -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    return 0


def _frame(pvr: tuple[float, float, float], device: str, ppm: float = 0.05):
    """The tiny rig, its grid at ``pvr``, the particles and one frame of its camera (``ppm``)."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer
    from lfcore.volume import VolumeGrid
    from lfpiv.rigfile import load_rig

    rig = load_rig(ROOT / "examples" / "tiny.toml")
    grid = VolumeGrid.from_rig(rig, pvr=pvr)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(5))
    cfg = rig.render.model_copy(update={"rays_per_particle": 20_000})
    images = [LightFieldRenderer(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(pts, 50_000.0,
                                                                                                     seed=1)
              for c in rig.camera]
    return rig, grid, pts, images


def _settings(plan: str, iterations: int):
    from lfcore.reconstruct import ReconSettings, protocol_settings

    if plan == "fast":  # the protocol's whole plan but the warm start (a series' only; slabs leave it out)
        return protocol_settings("fast", warm_start=False)
    if plan == "fixed":
        return protocol_settings("fixed", iterations=iterations)
    return ReconSettings(iterations=iterations)


def child(mode: str, pvr: tuple[float, float, float], n_slabs: int, iterations: int, out: str, device: str,
          plan: str = "plain", ppm: float = 0.05) -> None:
    import zarr

    from lfcore.projector import LightFieldProjector
    from lfcore.reconstruct import FrameReconstructor
    from lfcore.slabs import SlabReconstructor, plan_slabs

    rig, grid, pts, images = _frame(pvr, device, ppm)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    nz, ny, nx = grid.shape
    data = zarr.open_array(out, mode="w", shape=grid.shape, dtype=np.float32,
                           chunks=(min(nz, 16), min(ny, 256), min(nx, 256)), fill_value=0.0)
    settings = _settings(plan, iterations)
    base = _rss_bytes()
    t0, c0 = time.perf_counter(), time.process_time()
    if mode == "memory":
        res = FrameReconstructor(proj, settings).reconstruct(images)
        data[...] = res.volume
        peak_accounted = 0
    else:
        def write(z0: int, z1: int, planes: np.ndarray) -> None:
            data[z0:z1] = planes

        res = SlabReconstructor(proj, settings, slabs=plan_slabs(nz, n_slabs)).reconstruct(images, write=write)
        peak_accounted = res.peak_bytes
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"mode": mode, "voxels": grid.n_voxels, "shape": list(grid.shape), "active": res.active_voxels,
                      "weight_bytes": res.weight_bytes, "peak_rss": peak, "base_rss": base,
                      "peak_accounted": peak_accounted, "seconds": seconds, "slabs": res.slabs, "cpu": cpu,
                      "iterations": res.iterations, "stopped": res.stopped, "final": res.final_voxels,
                      "operator": res.operator}))


#: The correlation of ``--correlate``: two passes and two deformation passes (cubic B-spline).
CORRELATE_WINDOWS = ((32, 32, 16), (16, 16, 8))


def _correlation_config(batch_mib: int):
    from lfcore.correlate import CorrelationConfig

    return CorrelationConfig(windows=CORRELATE_WINDOWS, overlap=0.75, batch_bytes=batch_mib << 20)


def make_pair(shape: tuple[int, int, int], out: str) -> None:
    """A blob pair of ``shape`` (z, y, x), moved by a flow that varies along z, into a zarr array
    (2, z, y, x) chunked as a run store's volumes."""
    import zarr

    sys.path.insert(0, str(ROOT))
    from tests.blobs import blob_pair

    nz = shape[0]

    def flow(p: np.ndarray) -> np.ndarray:
        r = p[:, 2] - nz / 2
        return np.stack([0.5 + 0.004 * r, -0.3 + 0.0 * r, 0.6 - 0.003 * r], axis=1)

    a, b = blob_pair(shape, flow, seed=3, density=0.01)
    data = zarr.open_array(out, mode="w", shape=(2, *shape), dtype=np.float32,
                           chunks=(1, min(nz, 16), min(shape[1], 256), min(shape[2], 256)), fill_value=0.0)
    data[0], data[1] = a, b


def correlate_child(mode: str, n_slabs: int, out: str, device: str, batch_mib: int) -> None:
    import zarr

    from lfcore.correlate import Correlator
    from lfcore.slab_correlate import SlabCorrelator, correlator_bytes

    data = zarr.open_array(out, mode="r")
    shape = tuple(data.shape[1:])
    cfg = _correlation_config(batch_mib)
    base = _rss_bytes()
    t0 = time.perf_counter()
    if mode == "memory":
        a, b = data[0], data[1]
        corr = Correlator(shape, config=cfg, device=device)
        field = corr(a, b)
        accounted, slabs, deepest = correlator_bytes(corr) + a.nbytes + b.nbytes, 1, shape[0]
    else:
        corr = SlabCorrelator(shape, cfg, n_slabs, device=device)
        field = corr(lambda lo, hi: (data[0, lo:hi], data[1, lo:hi]))
        accounted, slabs, deepest = corr.peak_bytes, len(corr.slabs), max(s.depth for s in corr.slabs)
    seconds = time.perf_counter() - t0
    # the high-water mark of this process's own memory: ru_maxrss would carry over the parent's,
    # which holds the rendered pair, across fork and exec
    peak = _rss_bytes("VmHWM")
    np.savez(out + f".{mode}.npz", displacement=field.displacement, outlier=field.outlier, replaced=field.replaced)
    print(json.dumps({"mode": mode, "voxels": int(np.prod(shape)), "shape": list(shape), "peak_rss": peak,
                      "base_rss": base, "peak_accounted": int(accounted), "seconds": seconds, "slabs": slabs,
                      "deepest": int(deepest), "vectors": int(np.prod(field.shape))}))


def correlate_main(args: argparse.Namespace) -> None:
    shape = tuple(int(v) for v in args.shape.split(","))[::-1]  # given x,y,z
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "pair.zarr")
        make_pair(shape, out)
        for mode in ("memory", "slabs"):
            run = subprocess.run([sys.executable, __file__, "--correlate", "--child", mode, "--slabs", str(args.slabs),
                                  "--out", out, "--device", args.device, "--batch-mib", str(args.batch_mib)],
                                 check=True, capture_output=True, text=True, cwd=ROOT)
            rows[mode] = json.loads(run.stdout.strip().splitlines()[-1])
            rows[mode]["field"] = dict(np.load(out + f".{mode}.npz"))
    a, b = rows["memory"]["field"], rows["slabs"]["field"]
    m = rows["memory"]
    print(f"{args.device}, blob pair {' x '.join(map(str, shape[::-1]))} voxels (x, y, z), {m['voxels']:,} voxels, "
          f"{m['vectors']:,} vectors, windows {CORRELATE_WINDOWS} at 75% and 2 deformation passes, batch "
          f"{args.batch_mib} MiB")
    for mode, r in rows.items():
        print(f"  {mode:7s} ({r['slabs']} slab(s), deepest {r['deepest']} planes): peak RSS "
              f"{r['peak_rss'] / 2**20:.0f} MiB, {(r['peak_rss'] - r['base_rss']) / 2**20:.0f} MiB over the "
              f"{r['base_rss'] / 2**20:.0f} MiB held before, accounted {r['peak_accounted'] / 2**20:.1f} MiB; "
              f"{r['seconds']:.1f} s")
    same = all(np.array_equal(a[k], b[k]) for k in ("outlier", "replaced"))
    print(f"  largest difference: {np.nanmax(np.abs(a['displacement'] - b['displacement'])):.2e} voxel; flags "
          f"{'identical' if same else 'DIFFERENT'}")


def plans_main(args: argparse.Namespace, pvr: tuple[float, float, float]) -> None:
    """Slabs by the plain plan and by fast's, and fast's in memory: CPU seconds and Q against the truth."""
    import zarr

    from lfcore import metrics

    runs = (("slabs", "fixed"), ("slabs", "fast"), ("memory", "fast"))
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode, plan in runs:
            out = str(Path(tmp) / f"{mode}-{plan}.zarr")
            run = subprocess.run([sys.executable, __file__, "--child", mode, "--plan", plan, "--pvr", args.pvr,
                                  "--slabs", str(args.slabs), "--iterations", str(args.iterations), "--out", out,
                                  "--device", args.device, "--ppm", str(args.ppm)],
                                 check=True, capture_output=True, text=True, cwd=ROOT)
            rows[mode, plan] = json.loads(run.stdout.strip().splitlines()[-1])
            rows[mode, plan]["volume"] = zarr.open_array(out, mode="r")[...]
    _, grid, pts, _ = _frame(pvr, "cpu", args.ppm)
    truth = metrics.truth_volume(grid, pts)
    m = rows["slabs", "fixed"]
    print(f"{args.device}, tiny rig at PVR {pvr}: {m['voxels']:,} voxels {tuple(m['shape'][::-1])} (x, y, z), "
          f"{len(pts):,} particles ({args.ppm:g} PPM), {args.slabs} slabs")
    for (mode, plan), r in rows.items():
        q = metrics.q_recon(r["volume"], truth)
        print(f"  {mode:6s} {plan:5s}: CPU {r['cpu']:.1f} s, wall {r['seconds']:.1f} s; {r['iterations']} iterations "
              f"({r['stopped']}); {r['active']:,} active, {r['final']:,} left; Q {q:.3f}; peak RSS "
              f"{r['peak_rss'] / 2**20:.0f} MiB ({(r['peak_rss'] - r['base_rss']) / 2**20:.0f} over), accounted "
              f"{r['peak_accounted'] / 2**20:.1f} MiB; {r['operator']}")
    a, b = rows["memory", "fast"]["volume"], rows["slabs", "fast"]["volume"]
    worst = np.abs(a - b).max() / max(float(a.max()), 1e-30)
    print(f"  fast in slabs against in memory: largest difference {worst:.2e} of the volume's maximum")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pvr", default="0.5,0.5,2")
    ap.add_argument("--slabs", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--correlate", action="store_true", help="correlation in slabs instead of reconstruction")
    ap.add_argument("--plans", action="store_true", help="slabs by fast's plan against slabs by the plain one")
    ap.add_argument("--plan", default="plain", help=argparse.SUPPRESS)
    ap.add_argument("--ppm", type=float, default=0.05, help="the frame's seeding, particles per microlens")
    ap.add_argument("--shape", default="128,128,384", help="--correlate: the pair's x,y,z voxels")
    ap.add_argument("--batch-mib", type=int, default=16, help="--correlate: the correlator's batch buffers")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.correlate:
        if args.child:
            correlate_child(args.child, args.slabs, args.out, args.device, args.batch_mib)
        else:
            correlate_main(args)
        return
    pvr = tuple(float(v) for v in args.pvr.split(","))
    if args.child:
        child(args.child, pvr, args.slabs, args.iterations, args.out, args.device, args.plan, args.ppm)
        return
    if args.plans:
        plans_main(args, pvr)
        return
    import zarr

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("memory", "slabs"):
            out = str(Path(tmp) / f"{mode}.zarr")
            run = subprocess.run([sys.executable, __file__, "--child", mode, "--pvr", args.pvr, "--slabs",
                                  str(args.slabs), "--iterations", str(args.iterations), "--out", out,
                                  "--device", args.device, "--ppm", str(args.ppm)],
                                 check=True, capture_output=True, text=True, cwd=ROOT)
            rows[mode] = json.loads(run.stdout.strip().splitlines()[-1])
            rows[mode]["volume"] = zarr.open_array(out, mode="r")[...]
    a, b = rows["memory"]["volume"], rows["slabs"]["volume"]
    m = rows["memory"]
    print(f"{args.device}, tiny rig at PVR {pvr}: {m['voxels']:,} voxels {tuple(m['shape'][::-1])} (x, y, z), "
          f"{m['active']:,} active, weights {m['weight_bytes'] / 2**20:.1f} MiB, {args.iterations} iterations")
    for mode, r in rows.items():
        acc = f", accounted {r['peak_accounted'] / 2**20:.1f} MiB" if r["peak_accounted"] else ""
        print(f"  {mode:7s} ({r['slabs']} slab(s)): peak RSS {r['peak_rss'] / 2**20:.0f} MiB, "
              f"{(r['peak_rss'] - r['base_rss']) / 2**20:.0f} MiB over the {r['base_rss'] / 2**20:.0f} MiB held "
              f"before{acc}; {r['seconds']:.1f} s")
    print(f"  largest difference: {np.abs(a - b).max() / max(float(a.max()), 1e-30):.2e} of the volume's maximum")


if __name__ == "__main__":
    main()
