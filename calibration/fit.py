"""Fitting a camera model to the calibration target: least squares on reprojection error.

Observations, per camera:

- the dots of every plane, named on the board (:mod:`calibration.dots`), whose world positions
  the board and the stage readback give (:class:`lfcore.target.DotBoard`; they define the world
  frame, so every camera fitted against them shares it);
- the micro-image centres of the white image (:class:`calibration.mla_grid.MlaGrid`).

Model: :class:`lfcore.rig.Camera`, the optics the renderer and the reconstruction use.
Parameters: the pose (a small rotation vector applied to the nominal rotation in the camera
frame, which has no gimbal lock however the camera points, and the focus point), the
magnification (the main-lens focal length stays nominal: with it, M fixes si and so, so the
perspective of the planes at different depths checks the scale), the MLA offset and rotation,
and optionally a radial distortion k1 (:func:`lfcore.chief_ray.project`).

Residuals, in pixels: found minus projected dot centroids (:func:`lfcore.chief_ray.project`,
independent of the MLA) in the chief-ray view and the four half-aperture views (their parallax
fixes the depth of the focal plane, so the magnification; each view's mean aperture point and
displacement are those :func:`calibration.dots.view_geometry` finds for the optics, since light
crosses between touching micro-images), and measured micro-image centres minus the model's nearest
micro-image centre (k times the nearest lenslet centre, :mod:`lfcore.white`), which fix the
MLA's offset and rotation. The two blocks share only the micro-image scale k = 1 + f_ml / si.
Dots further than 5 robust sigmas from the first fit (misnamed or merged) are dropped and the
fit repeated.

Dots whose centroid is biased (:func:`clear_dots`: in sharp focus, the hard edge of a dot a
couple of lenslets across is sampled by too few lenslets; far from focus, the blur discs of
neighbours at other depths on the tilted board overlap) are weighted down, or left out where
they overlap deeply: trusted equally, they pulled a fit started at the true camera 0.4 degree
away from it. The reported RMS is over the clear dots.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import PrivateAttr
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.dots import ViewGeometry, view_geometry
from calibration.mla_grid import MlaGrid
from lfcore.chief_ray import chief_ray_mla, defocus_radius_mm, image_scale, project
from lfcore.mla import nearest_lenslet, pixel_to_sensor, sensor_to_pixel
from lfcore.rig import AnyCamera, Camera, PinholeCamera, camera_from_dict
from lfcore.soloff import SoloffMap
from lfcore.target import DotBoard

__all__ = ["CameraFit", "FitError", "PlaneDots", "clear_dots", "fit_camera", "planes_with_dots",
           "rotation_deg_from_matrix"]


class FitError(ValueError):
    """A camera whose model cannot be fitted; one line naming it and saying why."""


@dataclass(frozen=True)
class PlaneDots:
    """The named dots of one plane of one camera.

    Attributes
    ----------
    plane
        Plane index in the store.
    stage_mm
        Stage readback of the plane, mm.
    indices
        (m, 2) int64 board indices (i, j).
    views_px
        (m, views, 2) found centroids (column, row), pixels, in the views of
        :data:`calibration.dots.VIEW_PUPILS`.
    """

    plane: int
    stage_mm: float
    indices: np.ndarray
    views_px: np.ndarray


@dataclass(frozen=True)
class CameraFit:
    """One camera's fitted model and how well it reprojects.

    Attributes
    ----------
    camera
        The fitted model.
    radial_k1
        Fitted radial distortion (0 unless fitted; not part of :class:`Camera`; a pinhole
        camera's k1, which is part of it).
    rms_px
        RMS distance between found and projected dots (chief-ray view) over all planes, pixels,
        of the clear dots (all used dots if fewer than 3 are clear).
    plane_rms_px
        (planes,) the same per plane; NaN for planes without dots.
    plane_dots
        (planes,) int, dots used per plane.
    lattice_rms_px
        RMS distance of the white image's micro-image centres from the model's, pixels (NaN
        without a grid).
    std
        1-sigma uncertainty of each parameter from the fit's covariance.
    residuals_px
        Per plane, (m, 2) found minus projected, pixels.
    dropped
        Dots rejected as outliers.
    set_aside
        Named dots left out because their centroid is biased by the sampling (in sharp focus)
        or by a neighbour's blur disc (see :func:`clear_dots`).
    """

    camera: Camera
    radial_k1: float
    rms_px: float
    plane_rms_px: np.ndarray
    plane_dots: np.ndarray
    lattice_rms_px: float
    std: dict[str, float]
    residuals_px: list[np.ndarray] = field(repr=False)
    dropped: int = 0
    set_aside: int = 0
    #: pinhole cameras: the third-order Soloff polynomial fitted to the same dots, its RMS over them
    #: and per plane (NaN without dots), pixels
    soloff: SoloffMap | None = None
    soloff_rms_px: float = math.nan
    soloff_plane_rms_px: np.ndarray | None = None

    def model_dict(self) -> dict[str, Any]:
        """The fitted camera as a rig-file ``[[camera]]`` table (JSON-compatible; keys without a
        value, such as an unset serial, are left out, as TOML has no null)."""
        return self.camera.model_dump(mode="json", exclude_none=True)


class _MatrixPose:
    """What :class:`_PosedCamera` and its pinhole twin share: the rotation is a given matrix."""

    _matrix: np.ndarray

    @classmethod
    def posed(cls, camera: AnyCamera, r: np.ndarray) -> Any:
        out = cls.model_construct(**dict(camera))  # its fields are a validated camera's
        out._matrix = np.array(r, dtype=np.float64)
        return out

    @property
    def rotation(self) -> np.ndarray:
        return self._matrix.copy()

    def plain(self) -> AnyCamera:
        """The camera as stored (rotation from its Euler angles)."""
        return camera_from_dict(dict(self))


class _PosedCamera(_MatrixPose, Camera):
    """A camera whose rotation is a given matrix rather than the matrix of its Euler angles.

    Near ry = +-90 degrees (a second camera at 90 degrees) a turn smaller than about 1e-6 rad
    does not survive the round trip through the angles of R = Rz Ry Rx
    (:func:`rotation_deg_from_matrix`): at ry = 90 exactly it comes back reversed, or about
    another axis. The fit's finite-difference steps (about 1.5e-8 rad) are such turns, so the
    Jacobian of the pose was wrong there and the solver could stay at the rig file's pose (it
    did, for cam1 of the 29 MP example over 51 planes). The residuals therefore project through
    the exact matrix; ``rotation_deg`` is only what gets stored.
    """

    _matrix: np.ndarray = PrivateAttr(default=None)


class _PosedPinhole(_MatrixPose, PinholeCamera):
    """A pinhole camera posed by its exact rotation matrix (see :class:`_PosedCamera`)."""

    _matrix: np.ndarray = PrivateAttr(default=None)


def rotation_deg_from_matrix(r: np.ndarray) -> tuple[float, float, float]:
    """``[rx, ry, rz]`` (degrees) with R = Rz(rz) Ry(ry) Rx(rx) equal to the (3, 3) matrix ``r``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # near ry = +-90 degrees one angle is arbitrary; R is kept
        z, y, x = Rotation.from_matrix(r).as_euler("ZYX", degrees=True)
    return (float(x), float(y), float(z))


_NAMES = ("rot_x_rad", "rot_y_rad", "rot_z_rad", "focus_x_mm", "focus_y_mm", "focus_z_mm", "magnification",
          "mla_offset_x_um", "mla_offset_y_um", "mla_rotation_deg", "radial_k1")


def _lattice_sample(grid: MlaGrid, n_max: int) -> np.ndarray:
    pts = grid.centres_px[grid.inliers]
    if len(pts) > n_max:
        pts = pts[np.linspace(0, len(pts) - 1, n_max).astype(int)]
    return pts


#: The eight board neighbours (di, dj) of a dot.
_NEIGHBOURS = np.array([[a, b] for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b], dtype=np.int64)


def _dot_extent(camera: Camera, board: DotBoard, indices: np.ndarray, stage_mm: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chief-ray position on the MLA (m, 2), blur radius (m,) and outer radius (m,) of each dot's image, mm."""
    w = board.dot_centres(indices, stage_mm)
    blur = defocus_radius_mm(camera, w)
    radius = board.radius_mm * np.where(np.all(indices == 0, axis=1), board.marker_scale, 1.0)
    return chief_ray_mla(camera, w), blur, blur + radius * image_scale(camera, w)


def clear_dots(camera: Camera, board: DotBoard, indices: np.ndarray, stage_mm: float, *,
               min_blur_lenslets: float = 0.75, min_gap_lenslets: float = 0.25) -> np.ndarray:
    """Which dots of a plane ``camera`` images so that their lenslet-sum centroid is unbiased.

    The centroid of a dot (:func:`calibration.dots.detect_dots`) places each lenslet's light at
    its micro-image centre. It is biased where that sampling or the segmentation is:

    - in sharp focus the image is a disc with a hard edge, a couple of lenslets across: the
      lenslets cut by its edge move the centroid toward their centres, by up to a few hundredths
      of a lenslet (tenths of a pixel), whatever the noise; a blur of about a lenslet smooths
      the edge over a lenslet and the sampling error averages out;
    - far from focus the blur discs of neighbouring dots (the board's tilt puts them at other
      depths) overlap: the lenslets they share go to one of them, pulling both apart, by up to
      several pixels.

    Parameters
    ----------
    camera
        The camera model (the current estimate).
    board
        The target.
    indices
        (m, 2) board indices of the dots.
    stage_mm
        Stage readback of the plane.
    min_blur_lenslets
        Smallest blur-disc diameter accepted, in lenslet pitches.
    min_gap_lenslets
        Smallest gap between the dot's image (dot plus blur) and each of its eight neighbours'
        on the MLA, in lenslet pitches.

    Returns
    -------
    numpy.ndarray
        (m,) bool, True for dots whose centroid can be trusted.
    """
    ij = np.asarray(indices, dtype=np.int64).reshape(-1, 2)
    pitch = camera.mla_pitch_um * 1e-3
    q, blur, outer = _dot_extent(camera, board, ij, stage_mm)
    gap = np.full(len(ij), np.inf)
    for d in _NEIGHBOURS:
        qn, _, outer_n = _dot_extent(camera, board, ij + d, stage_mm)
        gap = np.minimum(gap, np.hypot(*(q - qn).T) - outer - outer_n)
    with np.errstate(invalid="ignore"):
        return (2.0 * blur >= min_blur_lenslets * pitch) & (gap >= min_gap_lenslets * pitch)


def planes_with_dots(camera: str, board: DotBoard, planes: Sequence[PlaneDots], n_planes: int | None
                     ) -> tuple[list[PlaneDots], int, list[np.ndarray]]:
    """The planes that have dots, the number of planes (default: highest plane + 1) and each plane's
    (m, 3) world dot centres, mm.

    Raises
    ------
    FitError
        Fewer than 8 dots on 2 planes, too few to fit a pose and a magnification.
    """
    planes = [p for p in planes if len(p.indices)]
    total = sum(len(p.indices) for p in planes)
    if total < 8 or len(planes) < 2:
        raise FitError(f"camera '{camera}': {total} dot(s) on {len(planes)} plane(s); need at least 8 "
                       "dots on 2 planes at different depths to fit the pose and magnification")
    n_planes = max(p.plane for p in planes) + 1 if n_planes is None else n_planes
    return planes, n_planes, [board.dot_centres(p.indices, p.stage_mm) for p in planes]


def fit_camera(nominal: Camera, board: DotBoard, planes: Sequence[PlaneDots], grid: MlaGrid | None = None, *,
               n_planes: int | None = None, fit_distortion: bool = False, max_lattice_points: int = 600,
               outlier_sigma: float = 5.0, min_blur_lenslets: float = 0.75, min_gap_lenslets: float = 0.25,
               max_overlap_lenslets: float = -0.5, biased_weight: float = 0.2, wavelength_nm: float = 532.0,
               views: ViewGeometry | None = None) -> CameraFit:
    """Fit one camera's model to its named dots (and its white-image lattice).

    Parameters
    ----------
    nominal
        The starting model (the rig file's camera); the main-lens focal length, pitches and
        sensor are kept.
    board
        The target (its positions define the world frame).
    planes
        The named dots of each plane.
    grid
        The white image's microlens grid: fits the MLA offset and rotation (seeded from
        :meth:`MlaGrid.to_mla`); None keeps them nominal.
    n_planes
        Number of planes in the store (for the per-plane arrays; default: highest plane + 1).
    fit_distortion
        Also fit the radial distortion k1.
    max_lattice_points
        Micro-image centres used (evenly spread over the sensor).
    outlier_sigma
        Dots further than this many robust sigmas from the first fit are dropped.
    min_blur_lenslets, min_gap_lenslets
        Dots in sharper focus, or closer to a neighbour's image, have biased centroids
        (:func:`clear_dots`, judged with the current model: the nominal one, then the fitted
        one); their residuals are weighted by ``biased_weight``.
    max_overlap_lenslets
        Dots whose image reaches further into a neighbour's (a negative gap, in lenslet pitches)
        are left out, unless fewer than 8 dots on 2 planes would remain.
    biased_weight
        Weight of a biased dot's residuals (1: as a clear dot's).
    wavelength_nm
        Wavelength of the target's light (the lenslets' diffraction blur moves light between
        neighbouring micro-images, see :func:`calibration.dots.view_geometry`).
    views
        ``view_geometry(nominal, wavelength_nm)`` computed already (a Monte Carlo of about a
        second; a caller fitting one camera twice passes it); None computes it.

    Raises
    ------
    FitError
        Too few dots for the parameters, or a fit that does not converge.
    """
    planes, n_planes, world = planes_with_dots(nominal.name, board, planes, n_planes)
    found = [np.asarray(p.views_px, dtype=np.float64) for p in planes]  # (m, views, 2) each
    if views is None:
        views = view_geometry(nominal, wavelength_nm)  # what each view sees, for the nominal optics
    r0 = nominal.rotation
    f0 = np.asarray(nominal.focus_mm)
    mla0 = grid.to_mla(nominal) if grid is not None else {"mla_offset_um": nominal.mla_offset_um,
                                                          "mla_rotation_deg": nominal.mla_rotation_deg}
    lattice = _lattice_sample(grid, max_lattice_points) if grid is not None else np.zeros((0, 2))
    x0 = np.array([0.0, 0.0, 0.0, *f0, nominal.magnification, *mla0["mla_offset_um"], mla0["mla_rotation_deg"],
                   0.0])
    free = np.ones(len(x0), dtype=bool)
    free[10] = fit_distortion
    if grid is None:
        free[7:10] = False

    def camera_of(x: np.ndarray) -> Camera:
        """The camera of parameters ``x``, posed by the exact rotation matrix (what the
        residuals see; see :class:`_PosedCamera`)."""
        r = r0 @ Rotation.from_rotvec(x[:3]).as_matrix()
        cam = nominal.model_copy(update={"rotation_deg": rotation_deg_from_matrix(r), "focus_mm": tuple(x[3:6]),
                                         "magnification": float(x[6]), "mla_offset_um": (float(x[7]), float(x[8])),
                                         "mla_rotation_deg": float(x[9])})
        return _PosedCamera.posed(cam, r)

    def dot_residuals(x: np.ndarray, keep: list[np.ndarray]) -> list[np.ndarray]:
        """Per plane (m, views, 2) found minus projected, pixels."""
        cam = camera_of(x)
        out = []
        for f, w, k in zip(found, world, keep, strict=True):
            proj = np.stack([project(cam, w, radial_k1=x[10], pupil_mm=tuple(a)) for a in views.pupils_mm], axis=1)
            out.append((f - proj - views.offsets_px)[k])
        return out

    def lattice_residuals(x: np.ndarray) -> np.ndarray:
        if not len(lattice):
            return np.zeros((0, 2))
        cam = camera_of(x)
        k = 1.0 + cam.mla_focal_length_mm / cam.image_distance_mm
        c = nearest_lenslet(cam, pixel_to_sensor(cam, lattice) / k)
        return lattice - sensor_to_pixel(cam, k * c)

    def solve(x_start: np.ndarray, weights: list[np.ndarray]) -> object:
        keep = [w > 0 for w in weights]

        def fun(xf: np.ndarray) -> np.ndarray:
            x = x_start.copy()
            x[free] = xf
            parts = [(r * w[k][:, None, None]).ravel()
                     for r, w, k in zip(dot_residuals(x, keep), weights, keep, strict=True)]
            out = np.concatenate([*parts, lattice_residuals(x).ravel()])
            return np.where(np.isfinite(out), out, 1e3)

        return least_squares(fun, x_start[free], x_scale="jac", method="trf", xtol=1e-12, ftol=1e-12,
                             gtol=1e-12, max_nfev=200 * int(free.sum()))

    def weights_of(x: np.ndarray) -> list[np.ndarray]:
        """Per plane (m,) weight of each dot: 1 clear, ``biased_weight`` in sharp focus or near a
        neighbour's image, 0 deep in a neighbour's (all of them kept if fewer than 8 remain)."""
        cam = camera_of(x)
        out = []
        for p in planes:
            clear = clear_dots(cam, board, p.indices, p.stage_mm, min_blur_lenslets=min_blur_lenslets,
                               min_gap_lenslets=min_gap_lenslets)
            out.append(np.where(clear, 1.0, biased_weight))
        crowded = [~clear_dots(camera_of(x), board, p.indices, p.stage_mm, min_blur_lenslets=0.0,
                               min_gap_lenslets=max_overlap_lenslets) for p in planes]
        cut = [np.where(c, 0.0, w) for w, c in zip(out, crowded, strict=True)]
        if sum(int((w > 0).sum()) for w in cut) >= 8 and sum(1 for w in cut if (w > 0).any()) >= 2:
            out = cut
        return out

    x = x0.copy()
    weights = weights_of(x)
    sol = solve(x, weights)
    x[free] = sol.x
    weights = weights_of(x)
    res = dot_residuals(x, [np.ones(len(f), dtype=bool) for f in found])
    trusted = [w == 1.0 for w in weights]
    if sum(int(t.sum()) for t in trusted) < 3:
        trusted = [w > 0 for w in weights]
    # A dot's worst view against the same statistic of the trusted dots: the views of a
    # defocused dot scatter more than its chief ray, and in-focus dots (weighted down, and on a
    # camera looking across the board the most numerous) scatter least, so their chief rays
    # set no scale for the clear dots (they made cam1 of the 29 MP example drop 713 of its
    # 714 clear dots once its pose was fitted).
    worst = [np.hypot(r[:, :, 0], r[:, :, 1]).max(axis=1) for r in res]
    scale_of = trusted if sum(int(t.sum()) for t in trusted) >= 8 else [w > 0 for w in weights]
    d = np.concatenate([m[t] for m, t in zip(worst, scale_of, strict=True)])
    sigma = max(float(np.median(d)) / 1.1774, 1e-6)  # misnamed or merged dots are far beyond
    outlier = [m > outlier_sigma * sigma for m in worst]
    dropped = int(sum((o & (w > 0)).sum() for o, w in zip(outlier, weights, strict=True)))
    weights = [np.where(o, 0.0, w) for o, w in zip(outlier, weights, strict=True)]
    trusted = [t & ~o for t, o in zip(trusted, outlier, strict=True)]
    set_aside = int(sum((w < 1.0).sum() for w in weights)) - dropped
    sol = solve(x, weights)
    x[free] = sol.x
    if not sol.success:
        raise FitError(f"camera '{nominal.name}': the fit did not converge ({sol.message})")
    res = dot_residuals(x, trusted)
    cam = camera_of(x).plain()
    res = [r[:, 0] for r in res]  # reported: the chief-ray view (all the light) of the trusted dots
    allres = np.concatenate(res)
    rms = float(np.sqrt(np.mean(np.sum(allres**2, axis=1))))
    plane_rms = np.full(n_planes, np.nan)
    plane_n = np.zeros(n_planes, dtype=np.int64)
    for p, r in zip(planes, res, strict=True):
        plane_n[p.plane] = len(r)
        if len(r):
            plane_rms[p.plane] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    lat = lattice_residuals(x)
    lat_rms = float(np.sqrt(np.mean(np.sum(lat**2, axis=1)))) if len(lat) else math.nan
    std: dict[str, float] = {}
    try:
        jac = sol.jac
        dof = max(1, len(sol.fun) - jac.shape[1])
        s2 = float(np.sum(sol.fun**2)) / dof
        cov = np.linalg.pinv(jac.T @ jac) * s2
        for name, v in zip(np.asarray(_NAMES)[free], np.sqrt(np.maximum(np.diag(cov), 0.0)), strict=True):
            std[str(name)] = float(v)
    except (ValueError, np.linalg.LinAlgError):
        pass
    return CameraFit(camera=cam, radial_k1=float(x[10]), rms_px=rms, plane_rms_px=plane_rms, plane_dots=plane_n,
                     lattice_rms_px=lat_rms, std=std, residuals_px=res, dropped=dropped, set_aside=set_aside)
