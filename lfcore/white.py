"""The white image of a plenoptic camera: what the sensor records under uniform illumination.

Physics. A uniformly lit diffuser in front of the main lens fills its exit pupil with light
from every direction, so each lenslet forms an image of the pupil on the sensor: a disc (the
micro-image). The chief ray from the pupil centre through a lenslet centre ``c`` (sensor-plane
coordinates, mm, see :mod:`lfcore.mla`) has slope ``c / si`` and meets the sensor ``f_ml``
behind the MLA, at ``c (1 + f_ml / si)``: micro-image centres form the lenslet lattice scaled
outward about the optical axis, NOT the lenslet centres themselves. The disc radius is the
pupil radius seen through the lenslet, ``f_ml (D / 2) / si`` (half a pitch for matched
f-numbers). The lenslet cell smears the disc by a further ``f_ml / si`` of the cell, far below a
pixel, and is ignored. Off axis the irradiance falls off as cos^4 of the chief-ray angle
(natural vignetting); :class:`WhiteImageConfig.vignetting` replaces that with a stronger falloff
of the same shape, as real lenses show.

Pure computation: arrays and frozen configs in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lfcore.chief_ray import diffraction_sigma_mm
from lfcore.mla import lenslet_centers, sensor_to_pixel
from lfcore.rig import Camera, RenderConfig, require_lightfield

__all__ = ["WhiteImageConfig", "micro_image_centres", "micro_image_scale", "white_image", "white_irradiance"]


@dataclass(frozen=True)
class WhiteImageConfig:
    """How bright and how imperfect a white image is.

    Parameters
    ----------
    level_counts
        Signal at the centre of an on-axis micro-image, counts (background excluded).
    vignetting
        Fractional darkening at the sensor corner, 0 <= v < 1, following a cos^4 profile; 0
        (default) keeps only the natural cos^4 of the chief-ray angle, which is tiny.
    dead_lenslets
        Number of lenslets that give no light (dust, defects), drawn with ``seed``.
    dead_at_edge
        Draw the dead lenslets among those whose micro-image centre is half a pitch to two
        pitches from the sensor border (True), or among all (False).
    seed
        Seed of the dead-lenslet draw and of the noise.
    supersample
        Sub-samples per pixel and axis when integrating the discs over the pixel area.
    """

    level_counts: float = 20000.0
    vignetting: float = 0.0
    dead_lenslets: int = 0
    dead_at_edge: bool = True
    seed: int = 0
    supersample: int = 4

    def __post_init__(self) -> None:
        if not (self.level_counts > 0 and math.isfinite(self.level_counts)):
            raise ValueError(f"level_counts must be positive, got {self.level_counts}")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if self.dead_lenslets < 0 or self.supersample < 1:
            raise ValueError("dead_lenslets must be >= 0 and supersample >= 1")


def micro_image_scale(camera: Camera) -> float:
    """k = 1 + f_ml / si: micro-image centres are the lenslet centres scaled by k about the axis."""
    return 1.0 + camera.mla_focal_length_mm / camera.image_distance_mm


def micro_image_centres(camera: Camera) -> np.ndarray:
    """Micro-image centres of every lenslet whose centre lies on the sensor.

    Returns
    -------
    numpy.ndarray
        (n, 2) float64 continuous pixel coordinates (column, row), in the order of
        :func:`lfcore.mla.lenslet_centers`.
    """
    return sensor_to_pixel(camera, lenslet_centers(camera) * micro_image_scale(camera))


def _falloff(camera: Camera, config: WhiteImageConfig, r_mm: np.ndarray) -> np.ndarray:
    # cos^4(atan(r / L)) = 1 / (1 + (r / L)^2)^2; natural vignetting has L = si (chief-ray angle
    # at the MLA); a given corner darkening v fixes L so that the corner gets 1 - v.
    if config.vignetting > 0:
        corner = 0.5 * math.hypot(*camera.sensor_size_mm)
        length = corner / math.sqrt((1.0 - config.vignetting) ** -0.5 - 1.0)
    else:
        length = camera.image_distance_mm
    return 1.0 / (1.0 + (r_mm / length) ** 2) ** 2


def _dead_keys(camera: Camera, config: WhiteImageConfig) -> np.ndarray:
    if config.dead_lenslets == 0:
        return np.zeros(0, dtype=np.int64)
    centres = lenslet_centers(camera)
    if config.dead_at_edge:
        cr = micro_image_centres(camera)
        nc, nr = camera.sensor_px
        edge = np.minimum.reduce([cr[:, 0], nc - cr[:, 0], cr[:, 1], nr - cr[:, 1]])
        ppl = camera.pixels_per_lenslet
        centres = centres[(edge > 0.5 * ppl) & (edge < 2.0 * ppl)]
    rng = np.random.default_rng([config.seed, 0xDEAD])
    pick = rng.choice(len(centres), size=min(config.dead_lenslets, len(centres)), replace=False)
    return _keys(camera, centres[pick])


def _keys(camera: Camera, centres_mm: np.ndarray) -> np.ndarray:
    # A lenslet's identity: its centre rounded to a hundredth of a pitch, packed in one integer.
    q = np.rint(np.asarray(centres_mm) / (0.01 * camera.mla_pitch_mm)).astype(np.int64)
    return q[..., 0] * (1 << 32) + q[..., 1]


def white_irradiance(camera: Camera, *, config: WhiteImageConfig = WhiteImageConfig(),
                     blur_sigma_px: float = 0.0) -> np.ndarray:
    """Noise-free white image: every micro-image a pupil disc, integrated over each pixel.

    Each lenslet's disc is splatted onto the pixels of its own bounding box (coverage
    integrated on ``config.supersample`` squared sub-samples per pixel, with an
    anti-aliasing ramp one sub-sample wide at the rim), weighted by the lenslet's falloff, and
    the discs are summed, so overlapping discs of an over-filled MLA add up.

    Parameters
    ----------
    camera
        The camera (MLA lattice, rotation and offset, main-lens and lenslet optics).
    config
        Brightness, vignetting, dead lenslets, supersampling.
    blur_sigma_px
        Gaussian blur (diffraction) applied after pixel integration, pixels.

    Returns
    -------
    numpy.ndarray
        (rows, columns) float64 counts, no background or noise.
    """
    require_lightfield(camera, "a white image")
    k = micro_image_scale(camera)
    ss = config.supersample
    r_px = camera.mla_focal_length_mm * 0.5 * camera.aperture_mm / camera.image_distance_mm / camera.pixel_mm
    h_px = 1.0 / ss  # width of the anti-aliasing ramp at the disc rim, pixels
    reach = r_px + 0.5 * h_px  # coverage is zero beyond this distance from a disc centre
    nc, nr = camera.sensor_px
    # Lenslets whose disc (centre k c on the sensor) can reach a pixel: c within reach of the
    # sensor suffices, since k >= 1.
    lenslets = lenslet_centers(camera, margin_mm=reach * camera.pixel_mm)
    weight = _falloff(camera, config, np.hypot(lenslets[:, 0], lenslets[:, 1]))
    dead = _dead_keys(camera, config)
    if len(dead):
        weight[np.isin(_keys(camera, lenslets), dead)] = 0.0
    centres = sensor_to_pixel(camera, k * lenslets)
    lit = (weight > 0) & np.all(centres > -reach, axis=1) & (centres[:, 0] < nc + reach) & (centres[:, 1] < nr + reach)
    centres, weight = centres[lit], weight[lit]

    box = int(math.ceil(2.0 * reach)) + 2  # pixels per side of every disc's bounding box
    sub = (np.arange(box * ss) + 0.5) / ss  # sub-sample positions within the box, pixels
    out = np.zeros(nr * nc)
    chunk = max(1, 4_000_000 // (box * ss) ** 2)
    for i in range(0, len(centres), chunk):
        c, w = centres[i:i + chunk], weight[i:i + chunk]
        origin = np.floor(c - reach).astype(np.int64)  # (column, row) of each box's first pixel
        dx2 = (origin[:, 0, None] + sub[None, :] - c[:, 0, None]) ** 2  # (n, box * ss)
        dy2 = (origin[:, 1, None] + sub[None, :] - c[:, 1, None]) ** 2
        d = np.sqrt(dy2[:, :, None] + dx2[:, None, :])  # (n, rows, columns) of sub-samples
        cover = np.clip((r_px - d) / h_px + 0.5, 0.0, 1.0)
        px = cover.reshape(len(c), box, ss, box, ss).mean(axis=(2, 4)) * w[:, None, None]
        rows = origin[:, 1, None] + np.arange(box)[None, :]  # (n, box)
        cols = origin[:, 0, None] + np.arange(box)[None, :]
        ok = ((rows >= 0) & (rows < nr))[:, :, None] & ((cols >= 0) & (cols < nc))[:, None, :]
        flat = (rows[:, :, None] * nc + cols[:, None, :])[ok]
        lo = int(flat.min()) if flat.size else 0
        out[lo:lo + (int(flat.max()) - lo + 1 if flat.size else 0)] += np.bincount(flat - lo, weights=px[ok])
    out = out.reshape(nr, nc) * config.level_counts
    if blur_sigma_px > 0:
        out = ndimage.gaussian_filter(out, blur_sigma_px, mode="nearest")
    return out


def white_image(camera: Camera, *, render: RenderConfig | None = None,
                config: WhiteImageConfig = WhiteImageConfig(), wavelength_nm: float = 532.0) -> np.ndarray:
    """A raw white image as the camera delivers it.

    The noise-free :func:`white_irradiance` (with the lenslet's diffraction blur,
    sigma = 0.42 lambda N_ml, when ``render.diffraction``) through ``render``'s camera response
    where it has one (:func:`lfcore.flatfield.sensor_response`), plus its background, shot
    noise (Poisson in electrons) and read noise, rounded and saturated at the bit depth.

    Parameters
    ----------
    camera
        The camera.
    render
        Background, noise, bit depth and diffraction (default: :class:`RenderConfig` defaults).
    config
        Brightness, vignetting, dead lenslets and the noise seed.
    wavelength_nm
        Wavelength of the diffraction blur.

    Returns
    -------
    numpy.ndarray
        (rows, columns) uint16 counts.
    """
    require_lightfield(camera, "a white image")
    render = RenderConfig() if render is None else render
    lam = wavelength_nm if render.diffraction else 0.0  # no diffraction: no blur
    sigma = diffraction_sigma_mm(lam, camera.lenslet_f_number) / camera.pixel_mm
    mean = white_irradiance(camera, config=config, blur_sigma_px=sigma)
    if render.has_response:  # the camera's response, as its particle images have it
        from lfcore.flatfield import sensor_response

        resp = sensor_response(camera, render)
        mean = mean * resp.gain + resp.dark
    else:
        mean = mean + render.background_counts
    rng = np.random.default_rng([config.seed, 0x3417E])
    v = rng.poisson(mean * render.gain_e_per_count) / render.gain_e_per_count if render.shot_noise else mean
    if render.read_noise_counts > 0:
        v = v + rng.normal(0.0, render.read_noise_counts, v.shape)
    return np.clip(np.rint(v), 0, 2**render.bit_depth - 1).astype(np.uint16)
