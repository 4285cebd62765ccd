"""A camera's per-pixel response, and its correction by dark and white images (flat field).

Physics. What a pixel records is ``dark + gain * light``: ``dark`` the offset the sensor gives
with no light at all (a mean level and a fixed pattern, the same in every frame), ``gain`` the
share of the light the optics let through to that pixel. In a light-field camera the gain holds
the main lens' fall-off toward the sensor's edges (vignetting), each micro-image's own fall-off
toward its rim (the lenslet's), and the shadows of dust on the microlens array or the sensor
window. A dark image (lens capped, laser off) measures ``dark``; a white image (a uniformly lit
diffuser) measures ``dark + gain * white light``. The white light a perfect camera of the same
optics records (``reference``: its micro-images as discs, :func:`lfcore.white.white_irradiance`)
divides out what the reconstruction's operator already models (which pixels a lenslet lights,
and how much of a rim pixel it covers), leaving the response alone.

:func:`sensor_response` renders a response (the ``[render]`` keys ``lens_falloff``,
``micro_vignetting``, ``dust_*`` and ``dark_fpn_counts``), :func:`flat_field` measures one from a
dark and a white image, and :func:`correct` takes it out of a raw frame, leaving NaN on the
pixels it cannot trust (between micro-images, under dense dust, dead), which the reconstruction
then leaves out of its operator (:func:`lfcore.reconstruct.preprocess`).

Pure computation: arrays and frozen configs in, arrays out. Images are indexed (row, column).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lfcore.rig import AnyCamera, RenderConfig, is_pinhole

__all__ = ["FlatField", "SensorResponse", "correct", "flat_field", "sensor_response"]


@dataclass(frozen=True)
class SensorResponse:
    """A camera's rendered response.

    Attributes
    ----------
    gain
        (rows, columns) float32: the share of the light reaching each pixel, 0..1.
    dark
        (rows, columns) float32: each pixel's offset without light, counts.
    """

    gain: np.ndarray
    dark: np.ndarray


def _camera_seed(render: RenderConfig, camera: AnyCamera) -> np.random.Generator:
    # each camera draws its own dust and fixed pattern, reproducibly, from its name
    return np.random.default_rng([render.response_seed, zlib.crc32(camera.name.encode())])


def lens_falloff(camera: AnyCamera, corner_loss: float) -> np.ndarray:
    """The main lens' fall-off over the sensor: cos^4 about the centre, ``1 - corner_loss`` at a corner.

    Parameters
    ----------
    camera
        The camera (sensor size and pixel pitch).
    corner_loss
        Fraction of the light lost at a sensor corner, 0 <= v < 1.

    Returns
    -------
    numpy.ndarray
        (rows, columns) float64 gain, 1 at the sensor centre.
    """
    nc, nr = camera.sensor_px
    if corner_loss <= 0:
        return np.ones((nr, nc))
    # cos^4(atan(r / L)) = 1 / (1 + (r / L)^2)^2, L chosen so that the corner gets 1 - v
    corner = 0.5 * math.hypot(nc, nr)
    length = corner / math.sqrt((1.0 - corner_loss) ** -0.5 - 1.0)
    y = (np.arange(nr) + 0.5 - 0.5 * nr)[:, None]
    x = (np.arange(nc) + 0.5 - 0.5 * nc)[None, :]
    return 1.0 / (1.0 + (x * x + y * y) / length**2) ** 2


def micro_vignetting(camera: AnyCamera, rim_loss: float) -> np.ndarray:
    """Each micro-image's fall-off: ``1 - rim_loss (r / R)^2`` at distance r from its centre, R its radius.

    Parameters
    ----------
    camera
        A light-field camera (its micro-image centres and radius, :mod:`lfcore.white`).
    rim_loss
        Fraction of the light lost at a micro-image's rim.

    Returns
    -------
    numpy.ndarray
        (rows, columns) float64 gain, 1 at every micro-image centre (and beyond a rim, 1 - rim_loss).
    """
    from scipy.spatial import cKDTree

    from lfcore.white import micro_image_centres

    nc, nr = camera.sensor_px
    if rim_loss <= 0 or is_pinhole(camera):
        return np.ones((nr, nc))
    radius = camera.mla_focal_length_mm * 0.5 * camera.aperture_mm / camera.image_distance_mm / camera.pixel_mm
    centres = micro_image_centres(camera)
    tree = cKDTree(centres)
    out = np.empty((nr, nc))
    cols = np.arange(nc) + 0.5
    step = max(1, 2_000_000 // nc)
    for r0 in range(0, nr, step):  # a few million pixels at a time
        rows = np.arange(r0, min(r0 + step, nr)) + 0.5
        pts = np.stack(np.broadcast_arrays(cols[None, :], rows[:, None]), axis=-1).reshape(-1, 2)
        d, _ = tree.query(pts)
        out[r0:r0 + len(rows)] = (1.0 - rim_loss * np.minimum(d / radius, 1.0) ** 2).reshape(len(rows), nc)
    return out


def sensor_response(camera: AnyCamera, render: RenderConfig) -> SensorResponse:
    """The response ``render`` gives ``camera``: lens fall-off, micro-image vignetting, dust, dark offset.

    Parameters
    ----------
    camera
        The camera. A pinhole camera has no micro-images: it takes the rest.
    render
        ``lens_falloff``, ``micro_vignetting``, ``dust_spots``, ``dust_opacity``,
        ``dust_radius_px``, ``background_counts``, ``dark_fpn_counts`` and ``response_seed``.

    Returns
    -------
    SensorResponse
        (rows, columns) gain and dark offset; with every response key off, a gain of 1 and the
        uniform ``background_counts``.
    """
    nc, nr = camera.sensor_px
    rng = _camera_seed(render, camera)
    gain = lens_falloff(camera, render.lens_falloff) * micro_vignetting(camera, render.micro_vignetting)
    if render.dust_spots:
        # a dust grain's shadow: a soft disc, darkest at its centre; places away from the border
        at = rng.uniform(0.1, 0.9, size=(render.dust_spots, 2)) * np.array([nc, nr])
        y = np.arange(nr)[:, None] + 0.5
        x = np.arange(nc)[None, :] + 0.5
        for cx, cy in at:
            r0, r1 = max(0, int(cy - 4 * render.dust_radius_px)), min(nr, int(cy + 4 * render.dust_radius_px) + 1)
            c0, c1 = max(0, int(cx - 4 * render.dust_radius_px)), min(nc, int(cx + 4 * render.dust_radius_px) + 1)
            d2 = ((x[:, c0:c1] - cx) ** 2 + (y[r0:r1] - cy) ** 2) / render.dust_radius_px**2
            gain[r0:r1, c0:c1] *= 1.0 - render.dust_opacity * np.exp(-d2)
    dark = np.full((nr, nc), render.background_counts)
    if render.dark_fpn_counts > 0:
        dark += rng.normal(0.0, render.dark_fpn_counts, size=(nr, nc))
        np.maximum(dark, 0.0, out=dark)
    return SensorResponse(gain.astype(np.float32), dark.astype(np.float32))


@dataclass(frozen=True)
class FlatField:
    """A camera's measured response, what :func:`correct` divides out.

    Attributes
    ----------
    dark
        (rows, columns) float32 dark offset, counts.
    gain
        (rows, columns) float32 relative gain (about 1 where the camera is at its best; 1 on
        masked pixels).
    mask
        (rows, columns) bool: pixels to leave out (unlit between micro-images, under dense dust,
        dead).
    """

    dark: np.ndarray
    gain: np.ndarray
    mask: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the images it corrects."""
        return tuple(self.gain.shape)  # type: ignore[return-value]

    @property
    def masked_fraction(self) -> float:
        """Share of the pixels left out."""
        return float(np.mean(self.mask))


def flat_field(dark: np.ndarray | float, white: np.ndarray, *, reference: np.ndarray | None = None,
               min_gain: float = 0.25, min_reference: float = 0.2, smooth_px: float = 0.0) -> FlatField:
    """The per-pixel gain and the unusable pixels of a camera, from its dark and white images.

    Parameters
    ----------
    dark
        (rows, columns) dark image (lens capped), or one level for every pixel, counts.
    white
        (rows, columns) white image (uniform light), counts, on the same offset as ``dark``.
    reference
        (rows, columns) white light of a perfect camera of the same optics (any scale): the
        micro-image discs the operator models (:func:`lfcore.white.white_irradiance`). Where it is
        below ``min_reference`` of its maximum (between micro-images, rims barely lit) pixels are
        masked. None: every pixel should see the same light (a classic flat field).
    min_gain
        Pixels whose gain is below this share of the best are masked (dense dust, dead pixels):
        correcting them would multiply their noise.
    min_reference
        See ``reference``.
    smooth_px
        Gaussian sigma, pixels, of a weighted local fit of the gain (ratio of the white's light
        to the reference, weighted by the reference), which tolerates a reference a fraction of a
        pixel off the real micro-images at the price of blurring the micro-images' own fall-off;
        0 (default): pixel by pixel, exact where the reference is.

    Returns
    -------
    FlatField
        Gain normalised to 1 at its 99th percentile over the usable pixels.

    Raises
    ------
    ValueError
        Images of different sizes, or a white image that is nowhere brighter than the dark.
    """
    w = np.asarray(white, dtype=np.float64)
    d = np.broadcast_to(np.asarray(dark, dtype=np.float64), w.shape) if np.ndim(dark) == 0 else \
        np.asarray(dark, dtype=np.float64)
    if w.ndim != 2 or d.shape != w.shape:
        raise ValueError(f"the dark image is {d.shape[0]} x {d.shape[1]} px but the white {w.shape[0]} x "
                         f"{w.shape[1]}; give images of the same camera")
    light = w - d
    if reference is None:
        ref = np.ones_like(w)
    else:
        ref = np.asarray(reference, dtype=np.float64)
        if ref.shape != w.shape:
            raise ValueError(f"the reference is {ref.shape} but the white image {w.shape}")
    top = float(ref.max()) if ref.size else 0.0
    if not top > 0 or not np.any(light > 0):
        raise ValueError("the white image is nowhere brighter than the dark image; give a white image taken with "
                         "light and a dark image taken without")
    ref = ref / top
    seen = ref >= min_reference
    if smooth_px > 0:
        # the least-squares gain of a Gaussian window: sum(ref * light) / sum(ref^2)
        wt = np.where(seen, ref, 0.0)
        num = ndimage.gaussian_filter(wt * light, smooth_px, mode="nearest")
        den = ndimage.gaussian_filter(wt * ref, smooth_px, mode="nearest")
        gain = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    else:
        gain = np.where(seen, light / np.where(seen, ref, 1.0), 0.0)
    best = np.percentile(gain[seen], 99.0) if np.any(seen) else 0.0
    if not best > 0:
        raise ValueError("the white image shows no light where its micro-images should be; give a white image of "
                         "this camera")
    gain = gain / best
    # a pixel under dense dust or dead keeps its noise but loses its light: leave it out
    raw_gain = np.where(seen, light / np.where(seen, ref, 1.0), 0.0) / best
    mask = ~seen | (gain < min_gain) | (raw_gain < min_gain)
    gain = np.where(mask, 1.0, gain)
    return FlatField(d.astype(np.float32), gain.astype(np.float32), mask)


def correct(raw: np.ndarray, flat: FlatField) -> np.ndarray:
    """A raw frame with the dark taken off and the gain divided out.

    Parameters
    ----------
    raw
        (rows, columns) raw counts.
    flat
        The camera's :class:`FlatField`.

    Returns
    -------
    numpy.ndarray
        (rows, columns) float32 light, counts above the dark as a pixel of gain 1 would record
        them; NaN on the masked pixels.

    Raises
    ------
    ValueError
        A frame of another size than the flat field's.
    """
    img = np.asarray(raw)
    if img.shape != flat.shape:
        raise ValueError(f"the frame is {img.shape[0]} x {img.shape[1]} px but the flat field {flat.shape[0]} x "
                         f"{flat.shape[1]}; use the calibration of this camera")
    out = (img.astype(np.float32) - flat.dark) / flat.gain
    out[flat.mask] = np.nan
    return out
