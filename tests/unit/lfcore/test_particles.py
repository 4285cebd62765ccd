"""Seeding density and the laser sheet."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.mla import lenslet_count
from lfcore.particles import particle_count, seed_particles, sheet_weights
from lfcore.rig import LaserConfig


def test_seeding_density_and_box(tiny_rig):
    n = particle_count(tiny_rig, ppm=0.5)
    assert n == round(0.5 * lenslet_count(tiny_rig.camera[0]))
    p = seed_particles(tiny_rig.volume, 5000, np.random.default_rng(0))
    half = 0.5 * np.asarray(tiny_rig.volume.size_mm)
    assert np.all(np.abs(p) <= half) and np.all(p.max(0) > 0.95 * half)
    with pytest.raises(ValueError, match="ppm must be a positive"):
        particle_count(tiny_rig, ppm=0.0)


def test_sheet_profiles(tiny_rig):
    vol = tiny_rig.volume
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.6]])
    g = sheet_weights(pts, LaserConfig(sheet_profile="gaussian", sheet_thickness_mm=1.0), vol)
    assert g[0] == 1.0 and g[1] == pytest.approx(np.exp(-2.0)) and g[2] == pytest.approx(np.exp(-2.0))
    t = sheet_weights(pts, LaserConfig(sheet_profile="top-hat", sheet_thickness_mm=1.0), vol)
    assert t.tolist() == [1.0, 1.0, 1.0, 0.0]
    x = sheet_weights(pts, LaserConfig(sheet_profile="top-hat", sheet_axis="x", sheet_thickness_mm=0.1), vol)
    assert x.tolist() == [1.0, 0.0, 1.0, 1.0]
    assert sheet_weights(pts, LaserConfig(), vol).tolist() == [1.0] * 4
