"""Particle candidates by ray bundling: the bright pixels' rays voted into the box, not a reconstruction.

IPR (:mod:`lfcore.ipr`) needs candidate positions to start its fit from. A quick volume reconstruction
gives them at a cost that grows with the voxels; this module gives them with no volume and no weights
(:attr:`lfcore.ipr.IprSettings.candidate_source` ``"rays"``):

1. **Bright pixels.** Each camera's image less its background (:func:`lfcore.reconstruct.estimate_background`,
   as the reconstruction subtracts it); a pixel is bright above ``threshold_sigma`` noise sigmas (the
   reconstruction's own lit-pixel rule, :func:`lfcore.reconstruct.preprocess`).
2. **Rays.** A light-field camera's pixel behind a lenslet is one direction of light through that lenslet
   (:mod:`lfcore._kernels.render`: a ray with image-side slope s_out through the MLA at q lands at
   c + f_ml s_out, c the lenslet's centre). With q taken at the lenslet's centre, the ray passed the main
   lens at A = c - si s_out and came from the object side with slope s_in = s_out + A / F: every point
   E = (A - s_in t, so - t) of the camera frame, t its distance in front of the lens. The true ray passed
   somewhere in the lenslet's cell, so each ray stands for a tube about an object-side lenslet
   (pitch / |M|) wide. A pinhole camera's pixel is its line of sight (:func:`lfcore.pinhole.line_of_sight`).
3. **Vote.** Each ray is sampled through the box at steps of at most one vote bin along every axis (bins a
   tube wide: whole voxels per axis); a bin's vote is its rays' light over the lenslets a particle there
   would light. At LF-PIV densities most pixels are lit and every bin is crossed by many lenslets' rays,
   so the vote only ranks the bins.
4. **Check.** The points of the most voted bins (``keep_bins``), every half tube, are checked against each
   lenslet that would see a particle there (:func:`point_scores`): a low percentile of the light at the
   pixels where its light would land, one pixel a lenslet. A particle lights all of them; the light of
   others lights some by chance.
5. **Candidates.** The checks' local maxima above ``min_score`` of the brightest (and the noise), each
   refined where the rays of its light in those lenslets meet (least squares, three times), the weaker
   of two within a voxel, then within half the resolution, left out.

The cost is the rays times the bins a ray crosses (the vote), the bins kept times the lenslets a point's
light reaches (the check), and the candidates times their lenslets (the refinement): no voxels' weights
and no volume; the vote's memory is the box's bins (a tube's width each: on issue 48's Mc rig 49 voxels a
bin). On the focal plane a particle's light falls in one lenslet, whose rays fan out from it: a point
fewer than ``min_lenslets`` lenslets see is no candidate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lfcore.reconstruct import estimate_background
from lfcore.volume import VolumeGrid

__all__ = ["Rays", "camera_rays", "point_scores", "ray_candidates"]


@dataclass
class Rays:
    """One camera's rays of its bright pixels, world mm.

    Attributes
    ----------
    origin
        (n, 3) a point of each ray (x, y, z), mm: where it passes the main lens.
    direction
        (n, 3) unit direction into the scene (x, y, z).
    weight
        (n,) the pixel's background-subtracted signal, counts.
    lenslet
        (n,) int64: which lenslet (a pinhole camera: which pixel) the ray came through, numbered
        within the camera.
    tube_mm
        The width of the tube each ray stands for near the box, mm (an object-side lenslet, or two of a
        pinhole camera's object-side pixels).
    camera
        The camera the rays came from.
    """

    origin: np.ndarray
    direction: np.ndarray
    weight: np.ndarray
    lenslet: np.ndarray
    tube_mm: float
    camera: object = None

    @property
    def n(self) -> int:
        return len(self.weight)


def camera_rays(camera, image: np.ndarray, *, threshold_sigma: float = 2.0,
                background: float | None = None) -> Rays:
    """The rays of a camera's bright pixels.

    Parameters
    ----------
    camera
        A light-field :class:`lfcore.rig.Camera` or a :class:`lfcore.rig.PinholeCamera`.
    image
        (rows, columns) raw image, counts.
    threshold_sigma
        A pixel is bright above the background by this many noise sigmas.
    background
        The background level, counts (None: :func:`lfcore.reconstruct.estimate_background`'s).

    Returns
    -------
    Rays
    """
    from lfcore.rig import is_pinhole

    img = np.asarray(image, dtype=np.float64)
    level, sigma = estimate_background(img)
    if background is not None:
        level = float(background)
    signal = img - level
    rows, cols = np.nonzero(np.nan_to_num(signal, nan=0.0) > threshold_sigma * sigma)
    weight = signal[rows, cols]
    centres = np.stack([cols + 0.5, rows + 0.5], axis=-1)
    if is_pinhole(camera):
        from lfcore.pinhole import line_of_sight

        origin, direction = line_of_sight(camera, centres)
        return Rays(origin, direction, weight, rows.astype(np.int64) * image.shape[1] + cols,
                    2.0 * camera.object_pixel_mm, camera)
    return _light_field_rays(camera, centres, weight)


def _light_field_rays(cam, centres: np.ndarray, weight: np.ndarray) -> Rays:
    """Rays of a light-field camera's pixels at (column, row) ``centres`` (see the module docstring)."""
    from lfcore.mla import nearest_lenslet, pixel_to_sensor

    si, f_ml, big_f = cam.image_distance_mm, cam.mla_focal_length_mm, cam.main_focal_length_mm
    xy = pixel_to_sensor(cam, centres)
    # a lenslet's micro-image is centred on its central ray, k c with k = 1 + f_ml / si
    c = nearest_lenslet(cam, xy / (1.0 + f_ml / si))
    s_out = (xy - c) / f_ml
    a = c - si * s_out  # where the ray passed the main lens (its centre taken through c)
    # pixels beyond the aperture's image are light of a neighbouring lenslet: left out
    reach = 0.5 * cam.aperture_mm + si * cam.pixel_mm / f_ml
    ok = np.hypot(a[:, 0], a[:, 1]) <= reach
    a, s_out, c, weight = a[ok], s_out[ok], c[ok], weight[ok]
    s_in = s_out + a / big_f
    origin = cam.camera_to_world(np.column_stack([a, np.full(len(a), cam.object_distance_mm)]))
    d = np.column_stack([-s_in, -np.ones(len(a))])
    direction = (d / np.linalg.norm(d, axis=1, keepdims=True)) @ cam.rotation.T
    _, lenslet = np.unique(np.round(c / (0.25 * cam.mla_pitch_mm)).astype(np.int64), axis=0, return_inverse=True)
    return Rays(origin, direction, weight, lenslet.ravel().astype(np.int64),
                cam.mla_pitch_mm / abs(cam.magnification), cam)


def ray_candidates(grid: VolumeGrid, cameras: Sequence, images: Sequence[np.ndarray], *,
                   threshold_sigma: float = 2.0, backgrounds: Sequence[float] | None = None,
                   keep_bins: float = 1.0, min_score: float = 0.1, percentile: float = 10.0,
                   max_samples: int = 5_000_000,
                   max_points: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Candidates where the cameras' bright pixels' rays bundle (see the module docstring).

    Parameters
    ----------
    grid
        The box.
    cameras
        The cameras (light-field or pinhole), in image order.
    images
        One raw (rows, columns) image per camera, counts.
    threshold_sigma
        A pixel is bright above its image's background by this many noise sigmas.
    backgrounds
        Each image's background level, counts (None: estimated, :func:`lfcore.reconstruct.estimate_background`).
    keep_bins
        The share of the vote bins that rays reach, the most voted first, whose voxels are checked.
    min_score
        A candidate's check (:func:`point_scores`) at least this share of the 99th percentile of the
        checked voxels' local maxima.
    percentile
        The check's percentile of a light-field camera's lenslets (:func:`point_scores`).
    max_samples
        Ray samples voted at once (memory: about 40 bytes a sample).
    max_points
        Voxels checked at once (memory: about 100 bytes a voxel and lenslet).

    Returns
    -------
    positions
        (n, 3) voxel index coordinates (z, y, x) of the candidates, strongest first.
    scores
        (n,) their checks, counts.
    """
    shape = np.asarray(grid.shape)  # (z, y, x)
    voxel = np.asarray(grid.voxel_mm)[::-1]  # (z, y, x)
    backgrounds = backgrounds if backgrounds is not None else [None] * len(cameras)
    rays = [camera_rays(cam, img, threshold_sigma=threshold_sigma, background=bg)
            for cam, img, bg in zip(cameras, images, backgrounds, strict=True)]
    signals = []  # the lit pixels' signal, as the reconstruction preprocesses the images (0 elsewhere)
    noise = []
    for img, bg in zip(images, backgrounds, strict=True):
        level, sigma = estimate_background(img)
        noise.append(sigma)
        sig = np.nan_to_num(np.asarray(img, np.float64) - (level if bg is None else float(bg)), nan=0.0)
        signals.append(np.where(sig > threshold_sigma * sigma, sig, 0.0))
    if not any(r.n for r in rays):
        return np.zeros((0, 3)), np.zeros(0)
    tube = max(r.tube_mm for r in rays)
    b = np.maximum(1, np.round(tube / voxel)).astype(np.int64)  # voxels a bin, (z, y, x)
    nb = -(-shape // b)
    n_bins = int(np.prod(nb))
    # 1. the vote: each camera's rays' light per bin over the lenslets a particle there would light
    centres = (np.stack(np.unravel_index(np.arange(n_bins), tuple(nb)), axis=1) + 0.5) * b - 0.5
    world = np.asarray(grid.origin_mm) + centres[:, ::-1] * voxel[::-1]
    vote = np.zeros(n_bins)
    for r in rays:
        light = np.zeros(n_bins)
        for bins, ray in _samples(grid, r, b, nb, max_samples=max_samples):
            light += np.bincount(bins, weights=r.weight[ray], minlength=n_bins)
        vote += light / _expected(r.camera, world)
    reached = np.flatnonzero(vote > 0)
    top = reached[np.argsort(-vote[reached], kind="stable")[:max(1, int(np.ceil(keep_bins * len(reached))))]]
    # 2. the check of those bins' voxels, every `step` voxels (half a tube: the check is a tube wide),
    # against each lenslet's (pixel's) own light
    step = np.maximum(1, b // 2)
    sub = np.stack(np.meshgrid(*[np.arange(0, k, st) for k, st in zip(b, step, strict=True)], indexing="ij"),
                   axis=-1).reshape(-1, 3)
    vox = (np.stack(np.unravel_index(top, tuple(nb)), axis=1)[:, None, :] * b + sub[None]).reshape(-1, 3)
    vox = vox[np.all(vox < shape, axis=1)]
    score = np.empty(len(vox))
    for s in range(0, len(vox), max(1, max_points)):
        pts = np.asarray(grid.origin_mm) + vox[s:s + max_points][:, ::-1] * voxel[::-1]
        score[s:s + max_points] = point_scores(cameras, signals, pts, percentile=percentile)
    # 3. the checks' local maxima (26 neighbours, among the checked voxels)
    key = np.ravel_multi_index(tuple(vox.T), tuple(shape))
    order = np.argsort(key)
    key, vox, score = key[order], vox[order], score[order]
    peak = score > 0
    offs = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)])
    offs = offs * step
    near = {}
    for o in offs:
        nbr = vox + o
        ok = np.all((nbr >= 0) & (nbr < shape), axis=1)
        nk = np.ravel_multi_index(tuple(np.clip(nbr, 0, shape - 1).T), tuple(shape))
        at = np.clip(np.searchsorted(key, nk), 0, len(key) - 1)
        v = np.where(ok & (key[at] == nk), score[at], -np.inf)
        # ties: the first in key order wins
        peak &= (score > v) | ((score == v) & (key < nk))
        near[tuple(o)] = v
    idx = np.flatnonzero(peak)
    if len(idx) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    # at least a lit pixel's signal, and min_score of the brightest
    cut = max(min_score * np.percentile(score[idx], 99), threshold_sigma * max(noise))
    idx = idx[score[idx] >= cut]
    # sub-voxel: a parabola through each axis' three checks
    pos = vox[idx].astype(np.float64)
    for ax in range(3):
        o = np.zeros(3, int)
        o[ax] = step[ax]
        lo, hi, mid = near[tuple(-o)][idx], near[tuple(o)][idx], score[idx]
        den = lo - 2.0 * mid + hi
        ok = np.isfinite(lo) & np.isfinite(hi) & (den < 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            pos[:, ax] += step[ax] * np.where(ok, np.clip(0.5 * (lo - hi) / np.where(ok, den, 1.0), -0.5, 0.5), 0.0)
    order = np.argsort(-score[idx], kind="stable")
    pos, sc = pos[order], score[idx][order]
    # 4. each refined where its lenslets' rays bundle; two that end within a voxel are one
    for s in range(0, len(pos), 2048):
        sl = slice(s, s + 2048)
        world = np.asarray(grid.origin_mm) + pos[sl][:, ::-1] * voxel[::-1]
        pos[sl] = ((_refine(cameras, signals, world, tube) - np.asarray(grid.origin_mm)) / voxel[::-1])[:, ::-1]
    pos, sc = _suppress(pos, sc, 1.0)
    # of two within the resolution (half a tube across a camera's rays, half its depth of a lenslet along
    # them) the weaker is the stronger's echo
    inside = np.all((pos >= -0.5) & (pos <= shape - 0.5), axis=1)
    return _suppress(pos[inside], sc[inside], 0.5 * _resolution(cameras, grid))


def point_scores(cameras: Sequence, signals: Sequence[np.ndarray], points_mm: np.ndarray, *,
                 percentile: float = 10.0, min_lenslets: int = 4) -> np.ndarray:
    """How well each point's would-be image is lit: the least over the cameras of each camera's check
    (one dark camera refuses it).

    A light-field camera's check is the ``percentile`` of its lenslets' signals, each lenslet whose cell
    meets the point's blur disc on the MLA read at the pixel the point's ray through the lenslet's centre
    lands on (where a particle there is brightest in that micro-image: a particle lights that pixel in
    every such lenslet, the light of others falls on some of them by chance); a pinhole camera's is its
    signal at the pixel the point projects to.

    Parameters
    ----------
    cameras
        The cameras, in image order.
    signals
        Each camera's background-subtracted image, clipped at 0, counts.
    points_mm
        (n, 3) world points (x, y, z), mm.
    percentile
        The percentile of a light-field camera's lenslets' signals.
    min_lenslets
        A light-field camera that sees a point through fewer lenslets abstains (near its focal plane
        a particle's light falls in one or two lenslets, and a lit pixel's whole ray through them
        would score); a point no camera checks scores 0.

    Returns
    -------
    numpy.ndarray
        (n,) counts.
    """
    from lfcore.rig import is_pinhole

    out = np.full(len(points_mm), np.nan)
    for cam, sig in zip(cameras, signals, strict=True):
        if is_pinhole(cam):
            from lfcore.pinhole import project

            v = _read(sig, project(cam, points_mm))
        else:
            v = _light_field_scores(cam, sig, points_mm, percentile, min_lenslets)
        out = np.fmin(out, v)  # a camera that cannot tell (NaN) abstains
    return np.nan_to_num(out, nan=0.0)


def _read(sig: np.ndarray, cr: np.ndarray) -> np.ndarray:
    """Signal at continuous (column, row) ``cr`` (..., 2), bilinear between pixel centres; NaN off the
    sensor."""
    x = np.asarray(cr, dtype=np.float64)[..., 0] - 0.5
    y = np.asarray(cr, dtype=np.float64)[..., 1] - 0.5
    inb = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (y >= -0.5) & (x < sig.shape[1] - 0.5) & (
        y < sig.shape[0] - 0.5)
    x = np.clip(np.nan_to_num(x), 0.0, sig.shape[1] - 1.0)
    y = np.clip(np.nan_to_num(y), 0.0, sig.shape[0] - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), sig.shape[1] - 2 if sig.shape[1] > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), sig.shape[0] - 2 if sig.shape[0] > 1 else 0)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, sig.shape[1] - 1), np.minimum(y0 + 1, sig.shape[0] - 1)
    v = ((1 - fy) * ((1 - fx) * sig[y0, x0] + fx * sig[y0, x1]) + fy * ((1 - fx) * sig[y1, x0] + fx * sig[y1, x1]))
    return np.where(inb, v, np.nan)


def _light_field_scores(cam, sig: np.ndarray, points_mm: np.ndarray, percentile: float,
                        min_lenslets: int, chunk: int = 8192) -> np.ndarray:
    """:func:`point_scores` of one light-field camera (``chunk`` points at a time); NaN where fewer than
    ``min_lenslets`` lenslets see the point."""
    out = np.full(len(points_mm), np.nan)
    for s in range(0, len(points_mm), chunk):
        _, cr, inside = _lenslet_pixels(cam, points_mm[s:s + chunk])
        # the percentile of the lenslets' reads (the nearest rank), the lenslets not seen sorted last
        r = _read(sig, cr)
        ok = inside & np.isfinite(r)
        seen = np.count_nonzero(ok, axis=1)
        v = np.sort(np.where(ok, r, np.inf), axis=1)
        rank = np.floor(percentile / 100.0 * np.maximum(seen - 1, 0)).astype(np.int64)
        got = np.take_along_axis(v, rank[:, None], axis=1)[:, 0] if v.shape[1] else np.zeros(len(rank))
        out[s:s + chunk] = np.where(seen >= min_lenslets, np.nan_to_num(got, posinf=0.0), np.nan)
    return out


def _lenslet_pixels(cam, points_mm: np.ndarray, *, margin_mm: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each point's light falls in each lenslet that its blur disc on the MLA (widened by
    ``margin_mm``) meets.

    Returns
    -------
    centres
        (n, k, 2) sensor-plane centres of the lenslets, mm (k: the most any point meets).
    pixels
        (n, k, 2) continuous (column, row) where the point's ray through each lenslet's centre lands.
    inside
        (n, k) bool: the lenslet meets the point's disc and that ray passes the main lens' aperture.
    """
    import math

    from lfcore.chief_ray import chief_ray_mla, defocus_radius_mm
    from lfcore.mla import HEX_ROW, nearest_lenslet, sensor_to_pixel

    si, big_f, f_ml, p = cam.image_distance_mm, cam.main_focal_length_mm, cam.mla_focal_length_mm, cam.mla_pitch_mm
    e = cam.world_to_camera(points_mm)
    depth = cam.object_distance_mm - e[:, 2]
    q0 = np.nan_to_num(chief_ray_mla(cam, points_mm), nan=1e6)
    reach = np.nan_to_num(defocus_radius_mm(cam, points_mm), nan=0.0) + 0.5 * p + margin_mm
    # the lattice's vectors on the sensor plane, and every lenslet within the widest disc of the points
    t = math.radians(cam.mla_rotation_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    a1 = rot @ np.array([p, 0.0])
    a2 = rot @ (np.array([0.5 * p, p * HEX_ROW]) if cam.mla_grid == "hex" else np.array([0.0, p]))
    widest = float(reach.max()) if len(reach) else p
    k = int(np.ceil(widest / (p * (HEX_ROW if cam.mla_grid == "hex" else 1.0)))) + 1
    ij = np.stack(np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij"), axis=-1).reshape(-1, 2)
    off = ij[:, :1] * a1 + ij[:, 1:] * a2
    off = off[np.hypot(off[:, 0], off[:, 1]) <= widest + p]
    c = nearest_lenslet(cam, q0)[:, None, :] + off[None]  # (n, lenslets, 2)
    inside = np.hypot(*(c - q0[:, None, :]).transpose(2, 0, 1)) <= reach[:, None]
    # the ray from the point through the lenslet's centre: q = A (1 + si / d - si / F) - si E_xy / d = c
    d = depth[:, None, None]
    den = 1.0 + si / d - si / big_f  # 0 on the focal plane: every ray of the point meets the MLA at one place
    ok = np.abs(den) > 1e-9
    a = np.where(ok, (c + si * e[:, None, :2] / d) / np.where(ok, den, 1.0), 0.0)
    inside &= (np.hypot(a[..., 0], a[..., 1]) <= 0.5 * cam.aperture_mm + margin_mm * si / f_ml) & (d[..., 0] > 0)
    s_out = (a - e[:, None, :2]) / d - a / big_f
    return c, sensor_to_pixel(cam, c + f_ml * s_out), inside


def _entry(cam, points_mm: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(n, k, 2) where on the MLA the light of each point enters each lenslet of centre ``c`` (n, k, 2):
    the centroid of the lenslet's cell (taken as a disc of half the pitch) within the point's blur disc."""
    from lfcore.chief_ray import chief_ray_mla, defocus_radius_mm

    q0 = np.nan_to_num(chief_ray_mla(cam, points_mm), nan=0.0)[:, None, :]
    big_r = np.nan_to_num(defocus_radius_mm(cam, points_mm), nan=0.0)[:, None]
    rho = 0.5 * cam.mla_pitch_mm
    out = c - q0
    r = np.hypot(out[..., 0], out[..., 1])
    u = out / np.where(r > 0, r, 1.0)[..., None]
    # the part x <= h of a unit disc (x outward from the blur disc's centre): area h sqrt(1 - h^2) +
    # arcsin h + pi / 2, first moment -2/3 (1 - h^2)^(3/2)
    h = np.clip((big_r - r) / rho, -1.0, 1.0)
    area = h * np.sqrt(1.0 - h * h) + np.arcsin(h) + 0.5 * np.pi
    xbar = np.where(area > 1e-9, -(2.0 / 3.0) * (1.0 - h * h) ** 1.5 / np.where(area > 1e-9, area, 1.0), 0.0)
    return c + (rho * xbar)[..., None] * u


def _refine(cameras: Sequence, signals: Sequence[np.ndarray], points_mm: np.ndarray, tube: float,
            iterations: int = 3) -> np.ndarray:
    """Each point moved to where the rays of its light bundle best (least squares).

    In each lenslet that would see a particle at the point (a pinhole camera: at the pixel it projects
    to), the light's centroid within a pixel of where the point's ray lands gives that lenslet's ray
    (as :func:`camera_rays` makes it), weighted by the light; the point nearest these rays, the rays
    farther than half a tube from it weighed down, is the new point. ``iterations`` times.
    """
    from lfcore.mla import pixel_to_sensor
    from lfcore.rig import is_pinhole

    pts = np.asarray(points_mm, dtype=np.float64).copy()
    win = np.array([[dx, dy] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.float64)
    for it in range(iterations):
        org, drn, wts = [], [], []
        for cam, sig in zip(cameras, signals, strict=True):
            if is_pinhole(cam):
                from lfcore.pinhole import line_of_sight, project

                cr = np.nan_to_num(project(cam, pts), nan=-1e6)[:, None, :]
                inside = np.ones(cr.shape[:2], bool)
            else:
                # lenslets a little beyond the disc too: the particle may lie farther from focus
                c, cr, inside = _lenslet_pixels(cam, pts, margin_mm=2.0 * cam.mla_pitch_mm)
            # the light's centroid among the 3 x 3 pixels about where the point's ray lands
            centre = np.floor(cr) + 0.5
            nbr = centre[..., None, :] + win  # (n, k, 9, 2)
            w = np.nan_to_num(_read(sig, nbr), nan=0.0) * inside[..., None]
            tot = w.sum(axis=-1)
            cen = np.sum(w[..., None] * nbr, axis=-2) / np.where(tot > 0, tot, 1.0)[..., None]
            if is_pinhole(cam):
                o, dv = line_of_sight(cam, cen)
            else:
                si, f_ml = cam.image_distance_mm, cam.mla_focal_length_mm
                s_out = (pixel_to_sensor(cam, cen) - c) / f_ml
                # the light entered the lenslet where its cell meets the point's blur disc: at the edge of
                # the disc, off its centre, toward the disc's (a ray through the centre would be biased)
                a = _entry(cam, pts, c) - si * s_out
                s_in = s_out + a / cam.main_focal_length_mm
                o = cam.camera_to_world(np.concatenate([a, np.full(a.shape[:-1] + (1,), cam.object_distance_mm)],
                                                       axis=-1))
                dv = np.concatenate([-s_in, -np.ones(a.shape[:-1] + (1,))], axis=-1)
                dv = (dv / np.linalg.norm(dv, axis=-1, keepdims=True)) @ np.asarray(cam.rotation).T
            org.append(o)
            drn.append(dv)
            wts.append(tot)
        o, dv, w = np.concatenate(org, axis=1), np.concatenate(drn, axis=1), np.concatenate(wts, axis=1)
        if it:  # the rays that pass far from the point are other particles' light
            rel = pts[:, None, :] - o
            dist = np.linalg.norm(rel - np.sum(rel * dv, axis=-1, keepdims=True) * dv, axis=-1)
            w = w * np.exp(-((dist / (0.5 * tube)) ** 2))
        proj = np.eye(3) - dv[..., :, None] * dv[..., None, :]  # (n, k, 3, 3)
        m = np.einsum("nk,nkij->nij", w, proj)
        v = np.einsum("nk,nkij,nkj->ni", w, proj, o)
        # a little pull to where the point was: the depth of a point that one lenslet sees is not known
        reg = 1e-6 * np.maximum(np.trace(m, axis1=1, axis2=2), 1e-12)
        m += reg[:, None, None] * np.eye(3)
        v += reg[:, None] * pts
        pts = np.linalg.solve(m, v[..., None])[..., 0]
    return pts


def _expected(camera, points_mm: np.ndarray) -> np.ndarray:
    """(n,) how many lenslets of ``camera`` a particle at each world point lights (a pinhole camera: 1)."""
    from lfcore.chief_ray import defocus_radius_mm
    from lfcore.rig import is_pinhole

    if camera is None or is_pinhole(camera):
        return np.ones(len(points_mm))
    p = camera.mla_pitch_mm
    cell = p * p * (np.sqrt(3.0) / 2.0 if camera.mla_grid == "hex" else 1.0)
    r = np.nan_to_num(defocus_radius_mm(camera, points_mm), nan=0.0) + 0.5 * p
    return np.maximum(np.pi * r * r / cell, 1.0)


def _samples(grid: VolumeGrid, r: Rays, b: np.ndarray, nb: np.ndarray, *, max_samples: int):
    """Yield (flat vote-bin index, ray index) of ``r``'s samples through the box, in blocks of rays."""
    voxel = np.asarray(grid.voxel_mm)[::-1]
    # bin coordinates (z, y, x): voxel v spans [v, v + 1), bin j spans [j b, (j + 1) b) voxels
    o = ((r.origin - np.asarray(grid.origin_mm))[:, ::-1] / voxel + 0.5) / b
    d = r.direction[:, ::-1] / voxel / b
    hi = np.asarray(grid.shape) / b
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.where(d != 0, (0.0 - o) / d, -np.inf)
        t1 = np.where(d != 0, (hi - o) / d, np.inf)
    inside_par = np.all((d != 0) | ((o >= 0) & (o < hi)), axis=1)
    t_in = np.max(np.minimum(t0, t1), axis=1)
    t_out = np.min(np.maximum(t0, t1), axis=1)
    dt = 1.0 / np.max(np.abs(d), axis=1)  # a step moves at most one bin along every axis
    steps = np.where(inside_par & (t_out > t_in), np.ceil((t_out - t_in) / dt), 0).astype(np.int64)
    ends = np.cumsum(steps)
    start = 0
    while start < len(steps):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + max_samples, side="right"))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        ray = np.repeat(np.arange(start, stop), steps[sl])
        first = np.concatenate([[0], np.cumsum(steps[sl])[:-1]])
        k = np.arange(len(ray)) - np.repeat(first, steps[sl])
        t = t_in[ray] + (k + 0.5) * dt[ray]
        p = np.floor(o[ray] + t[:, None] * d[ray]).astype(np.int64)
        ok = np.all((p >= 0) & (p < nb), axis=1)
        p, ray = p[ok], ray[ok]
        yield np.ravel_multi_index((p[:, 0], p[:, 1], p[:, 2]), tuple(nb)), ray
        start = stop


def _resolution(cameras: Sequence, grid: VolumeGrid) -> np.ndarray:
    """(3,) voxels (z, y, x): the finest over the cameras of how far apart two particles must be along
    each grid axis to be told apart, a tube's width across a camera's rays, its depth of a lenslet (a
    pinhole camera: its object-side pixel times 20) along them."""
    from lfcore.rig import is_pinhole

    voxel = np.asarray(grid.voxel_mm)[::-1]
    best = np.full(3, np.inf)
    for cam in cameras:
        axis = np.abs(np.asarray(cam.rotation)[:, 2])[::-1]  # (z, y, x) components of the optical axis
        across = 2.0 * cam.object_pixel_mm if is_pinhole(cam) else cam.mla_pitch_mm / abs(cam.magnification)
        along = 20.0 * cam.object_pixel_mm if is_pinhole(cam) else cam.depth_per_lenslet_mm
        best = np.minimum(best, (axis * along + (1.0 - axis) * across) / voxel)
    return np.maximum(best, 1.0)


def _suppress(pos: np.ndarray, votes: np.ndarray, within: np.ndarray | float = 1.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Leave out a candidate within ``within`` voxels (per axis (z, y, x)) of a stronger one (``pos``
    strongest first)."""
    from scipy.spatial import cKDTree

    if len(pos) < 2:
        return pos, votes
    scaled = pos / np.asarray(within, dtype=np.float64)
    keep = np.ones(len(pos), bool)
    tree = cKDTree(scaled)
    for i in range(len(pos)):
        if not keep[i]:
            continue
        near = np.asarray(tree.query_ball_point(scaled[i], 1.0, p=np.inf), dtype=np.int64)
        keep[near[near > i]] = False
    return pos[keep], votes[keep]
