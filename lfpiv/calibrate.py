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

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.timing import TimingError
from calibration.mla_grid import GridError, MlaGrid, check_white, detect_grid
from calibration.runner import PlaneRun, camera_only_plan, capture_frames, plane_targets, run_planes
from calibration.store import CalibrationStore, CalibrationStoreError
from lfcore.rig import Rig
from lfcore.white import WhiteImageConfig
from lfpiv import __version__
from lfpiv.acquire import open_rig
from lfpiv.errors import UsageError

__all__ = ["MlaResult", "calibrate_mla", "calibrate_volume", "plot_grids"]


@dataclass(frozen=True)
class MlaResult:
    """One camera's microlens calibration."""

    camera: str
    grid: MlaGrid
    mla: dict[str, Any]


def calibrate_mla(rig: Rig, out: str | Path, *, frames: int = 4, exposure_us: float | None = None,
                  sim_options: dict[str, Any] | None = None, white: WhiteImageConfig | None = None
                  ) -> list[MlaResult]:
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

            rg.lab.world.show(*white_scene(rig, white))
        for cam in rg.cameras:
            want = tuple(rig.camera_named(cam.name).sensor_px)
            if tuple(cam.sensor_px) != want:
                raise UsageError(f"camera '{cam.name}' delivers {cam.sensor_px[0]} x {cam.sensor_px[1]} pixels but "
                                 f"the rig file says sensor_px = {list(want)}; correct the rig file")
        images = capture_frames(rig, rg.cameras, rg.pulse_generator, frames, exposure)
        if rg.lab is not None:
            rg.lab.world.show(None)
    full_scale = 2**rig.render.bit_depth - 1
    results = []
    grids = {}
    for cam in rig.camera:
        stack = images[cam.name]
        mean = stack.astype(np.float64).mean(axis=0)
        try:
            check_white(stack.max(axis=0), full_scale)
            grid = detect_grid(mean)
        except GridError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
        grids[cam.name] = (mean, len(stack))
        results.append(MlaResult(cam.name, grid, grid.to_mla(cam)))
    store = _open_store(out, rig)  # written only when every camera's grid was found
    for res in results:
        mean, n = grids[res.camera]
        store.write_white(res.camera, mean, frames_averaged=n)
        store.write_grid(res.camera, res.grid, mla=res.mla)
    return results


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


def calibrate_volume(rig: Rig, out: str | Path, *, planes: int = 51, step_mm: float = 0.5,
                     centre_mm: float | None = None, settle_s: float = 0.0, exposure_us: float | None = None,
                     sim_options: dict[str, Any] | None = None,
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
    sim_options
        For ``hardware = "sim"``: keyword arguments of :class:`sim.lab.SimLab`, or ``{"lab": lab}``.
        The simulated target sits at world z = volume centre + (stage position - ``centre_mm``).
    progress
        Called as ``progress(plane, done, total)`` after each stored plane.

    Raises
    ------
    UsageError
        Impossible planes or timing, no stage port, a store of other cameras or other planes.
    DeviceError
        A device fault; :class:`calibration.runner.StageError` names the plane the stage missed.
    """
    from acquisition.stage import ZaberStage

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
        stage = ZaberStage(rg.stage_port, baud=rig.stage.baud)
        stage.open()
        try:
            stage.home()
            lo, hi = stage.travel_mm
            centre = 0.5 * (lo + hi) if centre_mm is None else centre_mm
            targets = plane_targets(planes, step_mm, centre)
            if targets[0] < lo or targets[-1] > hi:
                raise UsageError(f"planes {targets[0]:g}..{targets[-1]:g} mm leave the stage's travel {lo:g}..{hi:g} "
                                 "mm; give fewer --planes, a smaller --step-mm or another --centre-mm")
            lab = rg.lab

            def on_moved(plane: int, readback: float) -> None:
                if lab is not None:
                    from sim.scenes import dot_target_scene  # the application wires the simulated lab

                    z = rig.volume.centre_mm[2] + lab.stage.position_mm - centre  # the TRUE carriage position
                    lab.world.show(*dot_target_scene(rig, z))

            def grab() -> dict[str, np.ndarray]:
                return {k: v[0] for k, v in capture_frames(rig, rg.cameras, rg.pulse_generator, 1, exposure).items()}

            try:
                return run_planes(store, stage, grab, targets, step_mm, settle_s=settle_s, on_moved=on_moved,
                                  progress=progress)
            except CalibrationStoreError as exc:
                raise UsageError(str(exc)) from None
        finally:
            stage.close()
            if rg.lab is not None:
                rg.lab.world.show(None)
