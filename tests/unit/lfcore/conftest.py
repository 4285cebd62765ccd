"""Fixtures shared by lfcore's unit tests."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.particles import particle_count, seed_particles
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from tests.helpers import lightfield_scene


@pytest.fixture(scope="session")
def small_box(tiny_rig):
    """The tiny rig's first camera on a 0.5 x 0.4 x 1.2 mm box at 0.2 PPM: (cameras, grid, particles
    (n, 3) mm, the rendered frame). Big enough for the coarse grid when its size rule is lowered."""
    rig = tiny_rig.model_copy(update={"volume": tiny_rig.volume.model_copy(update={"size_mm": (0.5, 0.4, 1.2)})})
    _, grid, pts, img = lightfield_scene(rig, ppm=0.2, rays_per_particle=5_000)
    return rig.camera[:1], grid, pts, img


@pytest.fixture(scope="session")
def s2_scene(tiny_rig):
    """benchmarks/recon.py's S2: the tiny rig's camera and one at 90 degrees about y, a 0.8 x 0.7 x 0.8 mm
    box at PVR 2 seeded at 0.5 PPM, and both cameras' frames: (rig, grid, particles (n, 3) mm, images)."""
    d = tiny_rig.to_dict()
    d["camera"].append(dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
    d["volume"].update(size_mm=[0.8, 0.7, 0.8], pvr=[2.0, 2.0, 2.0])
    rig = Rig.from_dict(d)
    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=0.5), np.random.default_rng(1))
    render = rig.render.model_copy(update={"rays_per_particle": 5_000})
    img = [LightFieldRenderer(c, render, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, render.particle_counts, seed=1 + k) for k, c in enumerate(rig.camera)]
    return rig, grid, pts, img
