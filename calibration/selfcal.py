"""Volume self-calibration of pinhole cameras (Wieneke 2008): disparity maps from the particles
of a recording, and each camera's mapping corrected by them.

A calibration that is off by a fraction of a pixel already costs a tomographic reconstruction
most of its particles (their lines of sight no longer meet). Wieneke's self-calibration measures
the error on the particles themselves:

1. **Particles** in every camera's images: local maxima above the noise, centred to a fraction of
   a pixel by a three-point Gaussian fit along each axis (:func:`find_particles`).
2. **Triangulation** (:func:`match_particles`): every particle of the first camera with every
   particle of the second within ``radius_px`` of its epipolar line through the volume; the two
   lines of sight give a point, which must have a particle within ``radius_px`` in every other
   camera; the point is then triangulated from all of them (:func:`lfcore.pinhole.triangulate`)
   and each camera's *disparity* is where its particle is minus where its model puts the point.
   Matches of particles that do not belong together (ghosts) are many at the start, and
   uncorrelated.
3. **Disparity maps** (:func:`disparity_maps`): the volume is cut into sub-volumes, and in each,
   per camera, the disparities of every match (of every frame) are histogrammed: the true matches
   pile up on the camera's calibration error, the ghosts spread evenly over the search disc. The
   peak (the histogram's maximum, refined to the mean of the disparities near it) is the
   sub-volume's disparity; the mean position of those matches is where it holds.
4. **Correction** (:func:`correct_pinhole`, :func:`correct_soloff`): each camera's mapping is made
   to put those points where its particles are (the model's image plus the disparity): the
   pinhole model by refitting it (:func:`calibration.pinhole.refine_pinhole`), the Soloff
   polynomial by adding the low-order polynomial that fits the disparities (affine, or quadratic
   from denser maps).

Steps 2-4 are repeated with the search disc halved each time (fewer ghosts once the error is
small), and a last triangulation measures what disparity remains (:func:`self_calibrate`).

A correction common to all cameras (moving or turning the whole world frame) leaves every
disparity unchanged: self-calibration makes the cameras agree with each other, not with the
target, and the world frame stays the calibration's only to within such a shift, which is harmless
for the reconstruction. Pure: images and models in, corrected models and the maps out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from calibration.dots import background_level
from calibration.pinhole import refine_pinhole
from lfcore import pinhole
from lfcore.rig import PinholeCamera
from lfcore.soloff import SOLOFF_TERMS, SoloffMap

__all__ = ["SelfCalError", "SelfCalResult", "correct_pinhole", "correct_soloff", "disparity_maps", "find_particles",
           "match_particles", "self_calibrate"]


class SelfCalError(ValueError):
    """Self-calibration that cannot run (too few cameras, particles or matches); one line saying why."""


def find_particles(image: np.ndarray, *, threshold_sigma: float = 8.0) -> np.ndarray:
    """The particle images of one frame: local maxima above the noise, centred to a fraction of a
    pixel.

    Parameters
    ----------
    image
        (rows, columns) frame, counts.
    threshold_sigma
        A maximum counts if it stands this many noise sigmas above the background (the frame's
        median; sigma from the pixels at or below it).

    Returns
    -------
    numpy.ndarray
        (n, 2) continuous (column, row) positions, pixels: the three-point Gaussian estimator
        along each axis about the brightest pixel (pixel ``[r, c]`` centred at (c + 0.5, r + 0.5)).
        An isolated particle image 3 px across is centred to about 0.02 px; at 0.05 ppp most
        images overlap a neighbour, which pulls the centre by 0.2-0.5 px in a random direction:
        the disparity maps average that out over many particles.
    """
    img = np.asarray(image, dtype=np.float64)
    bg, sigma = background_level(np.asarray(image))
    s = img - bg
    peak = (s == ndimage.maximum_filter(s, size=3, mode="nearest")) & (s > threshold_sigma * max(sigma, 1e-3))
    peak[0, :] = peak[-1, :] = peak[:, 0] = peak[:, -1] = False  # the estimator needs both neighbours
    r, c = np.nonzero(peak)
    ln = np.log(np.maximum(s, 1.0))

    def offset(lo: np.ndarray, mid: np.ndarray, hi: np.ndarray) -> np.ndarray:
        den = 2.0 * (lo - 2.0 * mid + hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(den < 0, (lo - hi) / den, 0.0)
        return np.clip(d, -0.5, 0.5)

    dx = offset(ln[r, c - 1], ln[r, c], ln[r, c + 1])
    dy = offset(ln[r - 1, c], ln[r, c], ln[r + 1, c])
    return np.stack([c + 0.5 + dx, r + 0.5 + dy], axis=-1)


def _box_range(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """(t_in, t_out) of each ray o + t d through the box [lo, hi] (t_in > t_out: it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / direction
        t2 = (hi - origin) / direction
    t1 = np.where(np.isfinite(t1), t1, -np.inf)
    t2 = np.where(np.isfinite(t2), t2, np.inf)
    return np.minimum(t1, t2).max(axis=-1), np.maximum(t1, t2).min(axis=-1)


def match_particles(cameras: Sequence[PinholeCamera], particles: Sequence[np.ndarray], bounds_mm: tuple, *,
                    radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate particles seen by every camera within ``radius_px`` of where they should be.

    Parameters
    ----------
    cameras
        The pinhole cameras (two at least).
    particles
        Per camera, (n_c, 2) particle positions in one frame, pixels (:func:`find_particles`).
    bounds_mm
        (lo, hi): the volume's corners, (3,) mm each; matches outside it are left out.
    radius_px
        The search radius: the largest disparity accepted in any camera.

    Returns
    -------
    points : numpy.ndarray
        (m, 3) triangulated world positions, mm (true particles and ghosts).
    disparity : numpy.ndarray
        (cameras, m, 2) each camera's particle minus its model's image of the point, pixels.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds_mm)
    c0, c1 = cameras[0], cameras[1]
    p0, p1 = (np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in particles[:2])
    none = (np.zeros((0, 3)), np.zeros((len(cameras), 0, 2)))
    if len(p0) == 0 or len(p1) == 0:
        return none
    # samples along each line of sight of camera 0 through the volume, close enough that their images
    # in camera 1 leave no gap wider than the search radius
    o, d = pinhole.line_of_sight(c0, p0)
    t_in, t_out = _box_range(o, d, lo, hi)
    inside = t_out > t_in
    step = 0.5 * radius_px * c1.object_pixel_mm
    n_steps = np.where(inside, np.ceil((t_out - t_in) / step).astype(np.int64) + 1, 0)
    ray = np.repeat(np.arange(len(p0)), n_steps)
    k = np.arange(len(ray)) - np.repeat(np.cumsum(n_steps) - n_steps, n_steps)
    t = t_in[ray] + k * np.repeat((t_out - t_in) / np.maximum(n_steps - 1, 1), n_steps)
    seen = pinhole.project(c1, o[ray] + t[:, None] * d[ray])
    tree1 = cKDTree(p1)
    near = tree1.query_ball_point(seen, radius_px + 0.5 * radius_px, return_sorted=False)
    pairs = np.unique(np.array([(ray[i], j) for i, js in enumerate(near) for j in js], dtype=np.int64).reshape(-1, 2),
                      axis=0)
    if not len(pairs):
        return none
    # the point of each pair, then every other camera's nearest particle to its image
    px = np.full((len(cameras), len(pairs), 2), np.nan)
    px[0], px[1] = p0[pairs[:, 0]], p1[pairs[:, 1]]
    x = pinhole.triangulate(cameras[:2], px[:2])
    ok = np.all((x >= lo) & (x <= hi), axis=1)
    for ci in range(2, len(cameras)):
        pc = np.asarray(particles[ci], dtype=np.float64).reshape(-1, 2)
        if not len(pc):
            return none
        dist, j = cKDTree(pc).query(pinhole.project(cameras[ci], x))
        ok &= dist <= radius_px
        px[ci] = pc[np.minimum(j, len(pc) - 1)]
    px, x = px[:, ok], x[ok]
    if not len(x):
        return none
    x = pinhole.triangulate(cameras, px)
    disparity = px - np.stack([pinhole.project(c, x) for c in cameras])
    keep = np.all((x >= lo) & (x <= hi), axis=1) & np.all(np.hypot(disparity[..., 0], disparity[..., 1]) <= radius_px,
                                                          axis=0)
    return x[keep], disparity[:, keep]


def disparity_maps(points: np.ndarray, disparity: np.ndarray, bounds_mm: tuple, subvolumes: Sequence[int], *,
                   radius_px: float, min_matches: int = 20, bin_px: float = 0.1, peak_px: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each sub-volume's disparity of each camera: the peak of its matches' disparities.

    Parameters
    ----------
    points
        (m, 3) matched world positions, mm (of every frame).
    disparity
        (cameras, m, 2) their disparities, pixels.
    bounds_mm
        (lo, hi): the volume's corners, mm.
    subvolumes
        (nx, ny, nz) sub-volumes along world x, y and z.
    radius_px
        The search radius the matches were made with (the histogram's extent).
    min_matches
        Fewest matches a sub-volume needs for a disparity (fewer: NaN).
    bin_px
        The histogram's bin, pixels.
    peak_px
        The disparities within this distance of the histogram's peak are averaged (default:
        a third of ``radius_px``, at least 0.15 px).

    Returns
    -------
    maps : numpy.ndarray
        (cameras, nz, ny, nx, 2) disparity of each sub-volume, pixels (NaN: too few matches).
    where : numpy.ndarray
        (cameras, nz, ny, nx, 3) mean position of the matches at the peak, mm (NaN likewise).
    counts : numpy.ndarray
        (nz, ny, nx) int, matches in each sub-volume.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds_mm)
    nx, ny, nz = (int(n) for n in subvolumes)
    n_cam = disparity.shape[0]
    peak_px = max(0.15, radius_px / 3.0) if peak_px is None else peak_px
    cell = np.floor((points - lo) / (hi - lo) * np.array([nx, ny, nz])).astype(np.int64)
    cell = np.clip(cell, 0, np.array([nx, ny, nz]) - 1)
    flat = (cell[:, 2] * ny + cell[:, 1]) * nx + cell[:, 0]
    counts = np.bincount(flat, minlength=nx * ny * nz)
    maps = np.full((n_cam, nx * ny * nz, 2), np.nan)
    where = np.full((n_cam, nx * ny * nz, 3), np.nan)
    edges = np.arange(-radius_px, radius_px + bin_px, bin_px)
    for s in np.flatnonzero(counts >= min_matches):
        mine = flat == s
        for ci in range(n_cam):
            d = disparity[ci, mine]
            h, _, _ = np.histogram2d(d[:, 0], d[:, 1], bins=[edges, edges])
            h = ndimage.gaussian_filter(h, 1.5, mode="constant")
            i, j = np.unravel_index(int(np.argmax(h)), h.shape)
            centre = np.array([edges[i], edges[j]]) + 0.5 * bin_px
            for _ in range(3):  # the mean of the disparities near the peak: the ghosts' few barely move it
                near = np.hypot(*(d - centre).T) <= peak_px
                if not near.any():
                    break
                centre = d[near].mean(axis=0)
            if near.any():
                maps[ci, s], where[ci, s] = centre, points[mine][near].mean(axis=0)
    return (maps.reshape(n_cam, nz, ny, nx, 2), where.reshape(n_cam, nz, ny, nx, 3), counts.reshape(nz, ny, nx))


def correct_pinhole(camera: PinholeCamera, where_mm: np.ndarray, disparity: np.ndarray, *,
                    fit_distortion: bool = False) -> PinholeCamera:
    """The pinhole model refitted so that it maps each point where the camera saw it: its image
    plus the disparity measured there.

    Parameters
    ----------
    camera
        The model to correct.
    where_mm
        (k, 3) points where the disparities were measured, mm (NaN rows are left out).
    disparity
        (k, 2) their disparities, pixels.
    fit_distortion
        Also refit k1, k2, p1, p2 (held weakly, :data:`calibration.pinhole.PRIOR_SIGMA`).

    Returns
    -------
    PinholeCamera
        The corrected model.
    """
    ok = np.all(np.isfinite(where_mm), axis=1) & np.all(np.isfinite(disparity), axis=1)
    target = pinhole.project(camera, where_mm[ok]) + disparity[ok]
    fitted, _ = refine_pinhole(camera, where_mm[ok], target, fit_distortion=fit_distortion)
    return fitted.plain()


def correct_soloff(mapping: SoloffMap, where_mm: np.ndarray, disparity: np.ndarray) -> SoloffMap:
    """The Soloff polynomial plus the low-order polynomial (of its own terms) that fits the
    disparities: degree 1 in x, y and z (what an error of pose or scale makes over a field of
    view), degree 2 from 60 points (denser maps: a field that a mislaid lens distortion bends).

    Parameters
    ----------
    mapping
        The mapping to correct.
    where_mm, disparity
        As :func:`correct_pinhole`.
    """
    ok = np.all(np.isfinite(where_mm), axis=1) & np.all(np.isfinite(disparity), axis=1)
    if ok.sum() < 4:
        return mapping
    terms = SOLOFF_TERMS[SOLOFF_TERMS[:, 2] <= mapping.z_order]
    degree = 2 if ok.sum() >= 60 else 1
    use = terms.sum(axis=1) <= degree
    u = (where_mm[ok] - mapping.centre_mm) / mapping.scale_mm
    a = np.prod(u[:, None, :] ** terms[use], axis=-1)
    coef, *_ = np.linalg.lstsq(a, disparity[ok], rcond=None)
    out = mapping.coefficients.copy()
    out[:, use] += coef.T
    return SoloffMap(out, mapping.centre_mm, mapping.scale_mm, mapping.z_order)


@dataclass(frozen=True)
class SelfCalResult:
    """What a volume self-calibration did.

    Attributes
    ----------
    cameras
        The corrected pinhole models, in the order given.
    soloff
        The corrected Soloff polynomials (None where none was given).
    maps_px
        (passes, cameras, nz, ny, nx, 2) the disparity maps of each pass, pixels: pass 0 with the
        models given, the last one with the final models (NaN: a sub-volume with too few matches).
    counts
        (passes, nz, ny, nx) matches per sub-volume in each pass.
    rms_px
        (passes,) RMS disparity over the cameras and sub-volumes of each pass, pixels.
    max_px
        (passes,) the largest sub-volume disparity of each pass, pixels.
    radius_px
        (passes,) the search radius of each pass, pixels.
    frames
        Frames the particles were taken from.
    """

    cameras: tuple[PinholeCamera, ...]
    soloff: tuple[SoloffMap | None, ...]
    maps_px: np.ndarray
    counts: np.ndarray
    rms_px: np.ndarray
    max_px: np.ndarray
    radius_px: np.ndarray
    frames: int


def self_calibrate(cameras: Sequence[PinholeCamera], frames: Sequence[np.ndarray], bounds_mm: tuple, *,
                   subvolumes: Sequence[int] = (4, 4, 2), radius_px: float = 2.0, iterations: int = 3,
                   min_radius_px: float = 1.0, min_matches: int = 20, soloff: Sequence[SoloffMap | None] | None = None,
                   fit_distortion: bool = False, threshold_sigma: float = 8.0) -> SelfCalResult:
    """Wieneke's volume self-calibration of pinhole cameras on particle images (module docstring).

    Parameters
    ----------
    cameras
        The pinhole models to correct (two at least; three or more make the disparities of each
        camera independent of the others' errors).
    frames
        Per camera, (frames, rows, columns) particle images recorded at the same instants.
    bounds_mm
        (lo, hi): the volume's corners, (3,) mm each.
    subvolumes
        (nx, ny, nz) sub-volumes of the disparity maps.
    radius_px
        The first pass's search radius: larger than the calibration error.
    iterations
        Correction passes; each halves the search radius, down to ``min_radius_px``.
    min_radius_px
        The smallest search radius: the particles' own position error sets it (tenths of a pixel
        where particle images overlap, at Tomo-PIV's usual 0.05 ppp).
    min_matches
        Fewest matches a sub-volume needs for a disparity.
    soloff
        Per camera, its Soloff polynomial, corrected by the same maps (None: none).
    fit_distortion
        Also correct the distortion coefficients (only wide fields of view show them).
    threshold_sigma
        Particle detection threshold (:func:`find_particles`).

    Raises
    ------
    SelfCalError
        Fewer than two cameras, frames of different counts, or no sub-volume with enough matches.
    """
    cams = list(cameras)
    if len(cams) < 2:
        raise SelfCalError(f"{len(cams)} pinhole camera(s); volume self-calibration needs two or more")
    n_frames = {len(f) for f in frames}
    if len(frames) != len(cams) or len(n_frames) != 1:
        raise SelfCalError("give every camera's frames of the same instants (as many frames for each camera)")
    maps_out = list(soloff) if soloff is not None else [None] * len(cams)
    particles = [[find_particles(f[k], threshold_sigma=threshold_sigma) for f in frames]
                 for k in range(n_frames.pop())]
    maps, counts, rms, worst, radii = [], [], [], [], []
    radius = float(radius_px)
    for it in range(iterations + 1):
        pts, disp = [], []
        for per_camera in particles:
            x, d = match_particles(cams, per_camera, bounds_mm, radius_px=radius)
            pts.append(x)
            disp.append(d)
        x, d = np.concatenate(pts), np.concatenate(disp, axis=1)
        m, where, n = disparity_maps(x, d, bounds_mm, subvolumes, radius_px=radius, min_matches=min_matches)
        valid = np.all(np.isfinite(m), axis=-1)
        if not valid.any():
            raise SelfCalError(f"no sub-volume has {min_matches} matched particles (pass {it + 1}, search radius "
                               f"{radius:g} px, {len(x)} matches in all); give more frames, fewer --subvolumes, or a "
                               "larger --radius-px if the calibration is further off")
        mag = np.hypot(m[..., 0], m[..., 1])[valid]
        maps.append(m)
        counts.append(n)
        rms.append(float(np.sqrt(np.mean(mag**2))))
        worst.append(float(mag.max()))
        radii.append(radius)
        if it == iterations:
            break
        for ci in range(len(cams)):
            w, dd = where[ci].reshape(-1, 3), m[ci].reshape(-1, 2)
            cams[ci] = correct_pinhole(cams[ci], w, dd, fit_distortion=fit_distortion)
            if maps_out[ci] is not None:
                maps_out[ci] = correct_soloff(maps_out[ci], w, dd)
        radius = max(min_radius_px, 0.5 * radius)
    return SelfCalResult(tuple(cams), tuple(maps_out), np.stack(maps), np.stack(counts), np.array(rms),
                         np.array(worst), np.array(radii), len(particles))
