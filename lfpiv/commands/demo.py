"""``lfpiv demo``: the instrument on simulated hardware, end to end as far as it is built."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from lfpiv.commands import add_device, examples_dir, positive_int, warn_optics
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("demo", help="render a synthetic vortex-ring run on simulated hardware and picture it",
                       description="Render a synthetic vortex-ring run with the example rig and write "
                       "DIR/run.zarr and DIR/raw_images.png (a previous demo's files in DIR are replaced).")
    d.add_argument("--out", default="demo-output", metavar="DIR", help="output folder (default: demo-output)")
    d.add_argument("--rig", default=None, metavar="RIG", help="rig file (default: examples/one_camera.toml)")
    d.add_argument("--pairs", type=positive_int, default=2, help="double-frame pairs (default: 2)")
    d.add_argument("--rays", type=positive_int, default=None, help="rays per particle (default: the rig's)")
    add_device(d)
    d.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfcore.runstore import RunStore, RunStoreError
    from lfpiv.plots import plot_raw_images
    from lfpiv.rigfile import load_rig
    from lfpiv.synth import synthesize

    rig_path = Path(args.rig) if args.rig else examples_dir() / "one_camera.toml"
    rig = load_rig(rig_path)
    warn_optics(rig)
    out = Path(args.out)
    run_path = out / "run.zarr"
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the demo's output")
    if run_path.exists():
        # Replace only what an earlier demo wrote: never a user's recording.
        try:
            previous_demo = RunStore.open(run_path).attrs.get("demo") is True
        except RunStoreError:
            previous_demo = False
        if not previous_demo:
            raise UsageError(f"{run_path} exists and was not written by 'lfpiv demo'; choose another --out")
        shutil.rmtree(run_path)
    print(f"lfpiv demo: rendering a vortex ring seen by {len(rig.camera)} light-field camera(s) "
          f"from {rig_path} into {run_path}", file=sys.stderr)
    res = synthesize(rig, run_path, flow="vortex-ring", ppm=0.5, pairs=args.pairs, seed=1,
                     rays_per_particle=args.rays, device=args.device, attrs={"demo": True})
    png = plot_raw_images(res.store, out / "raw_images.png")
    print(f"rendered {res.store.n_pairs} pair(s), {res.particles_per_frame} particles per frame, "
          f"{res.rays:.3g} rays in {res.seconds:.1f} s ({res.rays / res.seconds:.3g} rays/s "
          f"on {res.store.truth()['attrs']['device']})")
    print(f"run store: {run_path}   (inspect with: lfpiv info {run_path})")
    print(f"picture:   {png}")
    return 0
