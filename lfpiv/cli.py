"""The ``lfpiv`` command.

Bad input never produces a traceback: it is reported as one line on stderr naming the problem
and the fix, with exit code 2. Ctrl-C exits with 130 after marking an unfinished run aborted.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from lfpiv import __version__
from lfpiv.errors import UsageError

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (no usage dump) raised as UsageError."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return v


def _examples_dir() -> Path:
    return Path(__file__).resolve().parents[1] / "examples"


def _build_parser() -> argparse.ArgumentParser:
    from lfcore.flows import FLOW_NAMES

    p = _Parser(prog="lfpiv", description="Light-field particle image velocimetry: rigs, runs, "
                "synthetic images.")
    p.add_argument("--version", action="version", version=f"lfpiv {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    d = sub.add_parser("demo", help="render a synthetic vortex-ring run on simulated hardware and picture it",
                       description="Render a synthetic vortex-ring run with the example rig and write "
                       "DIR/run.zarr and DIR/raw_images.png (a previous demo's files in DIR are replaced).")
    d.add_argument("--out", default="demo-output", metavar="DIR", help="output folder (default: demo-output)")
    d.add_argument("--rig", default=None, metavar="RIG", help="rig file (default: examples/one_camera.toml)")
    d.add_argument("--pairs", type=_positive_int, default=2, help="double-frame pairs (default: 2)")
    d.add_argument("--rays", type=_positive_int, default=None, help="rays per particle (default: the rig's)")
    d.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: a GPU if there is one)")

    s = sub.add_parser("synth", help="render a synthetic run of a known flow into a run store",
                       description="Seed particles, move them with a known flow and render every camera's "
                       "double-frame pairs into a new run store, with the truth beside them.")
    s.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    s.add_argument("--out", required=True, metavar="RUN", help="run store to create (a .zarr directory)")
    s.add_argument("--flow", default="vortex-ring", choices=FLOW_NAMES, metavar="FLOW",
                   help=f"one of {', '.join(FLOW_NAMES)} (default: vortex-ring)")
    s.add_argument("--omega", type=_positive_float, default=1.0,
                   help="wavelength factor of the A/B cases; the chapter used 0.25, 0.5, 1, 2 (default: 1)")
    s.add_argument("--ppm", type=_positive_float, default=0.5, help="particles per microlens (default: 0.5)")
    s.add_argument("--pairs", type=_positive_int, default=3, help="double-frame pairs (default: 3)")
    s.add_argument("--dt-ms", type=_positive_float, default=None,
                   help="time between frames A and B in ms (default: the rig's timing.dt_us)")
    s.add_argument("--seed", type=int, default=1, help="random seed (default: 1)")
    s.add_argument("--displacement-px", type=_positive_float, default=None,
                   help="peak particle displacement over dt in object-side pixels of the first camera "
                   "(default: 25 for A1..B4 as in the chapter, 10 otherwise)")
    s.add_argument("--particles", metavar="CSV", default=None,
                   help="render one pair of these points (header x_mm,y_mm,z_mm) instead of a flow")
    s.add_argument("--rays", type=_positive_int, default=None, help="rays per particle (default: the rig's)")
    s.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: a GPU if there is one)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar")

    i = sub.add_parser("info", help="describe a run store", description="Print a run's cameras, pairs, "
                       "flow and state.")
    i.add_argument("run", metavar="RUN", help="run store (a .zarr directory)")
    return p


def _warn_optics(rig) -> None:
    for w in rig.optics_warnings():
        print(f"lfpiv: warning: {w}", file=sys.stderr)


def _cmd_synth(args: argparse.Namespace) -> int:
    from lfpiv.rigfile import load_rig
    from lfpiv.synth import read_points_csv, synthesize

    rig = load_rig(args.rig)
    _warn_optics(rig)
    points = read_points_csv(args.particles) if args.particles else None
    res = synthesize(rig, args.out, flow=args.flow, ppm=args.ppm, pairs=args.pairs,
                     dt_s=None if args.dt_ms is None else args.dt_ms * 1e-3, seed=args.seed,
                     omega=args.omega, displacement_px=args.displacement_px, points=points,
                     rays_per_particle=args.rays, device=args.device, overwrite=args.overwrite,
                     progress=not args.quiet)
    print(f"wrote {res.store.path}: {res.store.n_pairs} pair(s) x {len(rig.camera)} camera(s), "
          f"{res.particles_per_frame} particles per frame, flow {res.flow['name']}; "
          f"{res.rays:.3g} rays in {res.seconds:.1f} s ({res.rays / res.seconds:.3g} rays/s)")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    import shutil

    from lfcore.runstore import RunStore, RunStoreError
    from lfpiv.plots import plot_raw_images
    from lfpiv.rigfile import load_rig
    from lfpiv.synth import synthesize

    rig_path = Path(args.rig) if args.rig else _examples_dir() / "one_camera.toml"
    rig = load_rig(rig_path)
    _warn_optics(rig)
    out = Path(args.out)
    run = out / "run.zarr"
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the demo's output")
    if run.exists():
        # Replace only what an earlier demo wrote: never a user's recording.
        try:
            previous_demo = RunStore.open(run).attrs.get("demo") is True
        except RunStoreError:
            previous_demo = False
        if not previous_demo:
            raise UsageError(f"{run} exists and was not written by 'lfpiv demo'; choose another --out")
        shutil.rmtree(run)
    print(f"lfpiv demo: rendering a vortex ring seen by {len(rig.camera)} light-field camera(s) "
          f"from {rig_path} into {run}", file=sys.stderr)
    res = synthesize(rig, run, flow="vortex-ring", ppm=0.5, pairs=args.pairs, seed=1,
                     rays_per_particle=args.rays, device=args.device, attrs={"demo": True})
    png = plot_raw_images(res.store, out / "raw_images.png")
    print(f"rendered {res.store.n_pairs} pair(s), {res.particles_per_frame} particles per frame, "
          f"{res.rays:.3g} rays in {res.seconds:.1f} s ({res.rays / res.seconds:.3g} rays/s "
          f"on {res.store.truth()['attrs']['device']})")
    print(f"run store: {run}   (inspect with: lfpiv info {run})")
    print(f"picture:   {png}")
    return 0


def _fmt_params(params: dict) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, list):
            return "(" + ", ".join(fmt(x) for x in v) + ")"
        return str(v)

    return ", ".join(f"{k}={fmt(v)}" for k, v in params.items() if k != "name")


def _cmd_info(args: argparse.Namespace) -> int:
    from lfcore.mla import lenslet_count
    from lfcore.runstore import RunStore
    from lfcore.volume import VolumeGrid

    store = RunStore.open(args.run)
    a = store.attrs
    rig = store.rig
    t = store.timing
    grid = VolumeGrid.from_rig(rig)
    v = rig.volume
    lines = [
        ("run", str(store.path)),
        ("state", f"{store.state} ({store.committed_pairs} of {store.n_pairs} pairs committed)"),
        ("created", f"{a.get('created')} by lfpiv {a.get('software_version')}"),
        ("timing", f"dt {t['dt_s'] * 1e3:g} ms, pairs at {t['rate_hz']:g} Hz"),
        ("volume", f"{' x '.join(f'{s:g}' for s in v.size_mm)} mm centred at "
                   f"({', '.join(f'{c:g}' for c in v.centre_mm)}); {' x '.join(str(n) for n in grid.shape[::-1])} "
                   f"voxels (x, y, z) at PVR ({', '.join(f'{p:g}' for p in v.pvr)})"),
    ]
    for cam in rig.camera:
        lines.append(("camera", f"{cam.name}: {cam.sensor_px[0]} x {cam.sensor_px[1]} px of {cam.pixel_pitch_um:g} um, "
                                f"{cam.mla_grid} MLA {cam.mla_pitch_um:g} um ({lenslet_count(cam)} lenslets, "
                                f"{cam.pixels_per_lenslet:.1f} px across), F {cam.main_focal_length_mm:g} mm "
                                f"f/{cam.f_number:g}, M {cam.magnification:g}, rotation "
                                f"({', '.join(f'{r:g}' for r in cam.rotation_deg)}) deg"))
    truth = store.truth()
    if truth:
        flow = truth["attrs"]["flow"]
        lines.append(("flow", f"{flow['name']}: {_fmt_params(flow)}"))
        ppm = truth["attrs"].get("ppm")
        lines.append(("truth", f"{truth['particles'].shape[2]} particles per frame"
                               + (f" ({ppm:g} PPM)" if ppm else "") + f", seed {truth['attrs'].get('seed')}"))
    else:
        lines.append(("flow", "unknown (recorded run, no truth)"))
    drops = store.drops()
    lines.append(("drops", "none" if not drops else f"{len(drops)} frame(s) lost, e.g. {drops[0]['reason']}"))
    width = max(len(k) for k, _ in lines)
    for k, val in lines:
        print(f"{k:<{width}}  {val}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfpiv`` command; returns the exit code."""
    from lfcore.device import DeviceError
    from lfcore.rig import RigError
    from lfcore.runstore import RunStoreError

    warnings.filterwarnings("ignore", category=UserWarning, module="zarr")
    try:
        args = _build_parser().parse_args(argv)
        return {"synth": _cmd_synth, "demo": _cmd_demo, "info": _cmd_info}[args.command](args)
    except (UsageError, RigError, RunStoreError, DeviceError) as exc:
        print(f"lfpiv: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("lfpiv: interrupted; what was recorded so far is kept", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    raise SystemExit(main())
