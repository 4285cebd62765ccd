"""Where a world point appears in a light-field camera's raw image: the chief-ray projection.

Same thin-lens optics as the renderer (:mod:`lfcore._kernels.render`). In the camera frame
(:meth:`lfcore.rig.Camera.world_to_camera`) a point E sends its chief ray through the centre of
the main lens (z = so) with transverse slope s = -E_xy / (so - E_z); the thin lens does not bend
it. It meets the MLA at q = si s, the centre of the point's (possibly defocused) image there:
the blur disc of a point is the aperture scaled about that chief ray, so q is also the centroid
of all its light on the MLA. Behind the MLA the central sub-aperture ray of the lenslet at q
lands f_ml further on, at (si + f_ml) s = k q with k = 1 + f_ml / si, which is exactly where the
white image puts that lenslet's micro-image centre (:mod:`lfcore.white`). So ``project`` gives,
in raw pixel coordinates, the point's position in the central perspective view, equivalently
the centroid of its light over the lenslets with each lenslet placed at its micro-image centre.
It does not depend on the MLA's offset or rotation: they decide which lenslets sample the image,
not where the image is. A ray through another aperture point A reaches the MLA at
q_A = A + si s_out, s_out = (A - E_xy) / (so - E_z) - A / F: away from the focal plane the views
through different parts of the aperture disagree (parallax), which tells the depth of the focal
plane, hence the magnification, that the central view alone leaves almost free for a narrow
field of view.

An optional radial distortion scales the sensor-plane position by 1 + k1 (r / r0)^2, with r0
half the sensor diagonal (so k1 is the fractional displacement at the corner). The renderer has
no distortion; real lenses have a little.

Pixel coordinates are continuous (column, row) as in :mod:`lfcore.mla`:
column = Nc/2 - x / pixel, row = Nr/2 + y / pixel.
"""

from __future__ import annotations

import math

import numpy as np

from lfcore.mla import sensor_to_pixel
from lfcore.rig import Camera

__all__ = ["chief_ray_mla", "defocus_radius_mm", "diffraction_sigma_mm", "image_scale", "project",
           "sensor_radius_mm"]


def sensor_radius_mm(camera: Camera) -> float:
    """r0: half the sensor diagonal, mm (the normalising radius of the distortion)."""
    return 0.5 * math.hypot(*camera.sensor_size_mm)


def _inverse_depth(camera: Camera, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (..., 3) and 1 / d, d their distance in front of the lens along the
    axis (NaN at or behind the lens plane)."""
    e = camera.world_to_camera(points_mm)
    depth = camera.object_distance_mm - e[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return e, np.where(depth > 0, 1.0 / depth, np.nan)


def chief_ray_mla(camera: Camera, points_mm: np.ndarray) -> np.ndarray:
    """Where each point's chief ray meets the MLA plane, in sensor-plane coordinates.

    Parameters
    ----------
    camera
        The camera (pose, main lens and magnification).
    points_mm
        (..., 3) world points, mm, last axis (x, y, z).

    Returns
    -------
    numpy.ndarray
        (..., 2) sensor-plane (x, y), mm; NaN for points at or behind the lens plane.
    """
    e, inv = _inverse_depth(camera, points_mm)
    return -camera.image_distance_mm * e[..., :2] * inv[..., None]


def diffraction_sigma_mm(wavelength_nm: float, f_number: float) -> float:
    """Sigma (mm) of the Gaussian that stands in for the Airy core of a lens working at
    ``f_number``: 0.42 lambda N."""
    return 0.42 * wavelength_nm * 1e-6 * f_number


def defocus_radius_mm(camera: Camera, points_mm: np.ndarray) -> np.ndarray:
    """Radius of each point's blur disc on the MLA (the aperture's cone cut by the MLA plane), mm.

    A point at distance d in front of the main lens images at si' with 1 / si' = 1 / F - 1 / d;
    its cone of light, of diameter D at the lens, has at the MLA the radius
    (D / 2) |si / si' - 1| = (D / 2) si |1 / so - 1 / d|: zero on the focal plane.

    Parameters
    ----------
    camera
        The camera.
    points_mm
        (..., 3) world points, mm.

    Returns
    -------
    numpy.ndarray
        (...) blur radius on the MLA, mm; NaN for points at or behind the lens plane.
    """
    _, inv = _inverse_depth(camera, points_mm)
    return 0.5 * camera.aperture_mm * camera.image_distance_mm * np.abs(1.0 / camera.object_distance_mm - inv)


def image_scale(camera: Camera, points_mm: np.ndarray) -> np.ndarray:
    """Local transverse scale si / d of the main lens' image on the MLA at each point's depth.

    A small object (a dot of radius r) at distance d in front of the lens spans about
    r si / d on the MLA (|M| on the focal plane), before its defocus blur.

    Returns
    -------
    numpy.ndarray
        (...) scale, dimensionless; NaN at or behind the lens plane.
    """
    return camera.image_distance_mm * _inverse_depth(camera, points_mm)[1]


def project(camera: Camera, points_mm: np.ndarray, *, radial_k1: float = 0.0,
            pupil_mm: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Raw-image position of world points in the central (or another) perspective view of ``camera``.

    Parameters
    ----------
    camera
        The camera.
    points_mm
        (..., 3) world points, mm.
    radial_k1
        Radial distortion: fractional displacement at the sensor corner (0: none, as rendered).
    pupil_mm
        Point A of the main-lens aperture (camera-frame x, y, mm) the ray passes: (0, 0) is the
        chief ray; a sub-aperture view, or the light-weighted mean of a part of the aperture
        (the ray position is linear in A), sees the point displaced in proportion to its defocus.

    Returns
    -------
    numpy.ndarray
        (..., 2) continuous (column, row) pixel coordinates; NaN behind the lens.
    """
    k = 1.0 + camera.mla_focal_length_mm / camera.image_distance_mm
    a = np.asarray(pupil_mm, dtype=np.float64)
    if not a.any():
        xy = k * chief_ray_mla(camera, points_mm)
    else:
        # Ray E -> A: slope in (A - E_xy) / (so - E_z), bent by the thin lens by -A / F, reaching
        # the MLA at q = A + si s_out (as the renderer traces it).
        e = camera.world_to_camera(points_mm)
        depth = camera.object_distance_mm - e[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s_out = (a - e[..., :2]) / np.where(depth > 0, depth, np.nan)[..., None] - a / camera.main_focal_length_mm
        xy = k * (a + camera.image_distance_mm * s_out)
    if radial_k1 != 0.0:
        r2 = np.sum(xy**2, axis=-1, keepdims=True) / sensor_radius_mm(camera) ** 2
        xy = xy * (1.0 + radial_k1 * r2)
    return sensor_to_pixel(camera, xy)
