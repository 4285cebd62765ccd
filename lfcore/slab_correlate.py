"""Correlation in depth slabs: volume pairs larger than memory, the vectors of the in-memory correlation.

The in-memory :class:`~lfcore.correlate.Correlator` holds both volumes of a pair, their deformed
copies and their B-spline coefficients: 24 bytes per voxel on the device, besides the two volumes
read from the store. Here the box is cut along z into slabs (:func:`lfcore.slabs.plan_slabs`);
each slab is read with a halo of planes on either side and correlated through every pass by the
same :class:`~lfcore.correlate.Correlator` (one copy of the algorithm), on the whole volume's
window grids restricted to the windows that lie in the slab and its halo, so its vectors sit where
the whole volume's do. Of the final vectors, each slab keeps those whose centres lie in it.

The halo is the depth over which the slab's own edges change what its kept vectors see; it is
found pass by pass along z (:func:`plan_correlation_slabs`), with the erosion of the region of
rows that are computed from the same data as in memory ("exact" rows):

* a window is exact if every voxel it reads (the window, moved by the shift or widened by the
  search radius) lies in the slab and its halo, and, when it is deformed, the predictor at each
  of those voxels is interpolated from exact rows of the previous pass (beyond the outermost
  centres it is extrapolated, which only the volume's own edges do alike) and the B-spline
  coefficients it samples (+-2 voxels around x -+ d/2) are exact;
* the normalized median test reads the 26 neighbours (1 row) and a replaced vector the
  vectors up to its fill sweep t away (a sweep fills outliers next to valid vectors): 1 + t rows;
* the predictor's Gaussian smoothing reads ``ceil(2 sigma)`` rows, the final median filter 1.

Where the slab's edge is the volume's own, nothing changes and nothing is eroded.

The cubic B-spline prefilter is the one global step: its recursive filter along z runs over the
whole slab, so the coefficients near a slab's edge differ from the whole volume's. The
difference decays as |z_p|^n with the distance n from the edge (pole z_p = sqrt(3) - 2): at most
:data:`BSPLINE_ERROR_GAIN` |z_p|^n times the largest |intensity| (the x and y passes, filtered
first, raise the samples' bound 3-fold each; the z pass's start at a cut edge adds at most 0.9 of
that times its gain 6). The coefficients a kept vector's deformation samples are therefore kept
:func:`prefilter_planes` planes inside (14 for 1e-6): the deformed volumes differ from the
in-memory ones by at most ``tolerance`` of the largest intensity. Every other step is the same
arithmetic on the same numbers, but for the float32 sample positions of the deformation, which
are taken in the slab's coordinates (z - lo) and round differently. Measured on blob pairs with
a linear flow (tests, benchmark): the in-memory vectors to 5e-7 .. 5e-6 voxel, flags identical.

Two things depend on the data: the predictor's largest z displacement ``max_shift`` (how far a
window's shift or deformation reaches) and the replacement's fill sweeps ``reach``. The slabs
are planned for assumed values; after each slab the correlation checks them on the rows its
kept vectors depend on, and where they were exceeded it plans that slab (and the slabs after it)
again for what it found and correlates it again, so the kept vectors are the in-memory ones
whatever the data (assumptions only grow, up to the whole box, so this ends).

Memory: per slab, :data:`BYTES_PER_SLAB_VOXEL` bytes per voxel of the slab and its halo plus the
correlator's batch buffers, instead of those of the whole box.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lfcore._deprecation import keyword_options
from lfcore.correlate import (
    DEFAULT_BATCH_BYTES,
    CorrelationConfig,
    Correlator,
    VectorField,
    WindowGrid,
    _axis_weights,
    _lag_plan,
    _padded,
    pass_grids,
)
from lfcore.device import MemoryBudgetError
from lfcore.slabs import plan_slabs
from lfcore.vectors import REPLACE_SWEEPS

__all__ = ["BSPLINE_ERROR_GAIN", "BYTES_PER_SLAB_VOXEL", "CorrelationSlab", "SlabCorrelator", "correlation_bytes",
           "correlator_bytes", "plan_correlation_slabs", "prefilter_planes", "slabs_for_budget"]

#: |sqrt(3) - 2|, the cubic B-spline prefilter's pole.
BSPLINE_POLE = 2.0 - math.sqrt(3.0)
#: Bound of a cut edge's effect on the coefficients n planes inside: gain * |pole|^n * max|intensity|.
BSPLINE_ERROR_GAIN = 50.0
#: Default bound of the prefilter's difference, relative to the largest intensity.
PREFILTER_TOLERANCE = 1e-6
#: Bytes per voxel a slab (with its halo) takes while it is correlated: its two volumes as read
#: (host), the correlator's two copies, two deformed volumes and two coefficient volumes (float32).
BYTES_PER_SLAB_VOXEL = 32
_INF = 1 << 40


@keyword_options("tolerance", since="0.1.0")
def prefilter_planes(*, tolerance: float = PREFILTER_TOLERANCE) -> int:
    """Planes between a cut edge and the first B-spline coefficient within ``tolerance`` (relative
    to the largest intensity) of the whole volume's (see the module docstring)."""
    if not 0 < tolerance < 1:
        raise ValueError(f"the prefilter tolerance must lie between 0 and 1, got {tolerance}")
    return max(0, math.ceil(math.log(tolerance / BSPLINE_ERROR_GAIN) / math.log(BSPLINE_POLE)))


@dataclass(frozen=True)
class CorrelationSlab:
    """One slab: the final vectors of rows ``k0 .. k1 - 1`` (whole grid, z), whose centres lie in
    planes ``z0 .. z1 - 1``, computed from planes ``lo .. hi - 1`` on the window grids ``grids``
    (one per pass, in the coordinates of the planes read)."""

    z0: int
    z1: int
    lo: int
    hi: int
    k0: int
    k1: int
    grids: tuple[WindowGrid, ...]
    #: per pass: (first, last) rows of the slab's grid (whole-grid indices) computed as in memory
    exact: tuple[tuple[int, int], ...]
    #: per pass: (first, last) rows whose outlier test and replacement are as in memory (the
    #: smoothing of the predictor and the final median filter read these)
    validated: tuple[tuple[int, int], ...]

    @property
    def halo(self) -> tuple[int, int]:
        """Planes read below and above the slab."""
        return self.z0 - self.lo, self.hi - self.z1

    @property
    def depth(self) -> int:
        return self.hi - self.lo


@dataclass(frozen=True)
class _Assumed:
    max_shift: float
    reach: int


class _Plan:
    """The z side of the passes of ``config`` over ``shape``: which rows a slab computes as in memory."""

    def __init__(self, shape: tuple[int, int, int], config: CorrelationConfig, tolerance: float) -> None:
        self.nz = shape[0]
        self.config = config
        self.grids = pass_grids(shape, config)
        self.modes = [m for _, m in config.passes]
        self.rz = 0 if config.search_radius is None else int(config.search_radius[2])
        self.cubic = config.interpolation == "cubic"
        self.prefilter = prefilter_planes(tolerance=tolerance) if self.cubic else 0
        n = len(self.modes)
        self.smooth_rows = [math.ceil(2.0 * config.smooth_predictor)
                            if config.smooth_predictor > 0 and i + 1 < n and self.modes[i + 1] == "deform" else 0
                            for i in range(n)]

    def centre(self, i: int, k: int) -> float:
        g = self.grids[i]
        return g.first[2] + g.step[2] * k + 0.5 * (g.window[2] - 1)

    def exact(self, lo: int, hi: int, a: _Assumed) -> list[tuple[int, int, int, int]] | None:
        """Per pass, the (first, last) whole-grid rows the planes ``lo .. hi - 1`` compute as the
        whole volume does (first > last: none), then the (first, last) rows whose outlier test and
        replacement are (before the smoothing and median filter), or None if a pass has no window
        in them."""
        cut_lo, cut_hi = lo > 0, hi < self.nz
        vol = (lo if cut_lo else -_INF, hi - 1 if cut_hi else _INF)
        p = self.prefilter
        coef = (vol[0] + p if cut_lo else -_INF, vol[1] - p if cut_hi else _INF) if self.cubic else vol
        pred = (-_INF, _INF)
        half = math.ceil(math.ceil(a.max_shift) / 2)
        out = []
        for i, g in enumerate(self.grids):
            f, s, c, w = g.first[2], g.step[2], g.counts[2], g.window[2]
            k_lo, k_hi = _rows_in(g, lo, hi)
            if k_lo > k_hi:
                return None
            k = np.arange(k_lo, k_hi + 1)
            start = f + s * k
            mode = self.modes[i]
            ok = np.ones(len(k), bool)
            if mode == "shift":
                reach = half + 1
                centre = start + 0.5 * (w - 1)
                ok = ((start - reach >= vol[0]) & (start + w - 1 + reach <= vol[1]) & (centre >= pred[0])
                      & (centre <= pred[1]))
            elif mode == "deform":
                r = self.rz
                z0, z1 = start - r, start + w - 1 + r
                d = half + (2 if self.cubic else 1)
                ok = ((z0 >= vol[0]) & (z1 <= vol[1]) & (z0 >= pred[0]) & (z1 <= pred[1]) & (z0 - d >= coef[0])
                      & (z1 + d <= coef[1]))
            if not ok.any():
                out.append((1, 0, 1, 0))
                pred = (_INF, -_INF)
                continue
            ra, rb = int(k[ok][0]), int(k[ok][-1])
            # the whole grid's own first and last rows have the same neighbours in the slab (and the
            # smoothing continues the grid by as many rows, min(radius, rows - 1), as there)
            t = max(1, self.smooth_rows[i])
            same = not self.smooth_rows[i] or min(t, k_hi - k_lo) == min(t, c - 1)
            # the median test and the replacement, then the smoothing and the final median filter
            va, vb = _erode(ra, rb, 1 + a.reach, c - 1, same)
            ea, eb = _erode(va, vb, self.smooth_rows[i] + (1 if i == len(self.grids) - 1 and self.config.median_filter
                                                           else 0), c - 1, same)
            out.append((ea, eb, va, vb))
            if ea > eb:
                pred = (_INF, -_INF)
            else:
                pred = (-_INF if ea == 0 else self.centre(i, ea), _INF if eb == c - 1 else self.centre(i, eb))
        return out

    def keeps(self, lo: int, hi: int, k0: int, k1: int, a: _Assumed) -> bool:
        ex = self.exact(lo, hi, a)
        return ex is not None and ex[-1][0] <= k0 and k1 - 1 <= ex[-1][1]

    def slab(self, z0: int, z1: int, k0: int, k1: int, a: _Assumed) -> CorrelationSlab:
        """The slab of final rows ``k0 .. k1 - 1``: the fewest planes that compute them as in memory."""
        g = self.grids[-1]
        top = g.first[2] + g.step[2] * k0  # the first kept window's first plane
        bottom = g.first[2] + g.step[2] * (k1 - 1) + g.window[2]
        # the fewest planes below (with the volume's top as the far side), then above; exactness only grows
        # as the slab widens, so each side is a bisection
        lo_ok, lo_bad = 0, top + 1
        while lo_bad - lo_ok > 1:
            m = (lo_ok + lo_bad) // 2
            lo_ok, lo_bad = (m, lo_bad) if self.keeps(m, self.nz, k0, k1, a) else (lo_ok, m)
        hi_ok, hi_bad = self.nz, bottom - 1
        while hi_ok - hi_bad > 1:
            m = (hi_ok + hi_bad) // 2
            hi_ok, hi_bad = (m, hi_bad) if self.keeps(lo_ok, m, k0, k1, a) else (hi_ok, m)
        lo, hi = lo_ok, hi_ok
        while not self.keeps(lo, hi, k0, k1, a):  # both cut edges together (a thin slab): widen
            lo, hi = max(0, lo - 1), min(self.nz, hi + 1)
        exact = self.exact(lo, hi, a)
        grids = []
        for gg in self.grids:
            ka, kb = _rows_in(gg, lo, hi)
            grids.append(WindowGrid(window=gg.window, step=gg.step,
                                    first=(gg.first[0], gg.first[1], gg.first[2] + gg.step[2] * ka - lo),
                                    counts=(gg.counts[0], gg.counts[1], kb - ka + 1)))
        return CorrelationSlab(z0=z0, z1=z1, lo=lo, hi=hi, k0=k0, k1=k1, grids=tuple(grids),
                               exact=tuple(e[:2] for e in exact), validated=tuple(e[2:] for e in exact))


def _erode(first: int, last: int, rows: int, end: int, keep_ends: bool) -> tuple[int, int]:
    """The rows ``first .. last`` less ``rows`` on each side, except at the grid's own ends (row 0
    and ``end``), which see the same neighbours in a slab as in the whole grid if ``keep_ends``."""
    return (first if first == 0 and keep_ends else first + rows, last if last == end and keep_ends else last - rows)


def _final_rows(plan: _Plan, slabs: Sequence[tuple[int, int]]) -> list[tuple[int, int, int, int]]:
    """(z0, z1, k0, k1) of the plane slabs that hold final window centres."""
    c = plan.grids[-1].counts[2]
    centres = np.array([plan.centre(len(plan.grids) - 1, k) for k in range(c)])
    out = []
    for j, (z0, z1) in enumerate(slabs):
        top = np.inf if j == len(slabs) - 1 else z1
        rows = np.flatnonzero((centres >= z0) & (centres < top))
        if len(rows):
            out.append((z0, z1, int(rows[0]), int(rows[-1]) + 1))
    return out


def plan_correlation_slabs(shape: tuple[int, int, int], config: CorrelationConfig, n_slabs: int, *,
                           max_shift: float | None = None, reach: int = 1,
                           tolerance: float = PREFILTER_TOLERANCE) -> list[CorrelationSlab]:
    """Cut the correlation of volumes of ``shape`` (z, y, x) into ``n_slabs`` depth slabs.

    Parameters
    ----------
    shape
        (nz, ny, nx) of the volumes.
    config
        The correlation.
    n_slabs
        Slabs of nearly equal depth (:func:`lfcore.slabs.plan_slabs`); a slab that holds no final
        window centre is left out.
    max_shift
        Assumed largest |z displacement| of the predictors, voxels (default: a quarter of the
        first window's depth, the quarter-window rule).
    reach
        Assumed largest number of sweeps the outlier replacement needs.
    tolerance
        Bound of the B-spline prefilter's difference, relative to the largest intensity.

    Returns
    -------
    list of CorrelationSlab
        Front to back; their kept rows ``k0 .. k1 - 1`` cover the final grid's rows once.

    Raises
    ------
    ValueError
        If ``n_slabs`` is below 1 or above ``nz``.
    CorrelationError
        If a window does not fit in the volume.
    """
    plan = _Plan(tuple(int(n) for n in shape), config, tolerance)
    a = _Assumed(max_shift=_default_shift(config) if max_shift is None else float(max_shift), reach=int(reach))
    edges = [(s.z0, s.z1) for s in plan_slabs(plan.nz, n_slabs)]
    return [plan.slab(z0, z1, k0, k1, a) for z0, z1, k0, k1 in _final_rows(plan, edges)]


def correlation_bytes(depth: int, shape: tuple[int, int, int], config: CorrelationConfig, device: str) -> int:
    """Bytes correlating ``depth`` planes of volumes of ``shape`` (z, y, x) takes (an estimate of
    :func:`correlator_bytes` and the two volumes): :data:`BYTES_PER_SLAB_VOXEL` per voxel, and the
    batch buffers of the passes (two complex FFT buffers of as many windows as the budget holds,
    or the direct correlation's lag sums), for the windows of the whole volume's grids that lie in
    ``depth`` planes."""
    kind = "cpu" if device == "cpu" else "cuda"
    budget = int(config.batch_bytes or DEFAULT_BATCH_BYTES[kind])
    fft = lags = 0
    for i, g in enumerate(pass_grids(shape, config)):
        rows = max(1, min(g.counts[2], (int(depth) - g.window[2]) // g.step[2] + 1))
        part = WindowGrid(window=g.window, step=g.step, first=g.first, counts=(g.counts[0], g.counts[1], rows))
        if config.search_radius is not None and i > 0:
            lags = max(lags, 24 * _lag_plan(part, config.search_radius, budget).entries)  # two vec3f buffers
            continue
        dims = _padded(g.window, config.zero_pad)
        p = int(np.prod(dims))
        nb = max(2, min(part.size, budget // (16 * p)))
        nb += nb % 2
        # two vec2f buffers, and per buffer row the sums (vec4) and the row peaks (value, index)
        fft = max(fft, 16 * nb * p + 24 * nb * dims[0] * dims[1])
    return BYTES_PER_SLAB_VOXEL * int(depth) * int(shape[1]) * int(shape[2]) + fft + lags


def slabs_for_budget(shape: tuple[int, int, int], config: CorrelationConfig, budget_bytes: int, *, device: str,
                     max_shift: float | None = None, reach: int = 1) -> int:
    """The fewest depth slabs whose deepest slab, halo included (:func:`plan_correlation_slabs`),
    correlates in ``budget_bytes`` (:func:`correlation_bytes`).

    Raises
    ------
    MemoryBudgetError
        If no number of slabs fits (the halo alone is too deep).
    """
    nz = int(shape[0])
    fewest = None
    for n in range(1, nz + 1):
        slabs = plan_correlation_slabs(shape, config, n, max_shift=max_shift, reach=reach)
        deepest = max(s.depth for s in slabs)
        if correlation_bytes(deepest, shape, config, device) <= budget_bytes:
            return n
        if fewest is None or deepest < fewest[1]:
            fewest = (n, deepest)
        if n > 1 and deepest >= fewest[1] and n >= 2 * fewest[0] + 8:
            break  # the halo, not the slab, sets the depth now: more slabs do not help
    need = correlation_bytes(fewest[1], shape, config, device)
    raise MemoryBudgetError(f"even {fewest[0]} depth slabs need {need / 2**20:.1f} MiB each (their halo is as deep as "
                            f"the passes need), more than the {budget_bytes / 2**20:.1f} MiB there is; use smaller "
                            "windows or a coarser --pvr")


def _default_shift(config: CorrelationConfig) -> float:
    return config.windows[0][2] / 4.0


def correlator_bytes(correlator: Correlator) -> int:
    """Bytes of the device arrays a correlator owns (views of them not counted twice)."""
    wp = correlator.wp
    total = 0
    for value in vars(correlator).values():
        items = value if isinstance(value, (list, tuple)) else (value,)
        for x in items:
            if isinstance(x, wp.array) and x.deleter is not None:  # owns its memory: not a view
                total += int(x.capacity)
    return total


class SlabCorrelator:
    """Correlate pairs slab by slab (see the module docstring): the vectors of
    :class:`~lfcore.correlate.Correlator` on the whole volume, without the whole volume.

    Parameters
    ----------
    shape
        (nz, ny, nx) of the whole volumes.
    config
        The correlation, as the in-memory path takes it.
    n_slabs
        Depth slabs (1 to nz).
    device
        Warp device, or None for the first GPU, else the CPU.
    max_shift, reach, tolerance
        As :func:`plan_correlation_slabs` takes them; ``max_shift`` and ``reach`` are checked
        after each slab and raised (and the slab correlated again) where the data exceed them.

    Raises
    ------
    ValueError
        If ``n_slabs`` is below 1 or above nz.
    CorrelationError
        Settings that cannot correlate these volumes.
    """

    def __init__(self, shape: tuple[int, int, int], config: CorrelationConfig, n_slabs: int, *,
                 device: str | None = None, max_shift: float | None = None, reach: int = 1,
                 tolerance: float = PREFILTER_TOLERANCE) -> None:
        self.shape = tuple(int(n) for n in shape)
        self.config = config
        self._plan = _Plan(self.shape, config, tolerance)
        self._assumed = _Assumed(max_shift=_default_shift(config) if max_shift is None else float(max_shift),
                                 reach=int(reach))
        self._edges = [(s.z0, s.z1) for s in plan_slabs(self.shape[0], n_slabs)]
        self.slabs = self._planned()
        self.grid = self._plan.grids[-1]
        # settings the device cannot run are refused here, on the shallowest slab
        first = min(self.slabs, key=lambda s: s.depth)
        probe = Correlator((first.depth, *self.shape[1:]), config=config, device=device, grids=first.grids)
        self.device, self.fft = probe.device, probe.fft
        del probe
        self.peak_bytes = 0  # the most bytes accounted at once in the last pair
        self.retries = 0  # slabs correlated again in the last pair, their assumptions exceeded
        self.last_fallback_fraction = 0.0

    def _planned(self) -> list[CorrelationSlab]:
        return [self._plan.slab(z0, z1, k0, k1, self._assumed)
                for z0, z1, k0, k1 in _final_rows(self._plan, self._edges)]

    @keyword_options("progress", since="0.1.0")
    def __call__(self, read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], *,
                 progress: Callable[[int], None] | None = None) -> VectorField:
        """Correlate one pair slab by slab.

        Parameters
        ----------
        read
            ``read(lo, hi)`` gives planes ``lo .. hi - 1`` of volumes A and B, each
            (hi - lo, ny, nx) float32 (e.g. from a zarr array chunked along z).
        progress
            Called with 1 after each pass of each slab.

        Returns
        -------
        VectorField
            On the whole volume's final grid, as :class:`~lfcore.correlate.Correlator` gives it.
        """
        g = self.grid
        cx, cy, cz = g.counts
        disp = np.full((cz, cy, cx, 3), np.nan)
        ratio, height = np.zeros((cz, cy, cx)), np.zeros((cz, cy, cx))
        outlier, replaced = np.zeros((cz, cy, cx), bool), np.zeros((cz, cy, cx), bool)
        self.peak_bytes = 0
        self.retries = 0
        fallback = 0.0
        for j in range(len(self.slabs)):
            while True:
                s = self.slabs[j]
                vol_a, vol_b = read(s.lo, s.hi)
                corr = Correlator((s.depth, *self.shape[1:]), config=self.config, device=self.device, grids=s.grids)

                self.fft = corr.fft
                self.peak_bytes = max(self.peak_bytes, correlator_bytes(corr) + vol_a.nbytes + vol_b.nbytes)
                f = corr(vol_a, vol_b, progress=progress)
                del vol_a, vol_b
                found = self._found(s, corr)
                if found.max_shift <= self._assumed.max_shift and found.reach <= self._assumed.reach:
                    break
                # the data exceed what this slab was planned for: plan again for what they need
                self._assumed = _Assumed(max(found.max_shift, self._assumed.max_shift),
                                         max(found.reach, self._assumed.reach))
                self.slabs = self._planned()
                self.retries += 1
            first = s.k0 - _first_row(self._plan.grids[-1], s.lo)
            rows = slice(first, first + s.k1 - s.k0)
            disp[s.k0:s.k1] = f.displacement[rows]
            ratio[s.k0:s.k1] = f.peak_ratio[rows]
            height[s.k0:s.k1] = f.peak_height[rows]
            outlier[s.k0:s.k1] = f.outlier[rows]
            replaced[s.k0:s.k1] = f.replaced[rows]
            fallback += corr.last_fallback_fraction * (s.k1 - s.k0) / cz
            del corr, f
            _release_freed_memory()
        self.last_fallback_fraction = fallback
        x, y, z = g.centres()
        return VectorField(x=x, y=y, z=z, displacement=disp, peak_ratio=ratio, peak_height=height, outlier=outlier,
                           replaced=replaced, grid=g)

    def _found(self, s: CorrelationSlab, corr: Correlator) -> _Assumed:
        """The largest predictor |z displacement| and replacement sweeps on the rows each pass
        computes as in memory (the only rows the kept vectors depend on)."""
        shift, reach = 0.0, 0
        n = len(corr.last_passes)
        for i, ((field, out), (ea, eb), (va, vb)) in enumerate(zip(corr.last_passes, s.exact, s.validated,
                                                                    strict=True)):
            k = _first_row(self._plan.grids[i], s.lo)
            if i + 1 < n and ea <= eb:  # the predictor of the next pass, where it is as in memory
                shift = max(shift, _largest_z(field[ea - k:eb - k + 1], self._plan.grids[i], self.shape,
                                              self._plan.grids[i + 1], self._plan.modes[i + 1]))
            rows = slice(va - k, vb - k + 1)  # every replaced vector the kept ones read
            if va <= vb and out[rows].any():
                reach = max(reach, _sweeps(out)[rows].max(initial=0))
        return _Assumed(max_shift=shift, reach=int(reach))


def _largest_z(field: np.ndarray, g: WindowGrid, shape: tuple[int, int, int], nxt: WindowGrid, mode: str) -> float:
    """Largest |z displacement| the predictor ``field`` (rows of grid ``g``) gives the next pass
    (grid ``nxt``) within those rows' planes: at the next windows' centres for a window shift, at
    every voxel for a deformation. Its trilinear interpolation, continued linearly past the
    outermost centres along x and y, is largest at its nodes or at the ends of that range."""
    if field.size == 0:
        return 0.0
    sx, sy, _ = g.centres()
    nx_c, ny_c, _ = nxt.centres()
    ends = ((nx_c[0], nx_c[-1]), (ny_c[0], ny_c[-1])) if mode == "shift" else ((0.0, shape[2] - 1.0),
                                                                               (0.0, shape[1] - 1.0))
    wx = _axis_weights(sx, np.concatenate([[ends[0][0]], sx, [ends[0][1]]]))
    wy = _axis_weights(sy, np.concatenate([[ends[1][0]], sy, [ends[1][1]]]))
    return float(np.abs(np.einsum("jb,ia,kba->kji", wy, wx, field[..., 2])).max())


def _release_freed_memory() -> None:
    """Hand the heap's freed pages back to the system (glibc's ``malloc_trim``), where there is one.

    Each slab frees its volumes and buffers (tens of MiB, of a slightly different size for each
    slab) before the next allocates its own; glibc serves allocations of that size from the heap
    once one has been freed, and without a trim the freed pages of earlier slabs stay resident
    beside the next slab's (measured: 458 MiB peak instead of 328 MiB over 8 slabs)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def _first_row(g: WindowGrid, lo: int) -> int:
    """The whole grid's first row (z) whose window starts at or after plane ``lo``."""
    return max(0, -((g.first[2] - lo) // g.step[2]))


def _rows_in(g: WindowGrid, lo: int, hi: int) -> tuple[int, int]:
    """The whole grid's first and last rows (z) whose windows lie in planes ``lo .. hi - 1``
    (first > last: none)."""
    return _first_row(g, lo), min(g.counts[2] - 1, (hi - g.window[2] - g.first[2]) // g.step[2])


def _sweeps(outlier: np.ndarray) -> np.ndarray:
    """The replacement sweep that fills each outlier: its chessboard distance to the nearest
    vector that is not one (every 26-neighbour of a valid vector is filled in the first sweep);
    :data:`REPLACE_SWEEPS` where none is that near (those are left unfilled, which also depends on
    that many rows)."""
    if outlier.all():
        return np.full(outlier.shape, REPLACE_SWEEPS)
    d = ndimage.distance_transform_cdt(outlier, metric="chessboard")
    return np.minimum(d, REPLACE_SWEEPS)


