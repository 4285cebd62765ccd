"""Fixtures shared by lfcore's unit tests."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.particles import particle_count, seed_particles
from lfcore.render import LightFieldRenderer
from lfcore.volume import VolumeGrid


@pytest.fixture(scope="session")
def small_box(tiny_rig):
    """The tiny rig's first camera on a 0.5 x 0.4 x 1.2 mm box at 0.2 PPM: (cameras, grid, particles
    (n, 3) mm, the rendered frame). Big enough for the coarse grid when its size rule is lowered."""
    rig = tiny_rig.model_copy(update={"volume": tiny_rig.volume.model_copy(update={"size_mm": (0.5, 0.4, 1.2)})})
    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=0.2), np.random.default_rng(3))
    cfg = rig.render.model_copy(update={"rays_per_particle": 5_000})
    img = LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, 50_000.0, seed=1)
    return rig.camera[:1], grid, pts, img
