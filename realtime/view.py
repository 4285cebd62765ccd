"""What the monitor shows of a processed pair: velocity, vorticity, projections, a slice, a vector plane.

:func:`derive` is a pure function of a :class:`~realtime.processing.ProcessedPair` and the
:class:`~realtime.settings.LiveSettings` taken for it: no threads, no counters, no clock. The
maximum-intensity projections and the slice of volume A are cut on the device (only these
planes come to the host); the in-plane vectors and the out-of-plane vorticity are those of the
vector plane nearest the slice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcore.camera_checks import CameraCheck, check_image
from lfcore.rig import Rig, is_pinhole
from lfcore.vectors import centres_mm, displacement_to_velocity, vorticity
from lfcore.views import Lattice
from realtime.processing import ProcessedPair
from realtime.settings import AXES, LiveSettings

__all__ = ["IN_PLANE", "Derived", "VectorSlice", "camera_checks", "derive"]

#: Per slice axis (the normal), the plane's horizontal and vertical axes.
IN_PLANE = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}
#: Component index of each axis in (x, y, z) vectors.
_COMPONENT = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class VectorSlice:
    """The vectors of one plane of the vector grid, in that plane.

    Attributes
    ----------
    axis
        Axis normal to the plane.
    index
        Index of the plane in the vector grid along ``axis``.
    position_mm
        World coordinate of the plane along ``axis``.
    h_mm, v_mm
        1-D world coordinates of the plane's horizontal and vertical axes (for axis z: x and y;
        for y: x and z; for x: y and z).
    uv
        (len(v_mm), len(h_mm), 2) in-plane velocity (horizontal, vertical) in m/s.
    normal_vorticity
        (len(v_mm), len(h_mm)) the vorticity component along ``axis`` in 1/s.
    """

    axis: str
    index: int
    position_mm: float
    h_mm: np.ndarray
    v_mm: np.ndarray
    uv: np.ndarray
    normal_vorticity: np.ndarray


@dataclass(frozen=True)
class Derived:
    """Velocity, vorticity and what the monitor shows of one pair.

    Attributes
    ----------
    mip
        Maximum-intensity projections of volume A along each axis: ``"z"`` (ny, nx),
        ``"y"`` (nz, nx), ``"x"`` (nz, ny).
    slice_axis, slice_index, slice_image
        The slice of volume A shown: (ny, nx) for z, (nz, nx) for y, (nz, ny) for x; the index
        clipped to the grid (None in the settings: the middle).
    extent_mm
        Per axis name, the (min, max) world coordinates of the voxel centres.
    vectors
        The vector plane nearest the slice.
    velocity
        (nz, ny, nx, 3) velocity (u, v, w) in m/s on the vector grid.
    vorticity
        (nz, ny, nx, 3) vorticity (x, y, z) in 1/s.
    grid_mm
        1-D world coordinates (x, y, z) of the vector grid.
    outlier_fraction
        Share of the vectors the median test flagged.
    """

    mip: dict[str, np.ndarray]
    slice_axis: str
    slice_index: int
    slice_image: np.ndarray
    extent_mm: dict[str, tuple[float, float]]
    vectors: VectorSlice
    velocity: np.ndarray
    vorticity: np.ndarray
    grid_mm: tuple[np.ndarray, np.ndarray, np.ndarray]
    outlier_fraction: float


def derive(pair: ProcessedPair, settings: LiveSettings) -> Derived:
    """Velocity, vorticity, projections, the slice and its vector plane of one processed pair.

    Parameters
    ----------
    pair
        The pair: volume A on the device (read, not changed), its vector field in voxels, the
        grid and the time between the frames.
    settings
        The slice axis and index (the other settings are the processing's).

    Returns
    -------
    Derived
        Velocity in m/s and vorticity in 1/s on the vector grid (the displacement's NaNs kept
        in the velocity, taken as zero for the vorticity), the projections and the slice on the
        host, the vector plane nearest the slice.
    """
    g, vf, s, ops = pair.grid, pair.field, settings, pair.ops
    vel = displacement_to_velocity(vf.displacement, g.voxel_mm, pair.dt_s)
    x_mm, y_mm, z_mm = centres_mm((vf.x, vf.y, vf.z), g.origin_mm, g.voxel_mm)
    vort = vorticity(np.nan_to_num(vel), x_mm, y_mm, z_mm)
    mip = {a: ops.projection(pair.volume, ax) for ax, a in enumerate("zyx")}  # only these come to the host
    ax = "zyx".index(s.slice_axis)  # array axis of the volume
    n = g.shape[ax]
    idx = n // 2 if s.slice_index is None else int(np.clip(s.slice_index, 0, n - 1))
    sl = ops.plane(pair.volume, ax, idx)
    # the vector plane nearest the voxel slice
    centres_vox = {"x": vf.x, "y": vf.y, "z": vf.z}[s.slice_axis]
    vi = int(np.argmin(np.abs(np.asarray(centres_vox) - idx)))
    coords = {"x": x_mm, "y": y_mm, "z": z_mm}
    h, v = IN_PLANE[s.slice_axis]
    plane = np.take(vel, vi, axis=ax)  # (v, h, 3) in array order
    wplane = np.take(vort, vi, axis=ax)[..., _COMPONENT[s.slice_axis]]
    uv = np.stack([plane[..., _COMPONENT[h]], plane[..., _COMPONENT[v]]], axis=-1)
    vs = VectorSlice(axis=s.slice_axis, index=vi, position_mm=float(coords[s.slice_axis][vi]),
                     h_mm=coords[h], v_mm=coords[v], uv=uv, normal_vorticity=wplane)
    extent = {a: (float(g.axis_mm(a)[0]), float(g.axis_mm(a)[-1])) for a in AXES}
    return Derived(mip=mip, slice_axis=s.slice_axis, slice_index=idx, slice_image=sl, extent_mm=extent, vectors=vs,
                   velocity=vel, vorticity=vort, grid_mm=(x_mm, y_mm, z_mm),
                   outlier_fraction=float(np.mean(vf.outlier)))


def camera_checks(rig: Rig, raw: dict[str, np.ndarray], *, lattices: dict[str, Lattice] | None = None
                  ) -> dict[str, CameraCheck]:
    """The checks before recording (:mod:`lfcore.camera_checks`) of each camera's raw frame.

    Parameters
    ----------
    rig
        The rig (cameras, volume, bit depths).
    raw
        Camera name -> (rows, columns) raw frame A.
    lattices
        Camera name -> micro-image lattice (the calibration's); missing: the camera's nominal one.

    Returns
    -------
    dict
        Camera name -> its :class:`~lfcore.camera_checks.CameraCheck`, for the cameras of ``raw``
        the rig has.
    """
    out = {}
    names = {c.name for c in rig.camera}
    for name, img in raw.items():
        if name not in names:
            continue
        cam = rig.camera_named(name)
        bits = cam.bit_depth if rig.hardware != "sim" else min(cam.bit_depth, rig.render.bit_depth)
        lat = None if is_pinhole(cam) else (lattices or {}).get(name)
        out[name] = check_image(np.asarray(img), cam, full_scale=float(2**bits - 1), volume=rig.volume, lattice=lat)
    return out
