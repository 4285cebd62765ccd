"""The lenslet lattice and the pixel convention."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcore import mla
from tests.conftest import tiny_variant


@pytest.mark.parametrize("grid", ["hex", "square"])
def test_lenslet_count_matches_sensor_area(tiny_rig, grid):
    cam = tiny_variant(tiny_rig, mla_grid=grid, sensor_px=[613, 487]).camera[0]
    cell = cam.mla_pitch_mm**2 * (math.sqrt(3) / 2 if grid == "hex" else 1.0)
    w, h = cam.sensor_size_mm
    assert mla.lenslet_count(cam) == pytest.approx(w * h / cell, rel=0.03)


@pytest.mark.parametrize("grid", ["hex", "square"])
def test_nearest_lenslet_is_the_voronoi_cell(tiny_rig, grid):
    cam = tiny_variant(tiny_rig, mla_grid=grid, mla_rotation_deg=3.0, mla_offset_um=[7.0, -4.0]).camera[0]
    centres = mla.lenslet_centers(cam)
    assert np.allclose(mla.nearest_lenslet(cam, centres), centres)
    pts = np.random.default_rng(1).uniform(-0.3, 0.3, size=(2000, 2))
    got = mla.nearest_lenslet(cam, pts)
    # brute force: the closest of all centres
    d2 = ((pts[:, None, :] - centres[None]) ** 2).sum(-1)
    assert np.allclose(got, centres[np.argmin(d2, axis=1)])


def test_hex_rows_along_x_with_a_centre_on_the_axis(tiny_rig):
    cam = tiny_rig.camera[0]
    c = mla.lenslet_centers(cam)
    assert np.any(np.all(np.isclose(c, 0.0), axis=1))
    p = cam.mla_pitch_mm
    row0 = c[np.isclose(c[:, 1], 0.0)]
    assert np.allclose(np.diff(np.sort(row0[:, 0])), p)
    row1 = c[np.isclose(c[:, 1], p * math.sqrt(3) / 2)]
    assert np.allclose(np.mod(row1[:, 0] / p, 1.0), 0.5)


def test_pixel_convention_is_upright(tiny_rig):
    cam = tiny_rig.camera[0]
    # The lens inverts (M < 0): world +x lands at sensor -x, read out toward larger columns.
    assert np.allclose(mla.sensor_to_pixel(cam, [0.0, 0.0]), [96.0, 80.0])
    right = mla.sensor_to_pixel(cam, [cam.magnification * 0.1, 0.0])
    up = mla.sensor_to_pixel(cam, [0.0, cam.magnification * 0.1])
    assert right[0] > 96.0 and up[1] < 80.0
    xy = np.random.default_rng(2).uniform(-0.4, 0.4, (10, 2))
    assert np.allclose(mla.pixel_to_sensor(cam, mla.sensor_to_pixel(cam, xy)), xy)
    centres = mla.pixel_centers_sensor(cam)
    assert centres.shape == (160, 192, 2)
    assert np.allclose(mla.sensor_to_pixel(cam, centres[3, 5]), [5.5, 3.5])
