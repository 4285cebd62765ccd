"""``lfpiv calibrate``: the microlens grid from white images, the volumetric calibration, the report."""

from __future__ import annotations

import argparse

from lfpiv.commands import positive_float, positive_int, warn_optics, whole_number


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("calibrate", help="calibrate the rig: microlens grids, target planes, report",
                       description="Calibrate the light-field cameras of a rig into a calibration store "
                       "(a .zarr directory). 'mla' takes white images and detects every microlens grid; "
                       "'volume' moves the dot target through the planes; 'report' says what a store holds. "
                       "The laser is never armed: only the camera trigger output is programmed.")
    steps = s.add_subparsers(dest="step", required=True, metavar="STEP", parser_class=type(s))

    m = steps.add_parser("mla", help="white images -> every microlens centre, pitch, rotation, offset",
                         description="Trigger every camera a few times on a uniformly lit diffuser (white "
                         "image), average the frames, detect every micro-image centre and fit the microlens "
                         "lattice; store the white images and grids. With hardware = \"sim\" the simulated lab "
                         "shows a white diffuser.")
    m.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    m.add_argument("--out", required=True, metavar="CALIB", help="calibration store (created or updated)")
    m.add_argument("--frames", type=positive_int, default=4, help="white frames averaged per camera (default: 4)")
    m.add_argument("--exposure-us", type=positive_float, default=None, metavar="US",
                   help="exposure per frame (default: the rig's timing.camera_exposure_us)")
    m.add_argument("--sim-level", type=positive_float, default=20000.0, metavar="COUNTS",
                   help="simulated lab only: white level at the sensor centre (default: 20000)")
    m.add_argument("--sim-vignetting", type=float, default=0.3, metavar="FRACTION",
                   help="simulated lab only: darkening at the sensor corners (default: 0.3)")
    m.add_argument("--sim-dead", type=lambda t: whole_number(t, 0), default=3, metavar="N",
                   help="simulated lab only: dead lenslets near the sensor edge (default: 3)")
    m.set_defaults(func=run_mla)

    v = steps.add_parser("volume", help="move the dot target through the planes and take every camera's image",
                         description="Home the stage, move the calibration target (white dots on black) through "
                         "the planes, wait for each readback, trigger every camera once and store each plane with "
                         "the stage readback. An interrupted run resumes where it stopped with the same command. "
                         "With hardware = \"sim\" the simulated lab renders the target at the stage's position.")
    v.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    v.add_argument("--out", required=True, metavar="CALIB", help="calibration store (created or resumed)")
    v.add_argument("--planes", type=positive_int, default=51, help="number of planes (default: 51)")
    v.add_argument("--step-mm", type=positive_float, default=0.5, metavar="MM",
                   help="distance between planes (default: 0.5)")
    v.add_argument("--centre-mm", type=float, default=None, metavar="MM",
                   help="stage position of the middle plane (default: the middle of the stage's travel)")
    v.add_argument("--settle-s", type=float, default=0.0, metavar="S", help="wait after each move (default: 0)")
    v.add_argument("--exposure-us", type=positive_float, default=None, metavar="US",
                   help="exposure per frame (default: the rig's timing.camera_exposure_us)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=run_volume)

    r = steps.add_parser("report", help="what a calibration store holds, how good it is",
                         description="Print what a calibration store holds (white images, microlens grids with "
                         "their RMS residual, target planes, fitted models); --plot also writes a PNG.")
    r.add_argument("store", metavar="CALIB", help="calibration store (.zarr directory)")
    r.add_argument("--plot", metavar="PNG", default=None,
                   help="write a PNG of the detected centres over the white image and their residuals")
    r.set_defaults(func=run_report)
    s.set_defaults(func=lambda args: s.error("give a step: mla, volume or report"))


def run_mla(args: argparse.Namespace) -> int:
    from lfcore.white import WhiteImageConfig
    from lfpiv.calibrate import calibrate_mla
    from lfpiv.errors import UsageError
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)
    try:
        white = WhiteImageConfig(level_counts=args.sim_level, vignetting=args.sim_vignetting,
                                 dead_lenslets=args.sim_dead)
    except ValueError as exc:
        raise UsageError(f"--sim-*: {exc}") from None
    results = calibrate_mla(rig, args.out, frames=args.frames, exposure_us=args.exposure_us, white=white)
    for res in results:
        g = res.grid
        ox, oy = res.mla["mla_offset_um"]
        print(f"{res.camera}: {g.grid} grid, pitch {g.pitch_px:.4f} px, rotation {g.rotation_deg:+.4f} deg, "
              f"offset ({g.offset_px[0]:+.3f}, {g.offset_px[1]:+.3f}) px, RMS {g.rms_px:.4f} px, "
              f"{int(g.inliers.sum())} of {g.n_lenslets} lenslets; MLA pitch {res.mla['mla_pitch_um']:.3f} um, "
              f"offset ({ox:+.2f}, {oy:+.2f}) um")
    print(f"wrote {args.out}")
    return 0


def run_volume(args: argparse.Namespace) -> int:
    import sys

    from lfpiv.calibrate import calibrate_volume
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)

    def bar(plane: int, done: int, total: int) -> None:
        if not args.quiet:
            filled = int(30 * done / total)
            print(f"\rplanes [{'#' * filled}{'.' * (30 - filled)}] {done}/{total}", end="", file=sys.stderr,
                  flush=True)

    try:
        res = calibrate_volume(rig, args.out, planes=args.planes, step_mm=args.step_mm, centre_mm=args.centre_mm,
                               settle_s=args.settle_s, exposure_us=args.exposure_us, progress=bar)
    finally:
        if not args.quiet:
            print(file=sys.stderr)
    lo = min(res.readback_mm, default=float("nan"))
    hi = max(res.readback_mm, default=float("nan"))
    print(f"took {len(res.taken)} plane(s) ({len(res.skipped)} already done) of {res.planes}"
          + (f", stage {lo:.4f}..{hi:.4f} mm" if res.taken else "") + f"; wrote {args.out}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    from calibration.store import CalibrationStore, CalibrationStoreError
    from lfpiv.calibrate import plot_grids
    from lfpiv.errors import UsageError

    try:
        store = CalibrationStore.open(args.store)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None
    for line in store.summary():
        print(line)
    if args.plot:
        print(f"wrote {plot_grids(store, args.plot)}")
    return 0
