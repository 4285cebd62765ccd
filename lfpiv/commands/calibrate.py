"""``lfpiv calibrate``: the microlens grid from white images, the volumetric calibration, the report."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import (
    add_pair_range,
    by_camera,
    non_negative_float,
    png_path,
    positive_float,
    positive_int,
    progress_bar,
    warn_optics,
    whole_number,
)
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("calibrate", help="calibrate the rig: microlens grids, target planes, report",
                       description="Calibrate the cameras of a rig, light-field and pinhole, into a calibration "
                       "store (a .zarr directory). 'mla' takes white images and detects every microlens grid "
                       "(pinhole cameras have none and are skipped); 'volume' moves the dot target through the "
                       "planes; 'fit' fits every camera's model to them (a pinhole camera's pinhole model with "
                       "distortion and its Soloff polynomial); 'selfcal' corrects the pinhole cameras' models on "
                       "a recorded run's particles (volume self-calibration); 'report' says what a store holds and "
                       "how well the models reproject. "
                       "The laser is never armed: only the camera trigger output is programmed.")
    steps = s.add_subparsers(dest="step", required=True, metavar="STEP", parser_class=type(s))

    m = steps.add_parser("mla", help="white images -> every microlens centre, pitch, rotation, offset",
                         description="Trigger every camera a few times on a uniformly lit diffuser (white "
                         "image), or read white images the lab recorded (--white), average the frames, reject hot "
                         "pixels, judge clipping against each camera's bit_depth, detect every micro-image centre "
                         "and fit the microlens lattice; store the white images and grids. With hardware = \"sim\" "
                         "the simulated lab shows a white diffuser.")
    m.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    m.add_argument("--out", required=True, metavar="CALIB", help="calibration store (created or updated)")
    m.add_argument("--white", action="append", default=[], metavar="CAM=FILE",
                   help="a white image file of camera CAM (TIFF, PNG, BMP, DaVis; repeat to average several; FILE "
                   "alone for a one-camera rig): no device is opened")
    m.add_argument("--dark", action="append", default=[], metavar="CAM=FILE",
                   help="a dark image file of camera CAM (lens capped, laser off; 8- or 16-bit PNG or TIFF, ...; "
                   "repeat to average several; FILE alone for a one-camera rig), kept beside its white image for "
                   "the flat field (lfpiv reconstruct --flat-field)")
    m.add_argument("--dark-frames", type=lambda t: whole_number(t, 0), default=0, metavar="N",
                   help="also take N dark frames per camera live after the white ones (the simulated lab shows "
                   "darkness; on hardware cap the lenses when asked); default: 0")
    m.add_argument("--frames", type=positive_int, default=4, help="white frames averaged per camera (default: 4)")
    m.add_argument("--exposure-us", type=positive_float, default=None, metavar="US",
                   help="exposure per frame (default: the rig's timing.camera_exposure_us)")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
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
                         "the stage readback; or, with --images and --positions, store the target images the lab "
                         "took with its own stage. An interrupted run resumes where it stopped with the same "
                         "command. With hardware = \"sim\" the simulated lab renders the target at the stage's "
                         "position. The board is the rig's [target] (dot pitch, diameter, marker, tilt, levels).")
    v.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    v.add_argument("--out", required=True, metavar="CALIB", help="calibration store (created or resumed)")
    v.add_argument("--images", action="append", default=[], metavar="CAM=PATTERN",
                   help="target images camera CAM took, one per plane in the order of --positions (PATTERN alone "
                   "for a one-camera rig): no device is opened")
    v.add_argument("--positions", default=None, metavar="CSV",
                   help="with --images: each plane's stage position, a CSV with a stage_mm column")
    v.add_argument("--planes", type=positive_int, default=51, help="number of planes (default: 51)")
    v.add_argument("--step-mm", type=positive_float, default=0.5, metavar="MM",
                   help="distance between planes (default: 0.5)")
    v.add_argument("--centre-mm", type=float, default=None, metavar="MM",
                   help="stage position of the middle plane (default: the middle of the stage's travel)")
    v.add_argument("--settle-s", type=non_negative_float, default=0.0, metavar="S",
                   help="wait after each move (default: 0)")
    v.add_argument("--exposure-us", type=positive_float, default=None, metavar="US",
                   help="exposure per frame (default: the rig's timing.camera_exposure_us)")
    v.add_argument("--spacing-mm", type=positive_float, default=None, metavar="MM",
                   help="dot spacing of the board (default: 3, or a quarter of a small volume's width)")
    v.add_argument("--tilt-deg", type=float, default=None, metavar="DEG",
                   help="board tilt about world y (default: its normal bisects the cameras' optical axes)")
    v.add_argument("--fit", action="store_true", help="when every plane is taken, run 'calibrate fit' on the store")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=run_volume)

    f = steps.add_parser("fit", help="fit every camera's model to the target planes (reprojection least squares)",
                         description="Find the dots of every plane in each camera's light-field images (lenslet "
                         "sums, centroids in the chief-ray and four half-aperture views), name them on the board "
                         "(the larger marker dot is (0, 0)), and fit each camera's pose, magnification, MLA offset "
                         "and rotation by least squares on the reprojection error, with the board positions from "
                         "the stage readback as the world frame. Stores the models and prints the RMS per camera.")
    f.add_argument("store", metavar="CALIB", help="calibration store with grids and planes")
    f.add_argument("--distortion", action="store_true", help="also fit a radial distortion k1 of the light-field "
                   "cameras (reported only; pinhole cameras always fit k1, k2, p1, p2)")
    f.add_argument("--min-dots", type=positive_int, default=2, help="fewest dots accepted per plane (default: 2)")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.set_defaults(func=run_fit)

    c = steps.add_parser("selfcal", help="volume self-calibration of the pinhole cameras on a recorded run",
                         description="Correct the fitted models of the pinhole (Tomo-PIV) cameras on the particles "
                         "of a recorded run (Wieneke 2008): find the particles in every frame, triangulate them "
                         "through the models, measure each camera's disparity in sub-volumes (the peak of the "
                         "disparities of every match, true and ghost), and correct each camera's pinhole model and "
                         "Soloff polynomial by it, several times with a shrinking search radius. The corrected "
                         "models are stored beside the fitted ones, which stay; 'reconstruct --calibration' uses "
                         "them. Light-field cameras are left out.")
    c.add_argument("run", metavar="RUN", help="run store of particle images recorded with the calibrated rig")
    c.add_argument("--calibration", required=True, metavar="CALIB", help="calibration store with fitted models")
    add_pair_range(c, "every committed pair")
    c.add_argument("--subvolumes", type=whole_triple, default=(4, 4, 2), metavar="NX,NY,NZ",
                   help="sub-volumes of the disparity maps along x, y, z (default: 4,4,2)")
    c.add_argument("--radius-px", type=positive_float, default=2.0, metavar="PX",
                   help="first search radius, more than the calibration's error (default: 2)")
    c.add_argument("--iterations", type=lambda t: whole_number(t, 0, 20), default=3,
                   help="correction passes, each halving the search radius down to 1 px (default: 3)")
    c.add_argument("--min-matches", type=positive_int, default=20,
                   help="fewest matched particles a sub-volume needs (default: 20)")
    c.set_defaults(func=run_selfcal)

    r = steps.add_parser("report", help="what a calibration store holds, how good it is",
                         description="Print what a calibration store holds (white images, microlens grids with "
                         "their RMS residual, target planes, fitted models); --plot also writes a PNG.")
    r.add_argument("store", metavar="CALIB", help="calibration store (.zarr directory)")
    r.add_argument("--plot", type=png_path, metavar="PNG", default=None,
                   help="write a PNG of the detected centres over the white image and their residuals")
    r.add_argument("--rms-plot", type=png_path, metavar="PNG", default=None,
                   help="write a PNG of the reprojection RMS per plane of every fitted camera")
    r.set_defaults(func=run_report)
    s.set_defaults(func=lambda args: s.error("give a step: mla, volume, fit, selfcal or report"))


def run_mla(args: argparse.Namespace) -> int:
    from lfpiv.jobs.calibrate import calibrate_mla, pinhole_cameras_skipped, white_config
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)
    white = white_config(level_counts=args.sim_level, vignetting=args.sim_vignetting, dead_lenslets=args.sim_dead)
    mpx = max(c.sensor_px[0] * c.sensor_px[1] for c in rig.camera) / 1e6
    large = mpx > 8  # say what a long silence is: about 3 s per megapixel on a 2-core CPU
    names = [c.name for c in rig.camera]
    whites = by_camera(args.white, "--white", names, many=True) if args.white else None
    darks = by_camera(args.dark, "--dark", names, many=True) if args.dark else None
    if args.dark_frames and whites is not None:
        raise UsageError("--dark-frames takes dark frames with the rig's cameras, --white reads files; give dark "
                         "image files with --dark instead")

    def dark_ready() -> None:
        print("lfpiv: cap every camera's lens (no light at all), then press Enter to take the dark frames",
              file=sys.stderr)
        sys.stdin.readline()

    if rig.hardware == "sim" and large and whites is None:
        print("lfpiv: simulated lab: rendering each camera's white image ...", file=sys.stderr)
    for name in pinhole_cameras_skipped(rig):
        print(f"lfpiv: note: camera '{name}' is a pinhole camera (no microlenses): skipped", file=sys.stderr)
    with progress_bar(len(rig.lightfield_cameras), "finding grids", "camera", args.quiet) as bar:
        results = calibrate_mla(rig, args.out, frames=args.frames, exposure_us=args.exposure_us, white=white,
                                whites=whites, darks=darks, dark_frames=args.dark_frames, dark_ready=dark_ready,
                                progress=bar,
                                status=(lambda line: bar.write(f"lfpiv: {line}")) if large else None)
    for res in results:
        g = res.grid
        ox, oy = res.mla["mla_offset_um"]
        print(f"{res.camera}: {g.grid} grid, pitch {g.pitch_px:.4f} px, rotation {g.rotation_deg:+.4f} deg, "
              f"offset ({g.offset_px[0]:+.3f}, {g.offset_px[1]:+.3f}) px, RMS {g.rms_px:.4f} px, "
              f"{int(g.inliers.sum())} of {g.n_lenslets} lenslets; MLA pitch {res.mla['mla_pitch_um']:.3f} um, "
              f"offset ({ox:+.2f}, {oy:+.2f}) um")
    for res in results:
        if res.dark_frames:
            print(f"{res.camera}: dark image, mean of {res.dark_frames} frame(s), stored beside the white image")
    for res in results:
        if res.hot_pixels:
            print(f"lfpiv: note: {res.camera}: {res.hot_pixels} hot pixel(s) of the white image replaced by their "
                  "neighbours", file=sys.stderr)
    stale = [res.camera for res in results if res.removed_model]
    if stale:
        print(f"lfpiv: note: removed the fitted model of {', '.join(stale)}, made through the earlier grid; "
              f"run 'lfpiv calibrate fit {args.out}' again", file=sys.stderr)
    print(f"wrote {args.out}")
    return 0


def run_volume(args: argparse.Namespace) -> int:
    from lfpiv.jobs.calibrate import board_for, calibrate_volume, calibrate_volume_from_files
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)

    def bar(plane: int, done: int, total: int) -> None:
        if not args.quiet:
            filled = int(30 * done / total)
            print(f"\rplanes [{'#' * filled}{'.' * (30 - filled)}] {done}/{total}", end="", file=sys.stderr,
                  flush=True)

    board = board_for(rig, args.spacing_mm, args.tilt_deg)
    if bool(args.images) != (args.positions is not None):
        raise UsageError("--images and --positions go together: the lab's target images and their stage positions")
    try:
        if args.images:
            images = by_camera(args.images, "--images", [c.name for c in rig.camera])
            res = calibrate_volume_from_files(rig, args.out, images=images, positions=args.positions, board=board,
                                              progress=bar)
        else:
            res = calibrate_volume(rig, args.out, planes=args.planes, step_mm=args.step_mm, centre_mm=args.centre_mm,
                                   settle_s=args.settle_s, exposure_us=args.exposure_us, board=board, progress=bar)
    finally:
        if not args.quiet:
            print(file=sys.stderr)
    lo = min(res.readback_mm, default=float("nan"))
    hi = max(res.readback_mm, default=float("nan"))
    print(f"took {len(res.taken)} plane(s) ({len(res.skipped)} already done) of {res.planes}"
          + (f", stage {lo:.4f}..{hi:.4f} mm" if res.taken else "") + f"; wrote {args.out}")
    if args.fit:
        args.store, args.distortion, args.min_dots = args.out, False, 2
        return run_fit(args)
    return 0


def run_fit(args: argparse.Namespace) -> int:
    from lfpiv.jobs.calibrate import calibrate_fit, open_calibration, rotation_angle_deg

    before = open_calibration(args.store)
    nominal = before.rig
    stale = [n for n in before.cameras if before.selfcal(n) is not None]
    with progress_bar(len(nominal.camera), "fitting", "camera", args.quiet) as bar:
        fits = calibrate_fit(args.store, fit_distortion=args.distortion, min_dots=args.min_dots, progress=bar)
    if stale:
        print(f"lfpiv: note: removed the self-calibration of {', '.join(stale)}, made on the earlier models; run "
              "'lfpiv calibrate selfcal' again", file=sys.stderr)
    for fit in fits:
        c = fit.camera
        turned = rotation_angle_deg(nominal.camera_named(c.name).rotation_deg, c.rotation_deg)
        if c.kind == "pinhole":
            pp = c.principal_point_px
            print(f"{c.name}: RMS {fit.rms_px:.4f} px (pinhole), {fit.soloff_rms_px:.4f} px (Soloff) over "
                  f"{int(fit.plane_dots.sum())} dots on {int((fit.plane_dots > 0).sum())} planes ({fit.dropped} "
                  f"dropped); magnification {c.magnification:.5f}, rotation "
                  f"[{', '.join(f'{v:.4f}' for v in c.rotation_deg)}] deg ({turned:.3f} deg from the rig file), focus "
                  f"[{', '.join(f'{v:.4f}' for v in c.focus_mm)}] mm, principal point ({pp[0]:+.2f}, {pp[1]:+.2f}) px, "
                  f"k1 {c.k1:+.2e} k2 {c.k2:+.2e} p1 {c.p1:+.2e} p2 {c.p2:+.2e}")
            continue
        ox, oy = c.mla_offset_um
        print(f"{c.name}: RMS {fit.rms_px:.4f} px over {int(fit.plane_dots.sum())} clear dots on "
              f"{int((fit.plane_dots > 0).sum())} planes ({fit.set_aside} weighted down or left out as "
              f"in sharp focus or crowded); magnification {c.magnification:.5f}, rotation "
              f"[{', '.join(f'{v:.4f}' for v in c.rotation_deg)}] deg ({turned:.3f} deg from the rig file), focus "
              f"[{', '.join(f'{v:.4f}' for v in c.focus_mm)}] mm, MLA offset ({ox:+.3f}, {oy:+.3f}) um, rotation "
              f"{c.mla_rotation_deg:+.4f} deg" + (f", k1 {fit.radial_k1:+.2e}" if args.distortion else ""))
    print(f"wrote the models to {args.store}")
    return 0


def whole_triple(text: str) -> tuple[int, int, int]:
    """argparse type of ``--subvolumes``: three whole numbers of at least 1, 'NX,NY,NZ'."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"give three whole numbers NX,NY,NZ, got '{text}'")
    return tuple(whole_number(p, 1, 64) for p in parts)  # type: ignore[return-value]


def run_selfcal(args: argparse.Namespace) -> int:
    from lfpiv.jobs.calibrate import calibrate_selfcal

    out = calibrate_selfcal(args.run, args.calibration, pairs=args.pairs, subvolumes=args.subvolumes,
                            radius_px=args.radius_px, iterations=args.iterations, min_matches=args.min_matches)
    res = out.result
    if out.left_out:
        print(f"lfpiv: note: light-field camera(s) {', '.join(out.left_out)} left out (their particle images are "
              "not points)", file=sys.stderr)
    print(f"self-calibrated {', '.join(out.cameras)} from the {out.started_from} models on {out.frames} frames of "
          f"{len(out.pairs)} pair(s), {args.subvolumes[0]} x {args.subvolumes[1]} x {args.subvolumes[2]} sub-volumes")
    for k in range(len(res.rms_px)):
        label = "before" if k == 0 else f"after correction {k}"
        print(f"  pass {k + 1} ({label}, search radius {res.radius_px[k]:g} px): {int(res.counts[k].sum())} "
              f"matches, disparity RMS {res.rms_px[k]:.3f} px, largest {res.max_px[k]:.3f} px")
    print(f"wrote the corrected models to {args.calibration}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    from lfpiv.jobs.calibrate import open_calibration
    from lfpiv.plots import plot_grids, plot_rms

    store = open_calibration(args.store)
    for line in store.summary():
        print(line)
    for name in store.cameras:
        m = store.model(name)
        if m is None:
            continue
        stage = store.stage_mm(name)
        soloff = m.get("soloff_plane_rms_px")  # pinhole cameras: the Soloff polynomial's too
        print(f"  {name}: plane  stage_mm  dots  rms_px" + ("  soloff_rms_px" if soloff else ""))
        for i, (s_mm, n, rms) in enumerate(zip(stage, m["plane_dots"], m["plane_rms_px"], strict=True)):
            line = f"  {name}: {i + 1:5d}  {s_mm:8.4f}  {n:4d}  " + ("   -" if rms is None else f"{rms:.4f}")
            if soloff:
                line += "  " + ("   -" if soloff[i] is None else f"{soloff[i]:.4f}").rjust(13)
            print(line)
    if args.plot:
        print(f"wrote {plot_grids(store, args.plot)}")
    if args.rms_plot:
        print(f"wrote {plot_rms(store, args.rms_plot)}")
    return 0
