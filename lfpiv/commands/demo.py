"""``lfpiv demo``: the whole instrument on simulated hardware, end to end.

Each step is an ordinary ``lfpiv`` command, printed before it runs, so the demo doubles as a
walk-through of what a user types in the lab.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shlex
import sys
import time
from pathlib import Path

from lfpiv.commands import add_device, examples_dir, positive_int, rays_per_particle
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("demo", help="the whole instrument on simulated hardware: calibrate, record, reconstruct, "
                       "vectors, pictures",
                       description="Calibrate two simulated light-field cameras (microlens grids and the "
                       "volumetric calibration planes), record a vortex ring on the simulated lab, reconstruct "
                       "it with DRT-MART, correlate the volumes into 3D vectors, evaluate against the truth, "
                       "export the field and draw pictures into DIR; then run the live monitor (a window with a "
                       "display, otherwise a screenshot). A previous demo's folder is replaced; any other "
                       "non-empty folder is refused.")
    d.add_argument("--out", default="demo-output", metavar="DIR", help="output folder (default: demo-output)")
    d.add_argument("--rig", default=None, metavar="RIG", help="rig file (default: examples/demo.toml)")
    d.add_argument("--pairs", type=positive_int, default=2, help="double-frame pairs to record (default: 2)")
    d.add_argument("--rays", type=rays_per_particle, default=None, help="rays per particle when rendering "
                   "(default: the rig's)")
    d.add_argument("--monitor", choices=("auto", "window", "screenshot", "no"), default="auto",
                   help="live monitor step: a window when a display is available, else a screenshot "
                   "(default: auto)")
    add_device(d)
    d.set_defaults(func=run)


def _step(title: str, argv: list[str]) -> None:
    from lfpiv.cli import main

    print(f"\nlfpiv demo: {title}\n$ lfpiv {shlex.join(argv)}", file=sys.stderr, flush=True)
    t = time.perf_counter()
    code = main(argv)
    if code != 0:
        raise SystemExit(code)
    print(f"({time.perf_counter() - t:.1f} s)", file=sys.stderr, flush=True)


def _monitor_mode(choice: str) -> str:
    if choice == "no":
        return "no"
    if importlib.util.find_spec("pyqtgraph") is None:
        print("lfpiv demo: skipping the live monitor (install it with: pip install 'lfpiv[gui]')", file=sys.stderr)
        return "no"
    if choice == "auto":
        return "window" if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else "screenshot"
    return choice


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.demo import check_device, demo_windows, pictures, prepare_folder
    from lfpiv.rigfile import load_rig

    rig_path = Path(args.rig) if args.rig else examples_dir() / "demo.toml"
    rig = load_rig(rig_path)
    if rig.hardware != "sim":
        raise UsageError(f"{rig_path} has hardware = \"{rig.hardware}\"; the demo runs on the simulated lab only")
    if args.device:  # checked before the previous demo's folder is cleared
        check_device(args.device)
    out = Path(args.out)
    prepare_folder(out)
    rig_s, calib, run_ = str(rig_path), str(out / "calib.zarr"), str(out / "run.zarr")
    dev = ["--device", args.device] if args.device else []
    rays = ["--sim-rays", str(args.rays)] if args.rays else []
    start = time.perf_counter()

    _step("calibration 1/3: the microlens grid of each camera from a white image",
          ["calibrate", "mla", "--rig", rig_s, "--out", calib])
    _step("calibration 2/3: the dot target through 5 stage planes, seen by both cameras (the laser stays off)",
          ["calibrate", "volume", "--rig", rig_s, "--planes", "5", "--step-mm", "0.2", "--out", calib])
    _step("calibration 3/3: the fit of each camera's model from the dots, both cameras in one world frame",
          ["calibrate", "fit", calib])
    _step("calibration report", ["calibrate", "report", calib, "--plot", str(out / "calibration.png")])
    _step(f"recording {args.pairs} double-frame pair(s) of a vortex ring: the pulse generator fires the laser and "
          "triggers both cameras", ["acquire", "--rig", rig_s, "--pairs", str(args.pairs), "--out", run_,
                                    "--sim-pool", str(min(args.pairs, 4)), "--quiet", *rays])
    _step("reconstruction: DRT-MART, both cameras jointly", ["reconstruct", run_, *dev])
    _step("3D multi-grid cross-correlation", ["correlate", run_, "--windows", demo_windows(run_), "--overlap", "0.5",
                                             "--quiet", *dev])
    _step("accuracy against the simulated truth", ["evaluate", run_, "--plot", str(out / "quality.png")])
    _step("export of the velocity field", ["export", run_, "--format", "netcdf", "--out", str(out / "field")])
    shown = [*pictures(run_, out), out / "quality.png", out / "calibration.png"]

    mode = _monitor_mode(args.monitor)
    if mode != "no":
        live = ["monitor", "--rig", rig_s, "--sim-pool", "2", "--quiet", *dev, *rays]
        if mode == "screenshot":
            os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
            live += ["--pairs", "30", "--out", str(out / "live.zarr"), "--screenshot", str(out / "monitor.png"),
                     "--after", "1"]
            shown.append(out / "monitor.png")
            title = "the live monitor, offscreen (no display): a screenshot after the first processed pair"
        else:
            live += ["--out", str(out / "live.zarr")]
            title = "the live monitor (close its window to finish)"
        _step(title, live)

    print(f"\nlfpiv demo: done in {time.perf_counter() - start:.0f} s. In {out}/:")
    print(f"  calib.zarr        calibration store        (lfpiv calibrate report {calib})")
    print(f"  run.zarr          the recorded run, with volumes/ and vectors/   (lfpiv info {run_})")
    print("  field/            the velocity field as netCDF")
    for p in shown:
        print(f"  {p.name:<17} picture")
    return 0
