"""Particle tracking (lfcore.track) from known displacements of known point sets."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.track import TrackSettings, bin_tracks, pair_nearest, reject_outliers, track_pair
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(20, 64, 64), voxel_mm=(0.01, 0.01, 0.05), origin_mm=(-0.315, -0.315, -0.475))


def _points(n, seed):
    rng = np.random.default_rng(seed)
    lo = np.asarray(GRID.origin_mm)
    size = np.asarray(GRID.voxel_mm) * (np.asarray(GRID.shape[::-1]) - 1)
    return lo + rng.random((n, 3)) * size


def test_a_known_uniform_displacement_is_tracked():
    a = _points(300, 0)
    shift = np.array([1.6, -0.9, 0.5]) * np.asarray(GRID.voxel_mm)  # voxels (x, y, z) in mm
    rng = np.random.default_rng(1)
    b = a + shift + rng.normal(scale=0.05, size=a.shape) * np.asarray(GRID.voxel_mm)
    b = b[rng.permutation(len(b))]
    res = track_pair(a, b, GRID, settings=TrackSettings(bin_voxels=(16, 16, 5)))
    kept = ~res.outlier
    assert kept.sum() >= 0.95 * len(a)
    # the mean of 300 tracks with 0.05-voxel noise: within 0.02 voxel per axis
    assert np.all(np.abs(res.displacement_mm[kept].mean(axis=0) - shift) < 0.02 * np.asarray(GRID.voxel_mm))
    good = np.isfinite(res.field_mm[..., 0])
    assert good.mean() > 0.9
    assert np.all(np.abs(res.field_mm[good] - shift) < 0.1 * np.asarray(GRID.voxel_mm))


def test_a_known_rotation_is_tracked_beyond_the_first_search():
    a = _points(600, 2)
    centre = np.array([0.0, 0.0, 0.0])
    omega = 0.012  # rad over dt about z: up to 0.0045 mm = 4.5 voxels at the corners
    rel = a - centre
    b = centre + np.column_stack([rel[:, 0] * np.cos(omega) - rel[:, 1] * np.sin(omega),
                                  rel[:, 0] * np.sin(omega) + rel[:, 1] * np.cos(omega), rel[:, 2]])
    res = track_pair(a, b, GRID, settings=TrackSettings(search_voxels=(5.0, 5.0, 1.0), bin_voxels=(8, 8, 5)))
    true = b - a
    # every track kept pairs a particle with its own image
    kept = ~res.outlier
    assert np.allclose(res.displacement_mm[kept], true[res.a_index[kept]], atol=1e-9)
    assert kept.sum() >= 0.9 * len(a)


def test_pairs_are_one_to_one_nearest_first():
    a = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    b = np.array([[0.09, 0.0, 0.0], [0.5, 0.0, 0.0]])
    ia, ib = pair_nearest(a, b, np.zeros(3), np.array([0.2, 0.2, 0.2]))
    assert list(zip(ia, ib, strict=True)) == [(1, 0)]  # a[0] would take b[0] too, but a[1] is nearer


def test_an_outlier_among_uniform_tracks_is_rejected():
    pos = _points(50, 3)
    d = np.tile([0.01, 0.0, 0.0], (50, 1))
    d[7] = [-0.02, 0.01, 0.0]
    out = reject_outliers(pos, d, neighbours=8, threshold=3.0, epsilon_mm=np.full(3, 0.002))
    assert out.tolist() == [i == 7 for i in range(50)]


def test_bins_cover_the_grid_and_count_tracks():
    pos = np.array([GRID.origin_mm, GRID.origin_mm])
    centres, field, counts = bin_tracks(pos, np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]]), GRID,
                                        bin_voxels=(16, 16, 5))
    assert [len(c) for c in centres] == [4, 4, 4]
    assert counts[0, 0, 0] == 2 and counts.sum() == 2
    assert np.allclose(field[0, 0, 0], [2.0, 2.0, 2.0])
    assert np.isnan(field[1, 1, 1]).all()


def test_settings_refuse_nonsense():
    with pytest.raises(ValueError, match="three positive"):
        TrackSettings(bin_voxels=(16, 16))
