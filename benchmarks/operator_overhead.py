"""The operator protocol's cost: one SMART iteration through the operator (lfcore.operator) against
the same kernels launched directly on the same stored weights, in alternating blocks in one process.

Run from the repository root::

    python benchmarks/operator_overhead.py                 # tiny rig, CPU
    python benchmarks/operator_overhead.py --device cuda

The reconstruction's algorithms see only the operator (``op.forward``, ``log_ratio``, ``op.update``);
this measures what that indirection adds per iteration beside the bare launches of the kernels it
wraps (``project_rows``/``project``, ``log_ratio``, ``smart_update``), which should be nothing
measurable. The blocks alternate, each first in every other round, so that a shared machine's drift
falls on both; the medians and their ratio are printed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore._kernels import mart as km  # noqa: E402
from lfcore.device import RowOffset, Rows, launch_rows, resolve_device, warp  # noqa: E402
from lfcore.operator import log_ratio  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import FrameReconstructor, ReconSettings, preprocess_images  # noqa: E402
from lfcore.render import LightFieldRenderer  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfcore.weight_build import LANES  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="cpu or cuda (default: a GPU if there is one)")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=50, help="iterations per block")
    args = ap.parse_args()
    device = resolve_device(args.device)
    wp = warp()
    rig = load_rig(ROOT / "examples" / "tiny.toml")
    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=0.5), np.random.default_rng(3))
    img = LightFieldRenderer(rig.camera[0], rig.render, wavelength_nm=rig.laser.wavelength_nm,
                             device=device).frame(pts, rig.render.particle_counts, seed=1)
    proj = projector_for(rig.camera, grid, device=device)
    frames = FrameReconstructor(proj, ReconSettings(projector="stored"))
    signals, lits, _, _ = preprocess_images(proj, [img], frames.settings)
    image = wp.array(np.concatenate([s.ravel() for s in signals]), dtype=float, device=device)
    op = frames.operator(frames.eliminate(lits))
    e = wp.array(np.ones(op.n_voxels, np.float32), dtype=float, device=device)
    projection = wp.zeros(proj.n_pixels, dtype=float, device=device)
    ratio = wp.empty(proj.n_pixels, dtype=float, device=device)
    parts = proj._parts  # the projector's private images for the CPU blocks, which the operator uses too

    def bare() -> None:
        projection.zero_()
        per = parts.open(projection)
        for c in op.chunks:
            if device == "cpu":
                launch_rows(km.project_rows, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), e, per],
                            device)
            else:
                launch_rows(km.project, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), LANES, e, per],
                            device, rest=(LANES,))
        parts.close(projection)
        wp.launch(km.log_ratio, dim=proj.n_pixels, inputs=[image, projection, 1.0, ratio], device=device)
        for c in op.chunks:
            if device == "cpu":
                launch_rows(km.smart_update, c.n, [Rows(c.offsets, extra=1), c.pix, c.w, RowOffset(c.first), ratio,
                                                   1.0, e], device)
            elif c.n:
                wp.launch_tiled(km.smart_update_tiled, dim=[c.n], block_dim=LANES, device=device,
                                inputs=[c.offsets, c.pix, c.w, c.first, ratio, 1.0, e])

    def through_the_operator() -> None:
        op.forward(e, out=projection)
        op.update(log_ratio(image, projection, 1.0, ratio), e, 1.0)

    ms: dict[str, list[float]] = {"bare kernels": [], "operator": []}
    blocks = (("bare kernels", bare), ("operator", through_the_operator))
    for f in (bare, through_the_operator):  # compiled and warm
        f()
    for r in range(args.rounds):
        for name, f in blocks if r % 2 == 0 else blocks[::-1]:
            e.fill_(1.0)
            wp.synchronize_device(device)
            t = time.perf_counter()
            for _ in range(args.iterations):
                f()
            wp.synchronize_device(device)
            ms[name].append(1e3 * (time.perf_counter() - t) / args.iterations)
    bare_ms, op_ms = (float(np.median(ms[k])) for k in ("bare kernels", "operator"))
    print(f"{device}: {op.n_voxels:,} active voxels, {op.nnz:,} weights ({op.kind}); {args.rounds} alternating rounds "
          f"of {args.iterations} iterations: bare kernels median {bare_ms:.2f} ms/iteration "
          f"({min(ms['bare kernels']):.2f}-{max(ms['bare kernels']):.2f}), through the operator {op_ms:.2f} "
          f"({min(ms['operator']):.2f}-{max(ms['operator']):.2f}); operator/bare {op_ms / bare_ms:.3f}")


if __name__ == "__main__":
    main()
