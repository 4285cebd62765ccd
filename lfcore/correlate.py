"""3D multi-grid FFT cross-correlation of two reconstructed volumes.

Volumes are float32 arrays indexed (z, y, x). Window sizes, overlaps and displacements are
given per axis in the order (x, y, z), like voxel sizes and PVRs elsewhere in lfpiv; the vector
grid is indexed (z, y, x) like the volumes.

Method (Soria 1996; Scarano 2002)
---------------------------------
Interrogation volumes of one pass lie on a regular grid: along each axis the step is
``round(window * (1 - overlap))`` voxels and the grid is centred in the volume. Every window of
the pass is correlated in one batched launch (a batch is as many windows as fit the memory
budget): the windows of A and B are copied into one complex buffer (A real, B imaginary), their
means are removed, and one complex 3D FFT gives both spectra, separated by Hermitian symmetry.
The cross-spectrum conj(A) B is scaled so that the correlation is the correlation coefficient,
two windows' correlations share one inverse FFT, and the highest peak gives the displacement
of B relative to A with a 3-point Gaussian fit per axis (the centroid of the three samples
where a Gaussian cannot be fitted). The peak ratio is the highest peak over the highest one
outside a box of +-``peak_exclusion`` voxels around it.

Without zero padding the correlation is circular: displacements must stay below half a window
(the quarter-window rule keeps them well inside). With ``zero_pad`` each window is padded to
twice its size, which removes the wrap-around at the cost of 8x the FFT work; the correlation
is then not corrected for the shrinking overlap of large shifts, which the predictor keeps small.

Multi-grid: the first pass uses no predictor. Each further window size uses the previous
pass's field (outliers replaced, interpolated trilinearly to the new centres) as a window
shift: B's window is moved by the rounded prediction relative to A's, half each way. Then
``deform_iterations`` passes at the final size deform both volumes symmetrically with the
predictor interpolated at every voxel (A sampled at x - d(x)/2, B at x + d(x)/2) by cubic
B-spline interpolation (trilinear interpolation biases 3-voxel particles by about 0.03 voxel;
the B-spline by 0.004); each pass measures the residual displacement at the window centres.
The predictor of a deformation pass is smoothed (Gaussian, ``smooth_predictor`` grid spacings),
without which the iteration feeds each vector's random error back and stops converging; it is
continued linearly beyond the outermost centres, so that edge windows are deformed correctly.
Outliers are found and replaced between passes (normalized median test, :mod:`lfcore.vectors`)
and after the last one, where the flags are kept; the chapter's median filter can follow.

Direct correlation around the predictor (``search_radius``): after the first pass, a window's
residual displacement is small, so its correlation is needed only at lags within +-r voxels.
These passes deform both volumes by the predictor and correlate them directly: the lag d is
split between the volumes (A's window moved back by floor(d/2), B's forward by the rest), so
that a window's edge cuts each particle pair alike at every lag and the pair peaks at its own
displacement (a fixed window of A against a moving B pulls every cut particle inwards). Lags
of one parity share their windows, so the 3-point Gaussian fit uses lags p - 2, p, p + 2 around
the highest, p; a peak within two lags of the box's face is an outlier (the displacement may
lie beyond it). Windows overlap (at 75% every voxel lies in 64 of them), so the lag sums are
taken once per block of voxels that divides both the window and the step, and summed into
windows along x, y and z. The work is 2 r + 1 cubed multiply-adds a voxel instead of the FFTs
of every window, and no small-window FFT bias remains: on blobs moved by (0.3, -0.7, 0.45)
voxels (tests) the RMS error falls from 0.018 to 0.006 voxel. The first pass, which has no
predictor, is always an FFT pass; it may use its own overlap (``first_overlap``).

FFT: on CUDA the 3D FFT is Warp's tile FFT (cuFFTDx) applied in place along each axis: along x
to whole lines, along y and z to blocks of columns turned in shared memory (no pass rotates the
buffer's axes in global memory); on the CPU it is scipy's pocketfft, multi-threaded, which
measured 3-5x faster than Warp's single-threaded CPU tile FFT at power-of-two sizes and over
100x faster at sizes such as 160 (which Warp's CPU path transforms as a direct DFT). The Warp
path can be forced with ``fft="warp"`` on any device; every other step is a Warp kernel on
every device. Warp's CUDA tile FFT takes any length cuFFTDx supports where Warp was built with
libmathdx (the PyPI wheels are), and power-of-two lengths only otherwise.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from lfcore._deprecation import keyword_options
from lfcore.device import RowOffset, Rows, launch_rows, resolve_device, warp
from lfcore.vectors import MedianTest, median_filter, normalized_median_test, replace_outliers, smooth

__all__ = ["CorrelationConfig", "CorrelationError", "Correlator", "VectorField", "WindowGrid", "correlate",
           "pass_grids", "window_grid"]

#: Memory for one batch of windows (both FFT buffers), per device kind.
DEFAULT_BATCH_BYTES = {"cpu": 256 << 20, "cuda": 8 << 30}
#: Threads per window in the reductions (window means, peak search).
REDUCE_THREADS = {"cpu": 1, "cuda": 128}
#: In the "elements" (GPU) layout, window axes up to this long other than x are transformed by
#: a direct DFT from shared memory (:func:`lfcore._kernels.correlate.dft_columns`) rather than
#: by the tile FFT, which would run them on a few threads a block.
SHORT_DFT = 32
MIN_WINDOW = 4
#: Largest search radius of the direct correlation (9^3 lags a window at 4).
MAX_SEARCH_RADIUS = 8
#: Shared memory for the grown blocks of A and B in the direct correlation.
LAG_TILE_BYTES = 40 << 10
#: Threads per block of voxels in the direct correlation on a GPU.
LAG_THREADS = 512


class CorrelationError(ValueError):
    """Settings that cannot correlate these volumes; the message names the setting."""


@dataclass(frozen=True)
class CorrelationConfig:
    """Settings of a multi-grid correlation.

    Attributes
    ----------
    windows
        One window size per pass, each (x, y, z) in voxels, largest first; e.g. the chapter's
        ((320, 320, 64), (160, 160, 32)).
    overlap
        Overlap of neighbouring windows per axis (x, y, z), each in [0, 1); a single number
        applies to every axis. 0.75 is the chapter's.
    deform_iterations
        Passes with volume deformation at the final window size after the window-shift passes.
    zero_pad
        Pad each window to twice its size before the FFT (linear instead of circular correlation).
    peak_exclusion
        Half-width in voxels of the box around the highest peak that the second peak of the
        peak ratio must lie outside.
    median_test
        Epsilon and threshold of the normalized median test (between passes and at the end).
    median_filter
        Apply the chapter's 3x3(x3) median filter to the final field.
    smooth_predictor
        Gaussian sigma, in grid spacings, of the smoothing of the predictor of a deformation
        pass (0 for none). Linear fields pass unchanged.
    interpolation
        Interpolation of the volume deformation: ``"cubic"`` (cubic B-spline on prefiltered
        coefficients, 64 voxels a sample) or ``"linear"`` (trilinear, 8 voxels, faster but
        biased by about 0.03 voxel on 3-voxel particles, where the B-spline's bias is 0.004).
    fft
        ``"auto"`` (scipy on the CPU, Warp on CUDA), ``"scipy"`` (CPU only) or ``"warp"``.
    batch_bytes
        Memory budget of one batch of windows; None for the device's default.
    search_radius
        Half-width in voxels (x, y, z), 2 to 8, of the lags at which the passes after the
        first are correlated directly around their predictor instead of by FFT (see the module
        notes); one number applies to every axis; None (the default) uses the FFT in every pass.
        With it, every pass after the first deforms the volumes (no window shift), and a window
        whose peak lies within two lags of the search box's face is replaced as an outlier.
        Each window's size and step must share a factor along every axis (true of any window at
        50% or 75% overlap of a multiple of 4). 3 suits residuals below 1 voxel.
    first_overlap
        Overlap of the first pass's windows, which only predict the next pass (as ``overlap``);
        None uses ``overlap``.
    """

    windows: tuple[tuple[int, int, int], ...] = ((320, 320, 64), (160, 160, 32))
    overlap: float | tuple[float, float, float] = 0.75
    deform_iterations: int = 2
    zero_pad: bool = False
    peak_exclusion: int = 2
    median_test: MedianTest = field(default_factory=MedianTest)
    median_filter: bool = False
    interpolation: str = "cubic"
    smooth_predictor: float = 1.0
    fft: str = "auto"
    batch_bytes: int | None = None
    search_radius: int | tuple[int, int, int] | None = None
    first_overlap: float | tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        wins = tuple(tuple(int(n) for n in w) for w in self.windows)
        if not wins:
            raise CorrelationError("give at least one window size")
        for w in wins:
            if len(w) != 3:
                raise CorrelationError(f"a window size is three numbers (x, y, z), got {w}")
            if min(w) < MIN_WINDOW:
                raise CorrelationError(f"window {_fmt(w)} is too small: every side needs at least {MIN_WINDOW} voxels")
        object.__setattr__(self, "windows", wins)
        object.__setattr__(self, "overlap", _per_axis_overlap(self.overlap, "overlap"))
        if self.first_overlap is not None:
            object.__setattr__(self, "first_overlap", _per_axis_overlap(self.first_overlap, "first_overlap"))
        if self.search_radius is not None:
            r = _per_axis(self.search_radius, int)
            if len(r) != 3 or min(r) < 2 or max(r) > MAX_SEARCH_RADIUS:
                raise CorrelationError(f"search_radius must be 2 to {MAX_SEARCH_RADIUS} voxels on every axis (one "
                                       f"number, or x, y, z), got {self.search_radius}")
            object.__setattr__(self, "search_radius", r)
        if self.deform_iterations < 0:
            raise CorrelationError(f"deform_iterations must be >= 0, got {self.deform_iterations}")
        if self.peak_exclusion < 1:
            raise CorrelationError(f"peak_exclusion must be at least 1 voxel, got {self.peak_exclusion}")
        if self.interpolation not in ("cubic", "linear"):
            raise CorrelationError(f"interpolation must be 'cubic' or 'linear', got '{self.interpolation}'")
        if self.fft not in ("auto", "scipy", "warp"):
            raise CorrelationError(f"fft must be 'auto', 'scipy' or 'warp', got '{self.fft}'")

    @property
    def passes(self) -> list[tuple[tuple[int, int, int], str]]:
        """(window, predictor) of every pass; predictor is 'none', 'shift' or 'deform'."""
        out = [(self.windows[0], "none")]
        out += [(w, "shift" if self.search_radius is None else "deform") for w in self.windows[1:]]
        out += [(self.windows[-1], "deform")] * self.deform_iterations
        return out


def _per_axis(value, cast) -> tuple:
    """One number for every axis, or one per axis, as a tuple of ``cast`` values."""
    return (cast(value),) * 3 if np.isscalar(value) else tuple(cast(v) for v in value)


def _per_axis_overlap(value, name: str) -> tuple[float, float, float]:
    ov = _per_axis(value, float)
    if len(ov) != 3 or not all(0.0 <= o < 1.0 for o in ov):
        raise CorrelationError(f"{name} must be at least 0 and below 1 on every axis, got {value}")
    return ov  # type: ignore[return-value]


def _fmt(w: tuple[int, ...]) -> str:
    return "x".join(str(n) for n in w)


@dataclass(frozen=True)
class WindowGrid:
    """The windows of one pass.

    Attributes
    ----------
    window
        (x, y, z) window size in voxels.
    step
        (x, y, z) distance between neighbouring windows in voxels.
    first
        (x, y, z) voxel index of the first window's first voxel.
    counts
        (x, y, z) number of windows along each axis.
    """

    window: tuple[int, int, int]
    step: tuple[int, int, int]
    first: tuple[int, int, int]
    counts: tuple[int, int, int]

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx) of the vector grid."""
        return self.counts[2], self.counts[1], self.counts[0]

    @property
    def size(self) -> int:
        return int(np.prod(self.counts))

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """1-D voxel coordinates (x, y, z) of the window centres along each axis."""
        return tuple(f + s * np.arange(n) + 0.5 * (w - 1)  # type: ignore[return-value]
                     for f, s, n, w in zip(self.first, self.step, self.counts, self.window, strict=True))

    def starts(self) -> np.ndarray:
        """(size, 3) int32 first voxel (x, y, z) of every window, x fastest."""
        sx, sy, sz = (f + s * np.arange(n) for f, s, n in zip(self.first, self.step, self.counts, strict=True))
        z, y, x = np.meshgrid(sz, sy, sx, indexing="ij")
        return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.int32)

    @property
    def origin(self) -> np.ndarray:
        """Voxel coordinates (x, y, z) of the first window's centre."""
        return np.asarray(self.first, float) + 0.5 * (np.asarray(self.window, float) - 1)


def window_grid(shape: tuple[int, int, int], window: tuple[int, int, int],
                overlap: tuple[float, float, float]) -> WindowGrid:
    """The grid of windows of size ``window`` (x, y, z) over a volume of ``shape`` (z, y, x).

    Raises
    ------
    CorrelationError
        If the window is larger than the volume along an axis.
    """
    n_xyz = (shape[2], shape[1], shape[0])
    steps, firsts, counts = [], [], []
    for axis, n, w, o in zip("xyz", n_xyz, window, overlap, strict=True):
        if w > n:
            raise CorrelationError(f"window {_fmt(window)} (x by y by z) is larger than the volume along {axis} "
                                   f"({w} > {n} voxels; the volume is {_fmt(n_xyz)}); choose smaller windows")
        s = max(1, int(round(w * (1.0 - o))))
        c = (n - w) // s + 1
        steps.append(s)
        counts.append(c)
        firsts.append((n - w - (c - 1) * s) // 2)  # centre the grid in the volume
    return WindowGrid(window=tuple(window), step=tuple(steps), first=tuple(firsts), counts=tuple(counts))


def _checked_grids(shape: tuple[int, int, int], config: CorrelationConfig,
                   grids: Sequence[WindowGrid]) -> list[WindowGrid]:
    """``grids``, one per pass of ``config``, each of the pass's window and inside ``shape`` (z, y, x)."""
    grids = list(grids)
    if len(grids) != len(config.passes):
        raise CorrelationError(f"{len(config.passes)} passes need as many window grids, got {len(grids)}")
    n_xyz = (shape[2], shape[1], shape[0])
    for g, (w, _) in zip(grids, config.passes, strict=True):
        if tuple(g.window) != tuple(w):
            raise CorrelationError(f"a window grid of {_fmt(g.window)} voxels for a pass of {_fmt(w)}")
        if min(g.counts) < 1 or min(g.step) < 1 or min(g.first) < 0 or any(
                f + (c - 1) * s + ww > n for f, c, s, ww, n in zip(g.first, g.counts, g.step, g.window, n_xyz,
                                                                 strict=True)):
            raise CorrelationError(f"the window grid {g} does not lie inside the volume {_fmt(n_xyz)} (x, y, z)")
    return grids


def pass_grids(shape: tuple[int, int, int], config: CorrelationConfig) -> list[WindowGrid]:
    """The window grid of every pass of ``config`` over volumes of ``shape`` (z, y, x); the last
    one is the grid of the vectors.

    Raises
    ------
    CorrelationError
        If a pass's window is larger than the volume.
    """
    first_ov = config.first_overlap or config.overlap
    return [window_grid(shape, w, first_ov if i == 0 else config.overlap) for i, (w, _) in enumerate(config.passes)]


@dataclass
class VectorField:
    """The result of a correlation, in voxels.

    Attributes
    ----------
    x, y, z
        1-D voxel coordinates of the window centres (voxel [0, 0, 0] has coordinates 0).
    displacement
        (nz, ny, nx, 3) displacement (x, y, z) of B relative to A in voxels, outliers replaced
        (NaN only where no valid vector was left to replace one).
    peak_ratio
        (nz, ny, nx) highest over second-highest correlation peak of the last pass.
    peak_height
        (nz, ny, nx) correlation coefficient at the highest peak of the last pass.
    outlier, replaced
        (nz, ny, nx) bool flags of the final outlier test and replacement.
    grid
        The windows of the last pass.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    displacement: np.ndarray
    peak_ratio: np.ndarray
    peak_height: np.ndarray
    outlier: np.ndarray
    replaced: np.ndarray
    grid: WindowGrid

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.displacement.shape[:3]


def _padded(window: tuple[int, int, int], zero_pad: bool) -> tuple[int, int, int]:
    """(Pz, Py, Px) of the FFT buffer."""
    p = tuple(2 * w if zero_pad else w for w in window)
    return p[2], p[1], p[0]


def _axis_weights(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(len(dst), len(src)) linear interpolation weights from points ``src`` to ``dst`` (1-D,
    regularly spaced), the end cells' lines continued beyond the outermost points (as the kernels'
    ``axis_weight``); one source point gives a constant."""
    w = np.zeros((len(dst), len(src)))
    if len(src) == 1:
        w[:, 0] = 1.0
        return w
    q = (dst - src[0]) / (src[1] - src[0])
    i0 = np.clip(np.floor(q).astype(int), 0, len(src) - 2)
    t = q - i0
    rows = np.arange(len(dst))
    w[rows, i0] = 1.0 - t
    w[rows, i0 + 1] += t
    return w


def _interp(field: np.ndarray, grid: WindowGrid, to: WindowGrid) -> np.ndarray:
    """Trilinear interpolation of a (nz, ny, nx, 3) field on ``grid`` at the centres of ``to``.

    Returns the (to.size, 3) values, x fastest. Beyond the outermost centres the field is
    extrapolated linearly (as the kernels' ``predictor_at`` does); along an axis with a single
    window it is constant. Both grids are regular, so the interpolation is separable: one small
    weight matrix per axis.
    """
    (sx, sy, sz), (dx, dy, dz) = grid.centres(), to.centres()
    out = np.einsum("kc,jb,ia,cbad->kjid", _axis_weights(sz, dz), _axis_weights(sy, dy), _axis_weights(sx, dx),
                    np.asarray(field, dtype=np.float64), optimize=True)
    return out.reshape(-1, 3)


@dataclass(frozen=True)
class _LagPlan:
    """How a pass is correlated directly: blocks of voxels, and windows made of them.

    ``block`` (x, y, z) voxels divides both the window and the step; a window is
    ``per_window`` blocks, the next window starts ``stride`` blocks further, ``blocks`` cover
    every window of the pass, and ``slab`` window rows along z are correlated at a time.
    """

    block: tuple[int, int, int]
    per_window: tuple[int, int, int]
    stride: tuple[int, int, int]
    blocks: tuple[int, int, int]
    columns: int
    slab: int
    entries: int


def _lag_plan(g: WindowGrid, radius: tuple[int, int, int], budget: int) -> _LagPlan:
    """The blocks of a directly correlated pass (see :class:`_LagPlan`).

    Raises
    ------
    CorrelationError
        If a window and its step share no factor worth a block, or one slab does not fit.
    """
    block = []
    for w, s in zip(g.window, g.step, strict=True):
        block.append(math.gcd(w, s))
    # both grown blocks (see kc.block_lag_sums) must fit in shared memory: shrink the largest side
    def tile_bytes(b):
        grown = [n + 2 * ((r + 1) // 2) for n, r in zip(b, radius, strict=True)]
        grown[0] += 1 - radius[0] % 2
        return 2 * 4 * int(np.prod(grown))

    while tile_bytes(block) > LAG_TILE_BYTES:
        ax = int(np.argmax(block))
        smaller = [f for f in range(block[ax] - 1, 0, -1) if block[ax] % f == 0]
        block[ax] = smaller[0] if smaller else 1
    if int(np.prod(block)) < 8:
        raise CorrelationError(f"window {_fmt(g.window)} and its step {_fmt(g.step)} share no block of voxels for the "
                               "direct correlation (search_radius); choose windows and an overlap whose step divides "
                               "the window (e.g. 75% or 50% overlap of a multiple of 4), or no search radius")
    per = tuple(w // b for w, b in zip(g.window, block, strict=True))
    stride = tuple(s // b for s, b in zip(g.step, block, strict=True))
    blocks = tuple((c - 1) * st + m for c, st, m in zip(g.counts, stride, per, strict=True))
    columns = int(np.prod([2 * r + 1 for r in radius])) + 1
    row_entries = blocks[0] * blocks[1] * columns  # one plane of blocks along z
    slab = 1
    while slab < g.counts[2] and ((slab * stride[2] + per[2]) * row_entries * 12 * 2 <= budget):
        slab += 1
    entries = ((slab - 1) * stride[2] + per[2]) * row_entries
    if entries * 12 * 2 > max(budget, 1 << 30):
        raise CorrelationError(f"the direct correlation of windows {_fmt(g.window)} needs "
                               f"{entries * 24 / 2**30:.1f} GiB for one row of windows; use a smaller search_radius")
    return _LagPlan(block=tuple(block), per_window=per, stride=stride, blocks=blocks, columns=columns, slab=slab,
                    entries=entries)


class Correlator:
    """Multi-grid correlation of volume pairs of one shape; device buffers are allocated once.

    Parameters
    ----------
    shape
        (nz, ny, nx) of the volumes.
    config
        Windows, overlap, passes and post-processing.
    device
        Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``) or None for the first GPU, else CPU.
    layout
        How the copy into the FFT buffer and the cross-spectrum are spread over threads:
        ``"rows"`` (a thread per buffer row, which suits CPU caches), ``"elements"`` (a thread
        per sample, so that a GPU's neighbouring threads touch neighbouring addresses, and short
        y and z axes transformed by a direct DFT) or ``"auto"`` (rows on the CPU, elements on
        a GPU). The results are the same to float round-off.
    grids
        The window grid of every pass (:func:`pass_grids` of ``shape`` by default). Depth slabs
        (:mod:`lfcore.slab_correlate`) give a part of the volume the whole volume's windows
        that lie in it, so that its vectors sit where the whole volume's do.

    Raises
    ------
    CorrelationError
        If a window is larger than the volume, or the FFT backend does not fit the device.
    """

    @keyword_options("config", "device", since="0.1.0")
    def __init__(self, shape: tuple[int, int, int], *, config: CorrelationConfig = CorrelationConfig(),
                 device: str | None = None, layout: str = "auto",
                 grids: Sequence[WindowGrid] | None = None) -> None:
        from lfcore._kernels import correlate as kc

        self._k = kc
        self.wp = warp()
        self.device = resolve_device(device)
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise CorrelationError(f"volumes must be 3-D (z, y, x), got shape {shape}")
        self.config = config
        kind = "cpu" if self.device == "cpu" else "cuda"
        if layout not in ("auto", "rows", "elements"):
            raise CorrelationError(f"layout must be 'auto', 'rows' or 'elements', got '{layout}'")
        self.layout = layout if layout != "auto" else ("rows" if kind == "cpu" else "elements")
        fft = config.fft if config.fft != "auto" else ("scipy" if kind == "cpu" else "warp")
        if fft == "scipy" and kind != "cpu":
            raise CorrelationError("fft='scipy' runs on the CPU only; use fft='warp' or 'auto' on a GPU")
        self.fft = fft
        self.threads = REDUCE_THREADS[kind]
        self.grids = pass_grids(self.shape, config) if grids is None else _checked_grids(self.shape, config, grids)
        budget = config.batch_bytes or DEFAULT_BATCH_BYTES[kind]
        wp = self.wp
        # passes correlated directly around the predictor (all after the first, with a search radius)
        self._lags: list[_LagPlan | None] = [
            _lag_plan(g, config.search_radius, budget) if config.search_radius is not None and i > 0 else None
            for i, g in enumerate(self.grids)]
        self._batch: list[int] = []
        biggest = 2
        for g, lag in zip(self.grids, self._lags, strict=True):
            if lag is not None:
                self._batch.append(0)
                continue
            p = int(np.prod(_padded(g.window, config.zero_pad)))
            nb = max(2, min(g.size, budget // (2 * 8 * p)))
            nb += nb % 2  # windows are correlated two per inverse FFT
            self._batch.append(nb)
            biggest = max(biggest, nb * p)
        nb_max = max(2, *self._batch)
        d = self.device
        self._buf = wp.empty(biggest, dtype=wp.vec2f, device=d)
        self._scratch = wp.empty(biggest, dtype=wp.vec2f, device=d)
        rows = max(nb * int(np.prod(_padded(g.window, config.zero_pad)[:2]))
                   for nb, g in zip(self._batch, self.grids, strict=True))
        lag_entries = max((lag.entries for lag in self._lags if lag is not None), default=1)
        self._lag_sums = [wp.empty(lag_entries, dtype=wp.vec3f, device=d) for _ in range(2)]
        self._sums = wp.empty(rows, dtype=wp.vec4, device=d)
        self._masks = [self._footprint(g.window, config.zero_pad) for g in self.grids]
        self._starts = [wp.array(g.starts(), dtype=wp.vec3i, device=d) for g in self.grids]
        self._vol_a, self._vol_b = (wp.empty(self.shape, dtype=wp.float32, device=d) for _ in range(2))
        deforms = "deform" in (m for _, m in config.passes)
        vol = self.shape if deforms else (1, 1, 1)
        if deforms and config.search_radius is not None:
            # the direct correlation reads B up to the radius beyond a window: pad with zeros
            rx, ry, rz = config.search_radius
            nz, ny, nx = self.shape
            self._def_a, self._def_b = (wp.zeros((nz + 2 * rz, ny + 2 * ry, nx + 2 * rx), dtype=wp.float32, device=d)
                                        for _ in range(2))
            self._def_in = tuple(v[rz:rz + nz, ry:ry + ny, rx:rx + nx] for v in (self._def_a, self._def_b))
        else:
            self._def_a, self._def_b = (wp.empty(vol, dtype=wp.float32, device=d) for _ in range(2))
            self._def_in = (self._def_a, self._def_b)
        coef = vol if deforms and config.interpolation == "cubic" else (1, 1, 1)
        self._coef_a, self._coef_b = (wp.empty(coef, dtype=wp.float32, device=d) for _ in range(2))
        self._row_val = wp.empty(rows, dtype=float, device=d)
        self._row_i = wp.empty(rows, dtype=int, device=d)
        self._part_val = wp.empty((nb_max, self.threads), dtype=float, device=d)
        self._part_idx = wp.empty((nb_max, self.threads), dtype=int, device=d)
        self._mean = wp.empty(nb_max, dtype=wp.vec2f, device=d)
        self._scale = wp.empty(nb_max, dtype=float, device=d)
        self._peak1 = wp.zeros(nb_max, dtype=wp.vec3i, device=d)
        self._peak2 = wp.zeros(nb_max, dtype=wp.vec3i, device=d)
        self._val1 = wp.empty(nb_max, dtype=float, device=d)
        self._val2 = wp.empty(nb_max, dtype=float, device=d)
        n_max = max(g.size for g in self.grids)
        self._disp = wp.empty(n_max, dtype=wp.vec3, device=d)
        self._height = wp.empty(n_max, dtype=float, device=d)
        self._ratio = wp.empty(n_max, dtype=float, device=d)
        self._fallback = wp.empty(n_max, dtype=int, device=d)
        self._valid = wp.empty(n_max, dtype=int, device=d)
        self.last_fallback_fraction = 0.0
        #: per pass of the last call: the field that predicts the next pass (outliers replaced,
        #: smoothed where a deformation follows; (nz, ny, nx, 3) voxels) and the outlier mask
        self.last_passes: list[tuple[np.ndarray, np.ndarray]] = []
        self._twiddles: dict = {}
        self._nonfinite = wp.zeros(1, dtype=int, device=d)

    # --- one pass -------------------------------------------------------------------------
    def _footprint(self, window: tuple[int, int, int], zero_pad: bool) -> list:
        """Spectra (x, y, z) of a window's footprint in its FFT buffer, 1-D per axis (separable)."""
        out = []
        for w in window:
            mask = np.zeros(2 * w if zero_pad else w)
            mask[:w] = 1.0
            f = np.fft.fft(mask)
            out.append(self.wp.array(np.stack([f.real, f.imag], axis=1).astype(np.float32), dtype=self.wp.vec2f,
                                     device=self.device))
        return out

    def _twiddle(self, n: int):
        """exp(-2 pi i m / n), m = 0 .. n - 1, on the device (made once per length)."""
        if n not in self._twiddles:
            w = np.exp(-2j * np.pi * np.arange(n) / n)
            self._twiddles[n] = self.wp.array(np.stack([w.real, w.imag], axis=1).astype(np.float32),
                                              dtype=self.wp.vec2f, device=self.device)
        return self._twiddles[n]

    def _view(self, buf, n: int, dims: tuple[int, ...]):
        return buf[: n * int(np.prod(dims))].reshape((n, *dims))

    def _fft3d(self, src, n: int, dims: tuple[int, int, int], inverse: bool):
        """3D FFT of ``n`` windows (Pz, Py, Px) in ``src``, unnormalised in both directions.

        Returns the (n, Pz, Py, Px) result: a view of ``src``, transformed in place.
        """
        wp, kc = self.wp, self._k
        if self.fft == "scipy":
            x = self._view(src, n, dims).numpy().view(np.complex64)[..., 0]
            f = scipy.fft.ifftn if inverse else scipy.fft.fftn
            y = f(x, axes=(1, 2, 3), norm="forward" if inverse else "backward", workers=os.cpu_count() or 1,
                  overwrite_x=True)
            if np.shares_memory(x, y):
                return self._view(src, n, dims)
            self._view(src, n, dims).numpy().view(np.complex64)[..., 0] = y
            return self._view(src, n, dims)
        nz, ny, nx = dims
        # x: whole lines; y and z: columns turned in shared memory (see kc.fft_columns); in place
        gpu = self.device != "cpu"
        rows = max(1, min(16, 1024 // nx)) if gpu else max(1, min(64, 4096 // nx))
        lines = self._view(src, n, dims).reshape((n * nz * ny, nx))
        if nx > 1:
            wp.launch_tiled(kc.fft_lines(nx, rows), dim=math.ceil(lines.shape[0] / rows), inputs=[lines, int(inverse)],
                            block_dim=max(1, nx // 2) if gpu else 1, device=self.device)
        for length, view in ((ny, lines), (nz, lines.reshape((n * nz, ny * nx)))):
            if length == 1:
                continue
            if self.layout == "elements" and length <= SHORT_DFT:
                blocks = (view.shape[0] // length, math.ceil(view.shape[1] / 16))
                wp.launch_tiled(kc.dft_columns(length, 16), dim=blocks, inputs=[view, self._twiddle(length),
                                                                                 int(inverse)],
                                block_dim=128 if gpu else 1, device=self.device)
                continue
            cols = max(1, min(16, 1024 // length)) if gpu else 16
            blocks = (view.shape[0] // length, math.ceil(view.shape[1] / cols))
            wp.launch_tiled(kc.fft_columns(length, cols), dim=blocks, inputs=[view, int(inverse)],
                            block_dim=max(1, length // 2) if gpu else 1, device=self.device)
        return self._view(src, n, dims)

    def _run_pass(self, vol_a, vol_b, i: int, shift_a: np.ndarray, shift_b: np.ndarray) -> None:
        """Correlate every window of pass ``i``; results land in the per-window device arrays."""
        wp, kc, d = self.wp, self._k, self.device
        g = self.grids[i]
        dims = _padded(g.window, self.config.zero_pad)
        p = int(np.prod(dims))
        size = wp.vec3i(*g.window)
        starts = self._starts[i]
        sa = wp.array(shift_a, dtype=wp.vec3i, device=d)
        sb = wp.array(shift_b, dtype=wp.vec3i, device=d)
        masks = self._masks[i]
        pad = wp.vec3i(dims[2], dims[1], dims[0])
        nb = self._batch[i]
        for first in range(0, g.size, nb):
            n = min(nb, g.size - first)
            buf = self._view(self._buf, n, dims)
            sums = self._sums[: n * dims[0] * dims[1]].reshape((n, dims[0] * dims[1]))
            if self.layout == "rows":
                launch_rows(kc.gather, n, [vol_a, vol_b, starts, sa, sb, RowOffset(first), size, Rows(buf), Rows(sums)],
                            d, rest=(dims[0], dims[1]))
            else:
                wp.launch(kc.gather_elements, dim=(n, *dims), device=d,
                          inputs=[vol_a, vol_b, starts, sa, sb, first, size, buf])
                lines = n * dims[0] * dims[1]
                rows = max(1, min(64, 4096 // dims[2]))
                wp.launch_tiled(kc.row_sums(dims[2], rows), dim=math.ceil(lines / rows),
                                inputs=[buf.reshape((lines, dims[2])), self._sums[:lines]],
                                block_dim=128 if d != "cpu" else 1, device=d)
            wp.launch(kc.window_stats, dim=n, device=d, inputs=[sums, float(np.prod(g.window)), self._mean,
                                                                 self._scale])
            spec = self._fft3d(self._buf, n, dims, inverse=False)
            # the packed cross-spectra go to the buffer that does not hold the spectra
            free = self._scratch
            slots = (n + 1) // 2
            packed = self._view(free, slots, dims)
            if self.layout == "rows":
                launch_rows(kc.cross_spectrum, slots, [Rows(spec, scale=2), Rows(self._mean[:n], scale=2),
                                                       Rows(self._scale[:n], scale=2), 1.0 / p, *masks, Rows(packed)],
                            d, rest=(dims[0], dims[1]))
            else:
                wp.launch(kc.cross_spectrum_elements, dim=(slots, *dims), device=d,
                          inputs=[spec, self._mean[:n], self._scale[:n], 1.0 / p, *masks, packed])
            corr = self._fft3d(free, slots, dims, inverse=True)
            # two windows share a correlation slot: CPU blocks start at even windows
            row_val = Rows(self._row_val[: n * dims[0] * dims[1]].reshape((n, dims[0] * dims[1])))
            row_i = Rows(self._row_i[: n * dims[0] * dims[1]].reshape((n, dims[0] * dims[1])))
            launch_rows(kc.row_peaks, n, [Rows(corr, div=2), row_val, row_i], d, rest=(dims[0] * dims[1],), align=2)
            for second, out, where in ((0, self._val1, self._peak1), (1, self._val2, self._peak2)):
                launch_rows(kc.peak_partial, n, [Rows(corr, div=2), row_val, row_i, self.threads, Rows(self._peak1),
                                                 self.config.peak_exclusion, second, Rows(self._part_val),
                                                 Rows(self._part_idx)], d, rest=(self.threads,), align=2)
                wp.launch(kc.peak_reduce, dim=n, device=d,
                          inputs=[self._part_val[:n], self._part_idx[:n], pad, out, where])
            wp.launch(kc.peak_fit, dim=n, device=d,
                      inputs=[corr, first, self._scale, self._peak1, self._val1, self._val2, self._disp,
                              self._height, self._ratio, self._fallback, self._valid])

    def _run_local(self, def_a, def_b, i: int) -> None:
        """Correlate every window of pass ``i`` directly at the lags of the search box.

        ``def_a`` and ``def_b`` are the deformed volumes padded by the search radius. Windows
        are taken in slabs of window rows along z (as many as the memory budget allows): the
        lag sums of the slab's blocks of voxels, summed into windows along x, y and z, then
        each window's peak.
        """
        wp, kc, d = self.wp, self._k, self.device
        g, lag = self.grids[i], self._lags[i]
        rx, ry, rz = self.config.search_radius
        bx, by, bz = lag.block
        mx, my, mz = lag.per_window
        sx, sy, sz = lag.stride
        cx, cy, cz = g.counts
        nbx, nby = lag.blocks[0], lag.blocks[1]
        cols = lag.columns
        kernel = kc.block_lag_sums(lag.block, self.config.search_radius)
        nl = wp.vec3i(2 * rx + 1, 2 * ry + 1, 2 * rz + 1)
        p_buf, q_buf = self._lag_sums
        # on a GPU, a thread per task (two x lags; up to LAG_THREADS, in whole warps)
        threads = min(LAG_THREADS, -(-kc.lag_tasks(self.config.search_radius) // 32) * 32) if d != "cpu" else 1
        for k0 in range(0, cz, lag.slab):
            kz = min(lag.slab, cz - k0)
            nbz = (kz - 1) * sz + mz
            origin = wp.vec3i(g.first[0] + rx, g.first[1] + ry, g.first[2] + rz + k0 * sz * bz)
            blocks = p_buf[: nbz * nby * nbx * cols].reshape((nbz * nby * nbx, cols))
            wp.launch_tiled(kernel, dim=nbz * nby * nbx, inputs=[def_a, def_b, origin, wp.vec3i(nbx, nby, nbz), blocks],
                            block_dim=threads, device=d)
            src = blocks.reshape((nbz, nby, nbx, cols))
            for axis, shape, m, stride, buf in ((2, (nbz, nby, cx, cols), mx, sx, q_buf),
                                                (1, (nbz, cy, cx, cols), my, sy, p_buf),
                                                (0, (kz, cy, cx, cols), mz, sz, q_buf)):
                dst = buf[: int(np.prod(shape))].reshape(shape)
                wp.launch(kc.window_sum_axis, dim=shape, inputs=[src, axis, m, stride, dst], device=d)
                src = dst
            n = kz * cy * cx
            wp.launch(kc.local_peak, dim=n, device=d,
                      inputs=[src.reshape((n, cols)), k0 * cy * cx, nl, float(np.prod(g.window)),
                              self.config.peak_exclusion, self._disp, self._height, self._ratio, self._fallback,
                              self._valid])

    def _prefilter(self, vol_a, vol_b) -> None:
        """Cubic B-spline coefficients of both volumes, once per pair."""
        wp, d = self.wp, self.device
        nz, ny, nx = self.shape
        for src, dst in ((vol_a, self._coef_a), (vol_b, self._coef_b)):
            wp.copy(dst, src)
            for axis, dims in ((0, (nz, ny)), (1, (nz, nx)), (2, (ny, nx))):
                launch_rows(self._k.bspline_prefilter, dims[0], [dst, axis, RowOffset(0)], d, rest=dims[1:])

    def _deform(self, vol_a, vol_b, pred: np.ndarray, pgrid: WindowGrid):
        """Both volumes deformed by the predictor (see the kernel ``deform_volumes``)."""
        wp = self.wp
        bspline = self.config.interpolation == "cubic"
        if bspline:
            vol_a, vol_b = self._coef_a, self._coef_b
        pred_dev = wp.array(np.ascontiguousarray(pred, dtype=np.float32), dtype=wp.vec3, device=self.device)
        launch_rows(self._k.deform_volumes, self.shape[0],
                    [vol_a, vol_b, pred_dev, wp.vec3(*pgrid.origin.astype(float)),
                     wp.vec3(*(float(s) for s in pgrid.step)), int(bspline), RowOffset(0), *self._def_in],
                    self.device, rest=self.shape[1:])
        return self._def_a, self._def_b

    # --- the multi-grid correlation ---------------------------------------------------------
    def _upload(self, volume, dst):
        """Copy one volume into its device buffer (allocated once); a volume already on the
        device is used where it is."""
        if isinstance(volume, self.wp.array):
            if tuple(volume.shape) != self.shape or volume.dtype != self.wp.float32:
                raise CorrelationError(f"this correlator takes float32 volumes of shape {self.shape} (z, y, x), got "
                                       f"{volume.dtype.__name__} {tuple(volume.shape)}")
            if str(volume.device) != self.device:
                raise CorrelationError(f"the volume is on {volume.device}, the correlator on {self.device}; "
                                       "build the correlator on the volume's device")
            return volume
        v = np.asarray(volume)
        if v.shape != self.shape:
            raise CorrelationError(f"this correlator takes volumes of shape {self.shape} (z, y, x), got {v.shape}")
        if self.device == "cpu" and not np.all(np.isfinite(v)):
            raise CorrelationError("volumes must be finite")
        dst.assign(np.ascontiguousarray(v, dtype=np.float32))
        if self.device != "cpu":
            # checked on the GPU: a host scan of two large volumes costs more than their copy
            self._nonfinite.zero_()
            self.wp.launch(self._k.count_nonfinite, dim=self.shape, inputs=[dst, self._nonfinite], device=self.device)
            if int(self._nonfinite.numpy()[0]):
                raise CorrelationError("volumes must be finite")
        return dst

    @keyword_options("progress", since="0.1.0")
    def __call__(self, volume_a: np.ndarray, volume_b: np.ndarray, *,
                 progress: Callable[[int], None] | None = None) -> VectorField:
        """Correlate one pair.

        Parameters
        ----------
        volume_a, volume_b
            (nz, ny, nx) float32 intensities of the first and second frame: NumPy arrays, or
            Warp arrays on the correlator's device (used in place, not copied; their values
            are taken as finite, as a reconstruction makes them).
        progress
            Called with 1 after each pass.

        Returns
        -------
        VectorField
            Displacements of B relative to A, in voxels, on the last pass's grid.
        """
        vol_a, vol_b = self._upload(volume_a, self._vol_a), self._upload(volume_b, self._vol_b)
        cfg = self.config
        if self._coef_a.shape == self.shape:
            self._prefilter(vol_a, vol_b)
        pred: tuple[np.ndarray, WindowGrid] | None = None
        self.last_passes = []
        for i, (_, mode) in enumerate(cfg.passes):
            g = self.grids[i]
            base = np.zeros((g.size, 3))
            s = np.zeros((g.size, 3), dtype=np.int64)
            va, vb = vol_a, vol_b
            if mode == "shift":
                s = np.rint(_interp(pred[0], pred[1], g)).astype(np.int64)
                base = s.astype(float)
            elif mode == "deform":
                base = pred[0].reshape(-1, 3) if pred[1] == g else _interp(pred[0], pred[1], g)
                va, vb = self._deform(vol_a, vol_b, *pred)
            if self._lags[i] is not None:
                self._run_local(va, vb, i)
            else:
                shift_a = (-(s // 2)).astype(np.int32)  # A's window moves back half the shift, B's forward the rest
                shift_b = (s + shift_a).astype(np.int32)
                self._run_pass(va, vb, i, shift_a, shift_b)
            n = g.size
            disp = self._disp.numpy()[:n].astype(np.float64) + base
            valid = self._valid.numpy()[:n] != 0
            disp[~valid] = np.nan
            disp = disp.reshape((*g.shape, 3))
            outlier = normalized_median_test(disp, test=cfg.median_test, device=self.device)

            disp, replaced = replace_outliers(disp, outlier, device=self.device)
            pred_field = np.where(np.isnan(disp), 0.0, disp)  # nothing left to predict from: rest
            if cfg.smooth_predictor > 0 and i + 1 < len(cfg.passes) and cfg.passes[i + 1][1] == "deform":
                pred_field = smooth(pred_field, sigma=cfg.smooth_predictor)
            pred = (pred_field, g)
            self.last_passes.append((pred_field, outlier))
            if progress is not None:
                progress(1)
        if cfg.median_filter:
            disp = median_filter(disp)
        g = self.grids[-1]
        n = g.size
        self.last_fallback_fraction = float(np.mean(self._fallback.numpy()[:n]))
        cx, cy, cz = g.centres()
        return VectorField(x=cx, y=cy, z=cz, displacement=disp,
                           peak_ratio=self._ratio.numpy()[:n].reshape(g.shape).copy(),
                           peak_height=self._height.numpy()[:n].reshape(g.shape).copy(),
                           outlier=outlier, replaced=replaced, grid=g)


@keyword_options("config", since="0.1.0")
def correlate(volume_a: np.ndarray, volume_b: np.ndarray, *, config: CorrelationConfig = CorrelationConfig(),
              device: str | None = None) -> VectorField:
    """Multi-grid cross-correlation of one volume pair (see :class:`Correlator`).

    Parameters
    ----------
    volume_a, volume_b
        (nz, ny, nx) float32 volumes of frames A and B.
    config
        Windows (x, y, z voxels per pass), overlap, passes, post-processing.
    device
        Warp device or None for the first GPU, else the CPU.

    Returns
    -------
    VectorField
        Displacements (x, y, z) of B relative to A in voxels on the final window grid.
    """
    return Correlator(np.shape(volume_a), config=config, device=device)(volume_a, volume_b)

