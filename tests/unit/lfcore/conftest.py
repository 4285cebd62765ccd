"""Fixtures shared by lfcore's unit tests."""

from __future__ import annotations

import pytest

from tests.helpers import lightfield_scene


@pytest.fixture(scope="session")
def small_box(tiny_rig):
    """The tiny rig's first camera on a 0.5 x 0.4 x 1.2 mm box at 0.2 PPM: (cameras, grid, particles
    (n, 3) mm, the rendered frame). Big enough for the coarse grid when its size rule is lowered."""
    rig = tiny_rig.model_copy(update={"volume": tiny_rig.volume.model_copy(update={"size_mm": (0.5, 0.4, 1.2)})})
    _, grid, pts, img = lightfield_scene(rig, ppm=0.2, rays_per_particle=5_000)
    return rig.camera[:1], grid, pts, img
