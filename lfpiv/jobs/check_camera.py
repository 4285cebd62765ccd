"""The checks before recording (``lfpiv check-camera``): per camera, the seeding density, the
saturated share, the micro-image fill, the histogram and a refocused plane, each against the
range the chapter recommends.

The frame checked is grabbed from the rig (real or simulated) by recording one double-frame pair
through the ordinary recording path (:func:`lfpiv.jobs.acquire.record`), which owns the order of
operations that keeps the laser safe (armed for one pulse pair, disarmed on every way out), into
a scratch run store that is removed afterwards; or it is a recorded run's frame, or image files.
The computation is :mod:`lfcore.camera_checks`.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lfcore.camera_checks import CameraCheck, check_image
from lfcore.rig import Rig, is_pinhole
from lfcore.views import Lattice, nominal_lattice
from lfpiv.errors import UsageError

__all__ = ["check_cameras", "check_frames", "grab_frames", "lattices_of"]

PathLike = str | os.PathLike[str]


def _full_scale(rig: Rig, name: str) -> float:
    cam = rig.camera_named(name)
    bits = cam.bit_depth if rig.hardware != "sim" else min(cam.bit_depth, rig.render.bit_depth)
    return float(2**bits - 1)


def lattices_of(rig: Rig, calibration: PathLike | None) -> tuple[dict[str, Lattice], list[str]]:
    """The micro-image lattice of every light-field camera: the calibration store's fitted grid
    where it has one, else the rig file's nominal MLA (with a note)."""
    out: dict[str, Lattice] = {}
    notes: list[str] = []
    store = None
    if calibration is not None:
        from lfpiv.jobs.calibrate import open_calibration

        store = open_calibration(calibration)
    for cam in rig.lightfield_cameras:
        grid = store.grid(cam.name) if store is not None and cam.name in store.cameras else None
        if grid is not None and tuple(grid.image_shape) == (cam.sensor_px[1], cam.sensor_px[0]):
            out[cam.name] = Lattice(origin_px=tuple(grid.origin_px), basis_px=np.asarray(grid.basis_px),
                                    grid=grid.grid)
        else:
            out[cam.name] = nominal_lattice(cam)
            notes.append(f"camera '{cam.name}': the rig file's nominal microlens lattice (no fitted grid"
                         f"{'' if store is None else ' in ' + str(calibration)}; lfpiv calibrate mla measures it)")
    return out, notes


def check_frames(rig: Rig, frames: Mapping[str, np.ndarray], *, calibration: PathLike | None = None
                 ) -> tuple[list[CameraCheck], list[str]]:
    """Check one raw frame of each camera.

    Parameters
    ----------
    rig
        The rig (cameras, volume).
    frames
        Camera name -> (rows, columns) raw frame.
    calibration
        Calibration store whose fitted microlens grids to use.

    Returns
    -------
    tuple
        (one :class:`lfcore.camera_checks.CameraCheck` per camera, in the rig's order; notes).
    """
    lattices, notes = lattices_of(rig, calibration)
    checks = []
    for cam in rig.camera:
        if cam.name not in frames:
            continue
        img = np.asarray(frames[cam.name])
        if img.shape != (cam.sensor_px[1], cam.sensor_px[0]):
            raise UsageError(f"camera '{cam.name}': the frame is {img.shape[1]} x {img.shape[0]} px but the rig says "
                             f"{cam.sensor_px[0]} x {cam.sensor_px[1]}")
        try:
            checks.append(check_image(img, cam, full_scale=_full_scale(rig, cam.name), volume=rig.volume,
                                      lattice=None if is_pinhole(cam) else lattices[cam.name]))
        except ValueError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
    return checks, notes


def grab_frames(rig: Rig, *, sim_options: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
    """Frame A of one double-frame pair from every camera of the rig (real or simulated).

    The pair is recorded by :func:`lfpiv.jobs.acquire.record` (one double pulse of the laser,
    disarmed on every way out) into a scratch run store, which is removed.

    Raises
    ------
    UsageError
        An impossible timing.
    DeviceError
        A device fault (the laser was disarmed).
    """
    from lfpiv.jobs.acquire import record

    scratch = Path(tempfile.mkdtemp(prefix="lfpiv-check-"))
    try:
        res = record(rig, scratch / "check.zarr", 1, sim_options=sim_options, stall_s=10.0, say=lambda _: None)
        if res.store.committed_pairs < 1:
            raise UsageError(f"no pair was recorded ({res.message}); check the cameras' trigger cables and "
                             "lfpiv devices")
        return {cam.name: np.asarray(res.store.read_frame(cam.name, 0, 0)) for cam in rig.camera}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def check_cameras(rig: Rig, *, run: PathLike | None = None, pair: int = 0,
                  images: Mapping[str, PathLike] | None = None, calibration: PathLike | None = None,
                  sim_options: dict[str, Any] | None = None, cameras: list[str] | None = None,
                  out: PathLike | None = None) -> tuple[list[CameraCheck], list[str]]:
    """The checks before recording, of a frame grabbed now, of a run's frame or of image files.

    Parameters
    ----------
    rig
        The rig.
    run, pair
        Check frame A of this pair of a recorded run instead of grabbing one.
    images
        Camera name -> raw image file, instead of grabbing.
    calibration
        Calibration store with the fitted microlens grids.
    sim_options
        Keyword arguments of the simulated lab (``hardware = "sim"``).
    cameras
        Only these cameras (default: every one).
    out
        A PNG to draw the checks into (:func:`lfpiv.plots.plot_camera_checks`), or None.

    Returns
    -------
    tuple
        (the checks, notes).
    """
    names = [c.name for c in rig.camera]
    for name in cameras or []:
        if name not in names:
            raise UsageError(f"--camera: '{name}' is not in the rig (it has {', '.join(names)})")
    if run is not None and images:
        raise UsageError("give a run (--run) or image files (--image), not both")
    if run is not None:
        from lfpiv.runs import open_run

        store = open_run(run)
        rig = store.rig
        frames = {c.name: store.read_frame(c.name, int(pair), 0) for c in rig.camera
                  if not cameras or c.name in cameras}
    elif images:
        from lfpiv.jobs.views import frame_of_image

        unknown = sorted(set(images) - set(names))
        if unknown:
            raise UsageError(f"--image: camera '{unknown[0]}' is not in the rig (it has {', '.join(names)})")
        frames = {name: frame_of_image(path, rig.camera_named(name)) for name, path in images.items()}
    else:
        frames = grab_frames(rig, sim_options=sim_options)
    if cameras:
        frames = {k: v for k, v in frames.items() if k in cameras}
    checks, notes = check_frames(rig, frames, calibration=calibration)
    if out is not None:
        from lfpiv.plots import plot_camera_checks

        plot_camera_checks(checks, out)
    return checks, notes
