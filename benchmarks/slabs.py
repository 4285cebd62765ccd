"""Depth slabs (:mod:`lfcore.slabs`) against the in-memory reconstruction: peak memory, time, the volume.

Run from the repository root::

    python benchmarks/slabs.py                       # tiny rig at PVR (0.5, 0.5, 2): 12.9 M voxels
    python benchmarks/slabs.py --pvr 1,1,2 --slabs 3
    python benchmarks/slabs.py --device cuda --pvr 0.25,0.25,2 --slabs 8   # on a GPU (benchmarks/gpu.sh slabs)

Each mode runs in a process of its own (so that its peak resident memory is its own): one frame of
the tiny rig's camera (0.05 PPM), DRT-MART, written into a zarr array chunked as a run store's
volumes are, in memory (the whole volume at once) and in slabs (slab by slab). Printed per mode: the
process's peak resident memory, its rise over the memory held once the projector is built, the
memory the slab path accounts for its weights and buffers, and the seconds; then the largest
difference between the two volumes relative to the volume's maximum. On a GPU the resident memory
is the host's, the accounted figure the device's.
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


def _rss_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def child(mode: str, pvr: tuple[float, float, float], n_slabs: int, iterations: int, out: str, device: str) -> None:
    import zarr

    from lfcore.particles import particle_count, seed_particles
    from lfcore.projector import Projector
    from lfcore.reconstruct import FrameReconstructor, ReconSettings
    from lfcore.render import LightFieldRenderer
    from lfcore.slabs import SlabReconstructor, plan_slabs
    from lfcore.volume import VolumeGrid
    from lfpiv.rigfile import load_rig

    rig = load_rig(ROOT / "examples" / "tiny.toml")
    grid = VolumeGrid.from_rig(rig, pvr)
    pts = seed_particles(rig.volume, particle_count(rig, 0.05), np.random.default_rng(5))
    cfg = rig.render.model_copy(update={"rays_per_particle": 20_000})
    images = [LightFieldRenderer(c, cfg, rig.laser.wavelength_nm, device=device).frame(pts, 50_000.0, seed=1)
              for c in rig.camera]
    proj = Projector(rig.camera, grid, device=device)
    nz, ny, nx = grid.shape
    data = zarr.open_array(out, mode="w", shape=grid.shape, dtype=np.float32,
                           chunks=(min(nz, 16), min(ny, 256), min(nx, 256)), fill_value=0.0)
    settings = ReconSettings(iterations=iterations)
    base = _rss_bytes()
    t0 = time.perf_counter()
    if mode == "memory":
        res = FrameReconstructor(proj, settings).reconstruct(images)
        data[...] = res.volume
        peak_accounted = 0
    else:
        def write(z0: int, z1: int, planes: np.ndarray) -> None:
            data[z0:z1] = planes

        res = SlabReconstructor(proj, settings, slabs=plan_slabs(nz, n_slabs)).reconstruct(images, write=write)
        peak_accounted = res.peak_bytes
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"mode": mode, "voxels": grid.n_voxels, "shape": list(grid.shape), "active": res.active_voxels,
                      "weight_bytes": res.weight_bytes, "peak_rss": peak, "base_rss": base,
                      "peak_accounted": peak_accounted, "seconds": seconds, "slabs": res.slabs}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pvr", default="0.5,0.5,2")
    ap.add_argument("--slabs", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    pvr = tuple(float(v) for v in args.pvr.split(","))
    if args.child:
        child(args.child, pvr, args.slabs, args.iterations, args.out, args.device)
        return
    import zarr

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("memory", "slabs"):
            out = str(Path(tmp) / f"{mode}.zarr")
            run = subprocess.run([sys.executable, __file__, "--child", mode, "--pvr", args.pvr, "--slabs",
                                  str(args.slabs), "--iterations", str(args.iterations), "--out", out,
                                  "--device", args.device],
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
