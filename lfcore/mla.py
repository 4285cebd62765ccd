"""The microlens array lattice and the sensor's pixel coordinates.

Sensor-plane coordinates are the camera frame's transverse (x, y) in mm, with the optical axis
at the origin; they are the same at the MLA and at the sensor. The MLA is centred on the sensor
with a lenslet centre on the sensor centre (before ``mla_offset_um`` and ``mla_rotation_deg``).
Hexagonal grids have rows along sensor x, odd rows shifted by half a pitch, and a row spacing of
p * sqrt(3) / 2; each lenslet's aperture is its Voronoi cell (square or hexagon).

Pixel coordinates are continuous (column, row): pixel ``[r, c]`` of an image array covers
``c <= column < c + 1`` and ``r <= row < r + 1``. The image formed by the main lens is inverted
(M < 0), and the sensor is read out so that the raw image appears upright, as seen from the
camera: column = Nc/2 - x / pixel and row = Nr/2 + y / pixel. World +x of an identity-pose
camera therefore appears to the right, world +y toward the top (row 0).
"""

from __future__ import annotations

import math

import numpy as np

from lfcore.rig import Camera

__all__ = [
    "lenslet_centers",
    "lenslet_count",
    "nearest_lenslet",
    "pixel_centers_sensor",
    "pixel_to_sensor",
    "sensor_to_pixel",
]

HEX_ROW = math.sqrt(3.0) / 2.0


def _to_lattice(cam: Camera, xy: np.ndarray) -> np.ndarray:
    t = math.radians(cam.mla_rotation_deg)
    c, s = math.cos(t), math.sin(t)
    d = xy - np.asarray(cam.mla_offset_um) * 1e-3
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def _from_lattice(cam: Camera, uv: np.ndarray) -> np.ndarray:
    t = math.radians(cam.mla_rotation_deg)
    c, s = math.cos(t), math.sin(t)
    xy = np.stack([c * uv[..., 0] - s * uv[..., 1], s * uv[..., 0] + c * uv[..., 1]], axis=-1)
    return xy + np.asarray(cam.mla_offset_um) * 1e-3


def nearest_lenslet(cam: Camera, xy_mm: np.ndarray) -> np.ndarray:
    """Centre of the lenslet whose aperture contains each sensor-plane point.

    Parameters
    ----------
    cam
        The camera.
    xy_mm
        (..., 2) sensor-plane points in mm.

    Returns
    -------
    numpy.ndarray
        (..., 2) lenslet centres in mm.
    """
    p = cam.mla_pitch_mm
    uv = _to_lattice(cam, np.asarray(xy_mm, dtype=np.float64))
    if cam.mla_grid == "square":
        return _from_lattice(cam, np.round(uv / p) * p)
    h = p * HEX_ROW
    j0 = np.floor(uv[..., 1] / h)
    best = None
    best_d2 = None
    for j in (j0, j0 + 1):
        shift = np.where(np.mod(j, 2) == 1, 0.5 * p, 0.0)
        cu = np.round((uv[..., 0] - shift) / p) * p + shift
        cand = np.stack([cu, j * h], axis=-1)
        d2 = np.sum((uv - cand) ** 2, axis=-1)
        if best is None:
            best, best_d2 = cand, d2
        else:
            closer = d2 < best_d2
            best = np.where(closer[..., None], cand, best)
            best_d2 = np.minimum(d2, best_d2)
    return _from_lattice(cam, best)


def lenslet_centers(cam: Camera, *, margin_mm: float = 0.0) -> np.ndarray:
    """Centres of every lenslet whose centre lies on the sensor.

    Parameters
    ----------
    cam
        The camera.
    margin_mm
        Also include lenslets whose centre lies up to this far outside the sensor edges, mm
        (0: only those on the sensor, the denominator of PPM).

    Returns
    -------
    numpy.ndarray
        (n, 2) sensor-plane coordinates in mm, rows ordered by lattice row then column.
    """
    p = cam.mla_pitch_mm
    w, h_s = cam.sensor_size_mm
    w, h_s = w + 2.0 * margin_mm, h_s + 2.0 * margin_mm
    reach = 0.5 * math.hypot(w, h_s) + math.hypot(*cam.mla_offset_um) * 1e-3 + p
    row = p * (HEX_ROW if cam.mla_grid == "hex" else 1.0)
    nj, ni = int(reach / row) + 1, int(reach / p) + 1
    j, i = np.meshgrid(np.arange(-nj, nj + 1), np.arange(-ni, ni + 1), indexing="ij")
    shift = (np.mod(j, 2) == 1) * 0.5 * p if cam.mla_grid == "hex" else 0.0
    uv = np.stack([i * p + shift, j * row], axis=-1).reshape(-1, 2)
    xy = _from_lattice(cam, uv)
    inside = (np.abs(xy[:, 0]) < 0.5 * w) & (np.abs(xy[:, 1]) < 0.5 * h_s)
    return xy[inside]


def lenslet_count(cam: Camera) -> int:
    """Number of lenslets whose centre lies on the sensor (the denominator of PPM)."""
    return int(len(lenslet_centers(cam)))


def sensor_to_pixel(cam: Camera, xy_mm: np.ndarray) -> np.ndarray:
    """Sensor-plane points (mm) to continuous (column, row) pixel coordinates, shape (..., 2)."""
    xy = np.asarray(xy_mm, dtype=np.float64)
    nc, nr = cam.sensor_px
    return np.stack([0.5 * nc - xy[..., 0] / cam.pixel_mm, 0.5 * nr + xy[..., 1] / cam.pixel_mm], axis=-1)


def pixel_to_sensor(cam: Camera, colrow: np.ndarray) -> np.ndarray:
    """Continuous (column, row) pixel coordinates to sensor-plane points in mm, shape (..., 2)."""
    cr = np.asarray(colrow, dtype=np.float64)
    nc, nr = cam.sensor_px
    return np.stack([(0.5 * nc - cr[..., 0]) * cam.pixel_mm, (cr[..., 1] - 0.5 * nr) * cam.pixel_mm], axis=-1)


def pixel_centers_sensor(cam: Camera) -> np.ndarray:
    """Sensor-plane position (mm) of every pixel centre, shape (rows, columns, 2)."""
    nc, nr = cam.sensor_px
    r, c = np.meshgrid(np.arange(nr) + 0.5, np.arange(nc) + 0.5, indexing="ij")
    return pixel_to_sensor(cam, np.stack([c, r], axis=-1))
