"""Particle tracks of a pair: frame A's particles paired with frame B's, and a field on a grid.

The particles of both frames (:mod:`lfcore.ipr`) are paired one-to-one, nearest first, each A
particle looking for a B particle within a search ellipsoid around where a predictor puts it:

1. **Pass 1**: predictor zero, the search as wide as the largest displacement expected
   (:attr:`TrackSettings.search_voxels`).
2. **Outliers**: a track whose displacement differs from the median of its nearest tracks by more
   than :attr:`TrackSettings.outlier_threshold` times their median deviation (the normalized median
   test of PIV, Westerweel and Scarano 2005, over the tracks' neighbours instead of a grid's) is
   rejected.
3. **Pass 2 on**: the predictor is the median of the pass before's tracks in each bin of the grid,
   and the search shrinks to :attr:`TrackSettings.refine_voxels` around it.
4. **Binning**: the field on a grid of bins :attr:`TrackSettings.bin_voxels` wide is the mean
   displacement of the tracks whose midpoint lies in each bin (NaN with fewer than
   :attr:`TrackSettings.min_tracks`).

Positions are world mm (x, y, z); the grid's voxels set the scale of the searches and bins.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import binned_statistic_dd

from lfcore.volume import VolumeGrid

__all__ = ["TrackResult", "TrackSettings", "bin_tracks", "pair_nearest", "reject_outliers", "track_pair"]


@dataclass(frozen=True)
class TrackSettings:
    """How a pair's particles are tracked (:func:`track_pair`).

    Attributes
    ----------
    search_voxels
        The first pass's search radius (x, y, z), voxels: the largest displacement expected.
    refine_voxels
        The later passes' search radius around the predictor (x, y, z), voxels.
    passes
        Pairing passes (the first without a predictor).
    bin_voxels
        The field's bins (x, y, z), voxels.
    min_tracks
        Fewest tracks a bin needs for a vector.
    neighbours
        Tracks the outlier test compares each track with.
    outlier_threshold
        The normalized median test's threshold.
    epsilon_voxels
        The test's noise floor, voxels.
    """

    search_voxels: tuple[float, float, float] = (4.0, 4.0, 2.0)
    refine_voxels: tuple[float, float, float] = (1.0, 1.0, 1.0)
    passes: int = 2
    bin_voxels: tuple[int, int, int] = (16, 16, 8)
    min_tracks: int = 2
    neighbours: int = 8
    outlier_threshold: float = 3.0
    epsilon_voxels: float = 0.2

    def __post_init__(self) -> None:
        for name in ("search_voxels", "refine_voxels", "bin_voxels"):
            v = getattr(self, name)
            if len(v) != 3 or min(v) <= 0:
                raise ValueError(f"{name} needs three positive values (x, y, z), got {v}")
        if self.passes < 1 or self.min_tracks < 1 or self.neighbours < 2 or self.outlier_threshold <= 0:
            raise ValueError("passes and min_tracks must be at least 1, neighbours at least 2, and the outlier "
                             "threshold positive")

    def as_dict(self) -> dict:
        """The settings as JSON-compatible values."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass
class TrackResult:
    """The tracks of one pair and their field.

    Attributes
    ----------
    a_index, b_index
        (m,) rows of frame A's and frame B's particles paired into each track.
    displacement_mm
        (m, 3) B minus A (x, y, z), mm.
    outlier
        (m,) tracks the last pass's outlier test rejected (left out of the field).
    x_mm, y_mm, z_mm
        The bin centres along each axis, mm.
    field_mm
        (z, y, x, 3) mean displacement (x, y, z) of each bin's tracks, mm; NaN where too few.
    counts
        (z, y, x) tracks in each bin.
    """

    a_index: np.ndarray
    b_index: np.ndarray
    displacement_mm: np.ndarray
    outlier: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    field_mm: np.ndarray
    counts: np.ndarray


def pair_nearest(a_mm: np.ndarray, b_mm: np.ndarray, predicted_mm: np.ndarray, radius_mm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs of A and B particles, nearest first, each B within the ellipsoid of semi-axes
    ``radius_mm`` (x, y, z) around its A particle moved by ``predicted_mm`` ((n, 3) or (3,)).

    Returns
    -------
    a_index, b_index
        (m,) int64 rows of ``a_mm`` and ``b_mm``, paired.
    """
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radius_mm, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    target = (a + np.broadcast_to(np.asarray(predicted_mm, dtype=np.float64), a.shape)) / r
    k = min(8, len(b))
    dist, cand = cKDTree(b / r).query(target, k=k, distance_upper_bound=1.0)
    dist, cand = dist.reshape(len(a), k), cand.reshape(len(a), k)
    ok = np.isfinite(dist)
    ia = np.broadcast_to(np.arange(len(a))[:, None], dist.shape)[ok]
    ib, d = cand[ok], dist[ok]
    used_a, used_b = np.zeros(len(a), bool), np.zeros(len(b), bool)
    out_a, out_b = [], []
    for i in np.argsort(d, kind="stable"):  # nearest first
        if not used_a[ia[i]] and not used_b[ib[i]]:
            used_a[ia[i]] = used_b[ib[i]] = True
            out_a.append(ia[i])
            out_b.append(ib[i])
    return np.asarray(out_a, np.int64), np.asarray(out_b, np.int64)


def reject_outliers(position_mm: np.ndarray, displacement_mm: np.ndarray, *, neighbours: int, threshold: float,
                    epsilon_mm: np.ndarray) -> np.ndarray:
    """The normalized median test over each track's nearest tracks: (m,) True where rejected.

    Per component, r = |d - median(d_neighbours)| / (median(|d_neighbours - median|) + epsilon); a
    track is an outlier where any component's r exceeds ``threshold``. ``epsilon_mm`` (x, y, z) is
    the noise floor.
    """
    pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(displacement_mm, dtype=np.float64).reshape(-1, 3)
    if len(pos) <= 2:
        return np.zeros(len(pos), bool)
    k = min(neighbours + 1, len(pos))
    _, idx = cKDTree(pos).query(pos, k=k)
    near = d[idx[:, 1:]]  # (m, k - 1, 3), without the track itself
    med = np.median(near, axis=1)
    spread = np.median(np.abs(near - med[:, None, :]), axis=1)
    r = np.abs(d - med) / (spread + np.asarray(epsilon_mm, dtype=np.float64))
    return np.any(r > threshold, axis=1)


def _edges(grid: VolumeGrid, bin_voxels: tuple[int, int, int]) -> list[np.ndarray]:
    """Bin edges (z, y, x), mm, covering the grid's voxels."""
    out = []
    for axis, b in zip("zyx", bin_voxels[::-1], strict=True):
        a = "xyz".index(axis)
        n = grid.shape[2 - a]
        lo = grid.origin_mm[a] - 0.5 * grid.voxel_mm[a]
        count = max(1, int(np.ceil(n / b)))
        out.append(lo + np.arange(count + 1) * b * grid.voxel_mm[a])
    return out


def bin_tracks(position_mm: np.ndarray, displacement_mm: np.ndarray, grid: VolumeGrid, *,
               bin_voxels: tuple[int, int, int], statistic: str = "mean", min_tracks: int = 1
               ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Tracks binned on the grid.

    Returns
    -------
    centres
        [x_mm, y_mm, z_mm]: the bin centres along each axis.
    field
        (z, y, x, 3) the ``statistic`` (``"mean"`` or ``"median"``) of the displacements in each
        bin, NaN where fewer than ``min_tracks``.
    counts
        (z, y, x) tracks per bin.
    """
    edges = _edges(grid, bin_voxels)
    pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(displacement_mm, dtype=np.float64).reshape(-1, 3)
    shape = tuple(len(e) - 1 for e in edges)
    centres = [0.5 * (e[1:] + e[:-1]) for e in edges[::-1]]
    if len(pos) == 0:
        return centres, np.full((*shape, 3), np.nan), np.zeros(shape, np.int64)
    sample = pos[:, ::-1]  # (z, y, x)
    counts = binned_statistic_dd(sample, None, statistic="count", bins=edges).statistic.astype(np.int64)
    stat = binned_statistic_dd(sample, [d[:, 0], d[:, 1], d[:, 2]], statistic=statistic, bins=edges).statistic
    field = np.moveaxis(np.asarray(stat), 0, -1)
    field[counts < min_tracks] = np.nan
    return centres, field, counts


def _predict(field: np.ndarray, centres: list[np.ndarray], at_mm: np.ndarray) -> np.ndarray:
    """The binned field at points: the value of the bin each lies in, the median of all bins where it
    is empty (zero where every bin is)."""
    idx = [np.clip(np.searchsorted(0.5 * (c[1:] + c[:-1]), at_mm[:, a]), 0, len(c) - 1)
           for a, c in enumerate(centres)]
    v = field[idx[2], idx[1], idx[0]]
    filled = field.reshape(-1, 3)
    filled = filled[np.all(np.isfinite(filled), axis=1)]
    fallback = np.median(filled, axis=0) if len(filled) else np.zeros(3)
    return np.where(np.isfinite(v), v, fallback)


def track_pair(a_mm: np.ndarray, b_mm: np.ndarray, grid: VolumeGrid, *, settings: TrackSettings | None = None
               ) -> TrackResult:
    """Track a pair's particles (see the module docstring).

    Parameters
    ----------
    a_mm, b_mm
        (n, 3) and (k, 3) world positions (x, y, z) of frame A's and frame B's particles, mm.
    grid
        The voxel grid: the scale of the searches and the bins.
    settings
        Searches, passes, bins and the outlier test.

    Returns
    -------
    TrackResult
    """
    s = settings or TrackSettings()
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    predicted = np.zeros_like(a)
    radius = np.asarray(s.search_voxels) * voxel
    for done in range(s.passes):
        ia, ib = pair_nearest(a, b, predicted, radius)
        disp = b[ib] - a[ia]
        mid = a[ia] + 0.5 * disp
        out = reject_outliers(mid, disp, neighbours=s.neighbours, threshold=s.outlier_threshold,
                              epsilon_mm=s.epsilon_voxels * voxel)
        centres, field, counts = bin_tracks(mid[~out], disp[~out], grid, bin_voxels=s.bin_voxels,
                                            statistic="median" if done + 1 < s.passes else "mean",
                                            min_tracks=s.min_tracks)
        if done + 1 < s.passes:
            predicted = _predict(field, centres, a)
            radius = np.asarray(s.refine_voxels) * voxel
    return TrackResult(a_index=ia, b_index=ib, displacement_mm=disp, outlier=out, x_mm=centres[0], y_mm=centres[1],
                       z_mm=centres[2], field_mm=field, counts=counts)
