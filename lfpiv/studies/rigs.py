"""The rigs the studies run on: the scale's defaults, or the user's own (``--rig``) made to fit the scale.

Defaults (the example rigs of ``examples/``):

- one camera: ``tiny`` a 96 x 80 pixel crop of the tiny rig; ``quick`` the tiny rig's optics
  (10 pixels per lenslet, M = -1) on a volume as deep in lenslets of blur as M's (``examples/
  one_camera.toml``: about +-7 either side of focus, where the tiny rig is +-3.6), 82 x 68 x 58
  voxels at PVR (2, 2, 10); ``chapter`` M itself (2048 x 2048 pixels, 14 per lenslet);
- two cameras: ``tiny`` a 128 x 128 pixel crop of the demo rig; ``quick`` the demo rig (two
  256 x 256 pixel cameras at 90 degrees around a 1.2 mm cube, PVR 3 on every axis); ``chapter``
  M's camera and a copy turned about world y around a 12 mm cube at PVR 3, the chapter's
  dual-camera voxels.

A user's rig is used as it is at ``chapter`` scale; at ``quick`` (``tiny``) each sensor is cropped
about its centre to at most 192 x 160 (96 x 80) pixels and the volume across each camera's view to
what the crop sees, its depth kept, so the study keeps the rig's lenslets, magnification and depth
of field at a size a laptop reconstructs in seconds.

A second camera at separation angle ``a`` is the first turned by ``a`` about world y through the
volume's centre (docs/reference/conventions.md).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lfcore.rig import Rig, rotation_matrix
from lfpiv.errors import UsageError
from lfpiv.rigfile import load_rig

__all__ = ["CROP_PX", "cropped", "describe", "dual_rig", "focus_at_near_faces", "one_camera", "single_rig",
           "with_angle"]

#: The largest sensor (columns, rows) of a user's rig at each scale below ``chapter``.
CROP_PX = {"tiny": (96, 80), "quick": (192, 160)}
#: A crop's field of view that the volume may fill across a camera's view (the rest is margin
#: for the light of particles near the volume's edge).
FILL = 0.9


def _example(name: str) -> dict[str, Any]:
    from lfpiv.commands import examples_dir

    return load_rig(examples_dir() / f"{name}.toml").to_dict()


def _default_single(scale: str) -> dict[str, Any]:
    if scale == "chapter":
        return _example("one_camera")
    d = _example("tiny")
    if scale == "quick":
        d["volume"]["size_mm"] = [0.9, 0.75, 3.2]  # +-7.3 lenslets of blur, as M's +-7.0
        return d
    return _crop(d, CROP_PX["tiny"])


def _default_dual(scale: str) -> dict[str, Any]:
    if scale == "quick":
        return _example("demo")
    if scale == "tiny":
        return _crop(_example("demo"), (128, 128))
    d = _example("one_camera")
    d["volume"].update(size_mm=[12.0, 12.0, 12.0], pvr=[3.0, 3.0, 3.0])
    d["laser"].update(sheet_profile="uniform")
    return _with_angle(d, 90.0)


def _crop(d: dict[str, Any], most_px: tuple[int, int]) -> dict[str, Any]:
    """Each sensor cropped about its centre to at most ``most_px`` (columns, rows), and the
    volume, across each camera's view, to :data:`FILL` of what its crop sees at focus."""
    d = {**d, "camera": [dict(c) for c in d["camera"]], "volume": dict(d["volume"])}
    size = np.asarray(d["volume"]["size_mm"], dtype=float)
    for cam in d["camera"]:
        cols, rows = cam["sensor_px"]
        # keep the parity of the sensor, so that its centre stays on the same lenslet
        c = min(cols, most_px[0] - (most_px[0] - cols) % 2)
        r = min(rows, most_px[1] - (most_px[1] - rows) % 2)
        cam["sensor_px"] = [int(c), int(r)]
        pix = cam["pixel_pitch_um"] * 1e-3 / abs(cam["magnification"])
        rot = rotation_matrix(tuple(cam["rotation_deg"]))
        for axis, n in ((0, c), (1, r)):  # the camera's x and y in the world
            world = np.abs(rot[:, axis])
            i = int(np.argmax(world))
            if world[i] > 0.7:
                size[i] = min(size[i], FILL * n * pix)
    d["volume"]["size_mm"] = [round(float(s), 6) for s in size]
    return d


def cropped(rig: Rig, scale: str) -> Rig:
    """The user's rig at ``scale``: as it is for ``chapter``, cropped (:data:`CROP_PX`) below it."""
    if scale == "chapter":
        return rig
    return Rig.from_dict(_crop(rig.to_dict(), CROP_PX[scale]), source="the cropped rig")


def one_camera(rig: Rig) -> Rig:
    """The rig with its first camera only."""
    d = rig.to_dict()
    d["camera"] = d["camera"][:1]
    return Rig.from_dict(d)


def single_rig(user: dict[str, Any] | None, scale: str) -> Rig:
    """The one-camera rig of a study: the user's (its first camera) or the scale's default."""
    if user is None:
        return Rig.from_dict(_default_single(scale))
    return one_camera(cropped(Rig.from_dict(user), scale))


def dual_rig(user: dict[str, Any] | None, scale: str) -> Rig:
    """The two-camera rig of a study: the user's (with a second camera at 90 degrees if it has
    one only) or the scale's default."""
    if user is None:
        return Rig.from_dict(_default_dual(scale))
    rig = cropped(Rig.from_dict(user), scale)
    return rig if len(rig.camera) >= 2 else with_angle(rig, 90.0)


def _euler_deg(r: np.ndarray) -> list[float]:
    """rotation_deg [rx, ry, rz] of R = Rz Ry Rx (docs/reference/conventions.md)."""
    s = float(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(s) < 1.0 - 1e-12:
        rx, ry, rz = math.atan2(r[2, 1], r[2, 2]), math.asin(s), math.atan2(r[1, 0], r[0, 0])
    else:  # looking along y: only rx + rz or rx - rz is defined; rx = 0
        rx, ry, rz = 0.0, math.copysign(math.pi / 2, s), math.atan2(-r[0, 1], r[1, 1])
    return [round(math.degrees(v), 9) + 0.0 for v in (rx, ry, rz)]


def _with_angle(d: dict[str, Any], angle_deg: float) -> dict[str, Any]:
    cam0 = d["camera"][0]
    rx, ry, rz = cam0["rotation_deg"]
    a = math.radians(angle_deg)
    turn = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    # R maps camera to world, so the turned camera is turn @ R (kept as [0, ry + a, 0] when it can be)
    rot = [0.0, float(ry) + angle_deg, 0.0] if rx == 0 and rz == 0 else _euler_deg(turn @ rotation_matrix((rx, ry, rz)))
    centre = np.asarray(d["volume"]["centre_mm"], dtype=float)
    focus = centre + turn @ (np.asarray(cam0["focus_mm"], dtype=float) - centre)
    name = "cam1" if cam0["name"] != "cam1" else "cam0b"
    cam1 = {**cam0, "name": name, "rotation_deg": rot, "focus_mm": [round(float(v), 9) + 0.0 for v in focus]}
    cam1.pop("serial", None)
    return {**d, "camera": [cam0, cam1]}


def with_angle(rig: Rig, angle_deg: float) -> Rig:
    """The rig's first camera and a copy of it turned by ``angle_deg`` about world y through the
    volume's centre (0: the same view twice; 180: facing it)."""
    try:
        return Rig.from_dict(_with_angle(one_camera(rig).to_dict(), float(angle_deg)))
    except ValueError as exc:
        raise UsageError(f"a second camera {angle_deg:g} degrees from the first: {exc}") from None


def focus_at_near_faces(rig: Rig) -> Rig:
    """The rig with each camera's focal plane moved along its optical axis onto the face of the
    volume nearest to it (the volume's centre at the middle of its depth of field otherwise).

    A plenoptic camera cannot place a particle within a lenslet's image on its focal plane: there
    the particle lights one lenslet, whatever its position in it. With the focal planes on the
    volume's faces no particle lies in the middle of that blind slab, and the depth that the
    volume spans is seen with the blur, and so the resolution, growing one way only.
    """
    d = rig.to_dict()
    centre = np.asarray(rig.volume.centre_mm, dtype=float)
    size = np.asarray(rig.volume.size_mm, dtype=float)
    for cam, c in zip(rig.camera, d["camera"], strict=True):
        axis = cam.optical_axis  # towards the camera
        reach = 0.5 * float(np.abs(axis) @ size)  # from the centre to the box's face along the axis
        c["focus_mm"] = [round(float(v), 9) + 0.0 for v in centre + reach * axis]
    return Rig.from_dict(d)


def describe(rig: Rig, pvr: tuple[float, float, float] | None = None) -> str:
    """One line: cameras, optics, volume, voxels."""
    from lfcore.volume import VolumeGrid

    cam = rig.camera[0]
    grid = VolumeGrid.from_rig(rig, pvr=pvr)
    nz, ny, nx = grid.shape
    depth = 0.5 * rig.volume.size_mm[2] / cam.depth_per_lenslet_mm
    angles = ""
    if len(rig.camera) > 1:
        cos = float(np.clip(np.dot(rig.camera[0].optical_axis, rig.camera[1].optical_axis), -1, 1))
        angles = f" at {math.degrees(math.acos(cos)):.0f} degrees"
    p = pvr or rig.volume.pvr
    off = [float(np.dot(np.asarray(c.focus_mm) - np.asarray(rig.volume.centre_mm), c.optical_axis))
           for c in rig.camera]
    focus = "" if max(abs(v) for v in off) < 1e-9 else (
        "; focal planes " + ", ".join(f"{v:+.3g}" for v in off) + " mm from the centre along the axes")
    return (f"{len(rig.camera)} camera(s){angles} of {cam.sensor_px[0]} x {cam.sensor_px[1]} pixels, "
            f"{cam.pixels_per_lenslet:.3g} pixels per {cam.mla_grid} lenslet, M = {cam.magnification:g}; volume "
            f"{' x '.join(f'{s:g}' for s in rig.volume.size_mm)} mm (+-{depth:.1f} lenslets of blur deep), "
            f"{nx} x {ny} x {nz} voxels at PVR ({', '.join(f'{v:g}' for v in p)}){focus}")
