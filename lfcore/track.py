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
3. **Pass 2 on**: the predictor at each A particle is a linear fit (a displacement and its gradient,
   by least squares) through the pass before's :attr:`TrackSettings.neighbours` tracks nearest it
   (the tracks kept by the outlier test), and the search shrinks around it to
   :attr:`TrackSettings.refine_voxels`, or, per axis, to 4 times the tracks' own robust scatter about
   the predictor (each track predicted from its neighbours without it) where that is wider, at most
   the first pass's search: where the particles are sparse against the flow's gradients a median
   of the neighbours misses by a voxel, and where the positions are less sure than the search
   the right partners fall outside it.
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
   tracks within a bin's width of them along every axis (or the tracks' mean spacing, where wider);
   or ``"divfree"``, as ``"fit"`` but the three components fitted together by a matrix-valued kernel
   whose fields are free of divergence (Narcowich and Ward 1994), an incompressible flow's, with a
   weighted compressible part: the weight and the smoothing chosen by cross-validation, and
   ``"fit"``'s field where the held-out tracks say it is better (``fit_tracks(divergence_free=True)``).

Along a time-resolved series (frames evenly spaced in time), the particles of every frame are
linked into tracks through the frames instead (:func:`link_series`: each track carried on by its own
velocity, started by :func:`track_pair`), each track fitted by local polynomials in time
(:func:`fit_series`, Shake-the-Box's second-order fit), and each pair's tracks are the fitted
positions at its two frames (:func:`pair_tracks`), made into a field as above (:func:`field_of_tracks`),
or, where the flow's pattern is carried along from pair to pair, with the neighbouring pairs' tracks
moved by its translation estimated from the tracks, where the pair's own held-out tracks say they
help (:func:`pooled_field_of_tracks`, :func:`pattern_shift`).

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

__all__ = ["DIVFREE_BLOCK_TRACKS", "DIVFREE_GLOBAL_TRACKS", "DIVFREE_SMOOTHING", "DIVFREE_WEIGHTS", "FIELDS",
           "FIT_BLOCK_MARGIN", "FIT_BLOCK_TRACKS", "FIT_CV_BLOCKS", "FIT_GLOBAL_TRACKS", "FIT_SMOOTHING",
           "MAX_CROWDING", "POOL_FOLDS", "FitChoice", "PoolChoice", "SeriesSettings",
           "SeriesTracks", "TrackResult", "TrackSettings", "bin_tracks", "field_of_tracks", "field_predictor",
           "fit_series", "fit_tracks", "link_series", "pair_nearest", "pair_tracks", "pattern_shift",
           "pooled_field_of_tracks", "predict_at", "predict_series", "reject_outliers", "search_crowding",
           "smooth_tracks", "track_pair"]

#: How the field is made from the tracks (:attr:`TrackSettings.field`).
FIELDS = ("bins", "smooth", "fit", "divfree")
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
#: The weights of the compressible (curl-free) part of the ``divfree`` field's kernel that
#: :func:`fit_tracks` chooses among (``divergence_free=True``): 0, a field exactly free of divergence;
#: 1, no preference (each component a biharmonic spline, one smoothing for all three).
DIVFREE_WEIGHTS = (0.0, 0.01, 0.1, 1.0)
#: The smoothing parameters of the ``divfree`` field (coordinates scaled to the tracks' extent).
DIVFREE_SMOOTHING = tuple(float(v) for v in np.logspace(-6.0, 3.0, 19))
#: Beyond this many tracks the ``divfree`` field is fitted in blocks (its systems are three times a
#: component's of the ``fit`` field, and their cost grows with the cube).
DIVFREE_GLOBAL_TRACKS = 500
#: About how many tracks a block of a ``divfree`` fit in blocks holds.
DIVFREE_BLOCK_TRACKS = 100
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
        The later passes' least search radius around the predictor (x, y, z), voxels: per axis
        widened to 4 times the pass before's tracks' robust scatter about the predictor where that
        is wider (at most :attr:`search_voxels`).
    passes
        Pairing passes (the first without a predictor).
    bin_voxels
        The field's bins (x, y, z), voxels.
    min_tracks
        Fewest tracks a bin needs for a vector.
    neighbours
        Tracks the outlier test compares each track with, and the later passes' predictor fits a
        linear displacement through around each particle.
    outlier_threshold
        The normalized median test's threshold.
    epsilon_voxels
        The test's noise floor, voxels.
    field
        How the field is made from the tracks: ``"fit"`` (the default: a smoothing spline through all
        the tracks, its smoothing chosen by cross-validation, :func:`fit_tracks`; on one camera's A1
        pair 0.079, 0.015, 0.041 voxel RMS and on a uniform flow 0.015, 0.033, 0.013, where
        ``"smooth"`` gives 0.097, 0.049, 0.112 and 0.066, 0.078, 0.129, benchmarks/RESULTS.md),
        ``"divfree"`` (as ``"fit"``, but the three components together by a kernel free of
        divergence where the cross-validation finds it better: an incompressible flow; on the demo's
        vortex ring along 5 time-resolved pairs 8.9% of the peak speed against ``"fit"``'s 11.7%,
        from the noise-free true tracks 5.2% against 6.8%; A1 unchanged, benchmarks/RESULTS.md),
        ``"smooth"`` (a
        Gaussian-weighted average around each bin's centre) or ``"bins"`` (each bin's mean); see the
        module docstring.
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
            if len(v) != 3 or not all(0 < x < np.inf for x in v):  # NaN too
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
        ``field="fit"`` or ``"divfree"``: the trend and smoothing chosen for each component (x, y,
        z; with :attr:`FitChoice.weight` where the divergence-free kernel was chosen); else None.
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
    weight
        ``fit_tracks(divergence_free=True)`` where it fitted the three components together by the
        matrix kernel: the weight of the kernel's compressible part, one of :data:`DIVFREE_WEIGHTS`
        (0: exactly free of divergence), ``smoothing`` one of :data:`DIVFREE_SMOOTHING` and
        ``degree`` 1; None where each component was fitted on its own.
    """

    degree: int
    smoothing: float
    cv_rms_mm: float
    weight: float | None = None


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


def _held_out(problems):
    """Each cross-validation fold of each problem ``(x, y, folds)``: its training positions and values,
    then its held-out positions and values."""
    for x, y, folds in problems:
        for fold in folds:
            train = np.ones(len(x), bool)
            train[fold] = False
            yield x[train], y[train], x[fold], y[fold]


def _rbf(x: np.ndarray, y: np.ndarray, degree: int, smoothing: float) -> RBFInterpolator:
    from scipy.interpolate import RBFInterpolator

    # A smoothing thin-plate spline: minimises the misfit plus smoothing x the bending energy,
    # with a polynomial trend of the given degree left unpenalised.
    return RBFInterpolator(x, y, kernel="thin_plate_spline", degree=degree, smoothing=smoothing)


def _choose_fit(problems: list[tuple[np.ndarray, np.ndarray, list[np.ndarray]]],
                at_choice: list[np.ndarray] | None = None) -> list[FitChoice]:
    """The trend and smoothing of each component by cross-validation over ``problems`` ((positions,
    (m, 3) values, folds) each, their held-out misfits pooled), by the one-standard-error rule: the
    smoothest fit whose held-out misfit is within a standard error of the least. The held-out
    tracks' squared misfits at the choice, (k, 3) in the order of the problems and their folds, are
    appended to ``at_choice`` where given."""
    # per component, degree: (smoothing, cv at it, least cv, its se, the smoothing's index)
    best: list[dict[int, tuple[float, float, float, float, int]]] = [{}, {}, {}]
    held: dict[int, list[np.ndarray]] = {}  # per degree, each smoothing's (k, 3) squared misfits
    for degree in (1, 2):
        if min(len(x) - max(len(f) for f in folds) for x, _, folds in problems) < 3 * (4 if degree == 1 else 10):
            continue  # too few tracks to cross-validate this trend
        cv, se = [], []
        try:
            for lam in FIT_SMOOTHING:
                # all three components
                r = [_rbf(xt, yt, degree, lam)(xf) - yf for xt, yt, xf, yf in _held_out(problems)]
                r2 = np.concatenate(r) ** 2
                cv.append(np.mean(r2, axis=0))
                se.append(np.std(r2, axis=0) / np.sqrt(len(r2)))
                held.setdefault(degree, []).append(r2)
        except np.linalg.LinAlgError:  # the tracks do not fix this trend (all near a plane, say)
            continue
        cvs, ses = np.asarray(cv), np.asarray(se)  # (smoothings, 3)
        for c in range(3):
            i0 = int(np.argmin(cvs[:, c]))
            i = int(np.nonzero(cvs[:, c] <= cvs[i0, c] + ses[i0, c])[0].max())  # the smoothest within one error
            best[c][degree] = (FIT_SMOOTHING[i], float(cvs[i, c]), float(cvs[i0, c]), float(ses[i0, c]), i)
    if not best[0]:
        raise np.linalg.LinAlgError("too few tracks")
    out = []
    for b in best:
        degree = 1 if 1 in b else 2
        if 2 in b and b[2][2] + b[2][3] < b[degree][2]:  # a curved trend only where clearly better
            degree = 2
        lam, cv_at, _, _, i = b[degree]
        out.append(FitChoice(degree=degree, smoothing=lam, cv_rms_mm=float(np.sqrt(cv_at))))
        if at_choice is not None:
            at_choice.append(held[degree][i][:, len(out) - 1])
    if at_choice is not None:
        at_choice[:] = [np.column_stack(at_choice)]
    return out


# --- the divergence-free field: matrix-valued radial basis functions (Narcowich and Ward 1994) ----

def _df_kernel(x: np.ndarray, y: np.ndarray, weight: float) -> np.ndarray:
    """The (3m, 3n) matrix kernel between points ``x`` (m, 3) and ``y`` (n, 3), rows and columns
    (point, component): the divergence-free kernel (grad grad^T - I laplacian) phi plus ``weight``
    times the curl-free one (-grad grad^T phi), phi = -r^4 log(r) / 4, whose generalized Fourier
    transform is positive (|omega|^-7): with r = x - y, the sum is
    -(1 - weight) (2 log|r| + 3/2) r r^T + |r|^2 (4 log|r| + 2 + weight (log|r| + 1/4)) I. Each column
    of its divergence-free part has no divergence; weight 1 is the polyharmonic spline
    -laplacian(phi) = |r|^2 (5 log|r| + 9/4) of each component on its own (the thin-plate spline's
    r^2 log r, the ``fit`` field's kernel, up to a term that the linear trend cancels)."""
    r = x[:, None, :] - y[None, :, :]
    d2 = np.sum(r * r, axis=-1)
    log_r = 0.5 * np.log(np.where(d2 > 0, d2, 1.0))  # r^2 log r and r r^T log r vanish at r = 0
    outer = r[..., :, None] * r[..., None, :]
    k = (-(1.0 - weight) * (2.0 * log_r + 1.5))[..., None, None] * outer + (
        d2 * (4.0 * log_r + 2.0 + weight * (log_r + 0.25)))[..., None, None] * np.eye(3)
    return k.transpose(0, 2, 1, 3).reshape(3 * len(x), 3 * len(y))


def _df_trend(x: np.ndarray, weight: float) -> np.ndarray:
    """The (3n, q) linear trend's basis at points ``x`` (n, 3), rows (point, component): the
    constants and the linear fields, without divergence (traceless gradient, q = 11) where
    ``weight`` is 0, any (q = 12) otherwise."""
    n = len(x)
    cols = []
    for a in range(3):
        col = np.zeros((n, 3))
        col[:, a] = 1.0
        cols.append(col)
    for a in range(3):
        for b in range(3):
            if a != b:
                col = np.zeros((n, 3))
                col[:, a] = x[:, b]
                cols.append(col)
    if weight > 0:
        for a in range(3):
            col = np.zeros((n, 3))
            col[:, a] = x[:, a]
            cols.append(col)
    else:  # u = x - y and v = y - z: stretching without divergence
        for a in range(2):
            col = np.zeros((n, 3))
            col[:, a], col[:, a + 1] = x[:, a], -x[:, a + 1]
            cols.append(col)
    return np.stack(cols, axis=-1).reshape(3 * n, len(cols))


class _DivFree:
    """The smoothing fit of the matrix kernel (:func:`_df_kernel`) plus its trend to the tracks at
    ``x`` (n, 3), for any smoothing at once: it minimises the misfit plus smoothing x the kernel's
    energy, c^T K c, with the trend unpenalised, i.e. (K + smoothing I) c + P b = d, P^T c = 0.
    With P = [Q1 Q2] R and c = Q2 g, g solves the eigensystem of Q2^T K Q2 for every smoothing
    (cross-validation), or, where ``smoothing`` is given, the Cholesky factors of Q2^T K Q2 +
    smoothing I for that one (a few times faster)."""

    def __init__(self, x: np.ndarray, weight: float, smoothing: float | None = None) -> None:
        from scipy.linalg import cho_factor, eigh, qr

        self.x, self.weight = x, weight
        self.k = _df_kernel(x, x, weight)
        p = _df_trend(x, weight)
        q, r = qr(p)
        if np.min(np.abs(np.diag(r))) < 1e-9 * np.max(np.abs(np.diag(r))):
            raise np.linalg.LinAlgError("the tracks do not fix the trend")
        self.q1, self.r1 = q[:, :p.shape[1]], r[:p.shape[1]]
        self.q2, self.smoothing = q[:, p.shape[1]:], smoothing
        m = self.q2.T @ self.k @ self.q2
        if smoothing is None:
            eig, v = eigh(m, driver="evd")
            self.eig = np.maximum(eig, 0.0)  # the kernel is positive on fields the trend leaves out
            self.basis = self.q2 @ v
        else:
            self.cho = cho_factor(m + smoothing * np.eye(len(m)))

    def coefficients(self, d: np.ndarray, smoothing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kernel's (s, 3n) and the trend's (s, q) coefficients of (n, 3) values ``d`` for each
        of the (s,) ``smoothing`` values (the one given at construction, where one was)."""
        from scipy.linalg import cho_solve, solve_triangular

        flat = d.reshape(-1)
        if self.smoothing is not None:
            smoothing = np.array([self.smoothing])
            c = (self.q2 @ cho_solve(self.cho, self.q2.T @ flat))[None, :]
        else:
            g = (self.basis.T @ flat)[None, :] / (self.eig[None, :] + smoothing[:, None])
            c = g @ self.basis.T
        rest = flat[None, :] - c @ self.k - smoothing[:, None] * c  # what the trend explains
        b = solve_triangular(self.r1, self.q1.T @ rest.T).T
        return c, b

    def __call__(self, at: np.ndarray, c: np.ndarray, b: np.ndarray, *, chunk: int = 2000) -> np.ndarray:
        """The fields of coefficients ``c``, ``b`` (s of each) at points ``at`` (m, 3): (s, m, 3)."""
        out = np.empty((len(c), len(at), 3))
        chunk = max(1, min(chunk, 200_000 // max(len(self.x), 1)))  # the kernel's (chunk, n, 3, 3) in memory
        for lo in range(0, len(at), chunk):
            pts = at[lo:lo + chunk]
            v = c @ _df_kernel(pts, self.x, self.weight).T + b @ _df_trend(pts, self.weight).T
            out[:, lo:lo + chunk] = v.reshape(len(c), len(pts), 3)
        return out


@dataclass(frozen=True)
class _DivFreeChoice:
    weight: float
    smoothing: float
    cv_mse: np.ndarray  # (3,) the held-out mean squared misfit of each component at the choice


def _choose_divfree(problems: list[tuple[np.ndarray, np.ndarray, list[np.ndarray]]]
                    ) -> list[tuple[np.ndarray, _DivFreeChoice]]:
    """The smoothing of each weight of the kernel's compressible part by cross-validation over
    ``problems`` ((positions, (m, 3) values, folds) each, the held-out misfits pooled over the three
    components): the smoothest fit whose held-out misfit is within a standard error of its least.
    Returns each weight's held-out tracks' squared misfits at its choice ((k,), the components
    summed, in the order of the problems and their folds) and the choice, in the order of
    :data:`DIVFREE_WEIGHTS`."""
    lams = np.asarray(DIVFREE_SMOOTHING)
    if min(len(x) - max(len(f) for f in folds) for x, _, folds in problems) < 12:
        raise np.linalg.LinAlgError("too few tracks")
    per_weight = []
    for weight in DIVFREE_WEIGHTS:
        r = []
        for xt, yt, xf, yf in _held_out(problems):
            fit = _DivFree(xt, weight)
            r.append(fit(xf, *fit.coefficients(yt, lams)) - yf[None])  # (s, m, 3)
        r2 = np.concatenate(r, axis=1) ** 2
        cv = np.mean(np.sum(r2, axis=2), axis=1)
        se = np.std(np.sum(r2, axis=2), axis=1) / np.sqrt(r2.shape[1])
        i0 = int(np.argmin(cv))
        i = int(np.nonzero(cv <= cv[i0] + se[i0])[0].max())  # the smoothest within one error
        per_weight.append((np.sum(r2[i], axis=1), _DivFreeChoice(weight, float(lams[i]), np.mean(r2[i], axis=0))))
    return per_weight


def _divfree_instead(problems: list[tuple[np.ndarray, np.ndarray, list[np.ndarray]]],
                     apart: np.ndarray) -> _DivFreeChoice | None:
    """The one-standard-error rule over the models, each at its own chosen smoothing, from the most
    constrained to the least: the matrix kernel at each weight of its compressible part
    (:func:`_choose_divfree`; weight 0, free of divergence, first), then the components fitted
    apart (``apart``: the held-out tracks' (k, 3) squared misfits at their choice, from
    :func:`_choose_fit` on the same folds). The first whose held-out misfit, pooled over the
    components, exceeds the least of all by at most the standard error of their difference (the
    same held-out tracks, paired: the tracks' own noise, common to both, cancels); None where that
    is the components apart, or too few tracks fix the kernel."""
    try:
        models: list[tuple[np.ndarray, _DivFreeChoice | None]] = list(_choose_divfree(problems))
    except np.linalg.LinAlgError:
        return None
    models.append((np.sum(apart, axis=1), None))
    best = min(models, key=lambda m: float(np.mean(m[0])))[0]
    for r2, ch in models:
        diff = r2 - best
        if np.mean(diff) <= np.std(diff) / np.sqrt(len(diff)):
            return ch
    return None


def _blocks(x: np.ndarray, at: np.ndarray, per_block: int = FIT_BLOCK_TRACKS) -> list[tuple[np.ndarray, np.ndarray]]:
    """The tracks (rows of ``x``) and points (rows of ``at``) of each block of a fit in blocks: the
    tracks' box cut into blocks of about ``per_block`` tracks, each fitted to its
    tracks and those within :data:`FIT_BLOCK_MARGIN` of a block's width around it, each point
    evaluated in the block it lies in (the nearest block beyond them)."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    ext = np.maximum(hi - lo, 1e-12)
    side = (float(np.prod(ext)) * per_block / len(x)) ** (1.0 / 3.0)
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
               folds: int = 5, seed: int = 0, divergence_free: bool = False, support_mm: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, tuple[FitChoice, ...]]:
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

    With ``divergence_free``, the three components are also fitted together by a matrix-valued
    radial basis function (Narcowich and Ward 1994; :func:`_df_kernel`): the divergence-free kernel
    (grad grad^T - I laplacian) phi of phi = -r^4 log r, whose every field is free of divergence,
    plus a weight (:data:`DIVFREE_WEIGHTS`) times the curl-free kernel -grad grad^T phi, and a linear
    trend (without divergence at weight 0). That is a smoothing fit whose roughness penalty charges
    the field's compressible part 1 / weight times its incompressible part: weight 0 an exactly
    incompressible field, weight 1 no preference. Each weight's smoothing (:data:`DIVFREE_SMOOTHING`)
    is cross-validated on the same folds as the components apart, and the one-standard-error rule
    chooses among the models, from the most constrained: weight 0, the larger weights, then the
    components apart; each model at its own chosen smoothing, the held-out misfits pooled over the
    components. So an incompressible flow's tracks get a field free of divergence, and a
    compressible flow's (Table 4.1's A1, u = 5 cos(kx)) the components apart, unchanged (cross-
    validated, beyond :data:`DIVFREE_GLOBAL_TRACKS` tracks, on the blocks of the matrix kernel). Beyond
    :data:`DIVFREE_GLOBAL_TRACKS` tracks the matrix kernel is fitted in blocks of about
    :data:`DIVFREE_BLOCK_TRACKS` tracks (its systems are three times a component's).

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
    divergence_free
        Also fit the three components together by the divergence-free kernel, and keep that fit
        where the cross-validation prefers it (above; ``TrackSettings(field="divfree")``).
    support_mm
        (k, 3) the positions whose nearness decides where the field has a value (``reach_mm``,
        ``min_tracks``; ``counts``); None: ``position_mm``. Tracks pooled from other pairs
        (:func:`pooled_field_of_tracks`) are fitted but leave the field where the pair's own tracks put it.

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
    support = pos if support_mm is None else np.asarray(support_mm, dtype=np.float64).reshape(-1, 3)
    if len(support):
        counts[:] = [len(n) for n in cKDTree(support / reach).query_ball_point(nodes / reach, r=1.0, p=np.inf)]
    use = counts >= max(1, min_tracks)
    if box_mm is not None:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box_mm)
        use &= np.all((nodes >= lo) & (nodes <= hi), axis=1)
    scale = float(np.max(np.ptp(pos, axis=0)))
    x = (pos - pos.mean(axis=0)) / (scale if scale > 0 else 1.0)
    at = (nodes[use] - pos.mean(axis=0)) / (scale if scale > 0 else 1.0)
    rng = np.random.default_rng(seed)
    if len(pos) > (DIVFREE_GLOBAL_TRACKS if divergence_free else FIT_GLOBAL_TRACKS):
        blocks = _blocks(x, at, DIVFREE_BLOCK_TRACKS if divergence_free else FIT_BLOCK_TRACKS)
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
        problems = [(x[rows], d[rows], s) for (rows, _), s in zip(sample, splits, strict=True)]
        at_choice: list[np.ndarray] = []
        choice = _choose_fit(problems, at_choice)
        df = None
        if divergence_free:
            from threadpoolctl import threadpool_limits

            # the kernel's systems (a few hundred to a thousand rows) gain little from BLAS threads, and
            # where the cores are shared the threads' waiting made them 10-20 times slower (a 2-core VM)
            limits = threadpool_limits(limits=1, user_api="blas")
            try:
                df = _divfree_instead(problems, at_choice[0])
                if df is not None:  # the three components together, by the matrix kernel
                    choice = [FitChoice(degree=1, smoothing=df.smoothing, cv_rms_mm=float(np.sqrt(m)),
                                        weight=df.weight) for m in df.cv_mse]
                    for rows, points in blocks:
                        if len(points):
                            fit = _DivFree(x[rows], df.weight, df.smoothing)
                            values[points] = fit(at[points], *fit.coefficients(d[rows], np.array([df.smoothing])))[0]
            finally:
                limits.restore_original_limits()
        if df is None and divergence_free and len(pos) > DIVFREE_GLOBAL_TRACKS:
            # the components apart chosen on the kernel's smaller blocks: fit them exactly as fit does
            # (its own blocks, its own cross-validation on them)
            return fit_tracks(pos, d, centres, reach_mm=reach, box_mm=box_mm, min_tracks=min_tracks, folds=folds,
                              seed=seed, support_mm=support_mm)
        if df is None:
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


#: The fewest tracks a later pass's linear predictor (:func:`_predict`) fits through; with fewer, their median.
LINEAR_PREDICTOR_TRACKS = 5


def _local_linear(mid: np.ndarray, disp: np.ndarray, idx: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Per point of ``at`` (n, 3), the value at it of the least-squares linear fit d = c + G (x - at)
    through the tracks ``idx`` (n, k) (midpoints ``mid``, displacements ``disp``): (n, 3). The offsets
    are scaled per axis by their RMS and the gradient lightly damped, so that neighbours nearly in a
    plane or a line give their mean's trend along it and no gradient across it."""
    x = mid[idx] - at[:, None, :]  # (n, k, 3)
    scale = np.sqrt(np.mean(x * x, axis=1))  # (n, 3)
    x = x / np.where(scale > 0, scale, 1.0)[:, None, :]
    design = np.concatenate([np.ones(x.shape[:2] + (1,)), x], axis=2)  # (n, k, 4)
    normal = np.einsum("nki,nkj->nij", design, design)
    k = idx.shape[1]
    normal[:, 1:, 1:] += 1e-6 * k * np.eye(3)  # a light ridge on the gradient only
    rhs = np.einsum("nki,nkc->nic", design, disp[idx])
    return np.linalg.solve(normal, rhs)[:, 0, :]


def _predict(mid_mm: np.ndarray, disp_mm: np.ndarray, at_mm: np.ndarray, *, neighbours: int,
             leave_out: bool = False) -> np.ndarray:
    """The displacement the tracks of a pass predict at points: the linear fit (a displacement and its
    gradient, least squares) through the ``neighbours`` tracks whose midpoints lie nearest each
    point, or, with fewer than :data:`LINEAR_PREDICTOR_TRACKS` tracks, their median per component
    (zero without tracks). The tracks themselves rather than a grid's bins: where a bin holds fewer
    tracks than a median needs (most bins, when the particles are sparse against the bins), a flow
    that varies across the box is still predicted where it is; and a fit rather than their median,
    which misses by the flow's gradient times the neighbours' lopsided reach (on issue 48's 512 x 512
    rig, A1 at 0.5 PPM: a voxel RMS along x, where the fit misses by 0.35). ``leave_out``: the points
    are the tracks' own midpoints, each predicted without itself (the predictor's own error)."""
    at = np.asarray(at_mm, dtype=np.float64).reshape(-1, 3)
    mid = np.asarray(mid_mm, dtype=np.float64).reshape(-1, 3)
    disp = np.asarray(disp_mm, dtype=np.float64).reshape(-1, 3)
    have = len(mid) - (1 if leave_out else 0)
    if have < 1 or not len(at):
        return np.zeros_like(at)
    k = min(neighbours, have)
    _, idx = cKDTree(mid).query(at, k=k + (1 if leave_out else 0))
    idx = np.asarray(idx).reshape(len(at), -1)
    if leave_out:  # drop each point's own track (or, where a tie hides it, the farthest)
        own = idx == np.arange(len(at))[:, None]
        idx = np.take_along_axis(idx, np.argsort(own, axis=1, kind="stable"), axis=1)[:, :k]
    if k < LINEAR_PREDICTOR_TRACKS:
        return np.median(disp[idx], axis=1)
    return _local_linear(mid, disp, idx, at)


def _search_radius(mid_mm: np.ndarray, disp_mm: np.ndarray, *, neighbours: int, least_mm: np.ndarray,
                   most_mm: np.ndarray) -> np.ndarray:
    """A later pass's search radius (x, y, z), mm: 4 times the tracks' robust scatter (1.4826 times
    the median absolute deviation) about :func:`_predict` of each from its neighbours without it,
    per axis at least ``least_mm`` and at most ``most_mm`` (``least_mm`` alone with too few tracks)."""
    least = np.asarray(least_mm, dtype=np.float64)
    if len(mid_mm) <= max(neighbours, LINEAR_PREDICTOR_TRACKS):
        return least
    err = np.asarray(disp_mm, dtype=np.float64) - _predict(mid_mm, disp_mm, mid_mm, neighbours=neighbours,
                                                           leave_out=True)
    scatter = 1.4826 * np.median(np.abs(err - np.median(err, axis=0)), axis=0)
    return np.clip(4.0 * scatter, least, np.maximum(least, np.asarray(most_mm, dtype=np.float64)))


def track_pair(a_mm: np.ndarray, b_mm: np.ndarray, grid: VolumeGrid, *, settings: TrackSettings | None = None,
               predictor: Predictor | None = None, keep_wide: bool = False) -> TrackResult:
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
    keep_wide
        After the last of two passes or more, pair the particles it left unpaired on both sides as the
        first pass does (within :attr:`TrackSettings.search_voxels`), around the last pass's
        predictor, and judge them by the outlier test with the rest: a particle much faster than its
        neighbours (a vortex core, narrower than the neighbours the predictor fits) lies outside the
        later passes' narrow search around their prediction.

    Returns
    -------
    TrackResult
    """
    s = settings or TrackSettings()
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    predicted = np.zeros_like(a) if predictor is None or not len(a) else predict_at(predictor, grid, a)
    radius = np.asarray(s.search_voxels) * voxel
    for done in range(s.passes):
        ia, ib = pair_nearest(a, b, predicted, radius)
        if keep_wide and done and done + 1 == s.passes:
            left_a = np.setdiff1d(np.arange(len(a)), ia)
            left_b = np.setdiff1d(np.arange(len(b)), ib)
            ja, jb = pair_nearest(a[left_a], b[left_b], predicted[left_a], np.asarray(s.search_voxels) * voxel)
            ia, ib = np.r_[ia, left_a[ja]], np.r_[ib, left_b[jb]]
        disp = b[ib] - a[ia]
        mid = a[ia] + 0.5 * disp
        out = reject_outliers(mid, disp, neighbours=s.neighbours, threshold=s.outlier_threshold,
                              epsilon_mm=s.epsilon_voxels * voxel)
        if done + 1 < s.passes:
            predicted = _predict(mid[~out], disp[~out], a, neighbours=s.neighbours)
            radius = _search_radius(mid[~out], disp[~out], neighbours=s.neighbours,
                                    least_mm=np.asarray(s.refine_voxels) * voxel,
                                    most_mm=np.asarray(s.search_voxels) * voxel)
    centres, field, counts, fit = _field(mid[~out], disp[~out], grid, s)
    return TrackResult(a_index=ia, b_index=ib, displacement_mm=disp, outlier=out, x_mm=centres[0], y_mm=centres[1],
                       z_mm=centres[2], field_mm=field, counts=counts, fit=fit)


def _field(mid: np.ndarray, disp: np.ndarray, grid: VolumeGrid, s: TrackSettings,
           extra: tuple[np.ndarray, np.ndarray] | None = None
           ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, tuple[FitChoice, FitChoice, FitChoice] | None]:
    """``s.field``'s field of the kept tracks (midpoints and displacements, mm) on the grid of bins;
    ``extra`` (midpoints, displacements): tracks pooled from other pairs, fitted with them (``"fit"``
    and ``"divfree"`` only) but leaving the field's points where the kept tracks put them."""
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    fit = None
    centres, field, counts = bin_tracks(mid, disp, grid, bin_voxels=s.bin_voxels, statistic="mean",
                                        min_tracks=s.min_tracks)
    if s.field == "smooth":
        field, counts = smooth_tracks(mid, disp, centres, sigma_mm=np.asarray(s.sigma_voxels) * voxel,
                                      min_tracks=s.min_tracks)
    elif s.field in ("fit", "divfree"):
        lo = np.asarray(grid.origin_mm, dtype=np.float64) - 0.5 * voxel
        box = (lo, lo + np.asarray(grid.shape[::-1], dtype=np.float64) * voxel)
        # a centre's value rests on the tracks within a bin's width, or their mean spacing where wider
        spacing = float(np.prod(np.ptp(mid, axis=0)) / max(len(mid), 1)) ** (1.0 / 3.0) if len(mid) else 0.0
        reach = np.maximum(np.asarray(s.bin_voxels) * voxel, spacing)
        pos, d = (mid, disp) if extra is None else (np.concatenate([mid, extra[0]]), np.concatenate([disp, extra[1]]))
        field, counts, fit = fit_tracks(pos, d, centres, reach_mm=reach, box_mm=box, min_tracks=s.min_tracks,
                                        divergence_free=s.field == "divfree", support_mm=mid)
    return centres, field, counts, fit  # type: ignore[return-value]


def field_of_tracks(a_mm: np.ndarray, b_mm: np.ndarray, grid: VolumeGrid, *, settings: TrackSettings | None = None
                    ) -> TrackResult:
    """The field of tracks already paired (e.g. a time-resolved series' tracks at one pair,
    :func:`pair_tracks`): the outlier test over them, then ``settings.field``'s field, as the last
    pass of :func:`track_pair` makes it.

    Parameters
    ----------
    a_mm, b_mm
        (m, 3) each track's positions (x, y, z) at frame A and at frame B, mm, row for row.
    grid
        The voxel grid: the scale of the bins and the outlier test's noise floor.
    settings
        Bins, the outlier test and the field (the searches and passes are not used).

    Returns
    -------
    TrackResult
        ``a_index`` and ``b_index`` both the rows 0 .. m - 1.
    """
    s = settings or TrackSettings()
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    disp = b - a
    mid = a + 0.5 * disp
    out = reject_outliers(mid, disp, neighbours=s.neighbours, threshold=s.outlier_threshold,
                          epsilon_mm=s.epsilon_voxels * voxel)
    centres, field, counts, fit = _field(mid[~out], disp[~out], grid, s)
    rows = np.arange(len(a), dtype=np.int64)
    return TrackResult(a_index=rows, b_index=rows.copy(), displacement_mm=disp, outlier=out, x_mm=centres[0],
                       y_mm=centres[1], z_mm=centres[2], field_mm=field, counts=counts, fit=fit)


# --- tracks through a time-resolved series (Shake-the-Box's long tracks) -------------------------

@dataclass(frozen=True)
class SeriesSettings:
    """How a time-resolved series' particles are linked into tracks through its frames and how the
    tracks are fitted (:func:`link_series`, :func:`fit_series`).

    Attributes
    ----------
    link_voxels
        The search radius (x, y, z), voxels, around where a track's own recent velocity puts it in
        the next frame.
    min_frames
        Fewest frames a track needs to be fitted and used (shorter ones are left out).
    fit_frames
        How many of a track's frames, the nearest in time, each local fit uses (at least
        ``degree + 1``; more average the position noise more, fewer follow a curved path closer).
    degree
        The polynomial's order in time (2: position, velocity and acceleration, as Shake-the-Box).
    pool_pairs
        Offer each pair's field the tracks of the pairs up to this many before and after it, moved
        by the pattern's translation estimated from the tracks, kept where its own held-out tracks
        say they help (:func:`pooled_field_of_tracks`; ``"fit"`` and ``"divfree"`` fields). 0: each
        pair's own tracks only.
    bridge_frames
        Join a track that ends to one that starts up to this many frames later, where its own
        recent velocity puts it there (:func:`_bridge_gaps`): a particle that reconstruction missed
        in a frame or two no longer breaks its track in two, and a pair whose particle is missing in
        frame A or B gets the track's fitted positions there. 0: tracks without gaps.
    relink
        Let the pair tracking's links carry on tracks that a straight line loses: a track of two
        frames or more whose own recent velocity finds no particle in the next frame takes the pair
        tracking's link of its particle (where that passes the outlier test), and the pair tracking
        pairs the particles its later passes leave unpaired as its first pass does
        (:func:`track_pair`'s ``keep_wide``). For particles on paths curved more sharply than
        :attr:`link_voxels` allows from frame to frame (a vortex core's); on one camera's smooth flow
        it also keeps depth-misplaced particles on their tracks (benchmarks/RESULTS.md). False: a
        track ends where its own velocity finds nothing.
    """

    link_voxels: tuple[float, float, float] = (1.0, 1.0, 1.0)
    min_frames: int = 4
    fit_frames: int = 6
    degree: int = 2
    pool_pairs: int = 0
    bridge_frames: int = 0
    relink: bool = False

    def __post_init__(self) -> None:
        if len(self.link_voxels) != 3 or not all(0 < x < np.inf for x in self.link_voxels):  # NaN too
            raise ValueError(f"link_voxels needs three positive values (x, y, z), got {self.link_voxels}")
        if self.degree < 1:
            raise ValueError(f"the tracks' polynomial order must be at least 1, got {self.degree}")
        if self.fit_frames < self.degree + 1:
            raise ValueError(f"a fit of order {self.degree} needs at least {self.degree + 1} frames, got "
                             f"fit_frames {self.fit_frames}")
        if self.min_frames < self.degree + 1:
            raise ValueError(f"a fit of order {self.degree} needs tracks of at least {self.degree + 1} frames, got "
                             f"min_frames {self.min_frames}")
        if self.pool_pairs < 0:
            raise ValueError(f"pool_pairs is how many pairs either side to pool, 0 or more, got {self.pool_pairs}")
        if self.bridge_frames < 0:
            raise ValueError(f"bridge_frames is how many missing frames a track may bridge, 0 or more, got "
                             f"{self.bridge_frames}")

    def as_dict(self) -> dict:
        """The settings as JSON-compatible values (``pool_pairs`` only where pooling, ``bridge_frames``
        only where bridging and ``relink`` only where on: vectors tracked before them read as tracked
        without)."""
        out = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}
        for key in ("pool_pairs", "bridge_frames", "relink"):
            if not out[key]:
                del out[key]
        return out


@dataclass
class SeriesTracks:
    """Tracks through the frames of a time-resolved series.

    Attributes
    ----------
    track
        (k,) the track each point belongs to, 0 .. tracks - 1, the points of a track together in
        frame order.
    frame
        (k,) the point's frame in the series (0, 1, 2, ...: frame A of pair 0, B of pair 0, A of
        pair 1, ...).
    row
        (k,) the particle's row in its frame's particles.
    position_mm
        (k, 3) the particle's position (x, y, z), mm, as reconstructed.
    fitted_mm
        (k, 3) the track's fitted position at the point's frame (:func:`fit_series`), mm; NaN for
        tracks shorter than :attr:`SeriesSettings.min_frames` (or before fitting).
    """

    track: np.ndarray
    frame: np.ndarray
    row: np.ndarray
    position_mm: np.ndarray
    fitted_mm: np.ndarray

    @property
    def n_tracks(self) -> int:
        """How many tracks (single particles included)."""
        return int(self.track.max()) + 1 if len(self.track) else 0

    def lengths(self) -> np.ndarray:
        """(tracks,) each track's number of frames."""
        return np.bincount(self.track, minlength=self.n_tracks)


def _extrapolate(points: list[np.ndarray]) -> np.ndarray:
    """Where a track's own recent velocity puts it one frame on: a straight line fitted to its last
    three positions (two where it has only two), which averages some of the positions' noise."""
    if len(points) >= 3:
        p2, p1, p0 = points[-3], points[-2], points[-1]
        return (p2 + p1 + p0) / 3.0 + (p0 - p2)  # the line's value two frames past its middle
    return 2.0 * points[-1] - points[-2]


def link_series(frames: list[np.ndarray], grid: VolumeGrid, *, settings: TrackSettings | None = None,
                series: SeriesSettings | None = None, predictor: Predictor | None = None) -> SeriesTracks:
    """Link the particles of a time-resolved series' frames into tracks through the frames.

    From each frame to the next: a track of two or more frames looks for the nearest particle
    within :attr:`SeriesSettings.link_voxels` of where its own recent velocity puts it
    (:func:`_extrapolate`), one particle per track, nearest first; a particle not on such a track
    starts one by the pair tracking of the two frames (:func:`track_pair`: ``settings``' searches
    and passes, its first pass around ``predictor`` in the first step and around the step before's
    field after it). The links of each step pass the outlier test of the pair tracking (the
    normalized median test over the nearest links); a track whose link fails it ends there, and
    the particle starts a new one. Particles left unlinked start new tracks. Last, each track of
    two frames or more is extended backwards to an unlinked particle of the frame before it, found
    the same way as forwards (the pair tracking leaves some particles of a frame unpaired that a
    track's own velocity finds). With :attr:`SeriesSettings.bridge_frames`, tracks are then
    joined across up to that many frames where their particle is missing (:func:`_bridge_gaps`).
    With :attr:`SeriesSettings.relink`, a track that its own velocity cannot carry on takes the pair
    tracking's link instead, and the pair tracking keeps its first pass's wide search for the
    particles its later passes leave unpaired.

    Parameters
    ----------
    frames
        Each frame's (n_f, 3) particle positions (x, y, z), mm, in time order, every frame the same
        time after the one before it.
    grid
        The voxel grid: the scale of the searches and bins.
    settings
        The pair tracking of the first links (its ``field`` is not used: the bins' medians predict).
    series
        The search around the extrapolated positions.
    predictor
        The first step's predicted displacement in voxels of ``grid`` (None: zero).

    Returns
    -------
    SeriesTracks
        Every particle of every frame on one track (single-frame tracks included), unfitted.
    """
    s = settings or TrackSettings()
    ser = series or SeriesSettings()
    pair_settings = TrackSettings(**{**asdict(s), "field": "bins"})  # the bins' medians are the next predictor
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    link_radius = np.asarray(ser.link_voxels, dtype=np.float64) * voxel
    pts = [np.asarray(f, dtype=np.float64).reshape(-1, 3) for f in frames]
    # the tracks as lists of (frame, row); the track that each particle of the current frame is on
    tracks: list[list[tuple[int, int]]] = [[(0, i)] for i in range(len(pts[0]) if pts else 0)]
    on = np.arange(len(tracks), dtype=np.int64)
    pred = predictor
    for f in range(len(pts) - 1):
        a, b = pts[f], pts[f + 1]
        next_on = np.full(len(b), -1, np.int64)
        links_a: list[int] = []
        links_b: list[int] = []
        links_cont: list[bool] = []
        long = np.nonzero([len(tracks[t]) >= 2 for t in on])[0] if len(a) else np.zeros(0, np.int64)
        used_a, used_b = np.zeros(len(a), bool), np.zeros(len(b), bool)
        if len(long) and len(b):
            # a track of two frames or more goes where its own velocity takes it
            guess = np.array([_extrapolate([pts[fr][r] for fr, r in tracks[on[i]][-3:]]) for i in long])
            ia, ib = pair_nearest(a[long], b, guess - a[long], link_radius)
            for i, j in zip(long[ia], ib, strict=True):
                links_a.append(int(i))
                links_b.append(int(j))
                links_cont.append(True)
                used_a[i] = used_b[j] = True
        if len(a) and len(b):
            # the rest start tracks by the pair tracking of the two frames
            res = track_pair(a, b, grid, settings=pair_settings, predictor=pred, keep_wide=ser.relink)
            pred = field_predictor(res, grid)
            for i, j, bad in zip(res.a_index, res.b_index, res.outlier, strict=True):
                # a particle on a track takes the pair's link only where its own velocity found nothing
                if not bad and not used_a[i] and not used_b[j] and (ser.relink or len(tracks[on[i]]) == 1):
                    links_a.append(int(i))
                    links_b.append(int(j))
                    links_cont.append(False)
                    used_a[i] = used_b[j] = True
        if links_a:
            la, lb = np.asarray(links_a), np.asarray(links_b)
            disp = b[lb] - a[la]
            bad = reject_outliers(a[la] + 0.5 * disp, disp, neighbours=s.neighbours, threshold=s.outlier_threshold,
                                  epsilon_mm=s.epsilon_voxels * voxel)
            for i, j, out in zip(la, lb, bad, strict=True):
                if not out:
                    tracks[on[i]].append((f + 1, int(j)))
                    next_on[j] = on[i]
        for j in np.nonzero(next_on < 0)[0]:  # a new track from each particle left over
            next_on[j] = len(tracks)
            tracks.append([(f + 1, int(j))])
        on = next_on
    _extend_back(tracks, pts, link_radius)
    for gap in range(1, ser.bridge_frames + 1):
        _bridge_gaps(tracks, pts, link_radius, gap)
    tracks = [t for t in tracks if t]
    k = sum(len(t) for t in tracks)
    track = np.empty(k, np.int64)
    frame = np.empty(k, np.int64)
    row = np.empty(k, np.int64)
    at = 0
    for t, members in enumerate(tracks):
        for fr, r in members:
            track[at], frame[at], row[at] = t, fr, r
            at += 1
    position = np.array([pts[fr][r] for fr, r in zip(frame, row, strict=True)]).reshape(-1, 3)
    return SeriesTracks(track=track, frame=frame, row=row, position_mm=position,
                        fitted_mm=np.full_like(position, np.nan))


def _extend_back(tracks: list[list[tuple[int, int]]], pts: list[np.ndarray], radius_mm: np.ndarray) -> None:
    """Extend tracks backwards in time, in place: a track of two frames or more that starts after the
    first frame takes the particle of the frame before it nearest where its own velocity puts it
    then, within ``radius_mm``, if that particle is on no other track (a particle the pair tracking
    of its frame and the next left unpaired: the forward linking starts a track only from a pair).
    The single-frame tracks so taken are emptied."""
    for f in range(len(pts) - 1, 0, -1):
        heads = [t for t, m in enumerate(tracks) if len(m) >= 2 and m[0][0] == f]
        single = [t for t, m in enumerate(tracks) if len(m) == 1 and m[0][0] == f - 1]
        if not heads or not single:
            continue
        start = np.array([pts[f][tracks[t][0][1]] for t in heads])
        guess = np.array([_extrapolate([pts[fr][r] for fr, r in tracks[t][:3][::-1]]) for t in heads])
        cand = np.array([pts[f - 1][tracks[t][0][1]] for t in single])
        ih, ic = pair_nearest(start, cand, guess - start, radius_mm)
        for h, c in zip(ih, ic, strict=True):
            tracks[heads[h]].insert(0, tracks[single[c]][0])
            tracks[single[c]] = []


def _line_at(frames: list[int], points: list[np.ndarray], at: float) -> np.ndarray:
    """Where a straight line fitted (least squares) to ``points`` at ``frames`` puts a track at frame
    ``at`` (a single point: that point)."""
    if len(points) < 2:
        return np.asarray(points[-1], dtype=np.float64)
    t = np.asarray(frames, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    t0 = float(t.mean())
    slope = np.sum((t - t0)[:, None] * (p - p.mean(axis=0)), axis=0) / float(np.sum((t - t0) ** 2))
    return p.mean(axis=0) + slope * (at - t0)


def _bridge_gaps(tracks: list[list[tuple[int, int]]], pts: list[np.ndarray], radius_mm: np.ndarray, gap: int
                 ) -> None:
    """Join tracks across ``gap`` missing frames, in place, frame by frame forwards: a track of two
    frames or more that ends at frame f takes the track (a single particle included) that starts at
    frame f + gap + 1 nearest where a straight line through its last three positions puts it then,
    within ``radius_mm`` times gap + 1 (the line's error grows with the frames bridged). A particle
    that reconstruction missed in a frame or two (near the cameras' focal planes, or where its image
    overlaps another's) no longer breaks its track in two. The tracks so taken are emptied."""
    last = len(pts) - 1
    for f in range(last - gap):
        g = f + gap + 1
        tails = [t for t, m in enumerate(tracks) if len(m) >= 2 and m[-1][0] == f]
        heads = [t for t, m in enumerate(tracks) if m and m[0][0] == g]
        if not tails or not heads:
            continue
        end = np.array([pts[f][tracks[t][-1][1]] for t in tails])
        guess = np.array([_line_at([fr for fr, _ in tracks[t][-3:]], [pts[fr][r] for fr, r in tracks[t][-3:]], g)
                          for t in tails])
        cand = np.array([pts[g][tracks[t][0][1]] for t in heads])
        it, ih = pair_nearest(end, cand, guess - end, radius_mm * (gap + 1))
        for i, j in zip(it, ih, strict=True):
            tracks[tails[i]].extend(tracks[heads[j]])
            tracks[heads[j]] = []


def _window(frames: np.ndarray, at: float, size: int) -> np.ndarray:
    """The indices of the ``size`` of ``frames`` nearest the time ``at`` (in frames)."""
    order = np.argsort(np.abs(frames - at), kind="stable")
    return np.sort(order[:size])


def _poly(frames: np.ndarray, values: np.ndarray, at: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares polynomials of ``degree`` in time through (n, 3) ``values`` at ``frames``,
    evaluated at ``at`` (frames): (len(at), 3)."""
    t0 = float(np.mean(frames))
    v = np.vander(frames - t0, degree + 1)
    coef, *_ = np.linalg.lstsq(v, values, rcond=None)
    return np.vander(np.asarray(at, dtype=np.float64) - t0, degree + 1) @ coef


def fit_series(tracks: SeriesTracks, *, series: SeriesSettings | None = None) -> SeriesTracks:
    """Fit every track of at least :attr:`SeriesSettings.min_frames` frames by polynomials in time
    (:attr:`SeriesSettings.degree`), each point's fitted position from the
    :attr:`SeriesSettings.fit_frames` of its track's frames nearest it: a local fit through a few
    frames averages the positions' noise (a particle moves smoothly from frame to frame, its
    reconstruction's errors do not) while following a curved path.

    Parameters
    ----------
    tracks
        The tracks through the series (:func:`link_series`): a track's points together, in frame
        order, positions (x, y, z) in mm; frames are the time in units of the frames' spacing ``dt``.
    series
        The fit's frames (``fit_frames``), order (``degree``) and the tracks it fits (``min_frames``).

    Returns
    -------
    SeriesTracks
        ``tracks`` with :attr:`SeriesTracks.fitted_mm` set (NaN on tracks too short).
    """
    ser = series or SeriesSettings()
    fitted = np.full_like(tracks.position_mm, np.nan)
    starts = np.r_[0, np.nonzero(np.diff(tracks.track))[0] + 1, len(tracks.track)] if len(tracks.track) else [0]
    for lo, hi in zip(starts[:-1], starts[1:], strict=True):
        if hi - lo < ser.min_frames:
            continue
        fr = tracks.frame[lo:hi].astype(np.float64)
        pos = tracks.position_mm[lo:hi]
        for k in range(hi - lo):
            w = _window(fr, fr[k], ser.fit_frames)
            fitted[lo + k] = _poly(fr[w], pos[w], fr[k:k + 1], min(ser.degree, len(w) - 1))[0]
    return SeriesTracks(track=tracks.track, frame=tracks.frame, row=tracks.row, position_mm=tracks.position_mm,
                        fitted_mm=fitted)


def pair_tracks(tracks: SeriesTracks, pair: int, *, series: SeriesSettings | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of a time-resolved series at one pair (frames ``2 pair`` and ``2 pair + 1``):
    each track of at least :attr:`SeriesSettings.min_frames` frames whose frames nearest the pair
    reach from frame A to frame B (without bridged gaps, :attr:`SeriesSettings.bridge_frames`: that
    holds both frames' particles; with them, one whose particle was missed in frame A or B too), its
    positions at frame A's and frame B's times from a polynomial (:attr:`SeriesSettings.degree`)
    fitted to its :attr:`SeriesSettings.fit_frames` frames nearest the pair's mid-time. Their
    difference is the displacement over dt at the pair's mid-time (exactly the fitted velocity
    there times dt, for a polynomial of order 2).

    Parameters
    ----------
    tracks
        The tracks through the series (:func:`link_series`), positions (x, y, z) in mm.
    pair
        The pair, numbered as ``tracks.frame`` counts frames: its frames are ``2 pair`` (A) and
        ``2 pair + 1`` (B).
    series
        The fit's frames, order and the shortest track used.

    Returns
    -------
    a_mm, b_mm
        (m, 3) each track's fitted positions (x, y, z) at frame A and frame B, mm.
    track
        (m,) the tracks' indices in ``tracks``.
    """
    ser = series or SeriesSettings()
    fa, fb = 2 * pair, 2 * pair + 1
    a_out, b_out, ids = [], [], []
    starts = np.r_[0, np.nonzero(np.diff(tracks.track))[0] + 1, len(tracks.track)] if len(tracks.track) else [0]
    for lo, hi in zip(starts[:-1], starts[1:], strict=True):
        fr = tracks.frame[lo:hi]
        if hi - lo < ser.min_frames:
            continue
        w = _window(fr.astype(np.float64), fa + 0.5, ser.fit_frames)
        if fr[w].min() > fa or fr[w].max() < fb:  # the fit must reach both frames (bridged gaps inside)
            continue
        ab = _poly(fr[w].astype(np.float64), tracks.position_mm[lo:hi][w], np.array([fa, fb], np.float64),
                   min(ser.degree, len(w) - 1))
        a_out.append(ab[0])
        b_out.append(ab[1])
        ids.append(int(tracks.track[lo]))
    a = np.asarray(a_out, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_out, dtype=np.float64).reshape(-1, 3)
    return a, b, np.asarray(ids, np.int64)


def predict_series(tracks: SeriesTracks, frame: int, *, series: SeriesSettings | None = None, missed: int = 1,
                   neighbours: int = 8) -> np.ndarray:
    """Where the tracks so far put their particles in the next frame (Shake-the-Box's prediction):
    the candidates that :meth:`lfcore.ipr.ParticleReconstructor.reconstruct` fits first in frame
    ``frame + 1``, beside the quick reconstruction's peaks.

    Each track of two frames or more whose last particle is in ``frame`` (or, for a track of three
    frames or more, up to ``missed`` frames before it: a particle the reconstruction missed in a
    frame stays predicted) is carried on by a polynomial in time through its last
    :attr:`SeriesSettings.fit_frames` positions: of :attr:`SeriesSettings.degree` (Shake-the-Box's 2:
    a curved path followed) through four positions or more, a straight line (least squares)
    through three, the last displacement through two. Each particle of ``frame`` on no such track
    (one found in this frame only, or a track's start) is carried on by the displacement of the
    ``neighbours`` tracks nearest it over their last frame (:func:`_predict`'s local linear fit, their
    median with fewer than :data:`LINEAR_PREDICTOR_TRACKS`; none without tracks).

    Parameters
    ----------
    tracks
        The tracks through frames 0 .. ``frame`` (:func:`link_series`), positions (x, y, z) in mm.
    frame
        The last frame linked.
    series
        The polynomial's order (``degree``) and the positions it goes through (``fit_frames``).
    missed
        How many frames at most a track's particle may have been missed before ``frame`` and it is
        still predicted (0: only tracks with a particle in ``frame``).
    neighbours
        The tracks that predict each lone particle's displacement.

    Returns
    -------
    numpy.ndarray
        (m, 3) predicted positions (x, y, z) in frame ``frame + 1``, mm.
    """
    ser = series or SeriesSettings()
    if not len(tracks.track):
        return np.zeros((0, 3))
    out: list[np.ndarray] = []
    lone: list[np.ndarray] = []
    mids: list[np.ndarray] = []  # the tracks' last steps: midpoints and displacements over a frame
    steps: list[np.ndarray] = []
    starts = np.r_[0, np.nonzero(np.diff(tracks.track))[0] + 1, len(tracks.track)]
    for lo, hi in zip(starts[:-1], starts[1:], strict=True):
        fr = tracks.frame[lo:hi].astype(np.float64)
        pos = tracks.position_mm[lo:hi]
        last = int(tracks.frame[hi - 1])
        n = hi - lo
        if n == 1:
            if last == frame:
                lone.append(pos[0])
            continue
        if last != frame and not (n >= 3 and frame - missed <= last < frame):
            continue
        k = min(n, ser.fit_frames)
        degree = 1 if k < 4 else min(ser.degree, k - 1)
        out.append(_poly(fr[-k:], pos[-k:], np.array([frame + 1.0]), degree)[0])
        if last == frame and fr[-2] == frame - 1:
            mids.append(0.5 * (pos[-1] + pos[-2]))
            steps.append(pos[-1] - pos[-2])
    if lone and mids:
        at = np.asarray(lone)
        out.extend(at + _predict(np.asarray(mids), np.asarray(steps), at, neighbours=neighbours))
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


# --- tracks pooled from neighbouring pairs of a series (a pattern carried by the flow) -----------

#: Folds of the cross-validation that decides whether a pair's field takes its neighbours' tracks
#: (:func:`pooled_field_of_tracks`).
POOL_FOLDS = 5


@dataclass(frozen=True)
class PoolChoice:
    """What :func:`pooled_field_of_tracks` found for one pair.

    Attributes
    ----------
    offsets
        The neighbouring pairs offered, as offsets from the pair (-2, -1, 1, 2, ...).
    shift_mm
        (x, y, z) the pattern's estimated translation from one pair to the next, mm
        (:func:`pattern_shift`): a neighbour ``k`` pairs on is moved back by ``k`` times it.
    tracks
        The neighbours' tracks pooled (inside the box once moved).
    pooled
        Whether the field took them: their held-out misfit on the pair's own tracks was lower than
        without them by more than its standard error.
    cv_own_mm, cv_pooled_mm
        The RMS misfit of the pair's own held-out tracks (the three components together), mm,
        fitted from the pair's own other tracks alone and with the neighbours' tracks.
    """

    offsets: tuple[int, ...]
    shift_mm: tuple[float, float, float]
    tracks: int
    pooled: bool
    cv_own_mm: float
    cv_pooled_mm: float


def _smooth_of(pos: np.ndarray, d: np.ndarray):
    """A smooth field of tracks (midpoints, displacements, mm) that can be evaluated anywhere: each
    component's smoothing spline (``fit``'s, chosen by cross-validation); their mean with too few."""
    mean = np.mean(d, axis=0) if len(d) else np.zeros(3)
    scale = float(np.max(np.ptp(pos, axis=0))) if len(pos) else 0.0
    if len(pos) < 15 or scale <= 0:
        return lambda at: np.broadcast_to(mean, (len(at), 3))
    centre = pos.mean(axis=0)
    x = (pos - centre) / scale
    split = [f for f in np.array_split(np.random.default_rng(0).permutation(len(x)), 5) if len(f)]
    try:
        choice = _choose_fit([(x, d, split)])
        fits = [_rbf(x, d[:, c], ch.degree, ch.smoothing) for c, ch in enumerate(choice)]
    except np.linalg.LinAlgError:
        return lambda at: np.broadcast_to(mean, (len(at), 3))
    return lambda at: np.column_stack([f((np.asarray(at) - centre) / scale) for f in fits])


def pattern_shift(position_mm: np.ndarray, displacement_mm: np.ndarray,
                  neighbours: list[tuple[int, np.ndarray, np.ndarray]], grid: VolumeGrid) -> np.ndarray:
    """The translation of the flow's pattern from one pair to the next, estimated from the tracks.

    Taylor's frozen pattern: the field of the pair ``k`` pairs on is this pair's moved by ``k``
    times a translation ``s`` (a vortex ring travelling at its own speed, a wake carried by the
    stream). ``s`` minimises the mean squared misfit between each neighbour's tracks and this
    pair's own field (a smoothing spline through its tracks, each component's smoothing chosen by
    cross-validation) at the neighbour's positions moved back by ``k s``, over the neighbours'
    tracks within the pair's own tracks' extent: first on grids of shifts (the field on a grid two
    voxels apart, trilinear), as far as twice the largest displacement of a track per axis, then by
    least squares (a soft L1 loss) on the spline itself. (Comparing this pair's tracks with each
    neighbour's field as well changed the demo ring's estimates by at most 0.04 voxel, at twice
    the cost.)

    Parameters
    ----------
    position_mm, displacement_mm
        (m, 3) this pair's tracks: midpoints and displacements (x, y, z), mm.
    neighbours
        Each neighbour as (k, its tracks' midpoints, their displacements): ``k`` its offset in pairs
        (-1 the pair before, 1 the one after).
    grid
        The voxel grid: the scale of the search.

    Returns
    -------
    numpy.ndarray
        (3,) the translation per pair (x, y, z), mm; zeros without tracks enough to compare.
    """
    from scipy.ndimage import map_coordinates
    from scipy.optimize import least_squares

    pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(displacement_mm, dtype=np.float64).reshape(-1, 3)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    if len(pos) < 15 or not neighbours:
        return np.zeros(3)
    # the neighbours' tracks within this pair's tracks' extent, each with its offset k
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    ks, xs, ys = [], [], []
    for k, p, v in neighbours:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        inside = np.all((p >= lo) & (p <= hi), axis=1)
        ks.append(np.full(int(inside.sum()), float(k)))
        xs.append(p[inside])
        ys.append(np.asarray(v, dtype=np.float64).reshape(-1, 3)[inside])
    k_all, x_all, y_all = np.concatenate(ks), np.concatenate(xs), np.concatenate(ys)
    if len(k_all) < 15:
        return np.zeros(3)
    field = _smooth_of(pos, d)
    step = 2.0 * voxel  # the field on a grid two voxels apart, for the searches on grids
    axes = [np.arange(lo[a], hi[a] + step[a], step[a]) for a in range(3)]
    gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    on_grid = field(np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])).reshape(*gx.shape, 3)
    cap = np.sum((2.0 * voxel) ** 2)  # a track more than about two voxels off counts as that far

    def coarse_cost(shifts: np.ndarray) -> np.ndarray:  # (s, 3) shifts in mm -> (s,) mean squared misfit
        out = np.empty(len(shifts))
        for i0 in range(0, len(shifts), 128):
            sh = shifts[i0:i0 + 128]
            at = x_all[None, :, :] - k_all[None, :, None] * sh[:, None, :]  # (s, n, 3)
            idx = ((at - lo) / step)[..., ::-1].reshape(-1, 3).T  # (z, y, x) rows
            pred = np.stack([map_coordinates(on_grid[..., c], idx, order=1, mode="nearest") for c in range(3)],
                            axis=-1).reshape(len(sh), -1, 3)
            out[i0:i0 + 128] = np.mean(np.minimum(np.sum((pred - y_all[None]) ** 2, axis=-1), cap), axis=1)
        return out

    reach = 2.0 * np.max(np.abs(d), axis=0) + voxel  # the pattern moves at most at about the flow's speed
    best = np.zeros(3)
    width = reach
    for _ in range(3):  # grids of 9^3 shifts, each a third as wide as the one before, around its best
        ticks = [np.linspace(-width[a], width[a], 9) + best[a] for a in range(3)]
        cand = np.stack(np.meshgrid(*ticks, indexing="ij"), axis=-1).reshape(-1, 3)
        cand = np.vstack([cand, np.zeros((1, 3))])  # no translation is always a candidate
        best = cand[int(np.argmin(coarse_cost(cand)))]
        width = np.maximum(width / 3.0, 0.25 * voxel)

    def residual(s_vox: np.ndarray) -> np.ndarray:
        return ((field(x_all - k_all[:, None] * (s_vox * voxel)) - y_all) / voxel).ravel()

    fit = least_squares(residual, best / voxel, loss="soft_l1", f_scale=0.5, diff_step=1e-3, max_nfev=50)
    return np.asarray(fit.x, dtype=np.float64) * voxel


def _fit_values(pos: np.ndarray, d: np.ndarray, at: np.ndarray, choice: tuple[FitChoice, ...]) -> np.ndarray:
    """The field of ``choice`` (:func:`fit_tracks`' for these tracks or others like them) fitted to
    tracks ``pos``, ``d`` (mm), at points ``at`` (mm): (len(at), 3), as :func:`fit_tracks` fits it
    (coordinates scaled to the tracks' extent, in blocks beyond its limits)."""
    scale = float(np.max(np.ptp(pos, axis=0))) if len(pos) else 0.0
    if choice[0].degree == 0 or len(pos) < 15 or scale <= 0:
        return np.broadcast_to(np.mean(d, axis=0), (len(at), 3)).copy()
    centre = pos.mean(axis=0)
    x, xa = (pos - centre) / scale, (np.asarray(at) - centre) / scale
    divfree = choice[0].weight is not None
    if len(pos) > (DIVFREE_GLOBAL_TRACKS if divfree else FIT_GLOBAL_TRACKS):
        blocks = _blocks(x, xa, DIVFREE_BLOCK_TRACKS if divfree else FIT_BLOCK_TRACKS)
    else:
        blocks = [(np.arange(len(x)), np.arange(len(xa)))]
    values = np.full((len(xa), 3), np.nan)
    for rows, points in blocks:
        if not len(points):
            continue
        if divfree:
            w, lam = float(choice[0].weight), float(choice[0].smoothing)  # type: ignore[arg-type]
            fit = _DivFree(x[rows], w, lam)
            values[points] = fit(xa[points], *fit.coefficients(d[rows], np.array([lam])))[0]
        else:
            for c, ch in enumerate(choice):
                values[points, c] = _rbf(x[rows], d[rows, c], ch.degree, ch.smoothing)(xa[points])
    return values


def _held_out_misfit(pos: np.ndarray, d: np.ndarray, extra: tuple[np.ndarray, np.ndarray] | None,
                     choice: tuple[FitChoice, ...], *, folds: int, seed: int) -> np.ndarray:
    """Each of the pair's own tracks' squared misfit (the components summed) when held out: the
    field of ``choice`` fitted to the other folds' own tracks (and ``extra``, the neighbours'
    tracks, never held out), in the order of the tracks."""
    split = [f for f in np.array_split(np.random.default_rng(seed).permutation(len(pos)), folds) if len(f)]
    x = pos if extra is None else np.concatenate([pos, extra[0]])
    y = d if extra is None else np.concatenate([d, extra[1]])
    # the neighbours' rows are in no fold: _held_out keeps them in every training set
    out = np.empty(len(pos))
    order = np.concatenate(split)
    r2 = []
    with _one_blas_thread():
        for xt, yt, xf, yf in _held_out([(x, y, split)]):
            r2.append(np.sum((_fit_values(xt, yt, xf, choice) - yf) ** 2, axis=1))
    out[order] = np.concatenate(r2)
    return out


class _one_blas_thread:
    """BLAS at one thread inside (the kernel's systems gain little from threads on shared cores)."""

    def __enter__(self):
        from threadpoolctl import threadpool_limits

        self._limits = threadpool_limits(limits=1, user_api="blas")
        return self

    def __exit__(self, *exc: object) -> None:
        self._limits.restore_original_limits()


def pooled_field_of_tracks(a_mm: np.ndarray, b_mm: np.ndarray, neighbours: list[tuple[int, np.ndarray, np.ndarray]],
                           grid: VolumeGrid, *, settings: TrackSettings | None = None, folds: int = POOL_FOLDS,
                           seed: int = 0) -> tuple[TrackResult, PoolChoice | None]:
    """The field of a pair's tracks (:func:`field_of_tracks`) with the tracks of neighbouring pairs
    of a series pooled into it where that helps.

    Where the flow's pattern is carried along from pair to pair (Taylor's frozen pattern: a vortex
    ring at its own speed, a wake in a stream), a neighbour's tracks are more samples of this
    pair's field once moved back by the pattern's translation. That translation is estimated from
    the tracks (:func:`pattern_shift`), each neighbour ``k`` pairs away moved back by ``k`` times
    it, and the ``"fit"`` or ``"divfree"`` field fitted to the pair's own tracks and the moved ones
    (its smoothing and model chosen by its own cross-validation). The pooled field is kept only
    where it predicts the pair's own held-out tracks better: the same folds of the pair's own
    tracks held out from both (the neighbours' tracks always in training), each model at its own
    choice, the pooled one's mean squared misfit lower by more than the standard error of the
    paired difference; otherwise the pair's own field, unchanged. The field's points (where it has
    a value) are the pair's own tracks' either way.

    Parameters
    ----------
    a_mm, b_mm
        (m, 3) the pair's tracks' positions (x, y, z) at frame A and frame B, mm, row for row.
    neighbours
        Each neighbouring pair's tracks as (k, a_mm, b_mm): ``k`` its offset in pairs (-1 the pair
        before, 1 the one after), each of the same time between frames as this pair's, the pairs
        evenly spaced in time.
    grid
        The voxel grid: the scale of the bins, the outlier test and the search of the translation.
    settings
        As :func:`field_of_tracks`; only ``"fit"`` and ``"divfree"`` pool.
    folds, seed
        The held-out test's folds of the pair's own tracks and their random split.

    Returns
    -------
    result
        The pair's tracks and its field (pooled or its own).
    choice
        The translation, the tracks pooled and the test's figures; None where nothing was offered
        to pool (no neighbours, a field that does not fit, or too few tracks).
    """
    s = settings or TrackSettings()
    own = field_of_tracks(a_mm, b_mm, grid, settings=s)
    if s.field not in ("fit", "divfree") or not neighbours or own.fit is None or own.fit[0].degree == 0:
        return own, None
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    mid = (a + 0.5 * own.displacement_mm)[~own.outlier]
    disp = own.displacement_mm[~own.outlier]
    moved = []
    for k, na, nb in neighbours:
        na = np.asarray(na, dtype=np.float64).reshape(-1, 3)
        nd = np.asarray(nb, dtype=np.float64).reshape(-1, 3) - na
        nm = na + 0.5 * nd
        if len(nm) < 2:
            continue
        bad = reject_outliers(nm, nd, neighbours=s.neighbours, threshold=s.outlier_threshold,
                              epsilon_mm=s.epsilon_voxels * voxel)
        moved.append((int(k), nm[~bad], nd[~bad]))
    if not moved:
        return own, None
    shift = pattern_shift(mid, disp, moved, grid)
    lo = np.asarray(grid.origin_mm, dtype=np.float64) - 0.5 * voxel
    hi = lo + np.asarray(grid.shape[::-1], dtype=np.float64) * voxel
    em = np.concatenate([nm - k * shift for k, nm, _ in moved])
    ed = np.concatenate([nd for _, _, nd in moved])
    inside = np.all((em >= lo) & (em <= hi), axis=1)
    extra = (em[inside], ed[inside])
    offsets = tuple(sorted(k for k, _, _ in moved))
    if not inside.any():
        return own, PoolChoice(offsets, tuple(float(v) for v in shift), 0, False, np.nan, np.nan)  # type: ignore[arg-type]
    centres, field, counts, fit = _field(mid, disp, grid, s, extra)
    r_own = _held_out_misfit(mid, disp, None, own.fit, folds=folds, seed=seed)
    r_pool = _held_out_misfit(mid, disp, extra, fit, folds=folds, seed=seed)  # type: ignore[arg-type]
    diff = r_pool - r_own
    better = bool(np.mean(diff) + np.std(diff) / np.sqrt(len(diff)) < 0.0)
    choice = PoolChoice(offsets, tuple(float(v) for v in shift), int(inside.sum()), better,  # type: ignore[arg-type]
                        float(np.sqrt(np.mean(r_own))), float(np.sqrt(np.mean(r_pool))))
    if not better:
        return own, choice
    return TrackResult(a_index=own.a_index, b_index=own.b_index, displacement_mm=own.displacement_mm,
                       outlier=own.outlier, x_mm=centres[0], y_mm=centres[1], z_mm=centres[2], field_mm=field,
                       counts=counts, fit=fit), choice
