"""The microlens grid from a white image: every micro-image centre, then the lattice through them.

Under uniform illumination each lenslet images the main-lens exit pupil onto the sensor, so a
white image is a lattice of bright discs (micro-images). Their centres are where the chief rays
from the pupil centre meet the sensor: the lenslet lattice scaled by k = 1 + f_ml / si about the
optical axis (:mod:`lfcore.white`). This is the lattice that decoding a light field needs;
:meth:`MlaGrid.to_mla` converts it to the MLA's own pitch, rotation and offset.

Method:

1. Coarse pitch from the first peak of the image's autocorrelation (after dividing out a
   quadratic vignetting surface); an image without that peak has no microlens structure.
2. Flat field: divide by a local bright envelope (maximum filter over a few pitches) so that
   vignetting neither hides the edge lenslets nor tilts the discs; dead lenslets stay dark.
3. Candidates: local maxima of the flat field smoothed to a third of a pitch, brighter than half
   the envelope.
4. Sub-pixel centre: each micro-image and its neighbourhood are point-symmetric about the
   centre (a disc in a lattice of discs, whether the discs touch or not), so the centre is the
   point e that minimizes sum_d w(d) (S(e + d) - S(e - d))^2 over offsets d within 0.6 pitch;
   solved by Gauss-Newton on a cubic-spline interpolant of the flat field. Unbiased for any
   point-symmetric micro-image, and it uses every pixel of the disc, so noise averages out.
5. Lattice: grid type and rotation from the nearest-neighbour directions, then a linear least
   squares fit of origin, pitch and rotation over integer lattice indices, grown outward from the
   centre so that a slightly wrong initial pitch cannot mislabel far lenslets, with outliers
   (partial discs, neighbours of dead lenslets) rejected by a robust threshold.

Coordinates are continuous pixel (column, row), as in :mod:`lfcore.mla`: pixel ``[r, c]``
covers ``c <= column < c + 1``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from lfcore.rig import Camera
from lfcore.white import micro_image_scale

__all__ = ["GridError", "MlaGrid", "WhiteImage", "check_white", "detect_grid", "pixels_by_nearest_centre",
           "white_from_frames"]

#: Angle between the two basis vectors of each lattice, degrees.
_BASIS_ANGLE = {"hex": 60.0, "square": 90.0}

#: Gaussian smoothing (pixels) before centring: sharp disc edges make the spline interpolant
#: depend on the sub-pixel phase, which biases the centres toward the pixel grid.
SMOOTH_PX = 1.0

#: Side of the central crop the coarse pitch is measured on, pixels (micro-images up to a few
#: hundred pixels across still show their first autocorrelation peak).
_PITCH_CROP_PX = 2048


class GridError(ValueError):
    """A white image from which no microlens grid can be detected; one line saying why and what to do."""


@dataclass(frozen=True)
class MlaGrid:
    """The micro-image lattice detected in a white image.

    Attributes
    ----------
    grid
        "hex" or "square".
    pitch_px
        Distance between neighbouring micro-image centres, pixels.
    rotation_deg
        Lattice rotation in the sensor-plane frame of :mod:`lfcore.mla` (the sign of
        ``Camera.mla_rotation_deg``), in (-30, 30] for hex and (-45, 45] for square grids. The
        image's (column, row) axes are mirrored, so lenslet rows run at ``-rotation_deg`` there.
    offset_px
        (column, row) of the lattice node nearest the sensor centre (Nc/2, Nr/2), minus that
        centre, pixels.
    image_shape
        (rows, columns) of the white image.
    centres_px
        (n, 2) measured micro-image centres (column, row), pixels.
    indices
        (n, 2) int64 lattice indices (n1, n2) of each centre along :attr:`basis_px`.
    residuals_px
        (n, 2) measured minus fitted centre, pixels.
    inliers
        (n,) bool, the centres the lattice was fitted to.
    rms_px
        RMS distance of the inlier centres from the fitted lattice, pixels.
    origin_px
        (column, row) of lattice node (0, 0).
    basis_px
        (2, 2): rows are the basis vectors a1, a2 in (column, row) pixels.
    """

    grid: str
    pitch_px: float
    rotation_deg: float
    offset_px: tuple[float, float]
    image_shape: tuple[int, int]
    centres_px: np.ndarray = field(repr=False)
    indices: np.ndarray = field(repr=False)
    residuals_px: np.ndarray = field(repr=False)
    inliers: np.ndarray = field(repr=False)
    rms_px: float = 0.0
    origin_px: tuple[float, float] = (0.0, 0.0)
    basis_px: np.ndarray = field(default_factory=lambda: np.eye(2), repr=False)

    def __post_init__(self) -> None:
        for name in ("centres_px", "indices", "residuals_px", "inliers", "basis_px"):
            getattr(self, name).flags.writeable = False

    @property
    def n_lenslets(self) -> int:
        return int(len(self.centres_px))

    def lattice_px(self, indices: np.ndarray | None = None) -> np.ndarray:
        """Fitted node positions (column, row) of lattice ``indices`` (n, 2); default: every detected lenslet."""
        n = self.indices if indices is None else np.asarray(indices, dtype=np.float64)
        return np.asarray(self.origin_px) + n @ self.basis_px

    def to_mla(self, camera: Camera) -> dict[str, float | tuple[float, float]]:
        """The MLA's own geometry, assuming the optical axis meets the sensor at its centre.

        Micro-image centres are the lenslet centres scaled by k = 1 + f_ml / si (nominal, from
        ``camera``) about the axis, and the image is read out mirrored in x (:mod:`lfcore.mla`).

        Returns
        -------
        dict
            ``mla_pitch_um``, ``mla_rotation_deg`` and ``mla_offset_um`` (x, y) in the units and
            conventions of :class:`lfcore.rig.Camera`.
        """
        k = micro_image_scale(camera)
        s = camera.pixel_pitch_um / k
        return {"mla_pitch_um": self.pitch_px * s, "mla_rotation_deg": self.rotation_deg,
                "mla_offset_um": (-self.offset_px[0] * s, self.offset_px[1] * s)}


def check_white(image: np.ndarray, full_scale: int = 65535) -> None:
    """Raise :class:`GridError` unless ``image`` looks like a usable white image.

    Parameters
    ----------
    image
        (rows, columns) raw counts.
    full_scale
        The sensor's saturation level, counts.
    """
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [1.0, 99.5])
    saturated = float(np.mean(img >= full_scale))
    if saturated > 0.005:
        raise GridError(f"white image saturated ({saturated:.1%} of pixels at full scale {full_scale}); "
                        "dim the diffuser or shorten the exposure")
    if hi < 0.05 * full_scale or hi - lo < 0.02 * full_scale:
        raise GridError(f"white image too dark (brightest pixels {hi:.0f} counts, {hi / full_scale:.1%} of full "
                        f"scale {full_scale}); brighten the diffuser, open the lens or expose longer")


#: A hot pixel outshines every one of its eight neighbours by this fraction of the white level:
#: no pixel of a real micro-image does (light varies smoothly within one, and an edge pixel has a
#: brighter neighbour inside), while a stuck or hot pixel does, in a micro-image or between them.
HOT_PIXEL_EXCESS = 0.2


@dataclass(frozen=True)
class WhiteImage:
    """A white image made of several frames (:func:`white_from_frames`).

    Attributes
    ----------
    image
        (rows, columns) float64 mean of the frames, hot pixels replaced.
    frames
        Frames averaged.
    hot_pixels
        Pixels replaced by the brightest of their neighbours.
    """

    image: np.ndarray
    frames: int
    hot_pixels: int


def white_from_frames(frames: np.ndarray, *, full_scale: int) -> WhiteImage:
    """The white image of a stack of white frames: checked, averaged, hot pixels rejected.

    Parameters
    ----------
    frames
        (n, rows, columns) raw counts of one camera under uniform illumination.
    full_scale
        The sensor's saturation level (2**bit_depth - 1 of the real camera), counts.

    Raises
    ------
    GridError
        Frames saturated or too dark to show the micro-images (:func:`check_white`).
    """
    stack = np.asarray(frames)
    if stack.ndim == 2:
        stack = stack[None]
    check_white(stack.max(axis=0), full_scale)
    mean = stack.astype(np.float64).mean(axis=0)
    # the brightest of the eight neighbours of every pixel
    padded = np.pad(mean, 1, mode="edge")
    rows, cols = mean.shape
    around = np.full_like(mean, -np.inf)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                np.maximum(around, padded[1 + dy:1 + dy + rows, 1 + dx:1 + dx + cols], out=around)
    level = float(np.percentile(mean, 99.5))
    hot = mean - around > HOT_PIXEL_EXCESS * level
    mean[hot] = around[hot]
    return WhiteImage(mean, len(stack), int(hot.sum()))


def _quadratic_surface(img: np.ndarray) -> np.ndarray:
    rows, cols = img.shape
    step = max(1, min(rows, cols) // 64)
    r, c = np.mgrid[0:rows:step, 0:cols:step]
    y, x = r / rows - 0.5, c / cols - 0.5
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1).reshape(-1, 6)
    c0, cx, cy, cxx, cxy, cyy = np.linalg.lstsq(design, img[::step, ::step].reshape(-1), rcond=None)[0]
    y = (np.arange(rows) / rows - 0.5)[:, None]
    x = (np.arange(cols) / cols - 0.5)[None, :]
    return c0 + cx * x + cy * y + cxx * x * x + cxy * x * y + cyy * y * y


def _coarse_pitch(img: np.ndarray) -> float:
    """Length of the shortest lattice vector, from the first autocorrelation peak.

    Measured on a central crop of at most ``_PITCH_CROP_PX`` square: the lattice is the same
    everywhere and a 29 MP autocorrelation would cost seconds and gigabytes for nothing.
    """
    rows, cols = img.shape
    r0, c0 = max(0, (rows - _PITCH_CROP_PX) // 2), max(0, (cols - _PITCH_CROP_PX) // 2)
    img = img[r0:r0 + _PITCH_CROP_PX, c0:c0 + _PITCH_CROP_PX]
    surface = np.maximum(_quadratic_surface(img), 1e-6 * max(img.max(), 1.0))
    f = img / surface - 1.0
    f -= f.mean()
    spec = np.fft.rfft2(f)
    ac = np.fft.fftshift(np.fft.irfft2(np.abs(spec) ** 2, s=f.shape))
    if ac.max() <= 0:
        raise GridError("no microlens structure (the image is uniform); is the MLA in place and the image in focus?")
    ac /= ac.max()
    rows, cols = ac.shape
    cy, cx = rows // 2, cols // 2
    rr, cc = np.mgrid[0:rows, 0:cols]
    radius = np.hypot(rr - cy, cc - cx)
    peaks = (ac == ndimage.maximum_filter(ac, size=3)) & (radius >= 2.0) & (radius <= min(rows, cols) / 3)
    if not peaks.any() or ac[peaks].max() < 0.15:
        raise GridError("no periodic microlens structure in the white image (autocorrelation shows no lattice "
                        "peak); check that the MLA is in place, the diffuser uniform and the image in focus")
    strong = peaks & (ac >= 0.5 * ac[peaks].max())
    idx = np.flatnonzero(strong.ravel())
    best = idx[np.argmin(radius.ravel()[idx])]
    pr, pc = divmod(int(best), cols)
    sub = [float(pr - cy), float(pc - cx)]
    for axis, (a, b, c) in enumerate(((ac[pr - 1, pc], ac[pr, pc], ac[pr + 1, pc]),
                                      (ac[pr, pc - 1], ac[pr, pc], ac[pr, pc + 1]))):
        den = a - 2 * b + c
        if den < 0:
            sub[axis] += 0.5 * (a - c) / den
    return float(math.hypot(*sub))


def _flat_field(img: np.ndarray, pitch: float) -> np.ndarray:
    size = int(2.5 * pitch) | 1
    # Only the multiplicative envelope matters (a constant offset keeps every micro-image
    # symmetric); a maximum filter follows vignetting and ignores dead lenslets.
    light = ndimage.gaussian_filter(img, 0.15 * pitch)
    hi = ndimage.gaussian_filter(ndimage.maximum_filter(light, size=size), pitch)
    return img / np.maximum(hi, 1e-6 * max(float(hi.max()), 1.0))


def _cell_normalised(img: np.ndarray, flat: np.ndarray, centres: np.ndarray, pitch: float) -> np.ndarray:
    """``img`` divided, cell by cell, by the level of the micro-image whose cell each pixel is in.

    Vignetting dims each micro-image as a whole (all its rays share one chief-ray angle), so
    equal discs with levels that step from cell to cell are what a white image is; a smooth
    envelope would instead tilt every disc and bias its centre. Pixels farther than 0.75 pitch
    from every centre (dead lenslets, the border) keep the smooth flat field.
    """
    rows, cols = img.shape
    r = max(1.0, 0.25 * pitch)
    g = np.arange(-np.ceil(r), np.ceil(r) + 1)
    dc, dr = np.meshgrid(g, g, indexing="xy")
    keep = np.hypot(dc, dr) <= r
    cc = np.clip(np.rint(centres[:, None, 0] - 0.5 + dc[keep][None]).astype(int), 0, cols - 1)
    rr = np.clip(np.rint(centres[:, None, 1] - 0.5 + dr[keep][None]).astype(int), 0, rows - 1)
    level = np.median(img[rr, cc], axis=1)
    level = np.maximum(level, 0.05 * np.median(level))
    out = flat.copy().reshape(-1)
    for pixels, _, idx in pixels_by_nearest_centre(img.shape, centres, 0.75 * pitch):
        out[pixels] = img.reshape(-1)[pixels] / level[idx]
    return out.reshape(rows, cols)


def pixels_by_nearest_centre(shape: tuple[int, int], centres: np.ndarray, max_distance_px: float
                             ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The pixels of an image within ``max_distance_px`` of a micro-image centre, and which
    centre is nearest, a block of rows at a time (a 29 MP image at once would take gigabytes).

    Parameters
    ----------
    shape
        (rows, columns) of the image.
    centres
        (n, 2) micro-image centres, continuous (column, row) pixel coordinates.
    max_distance_px
        Pixels whose centre is farther than this from every micro-image centre are left out.

    Yields
    ------
    pixels : numpy.ndarray
        (m,) int64 flat indices into the image of the block's pixels that have a centre.
    offsets : numpy.ndarray
        (m, 2) float64 (column, row) of each such pixel's centre minus its micro-image centre.
    nearest : numpy.ndarray
        (m,) int64 index into ``centres`` of that micro-image centre.
    """
    rows, cols = shape
    tree = cKDTree(centres)
    step = max(1, 4_000_000 // cols)
    for r0 in range(0, rows, step):
        pr, pc = np.mgrid[r0:min(rows, r0 + step), 0:cols]
        xy = np.stack([pc.ravel() + 0.5, pr.ravel() + 0.5], axis=-1)
        dist, idx = tree.query(xy, distance_upper_bound=max_distance_px, workers=-1)
        ok = np.isfinite(dist)
        yield r0 * cols + np.flatnonzero(ok), xy[ok] - centres[idx[ok]], idx[ok]


def _candidates(flat: np.ndarray, pitch: float) -> np.ndarray:
    sm = ndimage.gaussian_filter(flat, pitch / 3.0)
    size = max(3, int(0.7 * pitch) | 1)
    peak = (sm == ndimage.maximum_filter(sm, size=size)) & (sm > 0.5 * np.percentile(sm, 99))
    r, c = np.nonzero(peak)
    return np.stack([c + 0.5, r + 0.5], axis=-1).astype(np.float64)


def _symmetric_centres(flat: np.ndarray, start: np.ndarray, pitch: float, iterations: int = 8,
                       smooth_px: float | None = None, tol_px: float = 1e-3, block: int | None = None) -> np.ndarray:
    """Gauss-Newton point-symmetry centring of every micro-image; NaN where it fails.

    Micro-images are solved in blocks of ``block`` (default: about 16 MB of work arrays each)
    on a thread pool (scipy's interpolation releases the GIL), each one only until its step
    falls below ``tol_px``, so memory stays bounded and every core works: both passes over a
    29 MP sensor's 170 000 micro-images took 39 s on two cores.
    """
    sigma = SMOOTH_PX if smooth_px is None else smooth_px
    # The smoothed image and its exact derivatives (derivative-of-Gaussian filters), all
    # sampled through cubic splines: an exact Jacobian makes Gauss-Newton converge
    # quadratically (3 steps reach 1e-6 px; linearly interpolated finite differences took 8
    # steps to reach 1e-5 px).
    coeffs, gr, gc = (ndimage.spline_filter(ndimage.gaussian_filter(flat, sigma, order=o), order=3)
                      for o in ((0, 0), (1, 0), (0, 1)))
    radius = 0.6 * pitch
    # About one offset per pixel of the disc: the image is already smoothed over a pixel, and
    # on 14 px micro-images a 1 px step centres as accurately as a 0.5 px one (0.012 px RMS
    # against the truth either way) at half the cost; small micro-images get a finer step.
    step = min(1.0, max(0.5, pitch / 14.0))
    g = np.arange(-radius, radius + step / 2, step)
    dc, dr = np.meshgrid(g, g, indexing="xy")
    keep = (np.hypot(dc, dr) <= radius) & ((dr > 0) | ((dr == 0) & (dc > 0)))  # one of each +-d pair
    d = np.stack([dc[keep], dr[keep]], axis=-1)
    w = np.exp(-0.5 * (np.hypot(d[:, 0], d[:, 1]) / (0.4 * pitch)) ** 2)

    def sample(a: np.ndarray, pos: np.ndarray) -> np.ndarray:
        # array index = continuous coordinate - 0.5 (index i is the centre of pixel i)
        coords = [pos[..., 1].ravel() - 0.5, pos[..., 0].ravel() - 0.5]
        out = ndimage.map_coordinates(a, coords, order=3, prefilter=False, mode="nearest")
        return out.reshape(pos.shape[:-1])

    def solve(starts: np.ndarray) -> np.ndarray:
        e = starts.copy()
        active = np.arange(len(e))
        for _ in range(iterations):
            if not active.size:
                break
            plus, minus = e[active, None, :] + d[None], e[active, None, :] - d[None]
            res = sample(coeffs, plus) - sample(coeffs, minus)
            jac = np.stack([sample(gc, plus) - sample(gc, minus), sample(gr, plus) - sample(gr, minus)], axis=-1)
            jw = jac * w[None, :, None]
            h = np.einsum("nmi,nmj->nij", jw, jac) + 1e-9 * np.eye(2)
            rhs = -np.einsum("nmi,nm->ni", jw, res)
            delta = np.clip(np.linalg.solve(h, rhs[..., None])[..., 0], -0.25 * pitch, 0.25 * pitch)
            e[active] += delta
            active = active[np.hypot(delta[:, 0], delta[:, 1]) > tol_px]
        return e

    per_block = block or max(64, 1_000_000 // max(1, len(d)))
    blocks = [start[i:i + per_block] for i in range(0, len(start), per_block)]
    workers = max(1, min(os.cpu_count() or 1, len(blocks)))
    if workers == 1:
        parts = [solve(b) for b in blocks]
    else:
        with ThreadPoolExecutor(workers) as pool:
            parts = list(pool.map(solve, blocks))
    e = np.concatenate(parts) if parts else start.copy()
    moved = np.hypot(*(e - start).T) > 0.5 * pitch
    e[moved] = np.nan
    return e


def _basis(pitch: float, phi: float, grid: str) -> np.ndarray:
    b = math.radians(_BASIS_ANGLE[grid])
    return pitch * np.array([[math.cos(phi), math.sin(phi)], [math.cos(phi + b), math.sin(phi + b)]])


def _fit_similarity(pts: np.ndarray, n: np.ndarray, grid: str) -> tuple[np.ndarray, float, float]:
    """Least squares origin, pitch and angle (pixel frame) of ``pts = O + n @ basis``."""
    b = math.radians(_BASIS_ANGLE[grid])
    cb, sb = math.cos(b), math.sin(b)
    n1, n2 = n[:, 0].astype(float), n[:, 1].astype(float)
    one, zero = np.ones_like(n1), np.zeros_like(n1)
    a = np.concatenate([np.stack([one, zero, n1 + n2 * cb, -n2 * sb], axis=-1),
                        np.stack([zero, one, n2 * sb, n1 + n2 * cb], axis=-1)])
    y = np.concatenate([pts[:, 0], pts[:, 1]])
    (ox, oy, u, v), *_ = np.linalg.lstsq(a, y, rcond=None)
    return np.array([ox, oy]), float(math.hypot(u, v)), float(math.atan2(v, u))


def _lattice_orientation(pts: np.ndarray, pitch: float, grid: str | None) -> tuple[str, float, float]:
    tree = cKDTree(pts)
    dist, idx = tree.query(pts, k=min(9, len(pts)))
    near = (dist > 0.75 * pitch) & (dist < 1.25 * pitch)
    counts = near.sum(axis=1)
    if grid is None:
        grid = "hex" if np.median(counts[counts >= 3]) >= 5 else "square"
    vec = pts[idx] - pts[:, None, :]
    vec = vec[near]
    m = 6 if grid == "hex" else 4
    theta = np.arctan2(vec[:, 1], vec[:, 0])
    phi = float(np.angle(np.mean(np.exp(1j * m * theta))) / m)
    return grid, float(np.median(dist[near])), phi


def detect_grid(image: np.ndarray, grid: str | None = None, pitch_px: float | None = None) -> MlaGrid:
    """Detect every micro-image centre of a white image and fit the microlens lattice.

    Parameters
    ----------
    image
        (rows, columns) white image, counts (any dtype; averaged frames welcome).
    grid
        "hex" or "square", or None to decide from the image.
    pitch_px
        Approximate micro-image pitch in pixels, or None to measure it (autocorrelation).

    Returns
    -------
    MlaGrid
        The lattice and every detected centre with its residual.

    Raises
    ------
    GridError
        No periodic structure, too few micro-images, or a lattice that does not fit.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 8:
        raise GridError(f"a white image is a 2-D array of at least 8 x 8 pixels, got shape {img.shape}")
    if grid is not None and grid not in _BASIS_ANGLE:
        raise GridError(f"grid must be 'hex' or 'square', got {grid!r}")
    rows, cols = img.shape
    p0 = float(pitch_px) if pitch_px is not None else _coarse_pitch(img)
    if p0 < 3.0:
        raise GridError(f"micro-images {p0:.1f} pixels apart are too small to locate (need at least 3)")
    flat = _flat_field(img, p0)
    cand = _candidates(flat, p0)
    margin = 0.6 * p0 + 1.5
    inside = ((cand[:, 0] > margin) & (cand[:, 0] < cols - margin) & (cand[:, 1] > margin)
              & (cand[:, 1] < rows - margin))
    cand = cand[inside]
    if len(cand) < 9:
        raise GridError(f"only {len(cand)} micro-images found; need at least 9 (is the image a white image, "
                        "in focus, with the MLA in place?)")
    pts = _symmetric_centres(flat, cand, p0)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) >= 9:  # second pass on micro-images levelled one by one
        pts = _symmetric_centres(_cell_normalised(img, flat, pts, p0), pts, p0)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
    grid, p1, phi = _lattice_orientation(pts, p0, grid)

    # Grow the fit outward from the centre so a coarse pitch cannot mislabel far lenslets.
    centre = np.array([cols / 2.0, rows / 2.0])
    seed = pts[np.argmin(np.hypot(*(pts - centre).T))]
    origin, pitch, basis = seed, p1, _basis(p1, phi, grid)
    from_seed = np.hypot(*(pts - seed).T)
    radius = 4.0 * p1
    while True:
        sel = from_seed <= radius
        n = np.rint((pts[sel] - origin) @ np.linalg.inv(basis)).astype(np.int64)
        origin, pitch, phi = _fit_similarity(pts[sel], n, grid)
        basis = _basis(pitch, phi, grid)
        if sel.all():
            break
        radius *= 2.0
    n = np.rint((pts - origin) @ np.linalg.inv(basis)).astype(np.int64)
    # One centre per lattice node: keep the one nearest its node.
    dist = np.hypot(*(pts - origin - n @ basis).T)
    order = np.lexsort((dist, n[:, 1], n[:, 0]))
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(np.diff(n[order], axis=0) != 0, axis=1)
    keep = np.sort(order[first])
    pts, n = pts[keep], n[keep]

    inl = np.ones(len(pts), dtype=bool)
    for _ in range(5):
        origin, pitch, phi = _fit_similarity(pts[inl], n[inl], grid)
        basis = _basis(pitch, phi, grid)
        res = pts - origin - n @ basis
        r = np.hypot(res[:, 0], res[:, 1])
        sigma = 1.4826 * np.median(r[inl]) / 1.1774  # median of a 2-D Gaussian's radius is 1.1774 sigma
        new = r <= max(4.0 * sigma, 0.01 * pitch)
        if np.array_equal(new, inl):
            break
        inl = new
    if inl.sum() < 9:
        raise GridError(f"only {int(inl.sum())} micro-images lie on one lattice; the white image is too irregular")
    rms = float(np.sqrt(np.mean(np.sum(res[inl] ** 2, axis=1))))

    # Report the rotation folded into the lattice's symmetry range, in the sensor-plane sign.
    period = _BASIS_ANGLE[grid]
    phi_deg = (math.degrees(phi) + period / 2) % period - period / 2
    # The node nearest the sensor centre (check the neighbours of the rounded index).
    n0 = np.rint((centre - origin) @ np.linalg.inv(basis))
    cands = n0 + np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)])
    nodes = origin + cands @ basis
    node = nodes[np.argmin(np.hypot(*(nodes - centre).T))]
    off = node - centre
    return MlaGrid(grid=grid, pitch_px=pitch, rotation_deg=-phi_deg, offset_px=(float(off[0]), float(off[1])),
                   image_shape=(rows, cols), centres_px=pts, indices=n, residuals_px=res, inliers=inl,
                   rms_px=rms, origin_px=(float(origin[0]), float(origin[1])), basis_px=basis)
