"""Reconstruction quality against a synthetic run's truth.

- Q_recon (Elsinga et al. 2006): Q = sum(E1 E0) / sqrt(sum(E1^2) sum(E0^2)), with E0 the true
  particles drawn as Gaussian blobs 3 voxels across (at 1/e^2 of the peak).
- Particle detection: local maxima above a fraction of the brightest, located to sub-voxel
  precision by a three-point Gaussian fit per axis (centroid where the fit is impossible).
- Matching to the truth: one-to-one, nearest first, within a tolerance per axis; recall,
  ghosts (detections matched to nothing) and the position error per axis.
- Reconstructed particle diameters per axis, where the intensity falls to exp(-2) of the peak
  (two standard deviations of a Gaussian: 3 voxels for the ideal particle), as in the chapter.
- Mean intensity against depth, and the fraction of intensity outside the seeded region.
- :func:`evaluate_volume`: all of the above for one reconstructed volume against its truth.
- Vector fields against the truth flow: the flow on the vector grid (:func:`grid_velocity`),
  the RMS velocity error per component (:func:`velocity_errors`) and the chapter's divergence
  error |du/dx + dv/dy + dw/dz| (:func:`divergence_error`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from lfcore._deprecation import keyword_options
from lfcore.flows import Flow
from lfcore.vectors import divergence
from lfcore.volume import VolumeGrid

__all__ = [
    "MatchResult",
    "VelocityErrors",
    "VolumeEvaluation",
    "depth_profile",
    "detect_particles",
    "divergence_error",
    "evaluate_volume",
    "grid_velocity",
    "match_particles",
    "outside_fraction",
    "particle_diameters",
    "q_recon",
    "truth_volume",
    "velocity_errors",
]

#: Gaussian sigma of a true particle in voxels: 4 sigma = 3 voxels at 1/e^2.
TRUTH_SIGMA_VOXELS = 0.75


@keyword_options("brightness", since="0.1.0")
def truth_volume(grid: VolumeGrid, particles_mm: np.ndarray, *, brightness: np.ndarray | None = None,
                 sigma_voxels: float = TRUTH_SIGMA_VOXELS) -> np.ndarray:
    """E0: the true particles as Gaussian blobs on the grid.

    Parameters
    ----------
    grid
        The voxel grid.
    particles_mm
        (n, 3) world positions (x, y, z) in mm.
    brightness
        (n,) relative intensities; ones if None.
    sigma_voxels
        Blob sigma in voxels along every axis (anisotropic voxels give anisotropic blobs in mm).

    Returns
    -------
    numpy.ndarray
        (z, y, x) float32.
    """
    pts = np.asarray(particles_mm, dtype=np.float64).reshape(-1, 3)
    b = np.ones(len(pts)) if brightness is None else np.asarray(brightness, dtype=np.float64)
    vol = np.zeros(grid.shape, dtype=np.float32)
    idx = grid.world_to_index(pts)  # (z, y, x)
    r = int(np.ceil(3 * sigma_voxels))
    offs = np.arange(-r, r + 1)
    for p, bright in zip(idx, b, strict=True):
        c = np.rint(p).astype(int)
        ranges = [c[a] + offs for a in range(3)]
        ok = [(g >= 0) & (g < n) for g, n in zip(ranges, grid.shape, strict=True)]
        if not all(o.any() for o in ok):
            continue
        prof = [np.exp(-0.5 * ((g[o] - p[a]) / sigma_voxels) ** 2) for a, (g, o) in enumerate(zip(ranges, ok,
                                                                                                  strict=True))]
        blob = bright * prof[0][:, None, None] * prof[1][None, :, None] * prof[2][None, None, :]
        vol[np.ix_(ranges[0][ok[0]], ranges[1][ok[1]], ranges[2][ok[2]])] += blob.astype(np.float32)
    return vol


def q_recon(e1: np.ndarray, e0: np.ndarray) -> float:
    """Reconstruction quality Q of volume ``e1`` against the true volume ``e0`` (same shape)."""
    a = np.asarray(e1, dtype=np.float64)
    b = np.asarray(e0, dtype=np.float64)
    den = np.sqrt(np.sum(a * a) * np.sum(b * b))
    return float(np.sum(a * b) / den) if den > 0 else 0.0


def _subvoxel(vol: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """Three-point Gaussian fit along each axis around integer peaks; centroid as a fallback."""
    out = peaks.astype(np.float64)
    shape = np.asarray(vol.shape)
    for axis in range(3):
        lo = peaks.copy()
        hi = peaks.copy()
        lo[:, axis] -= 1
        hi[:, axis] += 1
        inside = (lo[:, axis] >= 0) & (hi[:, axis] < shape[axis])
        c = vol[tuple(peaks.T)].astype(np.float64)
        m = np.where(inside, vol[tuple(np.clip(lo, 0, shape - 1).T)], 0.0).astype(np.float64)
        p = np.where(inside, vol[tuple(np.clip(hi, 0, shape - 1).T)], 0.0).astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            lm, lc, lp = np.log(m), np.log(c), np.log(p)
            gauss = (lm - lp) / (2.0 * (lm - 2.0 * lc + lp))
            centroid = (p - m) / (m + c + p)
        ok = inside & (m > 0) & (p > 0) & np.isfinite(gauss) & (np.abs(gauss) < 1.0)
        shift = np.where(ok, gauss, np.nan_to_num(centroid))
        out[:, axis] += np.clip(shift, -0.5, 0.5)
    return out


def detect_particles(volume: np.ndarray, grid: VolumeGrid, *, threshold: float = 0.1
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Particles in a reconstructed volume.

    Parameters
    ----------
    volume
        (z, y, x) intensities.
    grid
        Its voxel grid.
    threshold
        Peaks below this fraction of the brightest voxel are ignored.

    Returns
    -------
    positions_mm
        (n, 3) world positions (x, y, z), sub-voxel.
    peaks
        (n,) peak intensities.
    indices
        (n, 3) integer (z, y, x) voxel of each peak.
    """
    vol = np.asarray(volume, dtype=np.float32)
    vmax = float(vol.max()) if vol.size else 0.0
    if vmax <= 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3), dtype=int)
    local_max = ndimage.maximum_filter(vol, size=3, mode="constant", cval=0.0) == vol
    idx = np.argwhere(local_max & (vol >= threshold * vmax))
    sub = _subvoxel(vol, idx)  # (z, y, x) fractional
    pos = np.asarray(grid.origin_mm) + sub[:, ::-1] * np.asarray(grid.voxel_mm)
    return pos, vol[tuple(idx.T)], idx


@dataclass(frozen=True)
class MatchResult:
    """Detected particles matched to the truth.

    Attributes
    ----------
    recall
        Matched true particles over true particles inside the volume.
    ghosts
        Detections matched to no true particle.
    ghost_fraction
        ``ghosts`` over detections.
    error_mm
        (m, 3) detected minus true position (x, y, z) of each match.
    n_true, n_detected, n_matched
        Counts.
    """

    recall: float
    ghosts: int
    ghost_fraction: float
    error_mm: np.ndarray
    n_true: int
    n_detected: int
    n_matched: int

    @property
    def rms_error_mm(self) -> np.ndarray:
        """RMS position error per axis (x, y, z) in mm (NaN without matches)."""
        if len(self.error_mm) == 0:
            return np.full(3, np.nan)
        return np.sqrt(np.mean(self.error_mm**2, axis=0))

    @property
    def bias_mm(self) -> np.ndarray:
        if len(self.error_mm) == 0:
            return np.full(3, np.nan)
        return self.error_mm.mean(axis=0)


def match_particles(detected_mm: np.ndarray, true_mm: np.ndarray, tolerance_mm: np.ndarray) -> MatchResult:
    """One-to-one matching of detections to true particles, nearest first.

    A pair matches if their separation, divided per axis by ``tolerance_mm`` (x, y, z), is at
    most 1 (an ellipsoid, since depth is resolved more coarsely than the lateral axes).
    """
    det = np.asarray(detected_mm, dtype=np.float64).reshape(-1, 3)
    tru = np.asarray(true_mm, dtype=np.float64).reshape(-1, 3)
    tol = np.asarray(tolerance_mm, dtype=np.float64)
    matched_d, matched_t = [], []
    if len(det) and len(tru):
        tree = cKDTree(tru / tol)
        dist, cand = tree.query(det / tol, k=min(8, len(tru)), distance_upper_bound=1.0)
        dist = np.atleast_2d(dist.reshape(len(det), -1))
        cand = np.atleast_2d(cand.reshape(len(det), -1))
        pairs = [(dist[i, k], i, cand[i, k]) for i in range(len(det)) for k in range(dist.shape[1])
                 if np.isfinite(dist[i, k])]
        used_d, used_t = set(), set()
        for _, i, t in sorted(pairs):
            if i not in used_d and t not in used_t:
                used_d.add(i)
                used_t.add(t)
                matched_d.append(i)
                matched_t.append(t)
    err = det[matched_d] - tru[matched_t] if matched_d else np.zeros((0, 3))
    n_m = len(matched_d)
    return MatchResult(recall=n_m / len(tru) if len(tru) else float("nan"), ghosts=len(det) - n_m,
                       ghost_fraction=(len(det) - n_m) / len(det) if len(det) else 0.0, error_mm=err,
                       n_true=len(tru), n_detected=len(det), n_matched=n_m)


def particle_diameters(volume: np.ndarray, indices: np.ndarray, *, level: float = float(np.exp(-2.0))
                       ) -> np.ndarray:
    """Diameter of each reconstructed particle along x, y, z, in voxels.

    Measured through the peak voxel along each axis: the distance between the two points where
    the intensity falls to ``level`` times the peak, its logarithm interpolated between voxels.

    Returns
    -------
    numpy.ndarray
        (n, 3) diameters in voxels, ordered (x, y, z).
    """
    vol = np.asarray(volume, dtype=np.float64)
    out = np.zeros((len(indices), 3))
    for n, idx in enumerate(np.asarray(indices, dtype=int)):
        peak = vol[tuple(idx)]
        for axis in range(3):
            line = np.moveaxis(vol, axis, -1)[tuple(np.delete(idx, axis))]
            c = idx[axis]
            cut = level * peak
            width = 0.0
            for step in (-1, 1):
                k = c
                while 0 <= k + step < len(line) and line[k + step] > cut:
                    k += step
                if 0 <= k + step < len(line):
                    # interpolate the logarithm: exact for an exponential fall-off
                    a, b = np.log(line[k]), np.log(max(line[k + step], 1e-30 * peak))
                    width += abs(k - c) + (a - np.log(cut)) / (a - b)
                else:
                    width += abs(k - c) + 0.5
            out[n, 2 - axis] = width
    return out


def depth_profile(volume: np.ndarray) -> np.ndarray:
    """Mean intensity of each z slice, shape (z,)."""
    return np.asarray(volume, dtype=np.float64).mean(axis=(1, 2))


def outside_fraction(volume: np.ndarray, grid: VolumeGrid, centre_mm, size_mm) -> float:
    """Fraction of the total intensity in voxels whose centre lies outside the given box."""
    vol = np.asarray(volume, dtype=np.float64)
    total = vol.sum()
    if total <= 0:
        return 0.0
    lo = np.asarray(centre_mm) - 0.5 * np.asarray(size_mm)
    hi = np.asarray(centre_mm) + 0.5 * np.asarray(size_mm)
    inside = [((grid.axis_mm(a) >= lo[i]) & (grid.axis_mm(a) <= hi[i])) for i, a in enumerate("xyz")]
    mask = inside[2][:, None, None] & inside[1][None, :, None] & inside[0][None, None, :]
    return float(vol[~mask].sum() / total)


@dataclass(frozen=True)
class VolumeEvaluation:
    """The quality of one reconstructed volume against the truth (see :func:`evaluate_volume`).

    Attributes
    ----------
    q
        Q_recon.
    match
        Detected particles matched to the true ones.
    diameters_vox
        (3,) median reconstructed particle diameter (x, y, z) in voxels; NaN without particles.
    outside
        Fraction of the intensity outside the seeded region.
    depth_profile, truth_profile
        (z,) mean intensity of each z slice of the volume and of the truth volume.
    """

    q: float
    match: MatchResult
    diameters_vox: np.ndarray
    outside: float
    depth_profile: np.ndarray
    truth_profile: np.ndarray


def evaluate_volume(volume: np.ndarray, grid: VolumeGrid, particles_mm: np.ndarray, brightness: np.ndarray, *,
                    centre_mm: tuple[float, float, float], size_mm: tuple[float, float, float],
                    threshold: float = 0.1, match_voxels: float = 2.0) -> VolumeEvaluation:
    """Q, detection and matching, diameters and depth profile of one volume.

    Parameters
    ----------
    volume
        (z, y, x) reconstructed intensities on ``grid``.
    grid
        The voxel grid.
    particles_mm, brightness
        (n, 3) true world positions (x, y, z) in mm and (n,) their brightness.
    centre_mm, size_mm
        The seeded region (the rig's volume), mm.
    threshold
        Detect peaks above this fraction of the brightest voxel.
    match_voxels
        A detection matches a true particle within this many voxels per axis.
    """
    e0 = truth_volume(grid, particles_mm, brightness=brightness)
    pos, _, idx = detect_particles(volume, grid, threshold=threshold)
    match = match_particles(pos, particles_mm, match_voxels * np.asarray(grid.voxel_mm))
    diam = particle_diameters(volume, idx)
    return VolumeEvaluation(q=q_recon(volume, e0), match=match,
                            diameters_vox=np.median(diam, axis=0) if len(diam) else np.full(3, np.nan),
                            outside=outside_fraction(volume, grid, centre_mm, size_mm),
                            depth_profile=depth_profile(volume), truth_profile=depth_profile(e0))


def grid_velocity(flow: Flow, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray, t_s: float) -> np.ndarray:
    """The flow's velocity on a vector grid at time ``t_s``.

    Parameters
    ----------
    flow
        The analytic flow.
    x_mm, y_mm, z_mm
        1-D world coordinates of the grid, mm.
    t_s
        Time on the flow's clock, s (for a pair: its first pulse plus half of dt).

    Returns
    -------
    numpy.ndarray
        (z, y, x, 3) velocity (u, v, w) in m/s.
    """
    zz, yy, xx = np.meshgrid(z_mm, y_mm, x_mm, indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    return flow.velocity(pts, t_s=t_s).reshape(*zz.shape, 3)


@dataclass(frozen=True)
class VelocityErrors:
    """RMS velocity error of measured vectors against the truth.

    Attributes
    ----------
    rms_m_s
        (3,) RMS error of u, v and w in m/s, over every vector of every pair (NaN ignored).
    peak_m_s
        The truth's largest speed, m/s.
    """

    rms_m_s: np.ndarray
    peak_m_s: float

    @property
    def of_peak(self) -> float:
        """The magnitude of the RMS error vector over the peak speed."""
        return float(np.linalg.norm(self.rms_m_s) / self.peak_m_s)


def velocity_errors(measured: np.ndarray, truth: np.ndarray) -> VelocityErrors:
    """The RMS error per component of ``measured`` against ``truth``.

    Parameters
    ----------
    measured, truth
        (..., 3) velocities (u, v, w) in m/s of the same shape, e.g. (pairs, z, y, x, 3).
    """
    err = np.asarray(measured, dtype=np.float64) - truth
    axes = tuple(range(err.ndim - 1))
    return VelocityErrors(rms_m_s=np.sqrt(np.nanmean(err**2, axis=axes)),
                          peak_m_s=float(np.nanmax(np.linalg.norm(truth, axis=-1))))


def divergence_error(velocity: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """The chapter's divergence error |du/dx + dv/dy + dw/dz| of each pair's field.

    Parameters
    ----------
    velocity
        (pairs, z, y, x, 3) velocity in m/s.
    x_mm, y_mm, z_mm
        1-D world coordinates of the grid, mm.

    Returns
    -------
    numpy.ndarray
        (pairs, z, y, x) in 1/s.
    """
    return np.abs(np.stack([divergence(v, x_mm, y_mm, z_mm) for v in velocity]))
