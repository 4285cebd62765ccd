"""``lfpiv synth``: render a synthetic run of a known flow into a run store."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import (
    add_device,
    positive_float,
    positive_int,
    rays_per_particle,
    seeding_ppm,
    seeding_ppp,
    warn_optics,
    whole_number,
)


def register(sub: argparse._SubParsersAction) -> None:
    from lfpiv.jobs.synth import FLOW_NAMES

    s = sub.add_parser("synth", help="render a synthetic run of a known flow into a run store",
                       description="Seed particles, move them with a known flow and render every camera's "
                       "double-frame pairs into a new run store, with the truth beside them.")
    s.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    s.add_argument("--out", required=True, metavar="RUN", help="run store to create (a .zarr directory)")
    s.add_argument("--flow", default="vortex-ring", choices=FLOW_NAMES, metavar="FLOW",
                   help=f"one of {', '.join(FLOW_NAMES)} (default: vortex-ring)")
    s.add_argument("--omega", type=positive_float, default=1.0,
                   help="wavelength factor of the A/B cases; the chapter used 0.25, 0.5, 1, 2 (default: 1)")
    density = s.add_mutually_exclusive_group()
    density.add_argument("--ppm", type=seeding_ppm, default=None,
                         help="particles per microlens of the first light-field camera (default: 0.5)")
    density.add_argument("--ppp", type=seeding_ppp, default=None,
                         help="particles per pixel of the first pinhole camera instead (Tomo-PIV; default for a rig of "
                         "pinhole cameras only: 0.05)")
    s.add_argument("--pairs", type=positive_int, default=3, help="double-frame pairs (default: 3)")
    s.add_argument("--dt-ms", type=positive_float, default=None,
                   help="time between frames A and B in ms (default: the rig's timing.dt_us)")
    s.add_argument("--time-resolved", action="store_true",
                   help="a time-resolved series: the same particles advected through every frame, A0, B0, A1, B1, "
                   "... each --dt-ms apart (a pair every 2 dt), for tracks through the frames (lfpiv track "
                   "--along-pairs); without it each pair is seeded afresh")
    s.add_argument("--rate-hz", type=positive_float, default=None,
                   help="pairs per second: pair i starts at i / rate (default: the rig's laser.rate_hz, or 1 / (2 dt) "
                   "with --time-resolved, which refuses any other)")
    s.add_argument("--seed", type=whole_number, default=1, help="random seed (default: 1)")
    s.add_argument("--displacement-px", type=positive_float, default=None,
                   help="peak particle displacement over dt in object-side pixels of the first camera "
                   "(default: 25 for A1..B4 as in the chapter, 10 otherwise)")
    s.add_argument("--particles", metavar="CSV", default=None,
                   help="render one pair of these points (header x_mm,y_mm,z_mm) instead of a flow")
    s.add_argument("--rays", type=rays_per_particle, default=None, help="rays per particle (default: the rig's)")
    add_device(s)
    s.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.synth import points_outside, read_points_csv, synthesize
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)
    points = read_points_csv(args.particles) if args.particles else None
    outside = 0 if points is None else points_outside(rig, points)
    if outside:
        v = rig.volume
        print(f"lfpiv: warning: {outside} of {len(points)} particles in {args.particles} lie outside the rig's "
              f"volume (centre {list(v.centre_mm)} mm, size {list(v.size_mm)} mm); they are rendered, but a "
              "reconstruction of the volume cannot hold them (positions are world millimetres)", file=sys.stderr)
    res = synthesize(rig, args.out, flow=args.flow, ppm=args.ppm, ppp=args.ppp, pairs=args.pairs,
                     dt_s=None if args.dt_ms is None else args.dt_ms * 1e-3, seed=args.seed,
                     omega=args.omega, displacement_px=args.displacement_px, points=points,
                     rays_per_particle=args.rays, device=args.device, overwrite=args.overwrite,
                     progress=not args.quiet, time_resolved=args.time_resolved, rate_hz=args.rate_hz)
    if not res.particle_images:  # light-field cameras only
        work = f"{res.rays:.3g} rays in {res.seconds:.1f} s ({res.rays / res.seconds:.3g} rays/s)"
    else:
        rays = f"{res.rays:.3g} rays ({res.rays / res.seconds:.3g} rays/s) and " if res.rays else ""
        work = f"{rays}{res.particle_images:.3g} particle images in {res.seconds:.1f} s"
    print(f"wrote {res.store.path}: {res.store.n_pairs} pair(s) x {len(rig.camera)} camera(s), "
          f"{res.particles_per_frame} particles per frame, flow {res.flow['name']}"
          f"{', a time-resolved series' if args.time_resolved else ''}; {work}")
    return 0
