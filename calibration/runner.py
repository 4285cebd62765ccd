"""Driving the rig for calibration: camera-only triggering and the volumetric plane run.

Pure orchestration over the device protocols of :mod:`acquisition.protocols`; it never knows
whether the devices are real or simulated.

Laser safety: :func:`camera_only_plan` keeps only the camera output of the rig's timing plan, so
the pulse generator cannot fire the laser during calibration however it is armed.

The volumetric run (:func:`run_planes`) moves the stage to each target, checks the readback,
triggers every camera once and stores the images with the readback. A plane is done when its
readback is stored (written after the images), so a run that was interrupted resumes with the
planes not yet done and never repeats one.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from acquisition.protocols import Camera, DeviceError, PulseGenerator, Stage, TimingPlan
from acquisition.timing import plan_timing
from calibration.store import CalibrationStore
from lfcore.rig import Rig

__all__ = ["PlaneRun", "StageError", "camera_only_plan", "capture_frames", "plane_targets", "run_planes"]


class StageError(DeviceError):
    """The stage did not reach a plane's target; the message names the plane."""


def camera_only_plan(rig: Rig, triggers: int) -> TimingPlan:
    """The rig's timing plan for ``triggers`` T0 periods with every laser output removed.

    Raises
    ------
    acquisition.timing.TimingError
        The rig's timing is impossible.
    """
    plan = plan_timing(rig, pulses=triggers)
    cams = tuple(c for c in plan.channels if c.role == "camera")
    return dataclasses.replace(plan, channels=cams, pulse_times_s=(),
                               notes=(*plan.notes, "calibration: camera trigger only, no laser output programmed"))


def capture_frames(rig: Rig, cameras: list[Camera], gen: PulseGenerator, frames: int, exposure_us: float,
                   timeout_s: float | None = None) -> dict[str, np.ndarray]:
    """Trigger every camera ``frames`` times through the pulse generator (camera output only).

    Parameters
    ----------
    rig
        The rig (timing, channel roles).
    cameras
        Opened cameras.
    gen
        The opened pulse generator.
    frames
        Triggers, one frame each.
    exposure_us
        Exposure per frame, microseconds.
    timeout_s
        How long to wait for the frames (default: the burst's duration plus 5 s).

    Returns
    -------
    dict
        Camera name -> (frames, rows, columns) uint16.

    Raises
    ------
    DeviceError
        A camera that delivers fewer frames than triggered, or a generator that cannot be
        disarmed; the generator is always disarmed (best effort) before returning.
    """
    plan = camera_only_plan(rig, frames)
    gen.program(plan)
    for cam in cameras:
        cam.configure(triggered=True, frames_per_trigger=1, exposure_us=exposure_us)
    got: dict[str, list[np.ndarray]] = {cam.name: [] for cam in cameras}
    wait_s = timeout_s if timeout_s is not None else frames * plan.period_s + 5.0
    failed = True
    try:
        for cam in cameras:
            cam.start()
        gen.arm()
        end = time.monotonic() + wait_s
        for cam in cameras:
            while len(got[cam.name]) < frames:
                left = end - time.monotonic()
                frame = cam.fetch(left) if left > 0 else None
                if frame is None:
                    raise DeviceError(f"camera '{cam.name}' delivered {len(got[cam.name])} of {frames} triggered "
                                      f"frames in {wait_s:.1f} s; check its trigger cable and link")
                if frame.complete:
                    got[cam.name].append(np.asarray(frame.data))
        failed = False
    finally:
        try:
            gen.disarm()
        except Exception as exc:  # noqa: BLE001 - never mask the first error
            if not failed:
                raise DeviceError(f"could not confirm the pulse generator is disarmed ({exc}); check it") from None
        for cam in cameras:
            cam.stop()
    return {name: np.stack(imgs) for name, imgs in got.items()}


def plane_targets(planes: int, step_mm: float, centre_mm: float) -> np.ndarray:
    """(planes,) stage targets, ``step_mm`` apart, centred on ``centre_mm``."""
    if planes < 1 or not step_mm > 0:
        raise ValueError(f"need at least one plane and a positive step, got {planes} planes of {step_mm} mm")
    return centre_mm + (np.arange(planes) - (planes - 1) / 2.0) * step_mm


@dataclass(frozen=True)
class PlaneRun:
    """What :func:`run_planes` did."""

    planes: int
    taken: tuple[int, ...]
    skipped: tuple[int, ...]
    readback_mm: tuple[float, ...]


def run_planes(store: CalibrationStore, stage: Stage, grab: Callable[[], dict[str, np.ndarray]],
               targets_mm: np.ndarray, step_mm: float, *, tolerance_mm: float = 0.002, settle_s: float = 0.0,
               on_moved: Callable[[int, float], None] | None = None,
               progress: Callable[[int, int, int], None] | None = None) -> PlaneRun:
    """Take every plane not yet in ``store``: move, check the readback, settle, grab, store.

    Parameters
    ----------
    store
        The calibration store (planes created here, or resumed if they exist with these targets).
    stage
        The stage, homed.
    grab
        Triggers the cameras once and returns camera name -> (rows, columns) image.
    targets_mm
        (planes,) stage targets.
    step_mm
        Their spacing (stored as an attribute).
    tolerance_mm
        Largest accepted distance between readback and target.
    settle_s
        Wait after each move before triggering (vibration of the target).
    on_moved
        Called as ``on_moved(plane, readback_mm)`` after each move (the simulated lab moves its
        target with it).
    progress
        Called as ``progress(plane, done, total)`` after each stored plane.

    Raises
    ------
    StageError
        The stage failed or stopped away from a plane's target (the planes before it are kept).
    """
    targets = np.asarray(targets_mm, dtype=np.float64)
    store.init_planes(targets, step_mm=step_mm)
    done = store.planes_done()
    taken: list[int] = []
    readbacks: list[float] = []
    skipped = tuple(int(i) for i in np.flatnonzero(done))
    n_done = len(skipped)
    for i, target in enumerate(targets):
        if done[i]:
            continue
        try:
            readback = float(stage.move_to(float(target)))
        except DeviceError as exc:
            raise StageError(f"plane {i + 1} of {len(targets)} (target {target:.4f} mm): {exc} "
                             f"({n_done} plane(s) are stored, rerun to resume)") from None
        if not abs(readback - target) <= tolerance_mm:
            raise StageError(f"plane {i + 1} of {len(targets)}: the stage stopped at {readback:.4f} mm, not at its "
                             f"target {target:.4f} mm; check its travel, load and limit switches "
                             f"({n_done} plane(s) are stored, rerun to resume)")
        if settle_s > 0:
            time.sleep(settle_s)
        if on_moved is not None:
            on_moved(i, readback)
        images = grab()
        for cam, image in images.items():
            store.write_plane(cam, i, image, readback)
        taken.append(i)
        readbacks.append(readback)
        n_done += 1
        if progress is not None:
            progress(i, n_done, len(targets))
    return PlaneRun(len(targets), tuple(taken), skipped, tuple(readbacks))
