"""Dots of the calibration target in a raw light-field image: found, centred, and named.

Method. Each lenslet's micro-image holds all the light that reached the MLA through that
lenslet, so the sum of its pixels (a Voronoi cell about its micro-image centre, background
removed) samples the image the main lens forms on the MLA, one sample per lenslet. A dot's
image there, sharp or defocused, is centred on its chief ray (:mod:`lfcore.chief_ray`), so the
flux-weighted mean of the micro-image centres of the lenslets it lights is where
:func:`lfcore.chief_ray.project` puts the dot, to a fraction of a lenslet: every ray of the
dot counts (not only the central sub-aperture's), so Monte-Carlo and shot noise average out.

1. Lenslet sums over cells of radius 0.6 pitch about the fitted lattice nodes of the white image
   (:class:`calibration.mla_grid.MlaGrid`); background: the frame's median pixel, corrected by
   the mean of the lenslets far from any lit one (lit pixels raise the median).
2. Lenslets brighter than ``threshold_sigma`` noise sigmas; each climbs the sums (smoothed over
   its lattice neighbours, in lattice index space: six on a hexagonal grid, eight on a square
   one) to a local maximum, so the faint overlap of two defocused dots is split at its valley.
   A maximum is a dot of its own only if a valley deeper than ``min_prominence`` of its height
   parts it from every brighter one (persistence, merged from the brightest down), so the
   noise on the top of a dot many lenslets wide does not split it; maxima closer than
   ``min_separation`` pitches are merged too, and groups with under ``min_flux_fraction`` of a
   dot's light (the tips of defocused dots) are left out.
3. Each dot's flux-weighted centroid over a disc of lenslets centred on it that holds its faint
   rim below the threshold too (see :func:`_window_centroids`), also with each lenslet's light split
   between the halves of the main-lens aperture (each pixel of a micro-image sees one aperture
   point): the views through opposite halves disagree in proportion to the dot's defocus. Dots
   touching the edge of the detected lattice are dropped (a cut dot's centroid is biased).
4. Naming: the marker dot (0, 0) is the one with clearly the most light (the dots are equally
   bright per area), the one nearest its predicted place if several are as bright; the
   board's dots projected by a nominal camera are shifted onto it, then an affine map from
   predicted to found positions is refined on nearest matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from calibration.mla_grid import MlaGrid, pixels_by_nearest_centre
from lfcore.chief_ray import diffraction_sigma_mm
from lfcore.mla import nearest_lenslet, pixel_to_sensor, sensor_to_pixel
from lfcore.rig import Camera

__all__ = ["VIEW_PUPILS", "DotError", "Dots", "LensletCells", "ViewGeometry", "background_level", "detect_dots",
           "lenslet_cells", "lenslet_sums", "match_dots", "view_geometry", "view_pupils_mm"]

#: The views a dot is centred in, as the mean aperture point of the light each takes, in units
#: of 4 R / (3 pi) (the centroid of a half disc of radius R): all the light (the chief ray),
#: then the +x, -x, +y and -y halves of the aperture (camera frame).
VIEW_PUPILS = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def view_pupils_mm(aperture_mm: float) -> np.ndarray:
    """(views, 2) mean aperture point (camera-frame x, y, mm) of each view, for aperture diameter D,
    if each pixel saw only its own micro-image (see :func:`view_geometry` for what the views see)."""
    return VIEW_PUPILS * 4.0 * (0.5 * aperture_mm) / (3.0 * np.pi)


@dataclass(frozen=True)
class ViewGeometry:
    """What each view of :data:`VIEW_PUPILS` sees, as :func:`lenslet_sums` forms it.

    Attributes
    ----------
    pupils_mm
        (views, 2) light-weighted mean aperture point (camera-frame x, y, mm) of each view.
    offsets_px
        (views, 2) mean displacement (column, row) of a view's light from where its rays meet
        the MLA, pixels: the light of one micro-image counted in a neighbour's cell is placed at
        the neighbour's centre.
    """

    pupils_mm: np.ndarray
    offsets_px: np.ndarray


def view_geometry(camera: Camera, wavelength_nm: float = 532.0, samples: int = 1_000_000, seed: int = 0
                  ) -> ViewGeometry:
    """The views of a dot as the dot finder forms them, for ``camera``'s optics (Monte Carlo).

    Where the main lens' image-side f-number matches the lenslets', micro-images touch: the
    light of a micro-image's rim (the aperture's edge) falls in pixels nearer a neighbour's
    centre, or is blurred into them by the lenslet's diffraction (sigma 0.42 lambda N, as
    :mod:`lfcore.render`). That light counts in the neighbour's cell, on the opposite half of
    the aperture, so each half view sees a smaller mean aperture point than the half disc's
    4 R / (3 pi), and is displaced by a fraction of a pitch. On the 29 MP example camera
    (f/4 lenslets, 14 pixels across) that is 4-6 % less parallax and 0.13-0.15 px: fitted with
    the half disc's instead, 51 simulated planes put the focal planes 8.5 and 10.8 um off (1.5
    and 0.3 um with these).

    Rays from every aperture point enter lenslets at uniformly spread points (a dot blurred
    over many lenslets), reach the sensor, and are counted as :func:`lenslet_sums` counts them.

    Parameters
    ----------
    camera
        The camera.
    wavelength_nm
        Wavelength of the target's light, for the diffraction blur.
    samples
        Rays traced.
    seed
        Seed of the rays (fixed: the same camera gives the same geometry).
    """
    rng = np.random.default_rng(seed)
    si, fml = camera.image_distance_mm, camera.mla_focal_length_mm
    k = 1.0 + fml / si
    r = 0.5 * camera.aperture_mm * np.sqrt(rng.random(samples))
    t = 2.0 * np.pi * rng.random(samples)
    a = np.stack([r * np.cos(t), r * np.sin(t)], axis=-1)
    # MLA points over the whole sensor: the micro-images' phase on the pixel grid drifts over the
    # field (a pitch of 14.01 pixels comes back in step every 92 lenslets), and with it the
    # light lost to neighbours (by up to 7 %); the fit takes the mean over the field
    half = 0.5 * np.array(camera.sensor_px) * camera.pixel_mm / k
    q = (rng.random((samples, 2)) - 0.5) * (2.0 * half)
    c = nearest_lenslet(camera, q)
    blur = diffraction_sigma_mm(wavelength_nm, camera.lenslet_f_number)
    x = c + fml * (q - a) / si + blur * rng.standard_normal((samples, 2))  # the renderer's ray, on the sensor
    pix = np.floor(sensor_to_pixel(camera, x)) + 0.5
    cell = nearest_lenslet(camera, pixel_to_sensor(camera, pix) / k)  # the micro-image the pixel is counted in
    wx, wy = _plus_halves(pix - sensor_to_pixel(camera, k * cell))  # as lenslet_cells splits them
    moved = sensor_to_pixel(camera, k * cell) - sensor_to_pixel(camera, k * c)
    pupils, offsets = [], []
    for w in (np.ones(samples), wx, 1.0 - wx, wy, 1.0 - wy):
        pupils.append(w @ a / w.sum())
        offsets.append(w @ moved / w.sum())
    pupils_mm, offsets_px = np.array(pupils), np.array(offsets)
    pupils_mm[0] = offsets_px[0] = 0.0  # all the light: centred on the chief ray (by symmetry)
    return ViewGeometry(pupils_mm, offsets_px)

#: Lattice adjacency in (n1, n2) index space; a hexagonal basis has a1 and a2 60 degrees apart,
#: so a2 - a1 is also a neighbour, a1 + a2 is not.
_HEX_ADJ = np.array([[0, 1, 1], [1, 1, 1], [1, 1, 0]], dtype=bool)
_SQUARE_ADJ = np.ones((3, 3), dtype=bool)


class DotError(ValueError):
    """A plane whose dots cannot be found or named; one line naming the camera and plane."""


@dataclass(frozen=True)
class Dots:
    """Dots found in one raw frame.

    Attributes
    ----------
    views_px
        (m, views, 2) continuous (column, row) centroids, pixels, in each view of
        :data:`VIEW_PUPILS` (view 0: all the light, centred on the chief ray).
    flux
        (m,) background-subtracted light of each dot, counts.
    lenslets
        (m,) int, lenslets above threshold in each dot.
    """

    views_px: np.ndarray
    flux: np.ndarray
    lenslets: np.ndarray

    def __len__(self) -> int:
        return int(len(self.views_px))

    @property
    def centres_px(self) -> np.ndarray:
        """(m, 2) centroids of all the light (the chief-ray view), pixels."""
        return self.views_px[:, 0]


@dataclass(frozen=True)
class LensletCells:
    """Which lenslet each pixel belongs to, and where in its micro-image: fixed by the grid.

    Computed once per camera (:func:`lenslet_cells`) and reused for every frame, since finding
    the nearest lattice node of 29 million pixels costs seconds.

    Attributes
    ----------
    image_shape
        (rows, columns) of the frames.
    pixels
        (m,) int64 flat indices of the pixels within 0.6 pitch of a lattice node, grouped by
        that node (in the order of ``grid.indices``).
    lenslet
        (m,) int32 index of that node, in the order of ``grid.indices`` (non-decreasing).
    wx, wy
        (m,) float32 fraction of each pixel on the +x and +y side of the main-lens aperture.
    n_lenslets
        Number of lattice nodes.
    npix_median
        Median number of pixels per cell.
    view_pixels
        (n_lenslets, 5) pixels of each cell in each view of :data:`VIEW_PUPILS` (fractions
        counted): what a background error of one count per pixel adds to each lenslet sum.
    starts
        (n_lenslets + 1,) int64: lenslet ``i``'s pixels are ``pixels[starts[i]:starts[i + 1]]``.
    """

    image_shape: tuple[int, int]
    pixels: np.ndarray
    lenslet: np.ndarray
    wx: np.ndarray
    wy: np.ndarray
    n_lenslets: int
    npix_median: float
    view_pixels: np.ndarray
    starts: np.ndarray


def _plus_halves(offsets_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of each pixel on the +x and on the +y half of the main-lens aperture, from its
    centre's (column, row) offset from its micro-image centre.

    A pixel delta from its micro-image centre sees the aperture point A = -(si / f_ml)
    delta_sensor, so A_x > 0 for columns right of the centre and A_y > 0 above it (row = Nr/2 +
    y / pixel); a pixel on the dividing line is shared by its fraction on each side.
    """
    d = np.asarray(offsets_px)
    return np.clip(d[..., 0] + 0.5, 0.0, 1.0), np.clip(0.5 - d[..., 1], 0.0, 1.0)


def lenslet_cells(grid: MlaGrid) -> LensletCells:
    """The cells (radius 0.6 pitch about each fitted lattice node of ``grid``) of every pixel."""
    nodes = grid.lattice_px()
    pixels, lenslet, wx, wy = [], [], [], []
    for px, d, idx in pixels_by_nearest_centre(grid.image_shape, nodes, 0.6 * grid.pitch_px):
        pixels.append(px)
        lenslet.append(idx.astype(np.int32))
        hx, hy = _plus_halves(d)
        wx.append(hx.astype(np.float32))
        wy.append(hy.astype(np.float32))
    # grouped by lenslet, so that summing a frame's cells is one pass over contiguous runs; each
    # list of blocks is let go once joined (29 MP: 29 million entries of each)
    order = np.argsort(np.concatenate(lenslet), kind="stable")

    def grouped(blocks: list[np.ndarray]) -> np.ndarray:
        joined = np.concatenate(blocks)[order]
        blocks.clear()
        return joined

    lens, pix, wx_all, wy_all = grouped(lenslet), grouped(pixels), grouped(wx), grouped(wy)
    npix, nx, ny = (np.bincount(lens, weights=w, minlength=len(nodes)) for w in (None, wx_all, wy_all))
    starts = np.concatenate([[0], np.cumsum(npix)]).astype(np.int64)
    return LensletCells(tuple(grid.image_shape), pix, lens, wx_all, wy_all, len(nodes), float(np.median(npix)),
                        np.stack([npix, nx, npix - nx, ny, npix - ny], axis=-1), starts)


def _cell_sums(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sum of ``values`` over each run ``starts[i]:starts[i + 1]`` (0 for an empty run)."""
    out = np.zeros(len(starts) - 1)
    full = starts[1:] > starts[:-1]
    if full.any():
        out[full] = np.add.reduceat(values, starts[:-1][full])
    return out


def lenslet_sums(frame: np.ndarray, grid: MlaGrid, cells: LensletCells | None = None) -> tuple[np.ndarray, float]:
    """Background-subtracted light of every lenslet of ``grid`` in ``frame``.

    Parameters
    ----------
    frame
        (rows, columns) raw image, counts.
    grid
        The microlens grid from the white image.
    cells
        :func:`lenslet_cells` of ``grid``, when several frames are summed (default: computed).

    Returns
    -------
    sums : numpy.ndarray
        (n, 5) counts per lenslet, in the order of ``grid.indices``: all its light, then the
        light through the +x, -x, +y and -y halves of the main-lens aperture (camera frame), the
        views of :data:`VIEW_PUPILS`.
    sigma : float
        Noise sigma of one sum (background pixels' robust sigma times sqrt(pixels per cell)).
    """
    img = np.asarray(frame)
    rows, cols = img.shape
    if (rows, cols) != tuple(grid.image_shape):
        raise DotError(f"frame of {cols} x {rows} pixels does not match the white image's "
                       f"{grid.image_shape[1]} x {grid.image_shape[0]}")
    cells = lenslet_cells(grid) if cells is None else cells
    bg, sig_px = background_level(img)
    v = img.ravel()[cells.pixels].astype(np.float64) - bg
    total, plus_x, plus_y = (_cell_sums(w, cells.starts) for w in (v, v * cells.wx, v * cells.wy))
    # a pixel's light is split between the two halves of each axis, so each minus half is
    # the rest of the total
    sums = np.stack([total, plus_x, total - plus_x, plus_y, total - plus_y], axis=-1)
    return sums, max(sig_px, 1e-3) * float(np.sqrt(cells.npix_median))


def background_level(img: np.ndarray) -> tuple[float, float]:
    """Median of ``img`` (the dark board fills most of a frame) and the noise sigma of one
    pixel (1.4826 times the median absolute deviation of the pixels at or below it).

    Camera frames (unsigned integers of up to 16 bits) take both from one histogram, exactly
    as :func:`numpy.median` would, in a fraction of its time on 29 MP.
    """
    if img.dtype.kind == "u" and img.dtype.itemsize <= 2:
        hist = np.bincount(img.ravel(), minlength=1)
        bg = _hist_median(hist, 0)
        below = hist[:int(bg) + 1][::-1]  # counts of bg - value = 0, 1, 2, ... (bg rounds down)
        mad = _hist_median(below, bg - int(bg)) if below.sum() else 1.0 / 1.4826
        return bg, 1.4826 * mad
    img = np.asarray(img, dtype=np.float64)
    bg = float(np.median(img))
    low = img[img <= bg]
    return bg, 1.4826 * float(np.median(bg - low)) if len(low) else 1.0


_background = background_level  # the name it had before pinhole cameras needed it too


def _hist_median(hist: np.ndarray, offset: float) -> float:
    """Median of the values ``offset + i`` taken ``hist[i]`` times (mean of the two middle ones
    for an even count, as :func:`numpy.median`)."""
    n = int(hist.sum())
    cum = np.cumsum(hist)
    lo = int(np.searchsorted(cum, (n - 1) // 2, side="right"))  # the value at sorted index (n-1)//2
    hi = int(np.searchsorted(cum, n // 2, side="right"))
    return offset + 0.5 * (lo + hi)


def detect_dots(frame: np.ndarray, grid: MlaGrid, *, threshold_sigma: float = 8.0, min_lenslets: int = 2,
                min_separation: float = 2.5, min_prominence: float = 0.35, min_flux_fraction: float = 0.1,
                cells: LensletCells | None = None, window_margin: float | None = 0.2,
                refine_background: bool = True) -> Dots:
    """Find every whole dot in a raw light-field frame and its centroid.

    Parameters
    ----------
    frame
        (rows, columns) raw image of the dot target, counts.
    grid
        The microlens grid (white image) of the same camera.
    threshold_sigma
        A lenslet is lit above this many noise sigmas of a lenslet sum.
    min_lenslets
        Smallest group of lit lenslets accepted as a dot.
    min_separation
        Intensity maxima closer than this many lenslet pitches belong to one dot.
    min_prominence
        Two touching groups of lit lenslets are two dots only if the fainter one's peak
        (smoothed over its neighbours) stands above the saddle between them by more than this
        fraction of the peak.
    min_flux_fraction
        Dots with less than this fraction of the typical dot's flux (the flux-weighted median)
        are left out: they are the tips of defocused dots too faint to find whole.
    cells
        :func:`lenslet_cells` of ``grid``, computed once for many frames (default: computed).
    window_margin
        Each dot is centred, in each view, over a disc of lenslets about its centroid (see
        :func:`_window_centroids`) reaching past its farthest lit lenslet by this fraction of
        that distance, and at least a pitch; None: over its lit lenslets only. Fitted on the
        simulated 29 MP example (51 planes, ``lfpiv calibrate fit``), this default left the poses
        0.0017 and 0.0035 degree off, a fixed margin of 2 pitches 0.0007 and 0.0031, of 1 pitch
        0.0018 and 0.0050, the lit lenslets only 0.042; on the demo rig, whose dots are a few
        lenslets across, the dark lenslets' noise made 2 pitches worse than 1.
    refine_background
        Correct the background (the frame's median) by the mean of the lenslets three rings or
        more from every lit one.

    Returns
    -------
    Dots
        Centroids in raw pixel coordinates, fluxes and sizes (of the lit lenslets).
    """
    cells = lenslet_cells(grid) if cells is None else cells
    allsums, sigma = lenslet_sums(frame, grid, cells)
    n = grid.indices - grid.indices.min(axis=0)
    shape = tuple(n.max(axis=0) + 1)
    valid = np.zeros(shape, dtype=bool)
    valid[n[:, 0], n[:, 1]] = True
    views = np.zeros((*shape, allsums.shape[1]))
    views[n[:, 0], n[:, 1]] = allsums
    pos = np.zeros((*shape, 2))
    pos[n[:, 0], n[:, 1]] = grid.lattice_px()
    adj = _HEX_ADJ if grid.grid == "hex" else _SQUARE_ADJ
    # The frame's median pixel is the background only while few pixels are lit: the light of
    # the dots (a tenth of the pixels of a plane with defocused dots) raises it by about a
    # count, which summed over a lenslet's 150 pixels is a tenth of the threshold, and over
    # the faint rim of a dot (below the threshold, but its light) pulls each view's centroid.
    # The mean of the lenslets far from every lit one is the background's error.
    npix = np.zeros_like(views)
    npix[n[:, 0], n[:, 1]] = cells.view_pixels
    bright = valid & (views[..., 0] > threshold_sigma * sigma)
    dark = valid & ~ndimage.binary_dilation(bright, adj, iterations=3)
    if refine_background and dark.sum() >= max(16, 0.05 * valid.sum()):
        views -= (views[dark, 0].sum() / npix[dark, 0].sum()) * npix
    val = views[..., 0]
    border = valid & ~ndimage.binary_erosion(valid, adj, border_value=0)
    lit = valid & (val > threshold_sigma * sigma)
    # Split touching dots where a valley separates them. Each lit lenslet climbs the smoothed
    # sums to its local maximum, so the lenslets of two overlapping dots part at the valley;
    # the maxima are then grouped from the brightest down (persistence), and a maximum stays
    # a dot of its own only if it stands above the saddle joining it to a brighter one by more
    # than ``min_prominence`` of its height. Noise on the flat top of a dot many lenslets wide
    # (large, or defocused) makes shallow maxima, which join their dot; the dip between two
    # dots is deep.
    sm = ndimage.correlate(np.where(valid, val, 0.0), adj.astype(float), mode="constant")
    sm /= np.maximum(ndimage.correlate(valid.astype(float), adj.astype(float), mode="constant"), 1.0)
    top = _climb(sm, lit, adj)
    region_of = np.full(sm.size, -1, dtype=np.int64)
    region_of[lit.ravel()] = _regions(sm, lit, adj, top, min_prominence)[top[lit.ravel()]]
    # Maxima closer than min_separation pitches (noise on a small dot) are one dot: greedy,
    # brightest first, each joining the brightest kept one within reach.
    roots = np.unique(region_of[region_of >= 0])
    smf, posf = sm.ravel(), pos.reshape(-1, 2)
    owner = {int(r): int(r) for r in roots}
    reach = min_separation * grid.pitch_px
    cells_of: dict[tuple[int, int], list[tuple[int, int]]] = {}  # kept maxima binned one reach wide
    n_kept = 0
    for r in roots[np.argsort(-smf[roots], kind="stable")]:
        cx, cy = (int(v) for v in np.floor(posf[r] / reach))
        near = [(rank, k) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for rank, k in cells_of.get((cx + dx, cy + dy), ())
                if np.hypot(*(posf[r] - posf[k])) < reach]
        if near:
            owner[int(r)] = min(near)[1]
        else:
            cells_of.setdefault((cx, cy), []).append((n_kept, int(r)))
            n_kept += 1
    lit_flat = np.flatnonzero(region_of >= 0)
    label = np.array([owner[int(r)] for r in region_of[lit_flat]], dtype=np.int64)
    # Per dot: lenslet count, whether it touches the lattice edge, flux and view centroids.
    kept, inv = np.unique(label, return_inverse=True)
    size = np.bincount(inv, minlength=len(kept))
    cut = np.bincount(inv, weights=border.ravel()[lit_flat], minlength=len(kept)) > 0
    w = val.ravel()[lit_flat]
    total = np.bincount(inv, weights=w, minlength=len(kept))
    wv = views.reshape(-1, views.shape[-1])[lit_flat]  # (lenslets, views)
    p = posf[lit_flat]
    num = np.stack([np.stack([np.bincount(inv, weights=wv[:, v] * p[:, c], minlength=len(kept)) for c in (0, 1)],
                             axis=-1) for v in range(wv.shape[1])], axis=1)  # (dots, views, 2)
    den = np.stack([np.bincount(inv, weights=wv[:, v], minlength=len(kept)) for v in range(wv.shape[1])], axis=1)
    good = (size >= min_lenslets) & ~cut & (total > 0)
    if good.any():
        # Every dot of the board sends the same light (equal areas, the marker more), so a group
        # with a small fraction of the typical dot's flux is the part of a defocused dot that
        # rose above the threshold: its centroid is biased. Typical: the flux-weighted median,
        # which such fragments, however many, barely move.
        f = np.sort(total[good])
        typical = f[np.searchsorted(np.cumsum(f), 0.5 * f.sum())]
        good &= total >= min_flux_fraction * typical
    centres = num[good] / den[good][:, :, None]
    flux, size = total[good], size[good]
    if good.any() and window_margin is not None:
        owner_of = np.full(sm.size, -1, dtype=np.int64)
        owner_of[lit_flat] = label
        dot_idx = np.flatnonzero(good)
        with np.errstate(invalid="ignore", divide="ignore"):
            c0 = num[:, 0] / den[:, 0, None]
        reach = np.zeros(len(kept))  # the farthest lit lenslet of each dot from its centroid
        np.maximum.at(reach, inv, np.hypot(*(p - c0[inv]).T))
        # a more blurred dot has a wider rim below the threshold: the margin grows with the dot
        radius = reach[dot_idx] + np.maximum(grid.pitch_px, window_margin * reach[dot_idx])
        centres = _window_centroids(centres, radius, kept[dot_idx], views.reshape(-1, views.shape[-1]), posf,
                                    valid.ravel(), owner_of)
    return Dots(np.asarray(centres, dtype=np.float64).reshape(-1, len(VIEW_PUPILS), 2),
                np.asarray(flux, dtype=np.float64), np.asarray(size, dtype=np.int64))


def _window_centroids(start: np.ndarray, radius: np.ndarray, dots: np.ndarray, views: np.ndarray, pos: np.ndarray,
                      valid: np.ndarray, owner: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Centroids of each dot in each view over a disc of lenslets centred on that centroid.

    A disc symmetric about the centroid holds all of a dot's light, its faint rim included
    (which a threshold cuts off, more on the more defocused far side of a dot on a tilted
    board, pulling the centroid to the near side and shrinking the parallax between views),
    and a uniform background error adds light centred on the centroid, which does not move it.

    Parameters
    ----------
    start
        (m, views, 2) centroids over the lit lenslets, pixels.
    radius
        (m,) disc radius of each dot, pixels.
    dots
        (m,) label of each dot in ``owner``.
    views
        (lenslets, views) sums; ``pos``: (lenslets, 2) micro-image centres, pixels; ``valid``:
        (lenslets,) bool, on the lattice (flat lattice index).
    owner
        (lenslets,) label of the dot whose lit lenslet it is, -1 if none: other dots' lit
        lenslets are left out of a disc.
    iterations
        Re-centrings of the discs.

    Returns
    -------
    numpy.ndarray
        (m, views, 2) centroids, pixels.
    """
    on = np.flatnonzero(valid)
    tree = cKDTree(pos[on])
    out = np.array(start, dtype=np.float64)
    m, nv = out.shape[:2]
    for _ in range(iterations):
        # one query a dot covers every view's disc: the views part by the parallax, within the dot
        spread = np.hypot(*(out - out[:, :1]).transpose(2, 0, 1)).max(axis=1)
        near = tree.query_ball_point(out[:, 0], radius + spread)
        dot = np.repeat(np.arange(m), [len(c) for c in near])
        cand = on[np.concatenate([np.asarray(c, dtype=np.int64) for c in near])]
        mine = (owner[cand] < 0) | (owner[cand] == dots[dot])
        dot, cand = dot[mine], cand[mine]
        for v in range(nv):
            inside = np.hypot(*(pos[cand] - out[dot, v]).T) <= radius[dot]
            w = views[cand, v] * inside
            total = np.bincount(dot, weights=w, minlength=m)
            ok = total > 0
            for c in (0, 1):
                out[ok, v, c] = np.bincount(dot, weights=w * pos[cand, c], minlength=m)[ok] / total[ok]
    return out


def _climb(sm: np.ndarray, lit: np.ndarray, adj: np.ndarray) -> np.ndarray:
    """(sm.size,) flat index of the local maximum each lit lenslet reaches by steepest ascent
    over its lit neighbours (``adj``); a lenslet with no brighter lit neighbour is its own."""
    shape = sm.shape
    climbed = np.where(lit, sm, -np.inf)
    flat = np.arange(sm.size).reshape(shape)
    best, parent = climbed.copy(), flat.copy()
    for d1, d2 in zip(*np.nonzero(adj), strict=True):
        shifted = np.full(shape, -np.inf)
        src = np.full(shape, -1)
        o1, o2 = d1 - 1, d2 - 1
        dst_sl = (slice(max(0, -o1), shape[0] - max(0, o1)), slice(max(0, -o2), shape[1] - max(0, o2)))
        src_sl = (slice(max(0, o1), shape[0] - max(0, -o1)), slice(max(0, o2), shape[1] - max(0, -o2)))
        shifted[dst_sl] = climbed[src_sl]
        src[dst_sl] = flat[src_sl]
        up = shifted > best
        best = np.where(up, shifted, best)
        parent = np.where(up, src, parent)
    top = parent.ravel()
    for _ in range(sm.size):  # pointer jumping: log2 of the longest climb
        nxt = top[top]
        if np.array_equal(nxt, top):
            break
        top = nxt
    return top


def _regions(sm: np.ndarray, lit: np.ndarray, adj: np.ndarray, top: np.ndarray, min_prominence: float
             ) -> np.ndarray:
    """The region peak (flat index) of each basin, by merging basins from the top down.

    Each lit lenslet belongs to the basin of the maximum it climbs to (``top``, flat indices).
    The lenslets are visited in decreasing ``sm`` (persistence of the maxima); one whose
    brighter lit neighbours lie in other basins than its own is a saddle between them: of the
    regions (merged basins) meeting there, the one with the highest peak takes every other
    whose peak rises above the saddle by no more than ``min_prominence`` of that peak. Only
    saddles are visited one by one (about a third of the lit lenslets of a plane of defocused,
    touching dots); the rest is array work.

    Returns
    -------
    numpy.ndarray
        (sm.size,) int64: at each basin's top, the flat index of its region's peak; -1 elsewhere.
    """
    shape = sm.shape
    flat = sm.ravel()
    idx = np.flatnonzero(lit.ravel())
    order = idx[np.argsort(-flat[idx], kind="stable")]
    rank = np.full(flat.size, flat.size, dtype=np.int64)  # visiting order; unlit lenslets never come first
    rank[order] = np.arange(len(order))
    rows, cols = np.divmod(idx, shape[1])
    own = top[idx]
    above = []  # per neighbour direction: the basin of a lenslet's brighter lit neighbour, or -1
    for d1, d2 in zip(*np.nonzero(adj), strict=True):
        if (d1, d2) == (1, 1):
            continue
        r2, c2 = rows + d1 - 1, cols + d2 - 1
        inside = (r2 >= 0) & (r2 < shape[0]) & (c2 >= 0) & (c2 < shape[1])
        j = np.where(inside, r2 * shape[1] + c2, 0)
        above.append(np.where(inside & (rank[j] < rank[idx]), top[j], -1))
    near = np.stack(above, axis=1)
    saddle = np.flatnonzero(((near >= 0) & (near != own[:, None])).any(axis=1))
    saddle = saddle[np.argsort(rank[idx[saddle]])]
    parent: dict[int, int] = {}

    def root(b: int) -> int:
        while (p := parent.get(b, b)) != b:
            parent[b] = parent.get(p, p)  # path splitting: point at the grandparent
            b = p
        return b

    for e in saddle.tolist():
        meet = {root(int(b)) for b in near[e] if b >= 0} | {root(int(own[e]))}
        if len(meet) < 2:
            continue
        height = flat[idx[e]]
        highest = max(meet, key=lambda k: flat[k])
        for k in meet - {highest}:
            if flat[k] - height <= min_prominence * flat[k]:
                parent[k] = highest
    out = np.full(flat.size, -1, dtype=np.int64)
    basins = np.unique(own)
    out[basins] = [root(int(b)) for b in basins]
    return out


def _affine(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    a = np.concatenate([src, np.ones((len(src), 1))], axis=1)
    m, *_ = np.linalg.lstsq(a, dst, rcond=None)
    return m  # (3, 2): dst = [src, 1] @ m


def match_dots(dots: Dots, predicted_px: np.ndarray, indices: np.ndarray, *, marker_ratio: float = 1.8,
               tolerance: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Name the found dots: pair each with a board dot.

    Parameters
    ----------
    dots
        Found dots.
    predicted_px
        (k, 2) positions of board dots ``indices`` predicted by a (nominal) camera model, pixels.
    indices
        (k, 2) board indices (i, j), with (0, 0) the marker.
    marker_ratio
        Dots with more than this many times the median flux are marker candidates; the one
        nearest the marker's predicted position is taken.
    tolerance
        Largest accepted distance from a predicted position, in predicted dot spacings.

    Returns
    -------
    found : numpy.ndarray
        (p,) int indices into ``dots``.
    board : numpy.ndarray
        (p, 2) int64 board indices (i, j) of those dots.
    """
    pred = np.asarray(predicted_px, dtype=np.float64)
    idx = np.asarray(indices, dtype=np.int64)
    keep = np.all(np.isfinite(pred), axis=1)
    pred, idx = pred[keep], idx[keep]
    if len(dots) == 0 or len(pred) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    spacing = float(np.median(cKDTree(pred).query(pred, k=2)[0][:, 1]))
    m = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    origin = np.flatnonzero(np.all(idx == 0, axis=1))
    if len(dots) >= 3 and len(origin):
        # The marker has clearly the most light; where crowded defocused dots merge into groups
        # as bright, the bright one nearest the marker's predicted place is taken.
        bright = np.flatnonzero(dots.flux > marker_ratio * np.median(dots.flux))
        if len(bright) and len(bright) < len(dots) / 2:
            best = bright[np.argmin(np.hypot(*(dots.centres_px[bright] - pred[origin[0]]).T))]
            m[2] = dots.centres_px[best] - pred[origin[0]]
    found = np.zeros(0, dtype=np.int64)
    which = np.zeros(0, dtype=np.int64)
    for _ in range(4):
        moved = np.concatenate([pred, np.ones((len(pred), 1))], axis=1) @ m
        dist, near = cKDTree(moved).query(dots.centres_px)
        ok = dist < tolerance * spacing
        # one dot per board position: the nearest
        order = np.lexsort((dist, near))
        first = np.ones(len(order), dtype=bool)
        first[1:] = near[order][1:] != near[order][:-1]
        sel = np.sort(order[first & ok[order]])
        found, which = sel, near[sel]
        if len(sel) >= 4:
            m = _affine(pred[which], dots.centres_px[found])
    return found.astype(np.int64), idx[which]
