"""Quality metrics on volumes whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import metrics
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(20, 30, 40), voxel_mm=(0.01, 0.01, 0.05), origin_mm=(-0.2, -0.15, -0.5))


def _points(n, seed=0):
    rng = np.random.default_rng(seed)
    lo = np.asarray(GRID.origin_mm) + 3 * np.asarray(GRID.voxel_mm)
    hi = np.asarray(GRID.origin_mm) + (np.asarray(GRID.shape[::-1]) - 4) * np.asarray(GRID.voxel_mm)
    return rng.uniform(lo, hi, (n, 3))


def test_q_of_the_truth_is_one_and_drops_with_shift():
    pts = _points(30)
    e0 = metrics.truth_volume(GRID, pts)
    assert metrics.q_recon(e0, e0) == pytest.approx(1.0)
    shifted = metrics.truth_volume(GRID, pts + [0.75 * 0.01, 0.0, 0.0])
    # two Gaussian blobs of sigma s offset by d overlap as exp(-d^2 / (4 s^2))
    assert metrics.q_recon(shifted, e0) == pytest.approx(np.exp(-(0.75**2) / (4 * 0.75**2)), abs=0.02)
    assert metrics.q_recon(np.zeros(GRID.shape), e0) == 0.0


def test_truth_blobs_are_three_voxels_across():
    p = np.asarray(GRID.origin_mm) + np.array([20, 15, 10]) * np.asarray(GRID.voxel_mm)
    e0 = metrics.truth_volume(GRID, [p])
    _, _, idx = metrics.detect_particles(e0, GRID)
    assert idx.tolist() == [[10, 15, 20]]
    assert metrics.particle_diameters(e0, idx)[0] == pytest.approx([3.0, 3.0, 3.0], abs=0.2)


def test_detection_and_matching():
    pts = _points(40, seed=1)
    e0 = metrics.truth_volume(GRID, pts)
    pos, peaks, _ = metrics.detect_particles(e0, GRID, threshold=0.3)
    m = metrics.match_particles(pos, pts, 2 * np.asarray(GRID.voxel_mm))
    assert m.recall > 0.9 and m.ghosts <= 2
    assert np.all(m.rms_error_mm / GRID.voxel_mm < 0.1)  # sub-voxel: the Gaussian fit
    ghost = np.asarray(GRID.origin_mm) + [0.01, 0.01, 0.05]
    m2 = metrics.match_particles(np.vstack([pos, ghost]), pts, 2 * np.asarray(GRID.voxel_mm))
    assert m2.ghosts == m.ghosts + 1 and m2.n_detected == m.n_detected + 1


def test_depth_profile_and_outside_fraction():
    vol = np.zeros(GRID.shape, np.float32)
    vol[2] = 1.0  # one slice, z index 2
    vol[10] = 3.0
    prof = metrics.depth_profile(vol)
    assert prof[2] == 1.0 and prof[10] == 3.0 and prof[0] == 0.0
    z = GRID.axis_mm("z")
    frac = metrics.outside_fraction(vol, GRID, (0.0, 0.0, z[10]), (10.0, 10.0, 0.06))
    assert frac == pytest.approx(0.25)
