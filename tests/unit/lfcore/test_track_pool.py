"""Tracks pooled from neighbouring pairs of a series (lfcore.track.pooled_field_of_tracks,
``lfpiv track --along-pairs --pool-pairs K``) from known truths: a steady pattern translating at a
known speed, sampled sparsely in each pair, is recovered better pooled than from the pair's own
tracks and its translation within a tolerance of the truth; a pattern that changes between the
pairs is left to the pair's own tracks by the cross-validation."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.flows import VortexRing
from lfcore.track import TrackSettings, field_of_tracks, pattern_shift, pooled_field_of_tracks
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(32, 32, 32), voxel_mm=(0.01, 0.01, 0.01), origin_mm=(-0.155, -0.155, -0.155))
VOX = np.asarray(GRID.voxel_mm)
_LO = np.asarray(GRID.origin_mm) - 0.5 * VOX
_HI = _LO + np.asarray(GRID.shape[::-1]) * VOX
SETTINGS = TrackSettings(bin_voxels=(4, 4, 4), field="fit")
#: the pattern's translation from one pair to the next, voxels (x, y, z)
SHIFT_VOX = np.array([1.2, -0.8, 0.5])


def _ring(centre, circulation=1.0, axis=(0.0, 0.3, 1.0)):
    ring = VortexRing(centre_mm=tuple(centre), axis=axis, radius_mm=0.07, core_mm=0.03, circulation_mm2_s=circulation)
    peak = np.max(np.abs(VortexRing(centre_mm=(0.0, 0.0, 0.0), axis=axis, radius_mm=0.07, core_mm=0.03,
                                    circulation_mm2_s=1.0).velocity(np.zeros((1, 3)))))
    return lambda p: 0.02 * ring.velocity(p) / peak  # displacements of up to about 2 voxels


def _tracks(flow, n, seed, noise=0.05):
    """A pair's tracks of ``flow``: midpoints spread over the box, A and B half a displacement either
    side, ``noise`` voxels of Gaussian noise per axis on each position."""
    rng = np.random.default_rng(seed)
    mid = _LO + 0.1 * (_HI - _LO) + rng.random((n, 3)) * 0.8 * (_HI - _LO)
    d = flow(mid)
    a = mid - 0.5 * d + rng.normal(scale=noise, size=mid.shape) * VOX
    b = mid + 0.5 * d + rng.normal(scale=noise, size=mid.shape) * VOX
    return a, b


def _error(res, flow):
    zz, yy, xx = np.meshgrid(res.z_mm, res.y_mm, res.x_mm, indexing="ij")
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    f = res.field_mm.reshape(-1, 3)
    good = np.all(np.isfinite(f), axis=1)
    return float(np.sqrt(np.mean(((f[good] - flow(nodes[good])) / VOX) ** 2))), good


def _series(flow_of_pair, n=200, pairs=(-1, 0, 1), seed=0):
    return {k: _tracks(flow_of_pair(k), n, seed + 10 * (k + 5)) for k in pairs}


def test_a_translating_pattern_is_recovered_better_pooled_and_its_translation_found():
    c0 = np.array([0.0, 0.0, -0.01])
    series = _series(lambda k: _ring(c0 + k * SHIFT_VOX * VOX))
    a, b = series[0]
    neighbours = [(k, *series[k]) for k in (-1, 1)]
    own = field_of_tracks(a, b, GRID, settings=SETTINGS)
    pooled, choice = pooled_field_of_tracks(a, b, neighbours, GRID, settings=SETTINGS)
    assert choice is not None and choice.pooled
    assert choice.offsets == (-1, 1) and choice.tracks > 300
    assert np.allclose(np.asarray(choice.shift_mm) / VOX, SHIFT_VOX, atol=0.3), choice.shift_mm
    assert choice.cv_pooled_mm < choice.cv_own_mm
    e_own, good_own = _error(own, _ring(c0))
    e_pooled, good_pooled = _error(pooled, _ring(c0))
    assert np.array_equal(good_own, good_pooled)  # the field's points are the pair's own tracks'
    assert e_pooled < 0.8 * e_own, (e_pooled, e_own)
    # the tracks themselves are the pair's own
    assert np.array_equal(pooled.displacement_mm, own.displacement_mm)


def test_the_translation_from_the_tracks_alone():
    c0 = np.array([0.0, 0.0, 0.0])
    moving = {k: _tracks_mid(_ring(c0 + k * SHIFT_VOX * VOX), 200, 100 + k) for k in (-2, -1, 0, 1, 2)}
    shift = pattern_shift(*moving[0], [(k, *moving[k]) for k in (-2, -1, 1, 2)], GRID)
    assert np.allclose(shift / VOX, SHIFT_VOX, atol=0.2), shift / VOX
    still = {k: _tracks_mid(_ring(c0), 200, 50 + k) for k in (-1, 0, 1)}  # a pattern at rest
    shift = pattern_shift(*still[0], [(k, *still[k]) for k in (-1, 1)], GRID)
    assert np.all(np.abs(shift / VOX) < 0.3), shift / VOX


def _tracks_mid(flow, n, seed):
    a, b = _tracks(flow, n, seed)
    return 0.5 * (a + b), b - a


@pytest.mark.parametrize("change", ["reversed", "turned"])
def test_a_pattern_that_changes_between_the_pairs_is_not_pooled(change):
    c0 = np.array([0.0, 0.0, -0.01])

    def flow_of_pair(k):
        if k == 0:
            return _ring(c0)
        # the neighbours' flow is another: the ring spinning the other way, or turned about x
        return _ring(c0, circulation=-1.0) if change == "reversed" else _ring(c0, axis=(1.0, 0.0, 0.2))

    series = _series(flow_of_pair)
    a, b = series[0]
    own = field_of_tracks(a, b, GRID, settings=SETTINGS)
    pooled, choice = pooled_field_of_tracks(a, b, [(k, *series[k]) for k in (-1, 1)], GRID, settings=SETTINGS)
    assert choice is not None and not choice.pooled
    assert choice.cv_pooled_mm > choice.cv_own_mm
    np.testing.assert_array_equal(pooled.field_mm, own.field_mm)


def test_nothing_to_pool():
    a, b = _tracks(_ring(np.zeros(3)), 120, 3)
    own = field_of_tracks(a, b, GRID, settings=SETTINGS)
    res, choice = pooled_field_of_tracks(a, b, [], GRID, settings=SETTINGS)
    assert choice is None
    np.testing.assert_array_equal(res.field_mm, own.field_mm)
    binned = TrackSettings(bin_voxels=(4, 4, 4), field="bins")  # only the fitted fields pool
    res, choice = pooled_field_of_tracks(a, b, [(1, a, b)], GRID, settings=binned)
    assert choice is None
