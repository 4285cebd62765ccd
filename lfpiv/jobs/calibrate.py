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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.timing import TimingError
from calibration.board import default_board
from calibration.fit import CameraFit, FitError
from calibration.mla_grid import GridError, MlaGrid, WhiteImage, detect_grid, white_from_frames
from calibration.planes import fit_from_planes
from calibration.runner import PlaneRun, camera_only_plan, capture_frames, plane_targets, run_planes
from calibration.selfcal import SelfCalError, SelfCalResult, self_calibrate
from calibration.store import CalibrationStore, CalibrationStoreError
from lfcore.flatfield import FlatField
from lfcore.rig import Camera, Rig, camera_from_dict, is_pinhole, rotation_angle_deg
from lfcore.runstore import RunStore
from lfcore.soloff import SoloffMap
from lfcore.target import DotBoard
from lfcore.white import WhiteImageConfig
from lfpiv import __version__
from lfpiv.errors import UsageError
from lfpiv.rigging import make_stage, open_rig

__all__ = ["MlaResult", "SelfCalSummary", "board_for", "calibrate_fit", "calibrate_mla", "calibrate_selfcal",
           "calibrate_volume",
           "calibrate_volume_from_files", "calibrated_rig", "default_board", "flat_fields", "open_calibration",
           "pinhole_cameras_skipped", "read_positions", "rotation_angle_deg", "white_config"]


@dataclass(frozen=True)
class MlaResult:
    """One camera's microlens calibration."""

    camera: str
    grid: MlaGrid
    mla: dict[str, Any]
    #: whether the store held a model fitted through an earlier grid, now removed
    removed_model: bool = False
    #: hot pixels of the white image, replaced before the grid was found
    hot_pixels: int = 0
    #: dark frames averaged into the stored dark image (0: none stored with this calibration)
    dark_frames: int = 0


def white_config(*, level_counts: float, vignetting: float, dead_lenslets: int) -> WhiteImageConfig:
    """The simulated white image of ``calibrate mla``'s ``--sim-*`` options, or a one-line
    :class:`UsageError`."""
    try:
        return WhiteImageConfig(level_counts=level_counts, vignetting=vignetting, dead_lenslets=dead_lenslets)
    except ValueError as exc:
        raise UsageError(f"--sim-*: {exc}") from None


def board_for(rig: Rig, spacing_mm: float | None = None, tilt_deg: float | None = None) -> DotBoard:
    """:func:`calibration.board.default_board` of ``calibrate volume``'s options, or a one-line
    :class:`UsageError`."""
    try:
        return default_board(rig, spacing_mm, tilt_deg)
    except ValueError as exc:
        raise UsageError(f"--spacing-mm/--tilt-deg: {exc}") from None


def open_calibration(path: str | Path, *, mode: str = "r") -> CalibrationStore:
    """The calibration store at ``path``, or a one-line :class:`UsageError`."""
    try:
        return CalibrationStore.open(path, mode=mode)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None


def calibrate_mla(rig: Rig, out: str | Path, *, frames: int = 4, exposure_us: float | None = None,
                  sim_options: dict[str, Any] | None = None, white: WhiteImageConfig | None = None,
                  whites: Mapping[str, Sequence[str | Path]] | None = None,
                  darks: Mapping[str, Sequence[str | Path]] | None = None, dark_frames: int = 0,
                  dark_ready: Callable[[], None] | None = None,
                  status: Callable[[str], None] | None = None,
                  progress: Callable[[int, int], None] | None = None) -> list[MlaResult]:
    """White images of every camera -> its microlens grid; both stored.

    The white images are taken with the rig's cameras (the laser cannot fire: only the camera
    output is programmed), or, with ``whites``, read from files the lab recorded. Either way each
    camera's frames are averaged, hot pixels rejected and clipping judged against the camera's
    own ``bit_depth`` (:func:`calibration.mla_grid.white_from_frames`), then every micro-image
    centre is found and the lattice fitted.

    Parameters
    ----------
    rig
        The rig.
    out
        Calibration store (created, or updated if it exists for the same cameras).
    frames
        White frames taken and averaged per camera (not with ``whites``).
    exposure_us
        Exposure (default: the rig's ``timing.camera_exposure_us``).
    sim_options
        For ``hardware = "sim"``: keyword arguments of :class:`sim.lab.SimLab`, or ``{"lab": lab}``.
    white
        For ``hardware = "sim"``: the simulated white image (level, vignetting, dead lenslets).
    whites
        Camera name -> white image files (TIFF, PNG, BMP, DaVis; every page of each is averaged);
        no device is opened. Every camera of the rig needs at least one.
    darks
        Camera name -> dark image files (no light: lens capped, laser off), averaged like the
        white ones and stored beside them: the flat field (:mod:`lfcore.flatfield`) subtracts
        them. Cameras not named get none.
    dark_frames
        Dark frames taken live per camera after the white ones (not with ``whites``): the
        simulated lab shows darkness; on hardware ``dark_ready`` is called first (cap the lenses).
    dark_ready
        Called before live dark frames are taken on hardware.
    status
        Called with a one-line message before each camera's grid detection (a minute on a
        29 MP sensor with two cores).
    progress
        Called as ``progress(done, total)`` as the cameras' grids are found.

    Raises
    ------
    UsageError
        A white image that is not white (too dark, saturated, no microlens structure) or a file
        that cannot be read, naming the camera; a store that belongs to other cameras.
    DeviceError
        A device fault (the generator was disarmed).

    Notes
    -----
    Pinhole cameras have no microlenses: they are skipped (no white image is taken or read for
    them; :func:`pinhole_cameras_skipped` names them for the note).
    """
    if frames < 1:
        raise UsageError(f"--frames must be at least 1, got {frames}")
    if Path(out).exists():  # an existing store must be one of these cameras: say so before any device opens
        _open_store(out, rig)
    lightfield = rig.lightfield_cameras
    if whites is not None:
        tomo = sorted(set(whites) & {c.name for c in rig.pinhole_cameras})
        if tomo:
            raise UsageError(f"--white: camera '{tomo[0]}' is a pinhole camera, which has no microlenses to find in a "
                             "white image; give white images of the light-field cameras only")
    if not lightfield:
        _open_store(out, rig)  # the store the volumetric calibration adds its planes to
        return []
    dark_images = _image_files(rig, darks, "--dark", required=False) if darks else {}
    if whites is not None:
        images = _white_files(rig, whites)
    else:
        images, live_darks = _white_frames(rig, frames, exposure_us, sim_options, white, dark_frames=dark_frames,
                                           dark_ready=dark_ready)
        dark_images = {**live_darks, **dark_images}
    results = []
    found: dict[str, WhiteImage] = {}
    dark_means: dict[str, tuple[np.ndarray, int]] = {}
    for k, cam in enumerate(lightfield):
        full = _full_scale(rig, cam)
        if cam.name in dark_images:
            dark_means[cam.name] = _checked_dark(cam, dark_images[cam.name], images[cam.name], full)
        try:
            w = white_from_frames(images[cam.name], full_scale=full)
            if status is not None:
                status(f"{cam.name}: detecting every micro-image centre in {w.image.size / 1e6:.0f} MP ...")
            grid = detect_grid(w.image)
        except GridError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
        found[cam.name] = w
        results.append(MlaResult(cam.name, grid, grid.to_mla(cam), hot_pixels=w.hot_pixels))
        if progress is not None:
            progress(k + 1, len(lightfield))
    # written only when every camera's grid was found; a new store is marked unfinished until then
    store = _open_store(out, rig, unfinished="calibrate mla")
    written = []
    for res in results:
        w = found[res.camera]
        dark, n_dark = dark_means.get(res.camera, (None, 0))
        # white, dark and grid in one atomic update: an interrupt leaves the old three or the new
        removed = store.write_mla(res.camera, white=w.image, white_frames=w.frames, grid=res.grid, mla=res.mla,
                                  dark=dark, dark_frames=n_dark)
        written.append(dataclasses.replace(res, removed_model=removed, dark_frames=n_dark))
    store.finish()
    return written


def _checked_dark(cam: Camera, darks: np.ndarray, whites: np.ndarray, full_scale: int) -> tuple[np.ndarray, int]:
    """The mean of a camera's dark frames, checked against its white frames: same size, darker."""
    stack = np.asarray(darks)
    stack = stack[None] if stack.ndim == 2 else stack
    white = np.asarray(whites)
    white = white[None] if white.ndim == 2 else white
    if stack.shape[1:] != white.shape[1:]:
        raise UsageError(f"camera '{cam.name}': the dark image is {stack.shape[2]} x {stack.shape[1]} px but the "
                         f"white image {white.shape[2]} x {white.shape[1]}; give a dark image of this camera")
    mean = stack.astype(np.float64).mean(axis=0)
    wmean = white.astype(np.float64).mean(axis=0)
    lit = np.percentile(wmean, 99.0)
    # a real dark image is below the white one wherever a micro-image is lit, and near it only in
    # the gaps between them (a fifth of a square lattice's pixels at most)
    if np.median(mean) >= lit or np.percentile(mean, 99.0) >= lit or np.mean(mean > wmean) > 0.25:
        raise UsageError(f"camera '{cam.name}': the dark image (median {np.median(mean):.0f} counts) is brighter "
                         f"than the white image on {np.mean(mean > wmean):.0%} of its pixels (the white: "
                         f"{lit:.0f} counts at its 99th percentile); give a dark image taken with the lens capped")
    if np.mean(stack >= full_scale) > 0.001:
        raise UsageError(f"camera '{cam.name}': the dark image is saturated; give a dark image taken with the lens "
                         "capped")
    return mean, len(stack)


def pinhole_cameras_skipped(rig: Rig) -> list[str]:
    """The cameras ``calibrate mla`` skips: pinhole cameras, which have no microlenses."""
    return [c.name for c in rig.pinhole_cameras]


def _full_scale(rig: Rig, cam: Camera) -> int:
    """Where a camera's pixels saturate: its ``bit_depth`` (a simulated one renders at most the
    ``[render]`` bit depth)."""
    bits = cam.bit_depth if rig.hardware != "sim" else min(cam.bit_depth, rig.render.bit_depth)
    return 2**bits - 1


def _white_frames(rig: Rig, frames: int, exposure_us: float | None, sim_options: dict[str, Any] | None,
                  white: WhiteImageConfig | None, *, dark_frames: int = 0,
                  dark_ready: Callable[[], None] | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``frames`` white frames of every camera, taken with the rig (laser off), and ``dark_frames``
    dark ones (no light) after them."""
    exposure = rig.timing.camera_exposure_us if exposure_us is None else exposure_us
    _check_timing(rig, frames)
    opts = {"pool_pairs": 1, "rays_per_particle": 16, **(sim_options or {})}
    with open_rig(rig, sim_options=opts) as rg:
        if rg.lab is not None:
            from sim.scenes import white_scene  # the application wires the simulated lab

            rg.lab.show(*white_scene(rg.lab.rig, white))  # the lab renders its own (true) rig
        lightfield = [cam for cam in rg.cameras if not is_pinhole(rig.camera_named(cam.name))]
        for cam in lightfield:
            want = tuple(rig.camera_named(cam.name).sensor_px)
            if tuple(cam.sensor_px) != want:
                raise UsageError(f"camera '{cam.name}' delivers {cam.sensor_px[0]} x {cam.sensor_px[1]} pixels but "
                                 f"the rig file says sensor_px = {list(want)}; correct the rig file")
        images = capture_frames(rig, lightfield, rg.pulse_generator, frames, exposure)
        darks: dict[str, np.ndarray] = {}
        if dark_frames > 0:
            if rg.lab is not None:
                from sim.scenes import dark_scene

                rg.lab.show(*dark_scene(rg.lab.rig))  # the lens capped: the sensor's own offset
            elif dark_ready is not None:
                dark_ready()
            darks = capture_frames(rig, lightfield, rg.pulse_generator, dark_frames, exposure)
        if rg.lab is not None:
            rg.lab.show(None)
    return images, darks


def _white_files(rig: Rig, whites: Mapping[str, Sequence[str | Path]]) -> dict[str, np.ndarray]:
    """Every frame of the white image files of every camera, checked against its sensor and bit depth."""
    return _image_files(rig, whites, "--white", required=True)


def _image_files(rig: Rig, files: Mapping[str, Sequence[str | Path]], option: str, *, required: bool
                 ) -> dict[str, np.ndarray]:
    """Every frame of the image files (8- or 16-bit PNG, TIFF, ...) given per camera with ``option``,
    checked against the camera's sensor and bit depth; ``required``: every light-field camera needs one."""
    from lfpiv.formats import FormatError
    from lfpiv.formats.images import FrameSource, inspect_image, read_frame

    names = [c.name for c in rig.camera]
    unknown = sorted(set(files) - set(names))
    if unknown:
        raise UsageError(f"{option}: camera '{unknown[0]}' is not in the rig (it has {', '.join(names)})")
    tomo = sorted(set(files) & {c.name for c in rig.pinhole_cameras})
    if tomo and not required:
        raise UsageError(f"{option}: camera '{tomo[0]}' is a pinhole camera, which calibrate mla skips; give images "
                         "of the light-field cameras only")
    missing = [c.name for c in rig.lightfield_cameras if not files.get(c.name)]
    if missing and required:
        raise UsageError(f"{option}: no white image for camera '{missing[0]}'; give {option} {missing[0]}=FILE for "
                         "every camera of the rig")
    out = {}
    whites = files
    for cam in rig.lightfield_cameras:
        if not files.get(cam.name):
            continue
        stack = []
        try:
            for f in whites[cam.name]:
                info = inspect_image(f)
                stack += [read_frame(FrameSource(Path(f), k), sensor_px=tuple(cam.sensor_px), bit_depth=cam.bit_depth)
                          for k in range(info.frames)]
        except FormatError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
        out[cam.name] = np.stack(stack)
    return out


def _check_timing(rig: Rig, triggers: int) -> None:
    """An impossible timing is reported before any device opens."""
    try:
        camera_only_plan(rig, triggers)
    except TimingError as exc:
        raise UsageError(str(exc)) from None


def _open_store(out: str | Path, rig: Rig, *, unfinished: str | None = None) -> CalibrationStore:
    """The store at ``out`` for ``rig``'s cameras, created if it does not exist (marked
    ``unfinished`` until its first calibration is written, when given)."""
    try:
        return CalibrationStore.open_or_create(out, rig, software_version=__version__, unfinished=unfinished)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None


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


def read_positions(path: str | Path) -> np.ndarray:
    """Each target plane's stage position from a CSV file: a header line naming ``stage_mm``
    (other columns, e.g. ``plane`` or ``file``, are ignored), then one row per plane in the order
    the images were taken.

    Returns
    -------
    numpy.ndarray
        (planes,) stage positions, mm.

    Raises
    ------
    UsageError
        A missing file, no ``stage_mm`` column, a value that is not a finite number, fewer than
        two planes, or positions that repeat.
    """
    import csv

    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except FileNotFoundError:
        raise UsageError(f"positions file {path} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"positions file {path} cannot be read ({exc}); save it as UTF-8 CSV") from None
    head = [c.strip() for c in rows[0]] if rows else []
    if "stage_mm" not in head:
        raise UsageError(f"{path}: the first line must be a header naming the column stage_mm (e.g. 'plane,stage_mm')")
    col = head.index("stage_mm")
    out = []
    for lineno, row in enumerate(rows[1:], start=2):
        try:
            v = float(row[col])
            if not np.isfinite(v):
                raise ValueError
        except (ValueError, IndexError):
            raise UsageError(f"{path}:{lineno}: stage_mm must be a number of mm, got {','.join(row)!r}") from None
        out.append(v)
    if len(out) < 2:
        raise UsageError(f"{path}: {len(out)} plane(s); the volumetric calibration needs at least two")
    if len(set(out)) != len(out):
        raise UsageError(f"{path}: a stage position appears twice; give each plane's own position")
    return np.asarray(out, dtype=np.float64)


class _RecordedPlanes:
    """Target images a lab took with its own stage, served as the volumetric run takes planes: a
    "stage" whose readback is the recorded position, and the images of the plane it is at."""

    def __init__(self, rig: Rig, images: Mapping[str, str], positions: np.ndarray) -> None:
        from lfpiv.formats import FormatError
        from lfpiv.formats.images import FrameSource, image_files, inspect_image

        names = [c.name for c in rig.camera]
        unknown = sorted(set(images) - set(names))
        if unknown:
            raise UsageError(f"--images: camera '{unknown[0]}' is not in the rig (it has {', '.join(names)})")
        missing = [n for n in names if n not in images]
        if missing:
            raise UsageError(f"--images: no target images for camera '{missing[0]}'; give --images "
                             f"{missing[0]}=PATTERN for every camera of the rig")
        self.rig, self.positions = rig, positions
        self.sources: dict[str, list[FrameSource]] = {}
        for cam in rig.camera:
            try:
                files = image_files(images[cam.name])
                frames = [FrameSource(f, k) for f in files for k in range(inspect_image(f).frames)]
            except FormatError as exc:
                raise UsageError(f"camera '{cam.name}': {exc}") from None
            if len(frames) != len(positions):
                raise UsageError(f"camera '{cam.name}': {images[cam.name]} holds {len(frames)} image(s) but the "
                                 f"positions list {len(positions)} plane(s); give one position per plane, in the "
                                 "order of the images")
            self.sources[cam.name] = frames
        self.at = 0

    def move_to(self, position_mm: float) -> float:
        self.at = int(np.argmin(np.abs(self.positions - position_mm)))
        return float(self.positions[self.at])

    def grab(self) -> dict[str, np.ndarray]:
        from lfpiv.formats import FormatError
        from lfpiv.formats.images import read_frame

        out = {}
        for cam in self.rig.camera:
            try:
                out[cam.name] = read_frame(self.sources[cam.name][self.at], sensor_px=tuple(cam.sensor_px),
                                           bit_depth=cam.bit_depth)
            except FormatError as exc:
                raise UsageError(f"camera '{cam.name}', plane {self.at + 1}: {exc}") from None
        return out


def calibrate_volume_from_files(rig: Rig, out: str | Path, *, images: Mapping[str, str], positions: str | Path,
                                board: DotBoard | None = None,
                                progress: Callable[[int, int, int], None] | None = None) -> PlaneRun:
    """Store target images the lab took with its own stage as the calibration's planes.

    After it, ``calibrate fit`` and ``reconstruct --calibration`` work as on planes that
    ``calibrate volume`` took with the rig's stage. The board is the rig's ``[target]`` (or the
    default board); its origin is at the volume's centre when the stage reads the middle of the
    positions. Resumable as ``calibrate volume`` is.

    Parameters
    ----------
    rig
        The rig.
    out
        Calibration store (with the microlens grids of ``calibrate mla``, or new).
    images
        Camera name -> glob pattern, folder or DaVis set of its target images, one image (or page)
        per plane in the order of ``positions``.
    positions
        CSV file of each plane's stage position (:func:`read_positions`).
    board
        The board (None: :func:`calibration.board.default_board` of the rig).
    progress
        Called as ``progress(plane, done, total)`` after each stored plane.

    Raises
    ------
    UsageError
        Unreadable or missing images, a positions file that does not match them, a store of
        other cameras or another target.
    """
    stage_mm = read_positions(positions)
    planes = _RecordedPlanes(rig, images, stage_mm)
    store = _open_store(out, rig)
    order = np.sort(stage_mm)
    centre = 0.5 * (order[0] + order[-1])
    brd = dataclasses.replace(board or default_board(rig), stage_centre_mm=float(centre))
    old = store.target()
    if old is not None and store.plane_targets() is not None and old != brd:
        raise UsageError(f"{out} holds planes of another target ({old}); give a new --out path")
    store.write_target(brd)
    step = float(np.median(np.abs(np.diff(stage_mm))))
    try:
        return run_planes(store, planes, planes.grab, stage_mm, step, tolerance_mm=0.0, progress=progress)
    except CalibrationStoreError as exc:
        raise UsageError(str(exc)) from None


def calibrate_fit(out: str | Path, *, fit_distortion: bool = False, min_dots: int = 2,
                  progress: Callable[[int, int], None] | None = None) -> list[CameraFit]:
    """Fit every camera's model to the stored planes and white-image grid; store the models.

    Dots are found and named with the nominal camera (the rig in the store), the model fitted,
    then the dots named again with the fitted model and the model refitted. A pinhole camera
    needs no microlens grid: its dots are blobs, and it is fitted with the pinhole model and
    distortion and with the Soloff polynomial (:mod:`calibration.pinhole`), both stored.

    Parameters
    ----------
    out
        Calibration store with microlens grids (``calibrate mla``) and planes (``calibrate volume``).
    fit_distortion
        Also fit a radial distortion (stored as ``radial_k1``; not used by the reconstruction).
    min_dots
        Fewest named dots accepted in a plane.
    progress
        Called as ``progress(done, total)`` as each camera's fit is done.

    Returns
    -------
    list of CameraFit
        One per camera, in rig order. A self-calibration of a camera's earlier model is removed
        with it (see :meth:`CalibrationStore.write_model`).

    Raises
    ------
    UsageError
        No planes or grid, a plane with too few dots (naming camera and plane), a failed fit.
    """
    store = open_calibration(out, mode="r+")
    board = store.target()
    if board is None or store.plane_targets() is None:
        raise UsageError(f"{out} holds no target planes; run 'lfpiv calibrate volume' first")
    rig = store.rig
    fits = []
    for nominal in rig.camera:
        grid = None if is_pinhole(nominal) else store.grid(nominal.name)
        if grid is None and not is_pinhole(nominal):
            raise UsageError(f"camera '{nominal.name}': no microlens grid in {store.path}; run 'lfpiv calibrate mla' "
                             "first")
        try:
            # the sim lights the target at the laser's wavelength
            fits.append(fit_from_planes(nominal, board, store.plane_frames(nominal.name), store.stage_mm(nominal.name),
                                        grid, wavelength_nm=rig.laser.wavelength_nm, fit_distortion=fit_distortion,
                                        min_dots=min_dots))
        except FitError as exc:
            raise UsageError(str(exc)) from None
        if progress is not None:
            progress(len(fits), len(rig.camera))
    for fit in fits:
        stats = {
            "rms_px": fit.rms_px, "plane_rms_px": _per_plane(fit.plane_rms_px),
            "plane_dots": [int(n) for n in fit.plane_dots], "lattice_rms_px": fit.lattice_rms_px,
            "radial_k1": fit.radial_k1, "std": fit.std, "dropped": fit.dropped, "set_aside": fit.set_aside,
            "views": "chief ray and four half-aperture views per dot"}
        if fit.soloff is not None:
            stats.update({"views": "one centroid per dot (a blob)", "soloff": fit.soloff.to_dict(),
                          "soloff_rms_px": fit.soloff_rms_px,
                          "soloff_plane_rms_px": _per_plane(fit.soloff_plane_rms_px)})
        store.write_model(fit.camera.name, fit.model_dict(), stats)  # and any self-calibration of the earlier one
    return fits


def _per_plane(values: np.ndarray) -> list[float | None]:
    """A per-plane array for the store's attributes (JSON has no NaN: None)."""
    return [None if not np.isfinite(v) else float(v) for v in values]


def calibrated_rig(run_rig: Rig, calibration: str | Path, cameras: Sequence[str] | None = None
                   ) -> tuple[Rig, dict[str, Any]]:
    """A run's rig with its cameras replaced by the fitted models of a calibration store.

    Everything but the cameras (volume, laser, timing) stays the run's; each camera of the run
    takes the fitted model of the camera of the same name, or its self-calibrated model where
    ``lfpiv calibrate selfcal`` corrected it.

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
    store = open_calibration(calibration)
    need = set(cameras) if cameras else {c.name for c in run_rig.camera}
    cams, rms, selfcalibrated = [], {}, []
    for cam in run_rig.camera:
        model = store.model(cam.name) if cam.name in store.cameras else None
        selfcal = store.selfcal(cam.name) if model is not None else None
        if selfcal is not None:  # a pinhole camera's model corrected by the volume self-calibration
            model = {**model, "camera": selfcal["camera"]}
            selfcalibrated.append(cam.name)
        if model is None:
            if cam.name in need:
                raise UsageError(f"camera '{cam.name}': no fitted model in {store.path}; run 'lfpiv calibrate fit "
                                 f"{store.path}' first")
            cams.append(cam)
            continue
        fitted = camera_from_dict(model["camera"])
        if tuple(fitted.sensor_px) != tuple(cam.sensor_px):
            raise UsageError(f"camera '{cam.name}': the calibration's model has {fitted.sensor_px[0]} x "
                             f"{fitted.sensor_px[1]} pixels but the run's camera {cam.sensor_px[0]} x "
                             f"{cam.sensor_px[1]}; use the calibration of this rig")
        cams.append(fitted.model_copy(update={"serial": cam.serial}))
        rms[cam.name] = float(model["rms_px"])
    info = {"store": str(Path(store.path).resolve()), "created": str(store.attrs.get("created", "")),
            "rms_px": rms}
    if selfcalibrated:
        info["self_calibrated"] = selfcalibrated
    return run_rig.model_copy(update={"camera": tuple(cams)}), info


@dataclass(frozen=True)
class SelfCalSummary:
    """What ``calibrate selfcal`` did: the result and where it came from."""

    result: SelfCalResult
    cameras: tuple[str, ...]
    #: the models it started from: "self-calibrated" (an earlier self-calibration) or "fitted"
    started_from: str
    frames: int
    pairs: tuple[int, ...]
    #: the light-field cameras of the run, left out
    left_out: tuple[str, ...]


def calibrate_selfcal(run: str | Path, calibration: str | Path, *, pairs: slice | None = None,
                      subvolumes: Sequence[int] = (4, 4, 2), radius_px: float = 2.0, iterations: int = 3,
                      min_matches: int = 20) -> SelfCalSummary:
    """Volume self-calibration of a calibration store's pinhole cameras on a recorded run.

    The particles of every frame of the chosen pairs are triangulated through the store's models
    (an earlier self-calibration's if there is one, else the fitted ones), the disparity maps of
    the sub-volumes measured, and each pinhole camera's model and Soloff polynomial corrected,
    ``iterations`` times (:func:`calibration.selfcal.self_calibrate`). The corrected models are
    stored beside the fitted ones (``<camera>/selfcal``), which stay as they were; a run
    reconstructed with ``--calibration`` then uses them.

    Parameters
    ----------
    run
        Run store of particle images recorded (or synthesized) with the calibrated rig.
    calibration
        Calibration store with fitted pinhole models (``lfpiv calibrate fit``).
    pairs
        The pairs whose frames (A and B) are used (default: every committed pair).
    subvolumes
        (nx, ny, nz) sub-volumes of the disparity maps.
    radius_px
        The first pass's search radius, pixels: more than the calibration's error.
    iterations
        Correction passes.
    min_matches
        Fewest matched particles a sub-volume needs for a disparity.

    Raises
    ------
    UsageError
        A store that cannot be opened, fewer than two pinhole cameras with fitted models, a run of
        other cameras, bad options, or too few matched particles.
    """
    from lfpiv.runs import open_run

    if len(subvolumes) != 3 or min(subvolumes) < 1:
        raise UsageError(f"--subvolumes must be three whole numbers of at least 1 (x, y, z), got {list(subvolumes)}")
    if not radius_px > 0 or iterations < 0 or min_matches < 1:
        raise UsageError("--radius-px must be positive, --iterations at least 0 and --min-matches at least 1")
    store: RunStore = open_run(run)
    calib = open_calibration(calibration, mode="r+")
    tomo = [c.name for c in store.rig.pinhole_cameras]
    left_out = tuple(c.name for c in store.rig.lightfield_cameras)
    if len(tomo) < 2:
        raise UsageError(f"{store.path} has {len(tomo)} pinhole camera(s); volume self-calibration needs two or more "
                         "(light-field cameras are not self-calibrated)")
    missing = [n for n in tomo if n not in calib.cameras or calib.model(n) is None]
    if missing:
        raise UsageError(f"camera '{missing[0]}': no fitted model in {calib.path}; run 'lfpiv calibrate fit "
                         f"{calib.path}' first")
    done = store.committed_pairs
    chosen = list(range(done))[pairs] if pairs is not None else list(range(done))
    if not chosen:
        raise UsageError(f"{store.path}: no committed pair in the chosen range (it has {done})")
    started = "self-calibrated" if all(calib.selfcal(n) is not None for n in tomo) else "fitted"
    cams, soloff = [], []
    for name in tomo:
        m = calib.selfcal(name) if started == "self-calibrated" else calib.model(name)
        cam = camera_from_dict(m["camera"])
        if tuple(cam.sensor_px) != tuple(store.rig.camera_named(name).sensor_px):
            raise UsageError(f"camera '{name}': the calibration's model has another sensor than the run's camera; "
                             "use the calibration of this rig")
        cams.append(cam)
        soloff.append(SoloffMap.from_dict(m["soloff"]) if m.get("soloff") else None)
    frames = [np.concatenate([np.asarray(store.frames(n)[p]) for p in chosen]) for n in tomo]
    try:
        res = self_calibrate(cams, frames, store.rig.volume.bounds_mm, subvolumes=tuple(int(v) for v in subvolumes),
                             radius_px=radius_px, iterations=iterations, min_matches=min_matches, soloff=soloff)
    except SelfCalError as exc:
        raise UsageError(str(exc)) from None
    nx, ny, nz = (int(v) for v in subvolumes)
    for k, name in enumerate(tomo):
        stats = {"run": str(Path(store.path).resolve()), "pairs": chosen, "frames": res.frames,
                 "started_from": started, "subvolumes": [nx, ny, nz], "rms_px": res.rms_px.tolist(),
                 "max_px": res.max_px.tolist(), "radius_px": res.radius_px.tolist(),
                 "camera_rms_px": [float(np.sqrt(np.nanmean(np.sum(m[k] ** 2, axis=-1)))) for m in res.maps_px]}
        if res.soloff[k] is not None:
            stats["soloff"] = res.soloff[k].to_dict()
        calib.write_selfcal(name, res.cameras[k].model_dump(mode="json", exclude_none=True), stats,
                            res.maps_px[:, k], res.counts)
    return SelfCalSummary(res, tuple(tomo), started, res.frames, tuple(chosen), left_out)


def flat_fields(run_rig: Rig, calibration: str | Path, cameras: Sequence[str] | None = None
                ) -> tuple[dict[str, FlatField], dict[str, Any], list[str]]:
    """The flat fields of a run's light-field cameras from a calibration store's dark and white images.

    Each camera's gain is its white image's light (less its dark image) over the white light a
    perfect camera of its optics records (:func:`lfcore.white.white_irradiance` of its fitted model
    where the store has one, else of the run's camera with the store's measured lattice), so what
    is left is the response alone (:func:`lfcore.flatfield.flat_field`).

    Parameters
    ----------
    run_rig
        The run's rig (the cameras the frames are of).
    calibration
        Calibration store with white images (``lfpiv calibrate mla``; dark images where taken).
    cameras
        The cameras reconstructed (default: all of the run's); pinhole cameras are left out.

    Returns
    -------
    flats : dict
        Camera name -> :class:`lfcore.flatfield.FlatField`.
    info : dict
        JSON-compatible: the store's path and, per camera, the share of its pixels masked and
        whether a dark image was used (for the ``volumes/`` settings).
    notes : list of str
        One line per camera without a dark image (its white image's own floor taken instead).

    Raises
    ------
    UsageError
        A store that cannot be opened, of other cameras or sensors (another rig), a camera without a
        white image, or images that make no flat field.
    """
    from lfcore.chief_ray import diffraction_sigma_mm
    from lfcore.flatfield import flat_field
    from lfcore.white import white_irradiance

    store = open_calibration(calibration)
    names = list(cameras) if cameras else [c.name for c in run_rig.camera]
    flats: dict[str, FlatField] = {}
    info: dict[str, Any] = {"store": str(Path(store.path).resolve()), "cameras": {}}
    notes = []
    for name in names:
        cam = run_rig.camera_named(name)
        if is_pinhole(cam):
            continue
        if name not in store.cameras:
            raise UsageError(f"{store.path} holds no camera '{name}' (it has {', '.join(store.cameras)}); give the "
                             "calibration of this rig")
        theirs = store.rig.camera_named(name)
        if tuple(theirs.sensor_px) != tuple(cam.sensor_px) or is_pinhole(theirs):
            raise UsageError(f"camera '{name}': {store.path} is a calibration of another camera "
                             f"({theirs.sensor_px[0]} x {theirs.sensor_px[1]} px, the run's {cam.sensor_px[0]} x "
                             f"{cam.sensor_px[1]}); give the "
                             "calibration of this rig")
        if (theirs.mla_grid != cam.mla_grid or abs(theirs.mla_pitch_um / cam.mla_pitch_um - 1) > 0.01
                or abs(theirs.pixel_pitch_um / cam.pixel_pitch_um - 1) > 0.01):
            raise UsageError(f"camera '{name}': {store.path} is a calibration of other optics ({theirs.mla_grid} "
                             f"lenslets of {theirs.mla_pitch_um:g} um, the run's {cam.mla_grid} of "
                             f"{cam.mla_pitch_um:g} um); give the calibration of this rig")
        white = store.white(name)
        if white is None:
            raise UsageError(f"camera '{name}': no white image in {store.path}; run 'lfpiv calibrate mla' first")
        dark = store.dark(name)
        if dark is None:
            notes.append(f"camera '{name}': no dark image in {store.path}: the white image's floor "
                         f"({np.percentile(white, 1.0):.0f} counts) is taken as every pixel's dark level")
        model = store.model(name)
        optics = camera_from_dict(model["camera"]) if model else cam.model_copy(
            update=_measured_lattice(store, name))
        sigma = diffraction_sigma_mm(run_rig.laser.wavelength_nm if run_rig.render.diffraction else 0.0,
                                     optics.lenslet_f_number) / optics.pixel_mm
        try:
            flat = flat_field(float(np.percentile(white, 1.0)) if dark is None else dark, white,
                              reference=white_irradiance(optics, blur_sigma_px=sigma))
        except ValueError as exc:
            raise UsageError(f"camera '{name}': {exc}") from None
        flats[name] = flat
        info["cameras"][name] = {"masked_fraction": round(flat.masked_fraction, 6), "dark": dark is not None}
    return flats, info, notes


def _measured_lattice(store: CalibrationStore, name: str) -> dict[str, Any]:
    """The lattice ``calibrate mla`` measured (pitch, rotation, offset), as camera keys; {} if none."""
    grid = store.grid(name)
    if grid is None:
        return {}
    mla = dict(store.group[name]["mla"].attrs.get("mla", {}))
    return {k: (tuple(v) if isinstance(v, list) else v) for k, v in mla.items()
            if k in ("mla_pitch_um", "mla_rotation_deg", "mla_offset_um")}
