"""Calibrating the rig, real or simulated (``lfpiv calibrate``): microlens grids from white images
and the volumetric run of the dot target through the stage planes.

Laser safety: calibration never needs the laser. The pulse generator is programmed with a plan
that holds ONLY the camera output (:func:`calibration.runner.camera_only_plan`), so however it is armed the laser
cannot fire; it is disarmed and every device released whatever happens.

With ``hardware = "sim"`` the simulated lab shows a white diffuser (:func:`sim.scenes.white_scene`)
to every camera while the white images are taken, and the dot target
(:func:`sim.scenes.dot_target_scene`) at the stage's true position during the volumetric run.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.timing import TimingError
from calibration.dots import DotError, Dots, detect_dots, lenslet_cells, match_dots, view_geometry
from calibration.fit import CameraFit, FitError, PlaneDots, fit_camera
from calibration.mla_grid import GridError, MlaGrid, check_white, detect_grid
from calibration.runner import PlaneRun, camera_only_plan, capture_frames, plane_targets, run_planes
from calibration.store import CalibrationStore, CalibrationStoreError
from lfcore.chief_ray import project
from lfcore.rig import Camera, Rig
from lfcore.target import DotBoard
from lfcore.white import WhiteImageConfig
from lfpiv import __version__
from lfpiv.acquire import make_stage, open_rig
from lfpiv.errors import UsageError

__all__ = ["MlaResult", "calibrate_fit", "calibrate_mla", "calibrate_volume", "calibrated_rig", "default_board",
           "plot_grids", "plot_rms"]


@dataclass(frozen=True)
class MlaResult:
    """One camera's microlens calibration."""

    camera: str
    grid: MlaGrid
    mla: dict[str, Any]
    #: whether the store held a model fitted through an earlier grid, now removed
    removed_model: bool = False


def calibrate_mla(rig: Rig, out: str | Path, *, frames: int = 4, exposure_us: float | None = None,
                  sim_options: dict[str, Any] | None = None, white: WhiteImageConfig | None = None,
                  status: Callable[[str], None] | None = None) -> list[MlaResult]:
    """Take white images with every camera, detect each microlens grid and store both.

    Parameters
    ----------
    rig
        The rig.
    out
        Calibration store (created, or updated if it exists for the same cameras).
    frames
        White frames averaged per camera.
    exposure_us
        Exposure (default: the rig's ``timing.camera_exposure_us``).
    sim_options
        For ``hardware = "sim"``: keyword arguments of :class:`sim.lab.SimLab`, or ``{"lab": lab}``.
    white
        For ``hardware = "sim"``: the simulated white image (level, vignetting, dead lenslets).
    status
        Called with a one-line message before each camera's grid detection (a minute on a
        29 MP sensor with two cores).

    Raises
    ------
    UsageError
        A white image that is not white (too dark, saturated, no microlens structure), naming
        the camera; a store that belongs to other cameras.
    DeviceError
        A device fault (the generator was disarmed).
    """
    if frames < 1:
        raise UsageError(f"--frames must be at least 1, got {frames}")
    exposure = rig.timing.camera_exposure_us if exposure_us is None else exposure_us
    _check_timing(rig, frames)
    if Path(out).exists():  # an existing store must be one of these cameras: say so before any device opens
        _open_store(out, rig)
    opts = {"pool_pairs": 1, "rays_per_particle": 16, **(sim_options or {})}
    with open_rig(rig, sim_options=opts) as rg:
        if rg.lab is not None:
            from sim.scenes import white_scene  # the application wires the simulated lab

            rg.lab.show(*white_scene(rg.lab.rig, white))  # the lab renders its own (true) rig
        for cam in rg.cameras:
            want = tuple(rig.camera_named(cam.name).sensor_px)
            if tuple(cam.sensor_px) != want:
                raise UsageError(f"camera '{cam.name}' delivers {cam.sensor_px[0]} x {cam.sensor_px[1]} pixels but "
                                 f"the rig file says sensor_px = {list(want)}; correct the rig file")
        images = capture_frames(rig, rg.cameras, rg.pulse_generator, frames, exposure)
        if rg.lab is not None:
            rg.lab.show(None)
    full_scale = 2**rig.render.bit_depth - 1
    results = []
    grids = {}
    for cam in rig.camera:
        stack = images[cam.name]
        mean = stack.astype(np.float64).mean(axis=0)
        try:
            check_white(stack.max(axis=0), full_scale)
            if status is not None:
                status(f"{cam.name}: detecting every micro-image centre in {mean.size / 1e6:.0f} MP ...")
            grid = detect_grid(mean)
        except GridError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
        grids[cam.name] = (mean, len(stack))
        results.append(MlaResult(cam.name, grid, grid.to_mla(cam)))
    store = _open_store(out, rig)  # written only when every camera's grid was found
    written = []
    for res in results:
        mean, n = grids[res.camera]
        store.write_white(res.camera, mean, frames_averaged=n)
        removed = store.write_grid(res.camera, res.grid, mla=res.mla)
        written.append(dataclasses.replace(res, removed_model=removed))
    return written


def _check_timing(rig: Rig, triggers: int) -> None:
    """An impossible timing is reported before any device opens."""
    try:
        camera_only_plan(rig, triggers)
    except TimingError as exc:
        raise UsageError(str(exc)) from None


def _open_store(out: str | Path, rig: Rig) -> CalibrationStore:
    try:
        return CalibrationStore.open_or_create(out, rig, software_version=__version__)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None


def plot_grids(store: CalibrationStore, out: str | Path, lenslets: int = 8) -> Path:
    """Save a PNG: per camera, the white image around the sensor centre with the detected
    centres (inliers +, outliers x) and fitted nodes (o), and the residuals over the sensor.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    UsageError
        The store holds no microlens grid.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    names = [n for n in store.cameras if store.grid(n) is not None]
    if not names:
        raise UsageError(f"{store.path} holds no microlens grid; run 'lfpiv calibrate mla' first")
    fig, axes = plt.subplots(len(names), 2, figsize=(11, 5 * len(names)), squeeze=False)
    for row, name in zip(axes, names, strict=True):
        grid, white = store.grid(name), store.white(name)
        rows, cols = white.shape
        half = 0.5 * lenslets * grid.pitch_px
        cx, cy = cols / 2, rows / 2
        c0, c1 = int(max(0, cx - half)), int(min(cols, cx + half))
        r0, r1 = int(max(0, cy - half)), int(min(rows, cy + half))
        ax = row[0]
        ax.imshow(white[r0:r1, c0:c1], cmap="gray", extent=(c0, c1, r1, r0), interpolation="nearest")
        cen, fit, inl = grid.centres_px, grid.lattice_px(), grid.inliers
        box = (cen[:, 0] > c0) & (cen[:, 0] < c1) & (cen[:, 1] > r0) & (cen[:, 1] < r1)
        ax.plot(fit[box, 0], fit[box, 1], "o", mfc="none", mec="tab:cyan", ms=8, label="fitted lattice")
        ax.plot(cen[box & inl, 0], cen[box & inl, 1], "+", color="tab:green", ms=8, label="detected")
        ax.plot(cen[box & ~inl, 0], cen[box & ~inl, 1], "x", color="tab:red", ms=8, label="outlier")
        ax.set_title(f"{name}: white image at the sensor centre")
        ax.legend(loc="upper right", fontsize=8)
        ax = row[1]
        res = grid.residuals_px
        scale = max(float(np.percentile(np.hypot(*res[inl].T), 95)), 1e-3)
        ax.quiver(cen[inl, 0], cen[inl, 1], res[inl, 0], -res[inl, 1], np.hypot(*res[inl].T), angles="xy",
                  scale_units="xy", scale=scale / grid.pitch_px, cmap="viridis")
        ax.plot(cen[~inl, 0], cen[~inl, 1], "x", color="tab:red", ms=5)
        ax.set_xlim(0, cols)
        ax.set_ylim(rows, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: residuals (arrow of one pitch = {scale:.3f} px), RMS {grid.rms_px:.4f} px")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


#: Fewest lenslets (in the volume, through the main lens) between neighbouring dots of a board.
MIN_DOT_LENSLETS = 2
#: Fewest dots across the narrowest camera's field of view.
MIN_DOTS_ACROSS = 2


def default_board(rig: Rig, spacing_mm: float | None = None, tilt_deg: float | None = None) -> DotBoard:
    """The board the volumetric run assumes unless told: 3 mm spacing (a quarter of the volume's
    smaller transverse size for small rigs), centred on the volume, tilted about world y so its
    normal bisects the cameras' optical axes (0 for one camera, 45 degrees for two at 90), with
    a marker dot (1.6 times larger) at its origin for two or more cameras; one camera names its
    dots from the nominal model alone (no marker)."""
    vol = rig.volume
    if spacing_mm is None:
        spacing_mm = min(3.0, 0.25 * min(vol.size_mm[0], vol.size_mm[1]))
    # a dot is found from the lenslets its light falls on: dots closer than two lenslets (in the
    # object space of the coarsest camera) share them and cannot be told apart
    least = max(MIN_DOT_LENSLETS * c.mla_pitch_mm / abs(c.magnification) for c in rig.camera)
    if spacing_mm < least:
        raise ValueError(f"dots {spacing_mm:g} mm apart are closer than {MIN_DOT_LENSLETS} lenslets of the cameras "
                         f"({least:.3g} mm in the volume), where they cannot be told apart; use a spacing of at least "
                         f"{least:.2g} mm")
    # and the fit needs a grid of dots in every camera's view, not one or two
    most = min(min(c.field_of_view_mm) for c in rig.camera) / MIN_DOTS_ACROSS
    if spacing_mm > most:
        raise ValueError(f"dots {spacing_mm:g} mm apart leave fewer than {MIN_DOTS_ACROSS} across the narrowest "
                         f"camera's field of view ({MIN_DOTS_ACROSS * most:.3g} mm); use a spacing of at most "
                         f"{most:.2g} mm")
    board = DotBoard.for_cameras(np.array([c.optical_axis for c in rig.camera]), spacing_mm=spacing_mm,
                                 centre_mm=vol.centre_mm, marker_scale=1.6 if len(rig.camera) > 1 else 1.0)
    return board if tilt_deg is None else dataclasses.replace(board, tilt_deg=tilt_deg)


def calibrate_volume(rig: Rig, out: str | Path, *, planes: int = 51, step_mm: float = 0.5,
                     centre_mm: float | None = None, settle_s: float = 0.0, exposure_us: float | None = None,
                     board: DotBoard | None = None, sim_options: dict[str, Any] | None = None,
                     sim_target: dict[str, Any] | None = None,
                     progress: Callable[[int, int, int], None] | None = None) -> PlaneRun:
    """Move the target through the planes and store every camera's image at each (resumable).

    Parameters
    ----------
    rig
        The rig (its stage and pulse generator ports, cameras, timing).
    out
        Calibration store, created or resumed (planes with a stored readback are not repeated).
    planes, step_mm
        Number of planes and their spacing along the stage axis.
    centre_mm
        Stage position of the middle plane (default: the middle of the stage's travel).
    settle_s
        Wait after each move before triggering.
    exposure_us
        Exposure (default: the rig's ``timing.camera_exposure_us``).
    board
        The dot board (:func:`default_board` if None); its ``stage_centre_mm`` is set to the
        middle plane's stage position and it is stored with the planes (it defines the world
        frame of the fit).
    sim_options
        For ``hardware = "sim"``: keyword arguments of :class:`sim.lab.SimLab`, or ``{"lab": lab}``.
        The simulated target's origin sits at world z = board centre + (stage position - ``centre_mm``).
    sim_target
        For ``hardware = "sim"``: keyword arguments of :func:`sim.scenes.dot_target_scene`
        (points_per_dot, rays_per_point, dot_counts, seed).
    progress
        Called as ``progress(plane, done, total)`` after each stored plane.

    Raises
    ------
    UsageError
        Impossible planes or timing, no stage port, a store of other cameras or other planes.
    DeviceError
        A device fault; :class:`calibration.runner.StageError` names the plane the stage missed.
    """
    if planes < 1 or not step_mm > 0:
        raise UsageError(f"--planes must be at least 1 and --step-mm positive, got {planes} and {step_mm}")
    exposure = rig.timing.camera_exposure_us if exposure_us is None else exposure_us
    _check_timing(rig, 1)
    store = _open_store(out, rig)
    opts = {"pool_pairs": 1, "rays_per_particle": 16, **(sim_options or {})}
    with open_rig(rig, sim_options=opts) as rg:
        if rg.stage_port is None:
            raise UsageError("stage.port is not set in the rig file; give the serial port of the calibration "
                             "stage, or set hardware = \"sim\"")
        stage = make_stage(rg.stage_port, rig)
        # the port opens here and closes on the way out, after stopping a move under way if
        # anything (Ctrl-C too) ends the calibration early
        with stage:
            try:
                stage.home()
                lo, hi = stage.travel_mm
                centre = 0.5 * (lo + hi) if centre_mm is None else centre_mm
                targets = plane_targets(planes, step_mm, centre)
                if targets[0] < lo or targets[-1] > hi:
                    raise UsageError(f"planes {targets[0]:g}..{targets[-1]:g} mm leave the stage's travel "
                                     f"{lo:g}..{hi:g} mm; give fewer --planes, a smaller --step-mm or another "
                                     "--centre-mm")
                lab = rg.lab
                brd = dataclasses.replace(board or default_board(rig), stage_centre_mm=float(centre))
                old = store.target()
                if old is not None and store.plane_targets() is not None and old != brd:
                    raise UsageError(f"{out} holds planes of another target ({old}); give a new --out path")
                store.write_target(brd)

                def on_moved(plane: int, readback: float) -> None:
                    if lab is not None:
                        from sim.scenes import dot_target_scene  # the application wires the simulated lab

                        z = brd.centre_mm[2] + lab.stage.position_mm - centre  # the TRUE carriage position
                        lab.show(*dot_target_scene(lab.rig, z, board=brd, **(sim_target or {})))

                def grab() -> dict[str, np.ndarray]:
                    frames = capture_frames(rig, rg.cameras, rg.pulse_generator, 1, exposure)
                    return {k: v[0] for k, v in frames.items()}

                try:
                    return run_planes(store, stage, grab, targets, step_mm, settle_s=settle_s, on_moved=on_moved,
                                      progress=progress)
                except CalibrationStoreError as exc:
                    raise UsageError(str(exc)) from None
            finally:
                if rg.lab is not None:
                    rg.lab.show(None)


def _detected_dots(store: CalibrationStore, nominal: Camera) -> list[tuple[int, Dots]]:
    """The dots of every taken plane of one camera, found once (naming them needs a model)."""
    grid = store.grid(nominal.name)
    if grid is None:
        raise UsageError(f"camera '{nominal.name}': no microlens grid in {store.path}; run 'lfpiv calibrate mla' "
                         "first")
    stage = store.stage_mm(nominal.name)
    frames = store.plane_frames(nominal.name)
    cells = lenslet_cells(grid)
    out = []
    for p in np.flatnonzero(np.isfinite(stage)):
        try:
            out.append((int(p), detect_dots(frames[int(p)], grid, cells=cells)))
        except DotError as exc:
            raise UsageError(f"camera '{nominal.name}', plane {p + 1} of {len(stage)}: {exc}") from None
    return out


def _named_dots(store: CalibrationStore, nominal: Camera, board: DotBoard, detected: list[tuple[int, Dots]],
                min_dots: int, model: Camera | None = None) -> list[PlaneDots]:
    """Name the dots of every plane of one camera (``model`` predicts where they are)."""
    cam = model or nominal
    stage = store.stage_mm(nominal.name)
    reach = 0.75 * math.hypot(*cam.field_of_view_mm) / math.cos(math.radians(board.tilt_deg)) + board.spacing_mm
    ij = board.indices(board.half_extent(reach + abs(float(np.nanmax(np.abs(stage - board.stage_centre_mm))))))
    out = []
    for p, dots in detected:
        found, which = match_dots(dots, project(cam, board.dot_centres(ij, stage[p])), ij)
        if len(found) < min_dots:
            raise UsageError(f"camera '{nominal.name}', plane {p + 1} of {len(stage)} (stage {stage[p]:.4f} mm): "
                             f"{len(found)} dot(s) found and named (of {len(dots)} seen), need at least "
                             f"{min_dots}; check the target's lighting, focus and the board settings")
        out.append(PlaneDots(p, float(stage[p]), which, dots.views_px[found]))
    return out


def calibrate_fit(out: str | Path, *, fit_distortion: bool = False, min_dots: int = 2) -> list[CameraFit]:
    """Fit every camera's model to the stored planes and white-image grid; store the models.

    Dots are found and named with the nominal camera (the rig in the store), the model fitted,
    then the dots named again with the fitted model and the model refitted.

    Parameters
    ----------
    out
        Calibration store with microlens grids (``calibrate mla``) and planes (``calibrate volume``).
    fit_distortion
        Also fit a radial distortion (stored as ``radial_k1``; not used by the reconstruction).
    min_dots
        Fewest named dots accepted in a plane.

    Returns
    -------
    list of CameraFit
        One per camera, in rig order.

    Raises
    ------
    UsageError
        No planes or grid, a plane with too few dots (naming camera and plane), a failed fit.
    """
    try:
        store = CalibrationStore.open(out, mode="r+")
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None
    board = store.target()
    if board is None or store.plane_targets() is None:
        raise UsageError(f"{out} holds no target planes; run 'lfpiv calibrate volume' first")
    rig = store.rig
    fits = []
    for nominal in rig.camera:
        try:
            detected = _detected_dots(store, nominal)
            planes = _named_dots(store, nominal, board, detected, min_dots)
            grid = store.grid(nominal.name)
            wavelength = rig.laser.wavelength_nm  # the sim lights the target at the laser's
            opts = {"n_planes": len(store.stage_mm(nominal.name)), "fit_distortion": fit_distortion,
                    "wavelength_nm": wavelength, "views": view_geometry(nominal, wavelength)}
            fit = fit_camera(nominal, board, planes, grid, **opts)
            planes = _named_dots(store, nominal, board, detected, min_dots, model=fit.camera)
            fit = fit_camera(nominal, board, planes, grid, **opts)
        except FitError as exc:
            raise UsageError(str(exc)) from None
        fits.append(fit)
    for fit in fits:
        store.write_model(fit.camera.name, fit.model_dict(), {
            "rms_px": fit.rms_px, "plane_rms_px": [None if not np.isfinite(v) else float(v) for v in fit.plane_rms_px],
            "plane_dots": [int(n) for n in fit.plane_dots], "lattice_rms_px": fit.lattice_rms_px,
            "radial_k1": fit.radial_k1, "std": fit.std, "dropped": fit.dropped, "set_aside": fit.set_aside,
            "views": "chief ray and four half-aperture views per dot"})
    return fits


def plot_rms(store: CalibrationStore, out: str | Path) -> Path:
    """Save a PNG of each fitted camera's reprojection RMS per plane against the stage position.

    Raises
    ------
    UsageError
        No camera has a fitted model.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in store.cameras if store.model(n) is not None]
    if not names:
        raise UsageError(f"{store.path} holds no fitted camera model; run 'lfpiv calibrate fit' first")
    fig, ax = plt.subplots(figsize=(7, 4))
    for name in names:
        m = store.model(name)
        rms = np.array([np.nan if v is None else v for v in m["plane_rms_px"]], dtype=float)
        ax.plot(store.stage_mm(name), rms, "o-", label=f"{name} (all planes {m['rms_px']:.3f} px)")
    ax.set_xlabel("stage position, mm")
    ax.set_ylabel("RMS reprojection error, px")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title("dot reprojection error per plane")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def calibrated_rig(run_rig: Rig, calibration: str | Path, cameras: Sequence[str] | None = None
                   ) -> tuple[Rig, dict[str, Any]]:
    """A run's rig with its cameras replaced by the fitted models of a calibration store.

    Everything but the cameras (volume, laser, timing) stays the run's; each camera of the run
    takes the fitted model of the camera of the same name.

    Parameters
    ----------
    run_rig
        The rig stored in the run.
    calibration
        Calibration store with fitted models (``lfpiv calibrate fit``).
    cameras
        The cameras that need a model (default: every camera of the run).

    Returns
    -------
    rig : Rig
        The run's rig with the fitted cameras.
    info : dict
        Which calibration was used (JSON-compatible, for the ``volumes/`` attrs): the store's
        path and creation time and, per camera, the reprojection RMS in pixels.

    Raises
    ------
    UsageError
        A store that cannot be opened, a camera with no fitted model in it (naming the camera
        and ``lfpiv calibrate fit``), or a model whose sensor differs from the run's camera.
    """
    try:
        store = CalibrationStore.open(calibration)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None
    need = set(cameras) if cameras else {c.name for c in run_rig.camera}
    cams, rms = [], {}
    for cam in run_rig.camera:
        model = store.model(cam.name) if cam.name in store.cameras else None
        if model is None:
            if cam.name in need:
                raise UsageError(f"camera '{cam.name}': no fitted model in {store.path}; run 'lfpiv calibrate fit "
                                 f"{store.path}' first")
            cams.append(cam)
            continue
        fitted = Camera.model_validate(model["camera"])
        if tuple(fitted.sensor_px) != tuple(cam.sensor_px):
            raise UsageError(f"camera '{cam.name}': the calibration's model has {fitted.sensor_px[0]} x "
                             f"{fitted.sensor_px[1]} pixels but the run's camera {cam.sensor_px[0]} x "
                             f"{cam.sensor_px[1]}; use the calibration of this rig")
        cams.append(fitted.model_copy(update={"serial": cam.serial}))
        rms[cam.name] = float(model["rms_px"])
    info = {"store": str(Path(store.path).resolve()), "created": str(store.attrs.get("created", "")),
            "rms_px": rms}
    return run_rig.model_copy(update={"camera": tuple(cams)}), info
