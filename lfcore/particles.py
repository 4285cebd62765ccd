"""Seeding particles and lighting them with the laser sheet."""

from __future__ import annotations

import numpy as np

from lfcore.mla import lenslet_count
from lfcore.rig import LaserConfig, Rig, VolumeConfig

__all__ = ["MAX_PPM", "particle_count", "seed_particles", "sheet_weights"]

#: Densest seeding accepted, particles per microlens. About 1 PPM is the usual limit of a
#: light-field reconstruction (the chapter tests up to 2); far beyond, the images are saturated
#: and a synthetic run of a large sensor would take more memory than a workstation has.
MAX_PPM = 10.0


def particle_count(rig: Rig, ppm: float) -> int:
    """Particles for a seeding density in particles per microlens (PPM) of the first camera."""
    if not (np.isfinite(ppm) and ppm > 0):
        raise ValueError(f"ppm must be a positive number, got {ppm}")
    if ppm > MAX_PPM:
        raise ValueError(f"ppm {ppm:g} is beyond {MAX_PPM:g} particles per microlens (about 1 is the usual limit of "
                         "a light-field reconstruction); give a lower density")
    return max(1, round(ppm * lenslet_count(rig.camera[0])))


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
