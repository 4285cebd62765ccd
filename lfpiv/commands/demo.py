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

from lfpiv.commands import add_device, examples_dir, positive_int, rays_per_particle, whole_number
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("demo", help="the whole instrument on simulated hardware: calibrate, record, reconstruct, "
                       "vectors, pictures",
                       description="Calibrate two simulated light-field cameras (microlens grids and the "
                       "volumetric calibration planes), record a vortex ring on the simulated lab, reconstruct "
                       "it with DRT-MART, correlate the volumes into 3D vectors, evaluate against the truth, "
                       "export the field and draw pictures into DIR; then the particle route on a copy of the same "
                       "recording (iterative particle reconstruction and tracking), with both routes' time and error "
                       "against the truth side by side; then run the live monitor (a window with a "
                       "display, otherwise a screenshot). A previous demo's folder is replaced; any other "
                       "non-empty folder is refused.")
    d.add_argument("--out", default="demo-output", metavar="DIR", help="output folder (default: demo-output)")
    d.add_argument("--rig", default=None, metavar="RIG", help="rig file (default: examples/demo.toml)")
    d.add_argument("--pairs", type=positive_int, default=2, help="double-frame pairs to record (default: 2)")
    d.add_argument("--particle-pairs", type=whole_number, default=1, metavar="N",
                   help="pairs the particle route (lfpiv particles, lfpiv track) processes, from the first; it takes "
                   "about 40 s a pair on a 2-core CPU; 0 leaves it out (default: 1)")
    d.add_argument("--rays", type=rays_per_particle, default=None, help="rays per particle when rendering "
                   "(default: the rig's)")
    d.add_argument("--monitor", choices=("auto", "window", "screenshot", "no"), default="auto",
                   help="live monitor step: a window when a display is available, else a screenshot "
                   "(default: auto)")
    add_device(d)
    d.set_defaults(func=run)


def _step(title: str, argv: list[str]) -> float:
    """Run one ``lfpiv`` command as the demo's step; its wall time, s."""
    from lfpiv.cli import main

    print(f"\nlfpiv demo: {title}\n$ lfpiv {shlex.join(argv)}", file=sys.stderr, flush=True)
    t = time.perf_counter()
    code = main(argv)
    if code != 0:
        raise SystemExit(code)
    seconds = time.perf_counter() - t
    print(f"({seconds:.1f} s)", file=sys.stderr, flush=True)
    return seconds


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
    from lfpiv.jobs.demo import (
        check_device,
        copy_recording,
        default_plan_method,
        demo_windows,
        pictures,
        prepare_folder,
        route_figures,
        route_table,
        routes_picture,
    )
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
    method = default_plan_method(rig).upper()  # fast's: MLOS-MART on several light-field cameras
    voxels_s = _step(f"reconstruction: {method}, the cameras jointly", ["reconstruct", run_, *dev])
    windows = demo_windows(run_)
    voxels_s += _step("3D multi-grid cross-correlation", ["correlate", run_, "--windows", windows, "--overlap", "0.5",
                                                         "--quiet", *dev])
    _step("accuracy against the simulated truth", ["evaluate", run_, "--plot", str(out / "quality.png")])
    _step("export of the velocity field", ["export", run_, "--format", "netcdf", "--out", str(out / "field")])
    shown = [*pictures(run_, out), out / "quality.png", out / "calibration.png"]

    n = min(args.particle_pairs, args.pairs)
    routes = None
    if n > 0:
        # The particle route on a copy of the same recording (its vectors/ beside the voxel route's), with
        # monitoring settings (20 candidate iterations, 2 rounds: as good as the defaults on this rig, in
        # about 60% of the time), bins the size of the last correlation window and a search as wide in every axis.
        # The fit's weights and residual mask are lfpiv particles' own default for these light-field cameras
        # (shot + 3, fit_defaults; on the demo ring recall 0.922 and 5.7% ghosts, field 10.6% of the peak speed,
        # against flat + 0's 0.905, 7.5% and 14.6% at 1.35x the CPU: benchmarks/RESULTS.md, twelfth session).
        prun = str(out / "particles.zarr")
        copy_recording(run_, prun)
        last = windows.split(",")[-1]
        particles_s = _step(f"the particle route on the same recording: iterative particle reconstruction of "
                            f"{n} pair(s)", ["particles", prun, "--pair-range", f"0:{n}", "--candidate-iterations",
                                             "20", "--rounds", "2", "--quiet", *dev])
        particles_s += _step("tracking: frame A's particles paired with frame B's, binned on a grid",
                             ["track", prun, "--search-voxels", "4,4,4", "--bin", last, "--quiet"])
        _step("accuracy of the particle route against the simulated truth", ["evaluate", prun])
        routes = [route_figures(run_, f"{method} + correlation", voxels_s, args.pairs),
                  route_figures(prun, "particles (IPR) + tracking", particles_s, n)]
        shown.append(routes_picture([(f"{method} + correlation", run_), ("particles + tracking", prun)],
                                    out / "routes.png"))

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
    if routes is not None:
        print(f"  particles.zarr    the same recording, with particles/, tracks/ and their vectors/   (lfpiv evaluate "
              f"{out / 'particles.zarr'})")
    print("  field/            the velocity field as netCDF")
    for p in shown:
        print(f"  {p.name:<17} picture")
    if routes is not None:
        # time is each route's steps (reconstruct + correlate; particles + track) on this machine; the
        # error is the RMS over the vectors each measured, as a share of the truth's peak speed on its grid
        print("\nThe two routes on the same recording, against the simulated truth:")
        print(route_table(routes))
    return 0
