"""The pinhole camera model of Tomo-PIV cameras: where a world point appears, and the line of
sight of a pixel.

A :class:`lfcore.rig.PinholeCamera` is a thin lens of focal length F at magnification M < 0:
its projection centre is the lens centre C (:attr:`~lfcore.rig.PinholeCamera.lens_centre_mm`,
the object distance so = si / (-M) from the focus point along the optical axis), its image
plane the sensor, si = F (1 - M) behind the lens. In the camera frame of
:meth:`~lfcore.rig.PinholeCamera.world_to_camera` (origin at the focus point, +z toward the lens)
a point E lies d = so - E_z in front of the lens, and its normalised image coordinates are

    x = E_x / d,    y = -E_y / d

(x to the right and y down the image, as OpenCV has them: the lens inverts the image and the
sensor is read out upright, as for the light-field cameras, :mod:`lfcore.mla`). OpenCV's
Brown-Conrady distortion moves them to

    x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y,    r^2 = x^2 + y^2,

and the pixel is (column, row) = (cx + f_px x_d, cy + f_px y_d), f_px = si / pixel pitch and
(cx, cy) the principal point. Pixel coordinates are continuous: pixel ``[r, c]`` covers
``c <= column < c + 1``, ``r <= row < r + 1``. Without distortion and with the principal point at
the sensor centre this is exactly the chief ray of a light-field camera of the same pose and lens
(:func:`lfcore.chief_ray.chief_ray_mla`), so both kinds share one world frame.

A pixel's line of sight starts at C and runs along R (x, -y, -1) for the undistorted (x, y) of
the pixel (the inverse of the distortion, by Newton's method). :func:`triangulate` finds the
point nearest the lines of sight of one particle's images in several cameras.

The Warp kernels' twin of these functions is :mod:`lfcore._kernels.pinhole` (the struct
:class:`~lfcore._kernels.pinhole.PinholeParams` from :func:`lfcore._kernels.pinhole.pinhole_params`,
and the functions ``pinhole_project`` and ``pinhole_ray``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lfcore.rig import PinholeCamera

__all__ = ["distort", "line_of_sight", "normalised_coordinates", "project", "projection_matrix", "triangulate",
           "undistort"]

#: Newton steps of :func:`undistort`: from the distorted point, a few reach float64 precision for
#: any distortion a lens has (|k1| r^2 of a few per cent at the corner).
UNDISTORT_STEPS = 8


def distort(xy: np.ndarray, k: Sequence[float]) -> np.ndarray:
    """OpenCV's radial and tangential distortion of normalised image coordinates.

    Parameters
    ----------
    xy
        (..., 2) undistorted normalised coordinates (x, y): x right, y down, in units of the
        focal length.
    k
        (k1, k2, p1, p2).

    Returns
    -------
    numpy.ndarray
        (..., 2) distorted normalised coordinates.
    """
    k1, k2, p1, p2 = (float(v) for v in k)
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    return np.stack([x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                     y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y], axis=-1)


def undistort(xy_d: np.ndarray, k: Sequence[float]) -> np.ndarray:
    """Inverse of :func:`distort` (Newton's method from the distorted point).

    Parameters
    ----------
    xy_d
        (..., 2) distorted normalised coordinates.
    k
        (k1, k2, p1, p2).

    Returns
    -------
    numpy.ndarray
        (..., 2) undistorted normalised coordinates.
    """
    k1, k2, p1, p2 = (float(v) for v in k)
    target = np.asarray(xy_d, dtype=np.float64)
    xy = target.copy()
    if not any((k1, k2, p1, p2)):
        return xy
    for _ in range(UNDISTORT_STEPS):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)  # d(radial)/d(r^2) times 2: d/dx = x dradial
        f = distort(xy, k) - target
        # Jacobian of distort at (x, y), symmetric: [[a, b], [b, d]]
        a = radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (d * f[..., 0] - b * f[..., 1]) / det
            dy = (-b * f[..., 0] + a * f[..., 1]) / det
        xy = xy - np.stack([dx, dy], axis=-1)
    return xy


def normalised_coordinates(camera: PinholeCamera, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised image coordinates of world points, and their depth.

    Parameters
    ----------
    camera
        The pinhole camera.
    points_mm
        (..., 3) world points, mm, last axis (x, y, z).

    Returns
    -------
    xy : numpy.ndarray
        (..., 2) (x, y) = (E_x / d, -E_y / d); NaN for points at or behind the lens plane.
    depth : numpy.ndarray
        (...) d, mm: distance of each point in front of the lens along the optical axis.
    """
    e = camera.world_to_camera(points_mm)
    depth = camera.object_distance_mm - e[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(depth > 0, 1.0 / depth, np.nan)
    return np.stack([e[..., 0] * inv, -e[..., 1] * inv], axis=-1), depth


def project(camera: PinholeCamera, points_mm: np.ndarray) -> np.ndarray:
    """Pixel position of world points in a pinhole camera's image, distortion included.

    Parameters
    ----------
    camera
        The pinhole camera.
    points_mm
        (..., 3) world points, mm, last axis (x, y, z).

    Returns
    -------
    numpy.ndarray
        (..., 2) continuous (column, row) pixel coordinates; NaN for points at or behind the
        lens plane.
    """
    xy, _ = normalised_coordinates(camera, points_mm)
    xy_d = distort(xy, camera.distortion)
    return np.asarray(camera.principal_point) + camera.focal_length_px * xy_d


def line_of_sight(camera: PinholeCamera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world line of sight of pixel positions: the ray from the lens centre that images there.

    Parameters
    ----------
    camera
        The pinhole camera.
    pixels
        (..., 2) continuous (column, row) pixel coordinates (a pixel's centre is
        ``(c + 0.5, r + 0.5)``).

    Returns
    -------
    origin : numpy.ndarray
        (..., 3) world position of the lens centre, mm (the same for every pixel).
    direction : numpy.ndarray
        (..., 3) unit world direction from the lens into the scene.
    """
    px = np.asarray(pixels, dtype=np.float64)
    xy_d = (px - np.asarray(camera.principal_point)) / camera.focal_length_px
    xy = undistort(xy_d, camera.distortion)
    d_cam = np.stack([xy[..., 0], -xy[..., 1], -np.ones(xy.shape[:-1])], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    direction = d_cam @ camera.rotation.T
    origin = np.broadcast_to(camera.lens_centre_mm, direction.shape).copy()
    return origin, direction


def projection_matrix(camera: PinholeCamera) -> np.ndarray:
    """The 3 x 4 camera matrix of the undistorted projection: [column, row, 1] ~ P [X, Y, Z, 1].

    Returns
    -------
    numpy.ndarray
        (3, 4) float64 P = K [R_cv | -R_cv C], with K the intrinsic matrix (f_px, principal
        point), R_cv = diag(1, -1, -1) R^T the world-to-OpenCV-camera rotation and C the lens
        centre (mm). Distortion is not included.
    """
    cx, cy = camera.principal_point
    f = camera.focal_length_px
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    r_cv = np.diag([1.0, -1.0, -1.0]) @ camera.rotation.T
    return k @ np.concatenate([r_cv, -(r_cv @ camera.lens_centre_mm)[:, None]], axis=1)


def triangulate(cameras: Sequence[PinholeCamera], pixels: np.ndarray) -> np.ndarray:
    """The world points nearest (least squares) to the lines of sight of their images.

    Parameters
    ----------
    cameras
        The pinhole cameras, one per row of ``pixels``.
    pixels
        (cameras, n, 2) continuous (column, row) image of each of n points in each camera; NaN
        where a camera did not see a point (it is left out of that point's fit).

    Returns
    -------
    numpy.ndarray
        (n, 3) world points, mm; NaN for points seen by fewer than two cameras.
    """
    px = np.asarray(pixels, dtype=np.float64)
    if px.ndim != 3 or px.shape[0] != len(cameras) or px.shape[2] != 2:
        raise ValueError(f"pixels must be (cameras={len(cameras)}, n, 2), got shape {px.shape}")
    n = px.shape[1]
    a = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    seen = np.zeros(n, dtype=np.int64)
    for cam, p in zip(cameras, px, strict=True):
        ok = np.all(np.isfinite(p), axis=-1)
        o, d = line_of_sight(cam, np.where(ok[:, None], p, 0.0))
        # the distance of X from a line (o, d) is |(I - d d^T)(X - o)|: normal equations
        proj = np.eye(3) - d[:, :, None] * d[:, None, :]
        proj *= ok[:, None, None]
        a += proj
        b += np.einsum("nij,nj->ni", proj, o)
        seen += ok
    out = np.full((n, 3), np.nan)
    good = seen >= 2
    if good.any():
        out[good] = np.linalg.solve(a[good], b[good][..., None])[..., 0]
    return out
