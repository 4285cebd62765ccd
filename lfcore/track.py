"""Particle tracks of a pair: frame A's particles paired with frame B's, and a field on a grid.

The particles of both frames (:mod:`lfcore.ipr`) are paired one-to-one, nearest first, each A
particle looking for a B particle within a search ellipsoid around where a predictor puts it:

1. **Pass 1**: the predictor given (a coarse correlation of the pair's volumes, or the previous
   pair's field: a :class:`lfcore.warm.Predictor`, interpolated trilinearly at each A particle),
   or zero without one; the search as wide as the predictor's largest error expected (without a
   predictor: the largest displacement, :attr:`TrackSettings.search_voxels`).
2. **Outliers**: a track whose displacement differs from the median of its nearest tracks by more
   than :attr:`TrackSettings.outlier_threshold` times their median deviation (the normalized median
   test of PIV, Westerweel and Scarano 2005, over the tracks' neighbours instead of a grid's) is
   rejected.
3. **Pass 2 on**: the predictor is the median of the pass before's tracks in each bin of the grid,
   and the search shrinks to :attr:`TrackSettings.refine_voxels` around it.
4. **The field** on a grid of bins :attr:`TrackSettings.bin_voxels` wide, at the bins' centres
   (:attr:`TrackSettings.field`): ``"bins"``, the mean displacement of the tracks whose midpoint
   lies in each bin (NaN with fewer than :attr:`TrackSettings.min_tracks`); or ``"smooth"``, a
   Gaussian-weighted average of the tracks around each centre (adaptive Gaussian windowing, Agui
   and Jimenez 1987) of width :attr:`TrackSettings.smooth_voxels` (NaN with fewer than
   :attr:`TrackSettings.min_tracks` tracks within 1.5 widths): a point value of the flow rather than
   a bin's mean, with each track's weight falling off smoothly instead of at the bin's walls; or
   ``"fit"``, a smoothing spline through all the tracks (:func:`fit_tracks`: a thin-plate radial
   basis function fit with a linear or quadratic trend, each component's smoothing chosen by
   cross-validation), evaluated at the centres inside the box with :attr:`TrackSettings.min_tracks`
   tracks within a bin's width of them along every axis (or the tracks' mean spacing, where wider).

Positions are world mm (x, y, z); the grid's voxels set the scale of the searches and bins.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import binned_statistic_dd

from lfcore.volume import VolumeGrid
from lfcore.warm import Predictor

if TYPE_CHECKING:
    from scipy.interpolate import RBFInterpolator

__all__ = ["FIELDS", "FIT_BLOCK_MARGIN", "FIT_BLOCK_TRACKS", "FIT_CV_BLOCKS", "FIT_GLOBAL_TRACKS", "FIT_SMOOTHING",
           "MAX_CROWDING", "FitChoice", "TrackResult", "TrackSettings", "bin_tracks",
           "field_predictor", "fit_tracks", "pair_nearest", "predict_at", "reject_outliers", "search_crowding",
           "smooth_tracks", "track_pair"]

#: How the field is made from the tracks (:attr:`TrackSettings.field`).
FIELDS = ("bins", "smooth", "fit")
#: The smoothing parameters :func:`fit_tracks` chooses among (coordinates scaled to the tracks' extent):
#: from nearly interpolating the tracks to nearly the trend alone.
FIT_SMOOTHING = tuple(float(v) for v in np.logspace(-4.0, 3.0, 15))
#: Beyond this many tracks :func:`fit_tracks` fits the box in blocks (one global fit of n tracks
#: costs n^3, and its cross-validation 150 such fits).
FIT_GLOBAL_TRACKS = 1000
#: About how many tracks a block of a fit in blocks holds.
FIT_BLOCK_TRACKS = 250
#: The margin around a block whose tracks its fit also uses, in blocks' widths.
FIT_BLOCK_MARGIN = 0.25
#: How many blocks the smoothing of a fit in blocks is cross-validated on.
FIT_CV_BLOCKS = 2
#: Most frame-B particles a first-pass search may hold on average (:func:`search_crowding`) for the
#: nearest one to be the right one often enough to pair meaningfully; beyond it a frame is refused.
MAX_CROWDING = 8.0


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
    field
        How the field is made from the tracks: ``"fit"`` (the default: a smoothing spline through all
        the tracks, its smoothing chosen by cross-validation, :func:`fit_tracks`; on one camera's A1
        pair 0.079, 0.015, 0.041 voxel RMS and on a uniform flow 0.015, 0.033, 0.013, where
        ``"smooth"`` gives 0.097, 0.049, 0.112 and 0.066, 0.078, 0.129, benchmarks/RESULTS.md),
        ``"smooth"`` (a Gaussian-weighted average around each bin's centre) or ``"bins"`` (each
        bin's mean); see the module docstring.
    smooth_voxels
        The Gaussian's sigma (x, y, z), voxels, of ``field="smooth"``; None: half a bin.
    """

    search_voxels: tuple[float, float, float] = (4.0, 4.0, 2.0)
    refine_voxels: tuple[float, float, float] = (1.0, 1.0, 1.0)
    passes: int = 2
    bin_voxels: tuple[int, int, int] = (16, 16, 8)
    min_tracks: int = 2
    neighbours: int = 8
    outlier_threshold: float = 3.0
    epsilon_voxels: float = 0.2
    field: str = "fit"
    smooth_voxels: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.field not in FIELDS:
            raise ValueError(f"the field is made by one of {', '.join(FIELDS)}, got '{self.field}'")
        for name in ("search_voxels", "refine_voxels", "bin_voxels", "smooth_voxels"):
            v = getattr(self, name)
            if v is None:
                continue
            if len(v) != 3 or min(v) <= 0:
                raise ValueError(f"{name} needs three positive values (x, y, z), got {v}")
        if self.passes < 1 or self.min_tracks < 1 or self.neighbours < 2 or self.outlier_threshold <= 0:
            raise ValueError("passes and min_tracks must be at least 1, neighbours at least 2, and the outlier "
                             "threshold positive")

    def as_dict(self) -> dict:
        """The settings as JSON-compatible values."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @property
    def sigma_voxels(self) -> tuple[float, float, float]:
        """The smooth field's Gaussian sigma (x, y, z), voxels: :attr:`smooth_voxels`, or half a bin."""
        if self.smooth_voxels is not None:
            return tuple(float(v) for v in self.smooth_voxels)  # type: ignore[return-value]
        return tuple(0.5 * float(b) for b in self.bin_voxels)  # type: ignore[return-value]


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
        (z, y, x) tracks in each bin (``field="smooth"``: within 1.5 sigma of each centre;
        ``field="fit"``: within a bin's width, or the tracks' mean spacing where wider, of each
        centre along every axis).
    fit
        ``field="fit"``: the trend and smoothing chosen for each component (x, y, z); else None.
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
    fit: tuple[FitChoice, FitChoice, FitChoice] | None = None


@dataclass(frozen=True)
class FitChoice:
    """What :func:`fit_tracks` chose for one component of the displacement.

    Attributes
    ----------
    degree
        The polynomial trend's degree (1: linear, 2: quadratic; 0: too few tracks to fit, the
        tracks' mean).
    smoothing
        The smoothing parameter (coordinates scaled to the tracks' extent), one of
        :data:`FIT_SMOOTHING`; 0 with ``degree`` 0.
    cv_rms_mm
        The cross-validated RMS misfit of the held-out tracks at that choice, mm (NaN with
        ``degree`` 0).
    """

    degree: int
    smoothing: float
    cv_rms_mm: float


def search_crowding(n_particles: int, grid: VolumeGrid, search_voxels: tuple[float, float, float]) -> float:
    """The mean number of a frame's ``n_particles`` particles (spread over ``grid``'s box) inside one
    search ellipsoid of semi-axes ``search_voxels`` (x, y, z voxels): how many candidates the first
    pass chooses the nearest of. About 1 or less pairs reliably; many more pairs mostly by chance."""
    box = float(np.prod(np.asarray(grid.shape, dtype=np.float64)))
    return float(n_particles) * 4.0 / 3.0 * np.pi * float(np.prod(np.asarray(search_voxels, dtype=np.float64))) / box


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


def smooth_tracks(position_mm: np.ndarray, displacement_mm: np.ndarray, centres: list[np.ndarray], *,
                  sigma_mm: np.ndarray, min_tracks: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The tracks' Gaussian-weighted average at the points of a grid (adaptive Gaussian windowing).

    At each point, sum(w d) / sum(w) over the tracks within 3 sigma, w = exp(-r^2 / 2) with r the
    distance in units of ``sigma_mm`` per axis (an ellipsoidal Gaussian).

    Parameters
    ----------
    position_mm, displacement_mm
        (m, 3) each track's position (its midpoint) and displacement (x, y, z), mm.
    centres
        [x_mm, y_mm, z_mm]: the grid's points along each axis.
    sigma_mm
        (3,) the Gaussian's sigma (x, y, z), mm.
    min_tracks
        Fewest tracks within 1.5 sigma a point needs for a value.

    Returns
    -------
    field
        (z, y, x, 3) the weighted mean displacement, mm; NaN where too few tracks.
    counts
        (z, y, x) tracks within 1.5 sigma of each point.
    """
    sigma = np.asarray(sigma_mm, dtype=np.float64).reshape(3)
    pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3) / sigma
    d = np.asarray(displacement_mm, dtype=np.float64).reshape(-1, 3)
    zz, yy, xx = np.meshgrid(centres[2], centres[1], centres[0], indexing="ij")
    shape = xx.shape
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]) / sigma
    field = np.full((len(nodes), 3), np.nan)
    counts = np.zeros(len(nodes), np.int64)
    if len(pos):
        tree = cKDTree(pos)
        for i, near in enumerate(tree.query_ball_point(nodes, r=3.0)):
            if not near:
                continue
            r2 = np.sum((pos[near] - nodes[i]) ** 2, axis=1)
            counts[i] = int(np.count_nonzero(r2 <= 1.5 ** 2))
            if counts[i] >= min_tracks:
                w = np.exp(-0.5 * r2)
                field[i] = w @ d[near] / w.sum()
    return field.reshape(*shape, 3), counts.reshape(shape)


def _rbf(x: np.ndarray, y: np.ndarray, degree: int, smoothing: float) -> RBFInterpolator:
    from scipy.interpolate import RBFInterpolator

    # A smoothing thin-plate spline: minimises the misfit plus smoothing x the bending energy,
    # with a polynomial trend of the given degree left unpenalised.
    return RBFInterpolator(x, y, kernel="thin_plate_spline", degree=degree, smoothing=smoothing)


def _choose_fit(problems: list[tuple[np.ndarray, np.ndarray, list[np.ndarray]]]) -> list[FitChoice]:
    """The trend and smoothing of each component by cross-validation over ``problems`` ((positions,
    (m, 3) values, folds) each, their held-out misfits pooled), by the one-standard-error rule: the
    smoothest fit whose held-out misfit is within a standard error of the least."""
    # per component, degree: (smoothing, cv at it, least cv, its se)
    best: list[dict[int, tuple[float, float, float, float]]] = [{}, {}, {}]
    for degree in (1, 2):
        if min(len(x) - max(len(f) for f in folds) for x, _, folds in problems) < 3 * (4 if degree == 1 else 10):
            continue  # too few tracks to cross-validate this trend
        cv, se = [], []
        try:
            for lam in FIT_SMOOTHING:
                r = []
                for x, y, folds in problems:
                    for fold in folds:
                        train = np.ones(len(x), bool)
                        train[fold] = False
                        r.append(_rbf(x[train], y[train], degree, lam)(x[fold]) - y[fold])  # all three components
                r2 = np.concatenate(r) ** 2
                cv.append(np.mean(r2, axis=0))
                se.append(np.std(r2, axis=0) / np.sqrt(len(r2)))
        except np.linalg.LinAlgError:  # the tracks do not fix this trend (all near a plane, say)
            continue
        cvs, ses = np.asarray(cv), np.asarray(se)  # (smoothings, 3)
        for c in range(3):
            i0 = int(np.argmin(cvs[:, c]))
            i = int(np.nonzero(cvs[:, c] <= cvs[i0, c] + ses[i0, c])[0].max())  # the smoothest within one error
            best[c][degree] = (FIT_SMOOTHING[i], float(cvs[i, c]), float(cvs[i0, c]), float(ses[i0, c]))
    if not best[0]:
        raise np.linalg.LinAlgError("too few tracks")
    out = []
    for b in best:
        degree = 1 if 1 in b else 2
        if 2 in b and b[2][2] + b[2][3] < b[degree][2]:  # a curved trend only where clearly better
            degree = 2
        lam, cv_at, _, _ = b[degree]
        out.append(FitChoice(degree=degree, smoothing=lam, cv_rms_mm=float(np.sqrt(cv_at))))
    return out


def _blocks(x: np.ndarray, at: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The tracks (rows of ``x``) and points (rows of ``at``) of each block of a fit in blocks: the
    tracks' box cut into blocks of about :data:`FIT_BLOCK_TRACKS` tracks, each fitted to its
    tracks and those within :data:`FIT_BLOCK_MARGIN` of a block's width around it, each point
    evaluated in the block it lies in (the nearest block beyond them)."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    ext = np.maximum(hi - lo, 1e-12)
    side = (float(np.prod(ext)) * FIT_BLOCK_TRACKS / len(x)) ** (1.0 / 3.0)
    count = np.maximum(1, np.rint(ext / side)).astype(int)
    width = ext / count
    cell = np.clip(np.floor((x - lo) / width), 0, count - 1).astype(int)
    cell_at = np.clip(np.floor((at - lo) / width), 0, count - 1).astype(int)
    out = []
    for idx in np.ndindex(*count):
        core_lo = lo + np.asarray(idx) * width
        near = np.all((x >= core_lo - FIT_BLOCK_MARGIN * width) & (x <= core_lo + (1 + FIT_BLOCK_MARGIN) * width),
                      axis=1)
        points = np.nonzero(np.all(cell_at == idx, axis=1))[0]
        if near.any() and (len(points) or np.all(cell == idx, axis=1).any()):
            out.append((np.nonzero(near)[0], points))
    return out


def fit_tracks(position_mm: np.ndarray, displacement_mm: np.ndarray, centres: list[np.ndarray], *,
               reach_mm: np.ndarray, box_mm: tuple[np.ndarray, np.ndarray] | None = None, min_tracks: int = 1,
               folds: int = 5, seed: int = 0) -> tuple[np.ndarray, np.ndarray, tuple[FitChoice, ...]]:
    """A smooth field fitted to all the tracks, evaluated at the points of a grid.

    Each component of the displacement is fitted separately by a smoothing thin-plate spline
    (:class:`scipy.interpolate.RBFInterpolator`, a linear or quadratic trend plus thin-plate radial
    basis functions on the tracks) in coordinates scaled to the tracks' extent. Its smoothing, one
    of :data:`FIT_SMOOTHING`, and the trend's degree are chosen from the tracks themselves by
    ``folds``-fold cross-validation, by the one-standard-error rule: the smoothest fit whose
    held-out misfit is within one standard error of the least, and the quadratic trend only where
    its least misfit is lower than the linear one's by more than its standard error. So noisier
    tracks get a smoother field and a uniform or linear flow its trend, without a width to tune.
    Beyond :data:`FIT_GLOBAL_TRACKS` tracks the box is fitted in blocks of about
    :data:`FIT_BLOCK_TRACKS` tracks (each with a margin of its neighbours' tracks), the smoothing
    cross-validated on a few blocks and used for all: the cost grows with the tracks, not their
    cube. With fewer than 15 tracks (too few to cross-validate a linear trend) or tracks that do not
    fix one (all in one plane, say) the field is their mean displacement.

    Parameters
    ----------
    position_mm, displacement_mm
        (m, 3) each track's position (its midpoint) and displacement (x, y, z), mm.
    centres
        [x_mm, y_mm, z_mm]: the grid's points along each axis.
    reach_mm
        (3,) how far from a point (x, y, z), mm, per axis, a track counts as near it: a point is
        given a value only with at least ``min_tracks`` tracks within that box around it, so the
        field is not extrapolated far beyond the tracks.
    box_mm
        (lower, upper) corners (x, y, z) of the measured box, mm: points outside it are NaN; None:
        no limit.
    min_tracks
        Fewest tracks within ``reach_mm`` a point needs for a value.
    folds
        Cross-validation folds.
    seed
        Seed of the folds' random split (the result is reproducible).

    Returns
    -------
    field
        (z, y, x, 3) the fitted displacement, mm; NaN outside the box or away from the tracks.
    counts
        (z, y, x) tracks within ``reach_mm`` of each point.
    choice
        The :class:`FitChoice` of each component (x, y, z).
    """
    pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(displacement_mm, dtype=np.float64).reshape(-1, 3)
    reach = np.asarray(reach_mm, dtype=np.float64).reshape(3)
    zz, yy, xx = np.meshgrid(centres[2], centres[1], centres[0], indexing="ij")
    shape = xx.shape
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    counts = np.zeros(len(nodes), np.int64)
    field = np.full((len(nodes), 3), np.nan)
    if len(pos) == 0:
        return field.reshape(*shape, 3), counts.reshape(shape), tuple(FitChoice(0, 0.0, np.nan) for _ in range(3))
    counts[:] = [len(n) for n in cKDTree(pos / reach).query_ball_point(nodes / reach, r=1.0, p=np.inf)]
    use = counts >= max(1, min_tracks)
    if box_mm is not None:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box_mm)
        use &= np.all((nodes >= lo) & (nodes <= hi), axis=1)
    scale = float(np.max(np.ptp(pos, axis=0)))
    x = (pos - pos.mean(axis=0)) / (scale if scale > 0 else 1.0)
    at = (nodes[use] - pos.mean(axis=0)) / (scale if scale > 0 else 1.0)
    rng = np.random.default_rng(seed)
    if len(pos) > FIT_GLOBAL_TRACKS:
        blocks = _blocks(x, at)
        sample = [blocks[i] for i in sorted(rng.choice(len(blocks), size=min(FIT_CV_BLOCKS, len(blocks)),
                                                       replace=False))]
    else:
        blocks = [(np.arange(len(x)), np.arange(len(at)))]
        sample = blocks
    splits = [[f for f in np.array_split(rng.permutation(len(rows)), folds) if len(f)] for rows, _ in sample]
    values = np.full((len(at), 3), np.nan)
    try:
        if len(pos) < 15 or scale <= 0:
            raise np.linalg.LinAlgError("too few tracks")
        choice = _choose_fit([(x[rows], d[rows], s) for (rows, _), s in zip(sample, splits, strict=True)])
        for c, ch in enumerate(choice):
            for rows, points in blocks:
                if len(points):
                    values[points, c] = _rbf(x[rows], d[rows, c], ch.degree, ch.smoothing)(at[points])
    except np.linalg.LinAlgError:  # too few tracks, or all in a plane or on a line: no trend to fit
        choice = [FitChoice(0, 0.0, np.nan) for _ in range(3)]
        values[:] = np.mean(d, axis=0)
    field[use] = values
    return field.reshape(*shape, 3), counts.reshape(shape), tuple(choice)  # type: ignore[return-value]


def predict_at(predictor: Predictor, grid: VolumeGrid, at_mm: np.ndarray) -> np.ndarray:
    """A predictor's displacement at world points, mm: trilinear between its points, the nearest
    point's beyond them.

    Parameters
    ----------
    predictor
        Displacements (x, y, z) in voxels of ``grid`` at points given in its voxel coordinates.
    grid
        The voxel grid the predictor's coordinates and displacements refer to.
    at_mm
        (n, 3) world points (x, y, z), mm.

    Returns
    -------
    numpy.ndarray
        (n, 3) displacements (x, y, z), mm.
    """
    from scipy.ndimage import map_coordinates

    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    at = np.asarray(at_mm, dtype=np.float64).reshape(-1, 3)
    vox = (at - np.asarray(grid.origin_mm)) / voxel  # voxel coordinates (x, y, z)
    idx = (vox - np.asarray(predictor.origin)) / np.asarray(predictor.step)  # the predictor's index (x, y, z)
    coords = idx[:, ::-1].T  # (z, y, x) rows for map_coordinates
    d = predictor.displacement.astype(np.float64)
    out = np.column_stack([map_coordinates(d[..., c], coords, order=1, mode="nearest") for c in range(3)])
    return out * voxel


def field_predictor(result: TrackResult, grid: VolumeGrid) -> Predictor | None:
    """A pair's tracked field as a :class:`~lfcore.warm.Predictor` (e.g. for the next pair of a
    time-resolved run): its bins' values in voxels, the empty bins set to the median of the others;
    None where every bin is empty."""
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    d = result.field_mm / voxel
    bad = ~np.all(np.isfinite(d), axis=-1)
    if bad.all():
        return None
    d[bad] = np.median(d[~bad], axis=0)
    centres = [result.x_mm, result.y_mm, result.z_mm]
    origin = [(c[0] - o) / v for c, o, v in zip(centres, grid.origin_mm, voxel, strict=True)]
    step = [(c[1] - c[0]) / v if len(c) > 1 else 1.0 for c, v in zip(centres, voxel, strict=True)]
    return Predictor(d.astype(np.float32), tuple(origin), tuple(step))  # type: ignore[arg-type]


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


def track_pair(a_mm: np.ndarray, b_mm: np.ndarray, grid: VolumeGrid, *, settings: TrackSettings | None = None,
               predictor: Predictor | None = None) -> TrackResult:
    """Track a pair's particles (see the module docstring).

    Parameters
    ----------
    a_mm, b_mm
        (n, 3) and (k, 3) world positions (x, y, z) of frame A's and frame B's particles, mm.
    grid
        The voxel grid: the scale of the searches and the bins.
    settings
        Searches, passes, bins, the outlier test and the field.
    predictor
        The first pass's predicted displacement, in voxels of ``grid`` (e.g.
        :func:`lfcore.warm.predictor_field` of the pair's volumes, or :func:`field_predictor` of the
        previous pair); None: zero.

    Returns
    -------
    TrackResult
    """
    s = settings or TrackSettings()
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    fit = None
    predicted = np.zeros_like(a) if predictor is None or not len(a) else predict_at(predictor, grid, a)
    radius = np.asarray(s.search_voxels) * voxel
    for done in range(s.passes):
        ia, ib = pair_nearest(a, b, predicted, radius)
        disp = b[ib] - a[ia]
        mid = a[ia] + 0.5 * disp
        out = reject_outliers(mid, disp, neighbours=s.neighbours, threshold=s.outlier_threshold,
                              epsilon_mm=s.epsilon_voxels * voxel)
        last = done + 1 == s.passes
        centres, field, counts = bin_tracks(mid[~out], disp[~out], grid, bin_voxels=s.bin_voxels,
                                            statistic="mean" if last else "median", min_tracks=s.min_tracks)
        if last and s.field == "smooth":
            field, counts = smooth_tracks(mid[~out], disp[~out], centres, sigma_mm=np.asarray(s.sigma_voxels) * voxel,
                                          min_tracks=s.min_tracks)
        elif last and s.field == "fit":
            lo = np.asarray(grid.origin_mm, dtype=np.float64) - 0.5 * voxel
            box = (lo, lo + np.asarray(grid.shape[::-1], dtype=np.float64) * voxel)
            kept = mid[~out]
            # a centre's value rests on the tracks within a bin's width, or their mean spacing where wider
            spacing = float(np.prod(np.ptp(kept, axis=0)) / max(len(kept), 1)) ** (1.0 / 3.0) if len(kept) else 0.0
            reach = np.maximum(np.asarray(s.bin_voxels) * voxel, spacing)
            field, counts, fit = fit_tracks(kept, disp[~out], centres, reach_mm=reach, box_mm=box,
                                            min_tracks=s.min_tracks)
        if not last:
            predicted = _predict(field, centres, a)
            radius = np.asarray(s.refine_voxels) * voxel
    return TrackResult(a_index=ia, b_index=ib, displacement_mm=disp, outlier=out, x_mm=centres[0], y_mm=centres[1],
                       z_mm=centres[2], field_mm=field, counts=counts, fit=fit)
