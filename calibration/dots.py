"""Dots of the calibration target in a raw light-field image: found, centred, and named.

Method. Each lenslet's micro-image holds all the light that reached the MLA through that
lenslet, so the sum of its pixels (a Voronoi cell about its micro-image centre, background
removed) samples the image the main lens forms on the MLA, one sample per lenslet. A dot's
image there, sharp or defocused, is centred on its chief ray (:mod:`lfcore.projection`), so the
flux-weighted mean of the micro-image centres of the lenslets it lights is where
:func:`lfcore.projection.project` puts the dot, to a fraction of a lenslet: every ray of the
dot counts (not only the central sub-aperture's), so Monte-Carlo and shot noise average out.

1. Lenslet sums over cells of radius 0.6 pitch about the fitted lattice nodes of the white image
   (:class:`calibration.mla_grid.MlaGrid`); background: the frame's median pixel.
2. Lenslets brighter than ``threshold_sigma`` noise sigmas; each climbs the sums (smoothed over
   its lattice neighbours, in lattice index space: six on a hexagonal grid, eight on a square
   one) to a local maximum, so the faint overlap of two defocused dots is split at its valley;
   maxima closer than ``min_separation`` pitches (noise on a flat defocused disc) are merged.
3. Each dot's flux-weighted centroid over its lenslets, also with each lenslet's light split
   between the halves of the main-lens aperture (each pixel of a micro-image sees one aperture
   point): the views through opposite halves disagree in proportion to the dot's defocus. Dots
   touching the edge of the detected lattice are dropped (a cut dot's centroid is biased).
4. Naming: the marker dot (0, 0) is the one with clearly the most light (the dots are equally
   bright per area); the board's dots projected by a nominal camera are shifted onto it, then an
   affine map from predicted to found positions is refined on nearest matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from calibration.mla_grid import MlaGrid

__all__ = ["VIEW_PUPILS", "DotError", "Dots", "detect_dots", "lenslet_sums", "match_dots", "view_pupils_mm"]

#: The views a dot is centred in, as the mean aperture point of the light each takes, in units
#: of 4 R / (3 pi) (the centroid of a half disc of radius R): all the light (the chief ray),
#: then the +x, -x, +y and -y halves of the aperture (camera frame).
VIEW_PUPILS = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def view_pupils_mm(aperture_mm: float) -> np.ndarray:
    """(views, 2) mean aperture point (camera-frame x, y, mm) of each view, for aperture diameter D."""
    return VIEW_PUPILS * 4.0 * (0.5 * aperture_mm) / (3.0 * np.pi)

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
    views_px : numpy.ndarray
        (m, views, 2) continuous (column, row) centroids, pixels, in each view of
        :data:`VIEW_PUPILS` (view 0: all the light, centred on the chief ray).
    flux : numpy.ndarray
        (m,) background-subtracted light of each dot, counts.
    lenslets : numpy.ndarray
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


def lenslet_sums(frame: np.ndarray, grid: MlaGrid) -> tuple[np.ndarray, float]:
    """Background-subtracted light of every lenslet of ``grid`` in ``frame``.

    Parameters
    ----------
    frame
        (rows, columns) raw image, counts.
    grid
        The microlens grid from the white image.

    Returns
    -------
    sums : numpy.ndarray
        (n, 5) counts per lenslet, in the order of ``grid.indices``: all its light, then the
        light through the +x, -x, +y and -y halves of the main-lens aperture (camera frame), the
        views of :data:`VIEW_PUPILS`.
    sigma : float
        Noise sigma of one sum (background pixels' robust sigma times sqrt(pixels per cell)).
    """
    img = np.asarray(frame, dtype=np.float64)
    rows, cols = img.shape
    if (rows, cols) != tuple(grid.image_shape):
        raise DotError(f"frame of {cols} x {rows} pixels does not match the white image's "
                       f"{grid.image_shape[1]} x {grid.image_shape[0]}")
    bg = float(np.median(img))
    low = img[img <= bg]
    sig_px = 1.4826 * float(np.median(bg - low)) if len(low) else 1.0  # MAD of the lower half
    nodes = grid.lattice_px()
    r, c = np.mgrid[0:rows, 0:cols]
    xy = np.stack([c.ravel() + 0.5, r.ravel() + 0.5], axis=-1)
    dist, idx = cKDTree(nodes).query(xy, distance_upper_bound=0.6 * grid.pitch_px)
    ok = np.isfinite(dist)
    v = img.ravel()[ok] - bg
    # Pupil halves: a pixel delta (column, row) from its micro-image centre sees the aperture
    # point A = -(si / f_ml) delta_sensor, so A_x > 0 for columns right of the centre and
    # A_y > 0 above it (row = Nr/2 + y / pixel); a pixel on the dividing line is shared by its fraction on each side.
    d = xy[ok] - nodes[idx[ok]]
    wx = np.clip(d[:, 0] + 0.5, 0.0, 1.0)
    wy = np.clip(0.5 - d[:, 1], 0.0, 1.0)
    weights = (v, v * wx, v * (1 - wx), v * wy, v * (1 - wy))
    sums = np.stack([np.bincount(idx[ok], weights=w, minlength=len(nodes)) for w in weights], axis=-1)
    npix = np.bincount(idx[ok], minlength=len(nodes))
    return sums, max(sig_px, 1e-3) * float(np.sqrt(np.median(npix)))


def detect_dots(frame: np.ndarray, grid: MlaGrid, *, threshold_sigma: float = 8.0, min_lenslets: int = 2,
                min_separation: float = 2.5) -> Dots:
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

    Returns
    -------
    Dots
        Centroids in raw pixel coordinates, fluxes and sizes.
    """
    allsums, sigma = lenslet_sums(frame, grid)
    sums = allsums[:, 0]
    n = grid.indices - grid.indices.min(axis=0)
    shape = tuple(n.max(axis=0) + 1)
    valid = np.zeros(shape, dtype=bool)
    valid[n[:, 0], n[:, 1]] = True
    val = np.zeros(shape)
    val[n[:, 0], n[:, 1]] = sums
    views = np.zeros((*shape, allsums.shape[1]))
    views[n[:, 0], n[:, 1]] = allsums
    pos = np.zeros((*shape, 2))
    pos[n[:, 0], n[:, 1]] = grid.lattice_px()
    adj = _HEX_ADJ if grid.grid == "hex" else _SQUARE_ADJ
    border = valid & ~ndimage.binary_erosion(valid, adj, border_value=0)
    lit = valid & (val > threshold_sigma * sigma)
    # Split touching dots: each lit lenslet climbs the smoothed sums to its local maximum;
    # maxima closer than min_separation (noise on a defocused dot's flat top) are merged into
    # the brighter one.
    sm = ndimage.correlate(np.where(valid, val, 0.0), adj.astype(float), mode="constant")
    sm /= np.maximum(ndimage.correlate(valid.astype(float), adj.astype(float), mode="constant"), 1.0)
    sm = np.where(lit, sm, -np.inf)
    flat = np.arange(sm.size).reshape(shape)
    best, parent = sm.copy(), flat.copy()
    for d1, d2 in zip(*np.nonzero(adj), strict=True):
        shifted = np.full(shape, -np.inf)
        src = np.full(shape, -1)
        o1, o2 = d1 - 1, d2 - 1
        dst_sl = (slice(max(0, -o1), shape[0] - max(0, o1)), slice(max(0, -o2), shape[1] - max(0, o2)))
        src_sl = (slice(max(0, o1), shape[0] - max(0, -o1)), slice(max(0, o2), shape[1] - max(0, -o2)))
        shifted[dst_sl] = sm[src_sl]
        src[dst_sl] = flat[src_sl]
        up = shifted > best
        best = np.where(up, shifted, best)
        parent = np.where(up, src, parent)
    par = parent.ravel()
    for _ in range(64):
        nxt = par[par]
        if np.array_equal(nxt, par):
            break
        par = nxt
    lit_flat = lit.ravel()
    roots = np.unique(par[lit_flat])
    rpos = pos.reshape(-1, 2)[roots]
    order = np.argsort(-sm.ravel()[roots])
    owner = {int(r): int(r) for r in roots}
    kept: list[int] = []
    for i in order:
        near = [k for k in kept if np.hypot(*(rpos[i] - rpos[np.searchsorted(roots, k)])) < min_separation
                * grid.pitch_px]
        if near:
            owner[int(roots[i])] = near[0]
        else:
            kept.append(int(roots[i]))
    region_of = np.full(sm.size, -1)
    region_of[lit_flat] = [owner[int(r)] for r in par[lit_flat]]
    border_flat = border.ravel()
    valf = val.ravel()
    posf = pos.reshape(-1, 2)
    centres, flux, size = [], [], []
    for k in kept:
        members = region_of == k
        if members.sum() < min_lenslets or np.any(members & border_flat):
            continue
        w = valf[members]
        total = float(w.sum())
        if total <= 0:
            continue
        wv = views.reshape(-1, views.shape[-1])[members]  # (lenslets, views)
        centres.append(np.einsum("lv,lc->vc", wv, posf[members]) / wv.sum(axis=0)[:, None])
        flux.append(total)
        size.append(int(members.sum()))
    return Dots(np.asarray(centres, dtype=np.float64).reshape(-1, len(VIEW_PUPILS), 2),
                np.asarray(flux, dtype=np.float64), np.asarray(size, dtype=np.int64))


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
        The brightest dot is the marker if it has this many times the median flux.
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
    if len(dots) >= 3:
        best = int(np.argmax(dots.flux))
        others = np.delete(dots.flux, best)
        origin = np.flatnonzero(np.all(idx == 0, axis=1))
        if dots.flux[best] > marker_ratio * np.median(others) and len(origin):
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
