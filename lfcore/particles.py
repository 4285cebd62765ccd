"""Seeding particles and lighting them with the laser sheet."""

from __future__ import annotations

import numpy as np

from lfcore._deprecation import keyword_options
from lfcore.mla import lenslet_count
from lfcore.rig import LaserConfig, Rig, VolumeConfig

__all__ = ["DEFAULT_PPM", "DEFAULT_PPP", "MAX_PPM", "MAX_PPP", "particle_count", "seeding_density", "seed_particles",
           "sheet_weights"]

#: Densest seeding accepted, particles per microlens. About 1 PPM is the usual limit of a
#: light-field reconstruction (the chapter tests up to 2); far beyond, the images are saturated
#: and a synthetic run of a large sensor would take more memory than a workstation has.
MAX_PPM = 10.0

#: Densest seeding accepted, particles per pixel of a pinhole (Tomo-PIV) camera: Tomo-PIV
#: reconstructs up to about 0.1 ppp (the chapter's 0.05 and 0.1); at 1 ppp the particle images
#: of about 3 px cover every pixel several times over.
MAX_PPP = 1.0

#: The seeding of a rig when none is given: 0.5 PPM where a light-field camera sets the scale
#: (the chapter's optimum), else 0.05 ppp (the usual Tomo-PIV density).
DEFAULT_PPM = 0.5
DEFAULT_PPP = 0.05


@keyword_options("ppm", "ppp", since="0.1.0")
def seeding_density(rig: Rig, *, ppm: float | None = None,
                    ppp: float | None = None) -> tuple[float | None, float | None]:
    """The seeding density of ``rig`` as (ppm, ppp), one of them None.

    ``ppm`` (particles per microlens) counts the lenslets of the first light-field camera,
    ``ppp`` (particles per pixel) the pixels of the first pinhole camera. With neither given:
    :data:`DEFAULT_PPM` if the rig has a light-field camera, else :data:`DEFAULT_PPP`.

    Raises
    ------
    ValueError
        Both given, a density that is not positive or beyond :data:`MAX_PPM` / :data:`MAX_PPP`,
        or a density of a kind of camera the rig lacks.
    """
    if ppm is not None and ppp is not None:
        raise ValueError("give the seeding in particles per microlens (ppm) or per pixel (ppp), not both")
    if ppm is None and ppp is None:
        return (DEFAULT_PPM, None) if rig.lightfield_cameras else (None, DEFAULT_PPP)
    if ppm is not None:
        _check_density(ppm, "ppm", MAX_PPM, "particles per microlens (about 1 is the usual limit of a light-field "
                       "reconstruction)", rig.lightfield_cameras, "the rig has only pinhole cameras, which have no "
                       "microlenses; give the seeding in particles per pixel (ppp) instead of ppm")
        return float(ppm), None
    _check_density(ppp, "ppp", MAX_PPP, "particles per pixel (Tomo-PIV reconstructs up to about 0.1)",
                   rig.pinhole_cameras, "the rig has no pinhole camera; give the seeding in particles per microlens "
                   "(ppm) instead of ppp")
    return None, float(ppp)


def _check_density(value: float, name: str, most: float, unit: str, cameras: tuple, none_of_them: str) -> None:
    """A density that is not positive, beyond ``most`` or of a kind of camera the rig lacks: ValueError."""
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value}")
    if value > most:
        raise ValueError(f"{name} {value:g} is beyond {most:g} {unit}; give a lower density")
    if not cameras:
        raise ValueError(none_of_them)


@keyword_options("ppm", since="0.1.0")
def particle_count(rig: Rig, *, ppm: float | None = None, ppp: float | None = None) -> int:
    """Particles for a seeding density: ``ppm`` particles per microlens of the first light-field
    camera, or ``ppp`` particles per pixel of the first pinhole camera (see
    :func:`seeding_density`, which also says which applies when neither is given)."""
    ppm, ppp = seeding_density(rig, ppm=ppm, ppp=ppp)
    if ppm is not None:
        return max(1, round(ppm * lenslet_count(rig.lightfield_cameras[0])))
    cols, rows = rig.pinhole_cameras[0].sensor_px
    return max(1, round(ppp * cols * rows))


def seed_particles(volume: VolumeConfig, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` particles uniformly at random in the volume box.

    Returns
    -------
    numpy.ndarray
        (n, 3) world positions in mm, (x, y, z).
    """
    lo, hi = volume.bounds_mm
    return rng.uniform(lo, hi, size=(n, 3))


def sheet_weights(points_mm: np.ndarray, laser: LaserConfig, volume: VolumeConfig) -> np.ndarray:
    """Relative illumination (0..1) of particles by the laser sheet.

    The sheet is centred on the volume centre, normal to ``laser.sheet_axis``. A Gaussian
    profile has ``sheet_thickness_mm`` as its full width at 1/e^2 of the peak intensity,
    I = exp(-8 d^2 / t^2) at a distance d from the sheet's centre plane; a top-hat profile is
    1 within half the thickness and 0 outside; ``uniform`` lights everything equally.

    Returns
    -------
    numpy.ndarray
        (n,) float64 weights.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if laser.sheet_profile == "uniform":
        return np.ones(len(pts))
    i = "xyz".index(laser.sheet_axis)
    d = pts[:, i] - volume.centre_mm[i]
    t = laser.sheet_thickness_mm
    if laser.sheet_profile == "gaussian":
        return np.exp(-8.0 * d**2 / t**2)
    return (np.abs(d) <= 0.5 * t).astype(np.float64)
