"""The checks a lab makes on a camera's raw image before it records: seeding density, saturation,
micro-image fill, the histogram and a look through the camera.

Seeding density of a light-field camera (particles per microlens, PPM). Each point of the
main lens' pupil sends a particle's light through exactly one lenslet, so in every perspective
view (:mod:`lfcore.views`, the samples of one pupil point) a particle lights one sample, whatever
its depth: a view is a picture of the seeding at one sample per lenslet. Particles seeded at
random therefore leave a share exp(-PPM v a) of a view's samples dark, with v the share of the
volume the camera sees and a the samples a particle lights per view (slightly above one: a
sample is a pixel wide, see :func:`view_samples_per_particle`), so PPM = -ln(dark) / (v a),
averaged over the central views. The dark samples are counted against the image's own noise
(the background and its spread, from the dark gaps between the micro-images). Particles far
from the focal plane spread their light over many micro-images and may fall under the noise:
with the volume +-7 lenslets of blur deep, the estimate is a fifth to a third low; within
+-4 lenslets it is within a fifth from 0.1 to 0.5 PPM, and a tenth to a fifth low at 1 PPM, where
most samples are lit.

Pinhole cameras count particle images (local maxima above the noise) per pixel; images that
merge are counted once, so the count falls short above about 0.02 PPP (by a fifth at 0.02, by
half at 0.05 on the 4-camera example).

The chapter recommends 0.5 PPM (it finds that density the best balance of reconstruction quality
and window size, and about 1 PPM the upper limit of light-field reconstruction) and images with
no saturated pixel.

Pure computation: arrays and frozen configs in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from lfcore.chief_ray import chief_ray_mla, defocus_radius_mm
from lfcore.rig import AnyCamera, Camera, VolumeConfig, is_pinhole
from lfcore.views import Lattice, Views, refocus, sample_views

__all__ = ["MAX_PPM", "MIN_PPM", "PPP_RANGE", "RECOMMENDED_PPM", "CameraCheck", "background_noise",
           "check_image", "view_samples_per_particle", "visible_share", "micro_image_fill", "particle_density_ppm",
           "particle_density_ppp"]

#: The chapter's recommended seeding of a light-field camera, particles per microlens.
RECOMMENDED_PPM = 0.5
#: The range marked as fine around it: the chapter's studies run 0.1 to 1 PPM, 1 PPM "typically
#: the upper particle density limit" of light-field reconstruction.
MIN_PPM, MAX_PPM = 0.1, 1.0
#: Particles per pixel of a Tomo-PIV camera marked as fine (0.05 the chapter's Tomo-PIV images).
PPP_RANGE = (0.02, 0.1)
#: Threshold of a lit lenslet or particle image above the background, in noise sigmas.
SIGMAS = 3.0


@dataclass(frozen=True)
class CameraCheck:
    """One camera's raw image, checked.

    Attributes
    ----------
    camera
        Its name.
    ppm
        Estimated particles per microlens (light-field cameras), else None.
    ppp
        Estimated particles per pixel (pinhole cameras), else None.
    saturated_fraction
        Share of the pixels at full scale.
    fill
        Micro-image diameter over the lattice pitch (light-field cameras; about 1 with matched
        f-numbers), else None.
    lit_lenslets
        Share of the lenslets with particle light (light-field cameras), else None.
    background, noise
        Background level and its noise sigma, counts.
    full_scale
        Counts at which a pixel saturates.
    histogram, bin_edges
        The raw image's histogram (counts per bin) and its bin edges (counts).
    preview
        A look through the camera: the refocused plane at the volume's centre (light-field) or
        the raw image (pinhole), 2-D float32.
    preview_label
        What ``preview`` is.
    """

    camera: str
    ppm: float | None
    ppp: float | None
    saturated_fraction: float
    fill: float | None
    lit_lenslets: float | None
    background: float
    noise: float
    full_scale: float
    histogram: np.ndarray = field(repr=False)
    bin_edges: np.ndarray = field(repr=False)
    preview: np.ndarray = field(repr=False)
    preview_label: str = ""

    def verdicts(self) -> list[tuple[str, bool]]:
        """Each figure with the chapter's range, one line each, and whether it lies in the range."""
        out: list[tuple[str, bool]] = []
        if self.ppm is not None:
            ok = MIN_PPM <= self.ppm <= MAX_PPM
            out.append((f"seeding {self.ppm:.2f} PPM (recommended {RECOMMENDED_PPM}, fine {MIN_PPM}-{MAX_PPM})"
                        + ("" if ok else ": " + ("seed more" if self.ppm < MIN_PPM else "seed less")), ok))
        if self.ppp is not None:
            ok = PPP_RANGE[0] <= self.ppp <= PPP_RANGE[1]
            out.append((f"seeding {self.ppp:.3f} PPP (fine {PPP_RANGE[0]}-{PPP_RANGE[1]})"
                        + ("" if ok else ": " + ("seed more" if self.ppp < PPP_RANGE[0] else "seed less")), ok))
        sat = self.saturated_fraction
        out.append((f"saturated {100 * sat:.3f}% of pixels (recommended none)"
                    + ("" if sat == 0 else ": lower the laser power, the exposure or the lens aperture"), sat == 0))
        if self.fill is not None:
            ok = 0.85 <= self.fill <= 1.1
            out.append((f"micro-image fill {self.fill:.2f} of the pitch (matched f-numbers fill about 1)"
                        + ("" if ok else ": " + ("open the main lens' aperture" if self.fill < 0.85
                                                 else "close the main lens' aperture (micro-images overlap)")), ok))
        return out


def background_noise(image: np.ndarray) -> tuple[float, float]:
    """Background level and noise sigma of a raw image from its darkest pixels.

    The 1st and 5th percentiles of a Gaussian background lie 2.326 and 1.645 sigma below its
    mean; a raw light-field image always has dark pixels (the gaps between micro-images), and a
    particle image mostly dark ones, so at least 5% of its pixels are background.

    Returns
    -------
    tuple
        (background, sigma), counts; sigma at least 0.5 (the quantisation of whole counts).
    """
    p1, p5 = np.percentile(np.asarray(image, dtype=np.float64), [1.0, 5.0])
    sigma = max((p5 - p1) / (2.326 - 1.645), 0.5)
    return float(p5 + 1.645 * sigma), float(sigma)


def _volume_points(volume: VolumeConfig, samples: int) -> np.ndarray:
    lo, hi = volume.bounds_mm
    axes = [np.linspace(a, b, samples) for a, b in zip(lo, hi, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _seen(camera: AnyCamera, pts: np.ndarray) -> np.ndarray:
    if is_pinhole(camera):
        from lfcore.pinhole import project as pinhole_project

        cr = pinhole_project(camera, pts)
        cols, rows = camera.sensor_px
        return (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
    q = chief_ray_mla(camera, pts)  # sensor-plane position of each point's image, mm
    w, h = camera.sensor_size_mm
    return (np.abs(q[:, 0]) < 0.5 * w) & (np.abs(q[:, 1]) < 0.5 * h)


def visible_share(camera: AnyCamera, volume: VolumeConfig, *, samples: int = 21) -> float:
    """Share of a uniformly seeded volume whose particles the camera images on its sensor.

    Parameters
    ----------
    camera
        The camera.
    volume
        The seeded volume.
    samples
        Points per axis of the grid the share is taken over.
    """
    return float(np.mean(_seen(camera, _volume_points(volume, samples))))


def view_samples_per_particle(camera: Camera, volume: VolumeConfig, *, samples: int = 21) -> float:
    """Mean number of samples a particle lights in one perspective view, over a volume seeded uniformly.

    Ideally one: each point of the pupil sends a particle's light through one lenslet only. But
    a sample is a pixel (with its bilinear neighbours), about two pixels wide across the pupil's
    image, so the pupil pixels that straddle a lenslet's edge light a view sample in both
    lenslets. The edges cross the particle's blur disc (radius r on the MLA) with length
    pi r^2 P / (2 A) for cells of perimeter P and area A, which the micro-image (pupil radius R
    pixels) shows r / R_mla times smaller: the extra share is r P w / (2 A R) with w = 2 pixels.
    """
    pts = _volume_points(volume, samples)
    pts = pts[_seen(camera, pts)]
    if not len(pts):
        return 1.0
    r = defocus_radius_mm(camera, pts)
    p = camera.mla_pitch_mm
    area, perimeter = ((math.sqrt(3) / 2 * p * p, 2 * math.sqrt(3) * p) if camera.mla_grid == "hex"
                       else (p * p, 4 * p))
    pupil_px = camera.mla_focal_length_mm * 0.5 * camera.aperture_mm / camera.image_distance_mm / camera.pixel_mm
    return float(1.0 + np.mean(r) * perimeter * 2.0 / (2.0 * area * pupil_px))


def _dark_share(image: np.ndarray, lattice: Lattice, background: float, noise: float) -> tuple[float, float]:
    """Share of the view samples without particle light, and share of the lenslets with some."""
    v = sample_views(image, lattice, radius_px=0.35 * lattice.pitch_px)  # the views well inside the disc
    signal = v.images[:, v.inside] - background  # (views, lenslets)
    lit = signal > SIGMAS * noise
    return float(1.0 - lit.mean()), float(lit.any(axis=0).mean())


def particle_density_ppm(image: np.ndarray, camera: Camera, lattice: Lattice, volume: VolumeConfig, *,
                         background: float | None = None, noise: float | None = None) -> tuple[float, float]:
    """Particles per microlens from a raw light-field image (module docstring).

    Parameters
    ----------
    image
        (rows, columns) raw image, counts.
    camera
        The camera (which part of the volume it sees).
    lattice
        Its micro-image lattice.
    volume
        The seeded volume.
    background, noise
        The image's background and noise sigma (default: :func:`background_noise`).

    Returns
    -------
    tuple
        (PPM, share of lenslets with particle light); PPM is inf when every view sample is lit
        (too dense to count).
    """
    b, s = background_noise(image) if background is None or noise is None else (background, noise)
    dark, lit = _dark_share(image, lattice, b, s)
    seen = visible_share(camera, volume)
    if seen == 0:
        return 0.0, lit
    per = view_samples_per_particle(camera, volume)
    ppm = math.inf if dark <= 0 else -math.log(dark) / (seen * per)
    return float(ppm), lit


def particle_density_ppp(image: np.ndarray, *, background: float | None = None,
                         noise: float | None = None) -> float:
    """Particles per pixel of a pinhole camera's image: local maxima (3 x 3) above the noise per pixel."""
    img = np.asarray(image, dtype=np.float32)
    b, s = background_noise(img) if background is None or noise is None else (background, noise)
    peaks = (img == ndimage.maximum_filter(img, size=3)) & (img > b + SIGMAS * s)
    return float(peaks.sum() / img.size)


def micro_image_fill(views: Views) -> float:
    """Micro-image diameter over the pitch, from the mean brightness of every view.

    The mean of each view over the lenslets is the aperture's image as every micro-image shows it;
    the offsets brighter than half its brightest form the disc, whose area gives its diameter.
    ``views`` should reach past the micro-image's rim (sample with ``radius_px`` about 0.6 pitch).
    """
    mean = views.images[:, views.inside].mean(axis=1)
    if mean.max() <= 0:
        return 0.0
    b = views.lattice.basis_px
    # keep the offsets inside the lattice's own cell (nearer this centre than any neighbour's)
    nbrs = np.array([i * b[0] + j * b[1] for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)])
    d = views.offsets_px.astype(np.float64)
    own = np.all(np.sum(d * d, axis=1)[:, None] <= np.sum((d[:, None, :] - nbrs[None]) ** 2, axis=2), axis=1)
    lit = (mean > 0.5 * mean[own].max()) & own
    return float(2.0 * math.sqrt(lit.sum() / math.pi) / views.lattice.pitch_px)


def check_image(image: np.ndarray, camera: AnyCamera, *, full_scale: float, volume: VolumeConfig,
                lattice: Lattice | None = None, bins: int = 64) -> CameraCheck:
    """Every check of one camera's raw image.

    Parameters
    ----------
    image
        (rows, columns) raw image, counts.
    camera
        The camera (light-field or pinhole).
    full_scale
        Counts at which its pixels saturate.
    volume
        The rig's volume (the seeding's depth, the refocused plane at its centre).
    lattice
        The micro-image lattice of a light-field camera (calibrated, else its nominal one).
    bins
        Histogram bins from 0 to ``full_scale``.

    Returns
    -------
    CameraCheck
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"a raw image is a 2-D array, got shape {img.shape}")
    background, noise = background_noise(img)
    hist, edges = np.histogram(img, bins=bins, range=(0.0, float(full_scale) + 1.0))
    saturated = float(np.mean(img >= full_scale))
    if is_pinhole(camera):
        return CameraCheck(camera=camera.name, ppm=None, ppp=particle_density_ppp(img, background=background,
                                                                                  noise=noise),
                           saturated_fraction=saturated, fill=None, lit_lenslets=None, background=background,
                           noise=noise, full_scale=float(full_scale), histogram=hist, bin_edges=edges,
                           preview=img.astype(np.float32), preview_label="raw image")
    if lattice is None:
        from lfcore.views import nominal_lattice

        lattice = nominal_lattice(camera)
    ppm, lit = particle_density_ppm(img, camera, lattice, volume, background=background, noise=noise)
    wide = sample_views(img, lattice, radius_px=0.6 * lattice.pitch_px)
    fill = micro_image_fill(wide)
    views = sample_views(img.astype(np.float32) - background, lattice)
    z = float(np.mean(volume.bounds_mm, axis=0)[2])
    try:
        plane = views.picture(refocus(views, camera, z))
        label = f"refocused at z = {z:g} mm"
    except ValueError:  # a camera looking across the rig's z: its central view
        plane = views.picture(views.centre)
        label = "central view"
    return CameraCheck(camera=camera.name, ppm=ppm, ppp=None, saturated_fraction=saturated, fill=fill,
                       lit_lenslets=lit, background=background, noise=noise, full_scale=float(full_scale),
                       histogram=hist, bin_edges=edges, preview=plane, preview_label=label)
