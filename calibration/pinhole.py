"""Calibrating a pinhole (Tomo-PIV) camera on the dot target: blobs, the pinhole fit, Soloff.

The same target and planes as the light-field cameras' volumetric calibration
(:mod:`calibration.planes`), but a pinhole camera's image of a dot is an ordinary blob: it is
found by thresholding above the background, and centred on its light (:func:`detect_blobs`).
Named on the board as the light-field dots are (:func:`calibration.dots.match_dots`), the dots
fit two mappings (:func:`fit_pinhole`):

- the pinhole model with lens distortion (:class:`lfcore.rig.PinholeCamera`,
  :mod:`lfcore.pinhole`) by least squares on the reprojection error, as Tsai's and Zhang's
  calibrations do: the pose (a small rotation vector applied to the starting rotation, and the
  focus point), the magnification (the focal length stays the rig file's: with it, M fixes the
  image and object distances, and the perspective of planes at different depths checks the
  scale), the principal point and OpenCV's k1, k2, p1, p2. Over a narrow field of view the
  principal point trades against the rotation, the magnification against the distance (the
  focus point slides along the optical axis: only the perspective of the planes' depths tells
  them apart) and the distortion hardly shows, so each of these is held to its starting value by
  a weak prior (one pixel of residual per
  :data:`PRIOR_SIGMA` of change): where the dots determine them the prior does not matter,
  where they do not it keeps them from wandering;
- the third-order Soloff polynomial that DaVis users know (:class:`lfcore.soloff.SoloffMap`),
  by linear least squares on the same dots.

Dots further than 5 robust sigmas from the first pinhole fit (misnamed or merged) are dropped
and both fits repeated without them. Pure: images, stage positions and the board in; the fits
out. :func:`refine_pinhole` is the pinhole least squares alone, on any world points and the pixels
they should map to (the volume self-calibration, :mod:`calibration.selfcal`, refits with it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.optimize import OptimizeResult, least_squares
from scipy.spatial.transform import Rotation

from calibration.dots import Dots, background_level
from calibration.fit import CameraFit, FitError, PlaneDots, _PosedPinhole, planes_with_dots, rotation_deg_from_matrix
from lfcore import pinhole
from lfcore.rig import PinholeCamera
from lfcore.soloff import SoloffMap
from lfcore.target import DotBoard

__all__ = ["PRIOR_SIGMA", "detect_blobs", "fit_pinhole", "refine_pinhole"]

#: The change of each weakly held parameter that costs as much as one pixel of reprojection
#: error: the magnification (a fraction of it), the principal point (a fraction of the sensor's
#: larger side) and k1, k2, p1, p2.
PRIOR_SIGMA = {"magnification": 0.02, "principal_point": 0.05, "k1": 0.5, "k2": 5.0, "p1": 0.005, "p2": 0.005}

_NAMES = ("rot_x_rad", "rot_y_rad", "rot_z_rad", "focus_x_mm", "focus_y_mm", "focus_z_mm", "magnification",
          "principal_point_x_px", "principal_point_y_px", "k1", "k2", "p1", "p2")


def detect_blobs(frame: np.ndarray, *, threshold_sigma: float = 8.0, min_pixels: int = 3, rim_px: float = 2.0
                 ) -> Dots:
    """Every whole dot (a bright blob) in a pinhole camera's image, and its centroid.

    Pixels brighter than the background (the frame's median) by ``threshold_sigma`` noise
    sigmas, in groups of touching pixels (8-connected), are dots; a group that touches the
    image's edge is cut and left out. Each dot is centred on its background-subtracted light
    over its pixels and those within ``rim_px`` of them (nearer to it than to any other dot),
    which holds the faint rim below the threshold too.

    Parameters
    ----------
    frame
        (rows, columns) image of the dot target, counts.
    threshold_sigma
        A pixel is lit above this many noise sigmas (1.4826 times the median absolute deviation
        of the pixels at or below the median).
    min_pixels
        Smallest group of lit pixels accepted as a dot.
    rim_px
        How far beyond its lit pixels a dot's light is summed, pixels.

    Returns
    -------
    calibration.dots.Dots
        Centroids in continuous (column, row) pixel coordinates (one view: ``views_px`` is
        (m, 1, 2)), each dot's light (counts) and its lit pixels.
    """
    img = np.asarray(frame)
    bg, sigma = background_level(img)
    signal = img.astype(np.float64) - bg
    lit = signal > threshold_sigma * max(sigma, 1e-3)
    labels, n = ndimage.label(lit, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return Dots(np.zeros((0, 1, 2)), np.zeros(0), np.zeros(0, dtype=np.int64))
    index = np.arange(1, n + 1)
    size = ndimage.sum_labels(lit, labels, index).astype(np.int64)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    # each pixel near a dot goes to the nearest dot's lit pixel
    dist, (ri, ci) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    grown = np.where(dist <= rim_px, labels[ri, ci], 0)
    w = np.clip(signal, 0.0, None)
    flux = ndimage.sum_labels(w, grown, index)
    rows, cols = np.indices(img.shape, dtype=np.float64) + 0.5  # pixel centres
    cx = ndimage.sum_labels(w * cols, grown, index)
    cy = ndimage.sum_labels(w * rows, grown, index)
    good = (size >= min_pixels) & ~np.isin(index, edge) & (flux > 0)
    centres = np.stack([cx[good] / flux[good], cy[good] / flux[good]], axis=-1)
    return Dots(centres[:, None, :], flux[good], size[good])


def _camera_of(start: PinholeCamera, x: np.ndarray) -> _PosedPinhole:
    """The camera of parameters ``x`` (see ``_NAMES``), posed by its exact rotation matrix."""
    r = start.rotation @ Rotation.from_rotvec(x[:3]).as_matrix()
    v = [float(t) for t in x]
    cam = start.model_copy(update={"rotation_deg": rotation_deg_from_matrix(r), "focus_mm": tuple(v[3:6]),
                                   "magnification": v[6], "principal_point_px": (v[7], v[8]), "k1": v[9], "k2": v[10],
                                   "p1": v[11], "p2": v[12]})
    return _PosedPinhole.posed(cam, r)


def refine_pinhole(start: PinholeCamera, points_mm: np.ndarray, pixels: np.ndarray, *, fit_distortion: bool = True
                   ) -> tuple[PinholeCamera, OptimizeResult]:
    """The pinhole model (pose, magnification, principal point, distortion) that maps world points
    onto their pixel positions best, by least squares from ``start``.

    Parameters
    ----------
    start
        The starting model; its focal length, pixel pitch and sensor are kept, and its
        magnification, principal point and distortion are the priors' centres (see
        :data:`PRIOR_SIGMA`).
    points_mm
        (n, 3) world points, mm.
    pixels
        (n, 2) continuous (column, row) pixel positions they should map to.
    fit_distortion
        Also fit k1, k2, p1, p2 (else they stay ``start``'s).

    Returns
    -------
    camera : PinholeCamera
        The fitted model (posed by its exact rotation matrix; ``.plain()`` is the stored form).
    result : scipy.optimize.OptimizeResult
        The solver's result (``fun`` holds the residuals, pixels, then the priors').
    """
    w = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    x0 = np.array([0.0, 0.0, 0.0, *start.focus_mm, start.magnification, *start.principal_point_px,
                   *start.distortion])
    free = np.ones(len(x0), dtype=bool)
    free[9:] = fit_distortion
    scale = PRIOR_SIGMA["principal_point"] * max(start.sensor_px)
    sigma = np.array([PRIOR_SIGMA["magnification"] * abs(start.magnification), scale, scale, PRIOR_SIGMA["k1"],
                      PRIOR_SIGMA["k2"], PRIOR_SIGMA["p1"], PRIOR_SIGMA["p2"]])

    def fun(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        r = (pinhole.project(_camera_of(start, x), w) - px).ravel()
        prior = (x[6:] - x0[6:]) / sigma
        return np.concatenate([np.where(np.isfinite(r), r, 1e3), prior[free[6:]]])

    sol = least_squares(fun, x0[free], x_scale="jac", method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=200 * int(free.sum()))
    x = x0.copy()
    x[free] = sol.x
    sol.x_full, sol.free = x, free
    return _camera_of(start, x), sol


def _std(sol: OptimizeResult, n_residuals: int) -> dict[str, float]:
    """1-sigma uncertainty of each fitted parameter from the Jacobian at the solution."""
    try:
        jac = sol.jac
        dof = max(1, n_residuals - jac.shape[1])
        s2 = float(np.sum(sol.fun[:n_residuals] ** 2)) / dof
        cov = np.linalg.pinv(jac.T @ jac) * s2
        return {str(k): float(v) for k, v in zip(np.asarray(_NAMES)[sol.free], np.sqrt(np.maximum(np.diag(cov), 0.0)),
                                                 strict=True)}
    except (ValueError, np.linalg.LinAlgError):
        return {}


def _plane_rms(res: list[np.ndarray], planes: Sequence[PlaneDots], n_planes: int) -> np.ndarray:
    out = np.full(n_planes, np.nan)
    for p, r in zip(planes, res, strict=True):
        if len(r):
            out[p.plane] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    return out


def fit_pinhole(nominal: PinholeCamera, board: DotBoard, planes: Sequence[PlaneDots], *, n_planes: int | None = None,
                fit_distortion: bool = True, outlier_sigma: float = 5.0) -> CameraFit:
    """Fit a pinhole camera's model and its Soloff polynomial to its named dots.

    Parameters
    ----------
    nominal
        The starting model (the rig file's camera).
    board
        The target (its positions define the world frame).
    planes
        The named dots of each plane (one view each).
    n_planes
        Number of planes in the store (for the per-plane arrays; default: highest plane + 1).
    fit_distortion
        Fit OpenCV's k1, k2, p1, p2 (held weakly to the nominal values, see :data:`PRIOR_SIGMA`).
    outlier_sigma
        Dots further than this many robust sigmas from the first fit are dropped.

    Returns
    -------
    CameraFit
        The pinhole model (``radial_k1`` its k1), its reprojection RMS over all planes and per
        plane, the uncertainties, and the Soloff polynomial with its own RMS.

    Raises
    ------
    FitError
        Too few dots (8 on 2 planes at different depths), or a fit that does not converge.
    """
    planes, n_planes, world = planes_with_dots(nominal.name, board, planes, n_planes)
    found = [np.asarray(p.views_px, dtype=np.float64)[:, 0] for p in planes]
    keep = [np.ones(len(f), dtype=bool) for f in found]

    def solve() -> tuple[PinholeCamera, OptimizeResult]:
        return refine_pinhole(nominal, np.concatenate([w[k] for w, k in zip(world, keep, strict=True)]),
                              np.concatenate([f[k] for f, k in zip(found, keep, strict=True)]),
                              fit_distortion=fit_distortion)

    cam, sol = solve()
    miss = [np.hypot(*(pinhole.project(cam, w) - f).T) for w, f in zip(world, found, strict=True)]
    sigma = max(float(np.median(np.concatenate(miss))) / 1.1774, 1e-6)  # misnamed or merged dots are far beyond
    keep = [m <= outlier_sigma * sigma for m in miss]
    dropped = int(sum((~k).sum() for k in keep))
    if sum(int(k.sum()) for k in keep) < 8:
        raise FitError(f"camera '{nominal.name}': only {sum(int(k.sum()) for k in keep)} dots agree with the first "
                       "fit; check the board settings and that the dots were named right")
    cam, sol = solve()
    if not sol.success:
        raise FitError(f"camera '{nominal.name}': the fit did not converge ({sol.message})")
    res = [(f - pinhole.project(cam, w))[k] for w, f, k in zip(world, found, keep, strict=True)]
    allres = np.concatenate(res)
    soloff = SoloffMap.fit(np.concatenate([w[k] for w, k in zip(world, keep, strict=True)]),
                           np.concatenate([f[k] for f, k in zip(found, keep, strict=True)]))
    sres = [(f - soloff.project(w))[k] for w, f, k in zip(world, found, keep, strict=True)]
    plain = cam.plain()
    return CameraFit(camera=plain, radial_k1=plain.k1, rms_px=float(np.sqrt(np.mean(np.sum(allres**2, axis=1)))),
                     plane_rms_px=_plane_rms(res, planes, n_planes),
                     plane_dots=np.bincount([p.plane for p in planes], weights=[int(k.sum()) for k in keep],
                                            minlength=n_planes).astype(np.int64),
                     lattice_rms_px=math.nan, std=_std(sol, 2 * len(allres)), residuals_px=res, dropped=dropped,
                     set_aside=0, soloff=soloff,
                     soloff_rms_px=float(np.sqrt(np.mean(np.sum(np.concatenate(sres) ** 2, axis=1)))),
                     soloff_plane_rms_px=_plane_rms(sres, planes, n_planes))
