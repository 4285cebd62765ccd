"""The divergence-free field of tracks (lfcore.track.fit_tracks(divergence_free=True), --field divfree)
from known flows: an incompressible one recovered better than by the components fitted apart, its
field free of divergence, and a compressible one not made worse."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.flows import VortexRing
from lfcore.track import DIVFREE_WEIGHTS, TrackSettings, field_of_tracks, fit_tracks
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(32, 32, 32), voxel_mm=(0.01, 0.01, 0.01), origin_mm=(-0.155, -0.155, -0.155))
VOX = np.asarray(GRID.voxel_mm)
_LO = np.asarray(GRID.origin_mm) - 0.5 * VOX
_BOX = (_LO, _LO + np.asarray(GRID.shape[::-1]) * VOX)
_REACH = np.full(3, 8 * 0.01)


def _points(n, seed):
    return _BOX[0] + np.random.default_rng(seed).random((n, 3)) * (_BOX[1] - _BOX[0])


def _centres(step=8):
    c = [_BOX[0][a] + (np.arange(32 // step) + 0.5) * step * VOX[a] for a in range(3)]
    zz, yy, xx = np.meshgrid(c[2], c[1], c[0], indexing="ij")
    return c, np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])


# a vortex ring across the box plus a solid-body rotation about z: free of divergence by construction;
# displacements of up to about 2 voxels
_RING = VortexRing(centre_mm=(0.0, 0.0, -0.02), axis=(0.0, 0.3, 1.0), radius_mm=0.08, core_mm=0.035,
                   circulation_mm2_s=1.0)


def _incompressible(p):
    rot = 0.004 * np.column_stack([-p[:, 1], p[:, 0], np.zeros(len(p))])
    return 0.008 * _RING.velocity(p) / np.max(np.abs(_RING.velocity(np.zeros((1, 3))))) * 1.0 + rot


def _rms_voxels(field, nodes, flow):
    f = field.reshape(-1, 3)
    good = np.all(np.isfinite(f), axis=1)
    return np.sqrt(np.mean(((f[good] - flow(nodes[good])) / VOX) ** 2)), good.mean()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_known_incompressible_flow_is_recovered_better_than_by_the_components_apart(seed):
    pos = _points(220, seed)
    rng = np.random.default_rng(10 + seed)
    d = _incompressible(pos) + rng.normal(scale=0.1, size=pos.shape) * VOX  # 0.1 voxel of noise per axis
    centres, nodes = _centres()
    apart, _, _ = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX)
    together, _, choice = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX, divergence_free=True)
    e_apart, filled = _rms_voxels(apart, nodes, _incompressible)
    e_together, _ = _rms_voxels(together, nodes, _incompressible)
    assert filled > 0.9
    assert choice[0].weight is not None and choice[0].weight <= 0.1  # the matrix kernel, near free of divergence
    assert e_together < 0.9 * e_apart, (e_together, e_apart)


def test_the_fitted_field_is_free_of_divergence():
    pos = _points(200, 5)
    d = _incompressible(pos)
    h = 1e-4  # mm: central differences of the evaluated field around a point
    x0 = np.array([0.021, -0.033, 0.012])
    centres = [x0[a] + np.array([-h, 0.0, h]) for a in range(3)]

    def gradient(f):  # (3, 3) d u_c / d x_a at x0 of a (z, y, x, 3) field on the 3 x 3 x 3 points
        return np.array([[(f[1, 1, 2, c] - f[1, 1, 0, c]) / (2 * h), (f[1, 2, 1, c] - f[1, 0, 1, c]) / (2 * h),
                          (f[2, 1, 1, c] - f[0, 1, 1, c]) / (2 * h)] for c in range(3)])

    field, _, choice = fit_tracks(pos, d, centres, reach_mm=np.full(3, 1.0), divergence_free=True)
    assert choice[0].weight == DIVFREE_WEIGHTS[0] == 0.0
    grad = gradient(field)
    assert np.abs(grad).max() > 0.01  # the flow does vary here (mm per mm)
    # zero up to the finite differences' own error (the components fitted apart: a percent or more)
    assert abs(np.trace(grad)) < 1e-4 * np.abs(grad).max()
    apart = gradient(fit_tracks(pos, d, centres, reach_mm=np.full(3, 1.0))[0])
    assert abs(np.trace(apart)) > 100 * abs(np.trace(grad))


def test_a_compressible_flow_is_not_made_worse():
    # Table 4.1's A1-like u = 3 voxels x cos(kx): its divergence is all of its gradient
    pos = _points(200, 7)

    def flow(p):
        return np.column_stack([3.0 * np.cos(2 * np.pi * p[:, 0] / 0.32), np.zeros(len(p)), np.zeros(len(p))]) * VOX

    rng = np.random.default_rng(8)
    d = flow(pos) + rng.normal(scale=0.1, size=pos.shape) * VOX
    centres, nodes = _centres()
    apart, _, _ = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX)
    together, _, choice = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX, divergence_free=True)
    e_apart, _ = _rms_voxels(apart, nodes, flow)
    e_together, _ = _rms_voxels(together, nodes, flow)
    assert choice[0].weight is None or choice[0].weight > 0  # never forced free of divergence
    assert e_together < 1.05 * e_apart, (e_together, e_apart)


def test_the_divfree_field_through_the_settings():
    pos = _points(150, 9)
    a = pos - 0.5 * _incompressible(pos)
    b = pos + 0.5 * _incompressible(pos)
    res = field_of_tracks(a, b, GRID, settings=TrackSettings(bin_voxels=(8, 8, 8), field="divfree"))
    assert res.fit is not None and res.fit[0].weight is not None
    zz, yy, xx = np.meshgrid(res.z_mm, res.y_mm, res.x_mm, indexing="ij")
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    err, filled = _rms_voxels(res.field_mm, nodes, _incompressible)
    assert filled > 0.9 and err < 0.1  # exact tracks: a tenth of a voxel or better between them


def test_many_tracks_are_fitted_in_blocks():
    from lfcore.track import DIVFREE_GLOBAL_TRACKS

    n = DIVFREE_GLOBAL_TRACKS + 100
    pos = _points(n, 11)
    rng = np.random.default_rng(12)
    d = _incompressible(pos) + rng.normal(scale=0.1, size=pos.shape) * VOX
    centres, nodes = _centres(4)
    apart, _, _ = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX)
    together, _, choice = fit_tracks(pos, d, centres, reach_mm=_REACH, box_mm=_BOX, divergence_free=True)
    e_apart, filled = _rms_voxels(apart, nodes, _incompressible)
    e_together, filled_together = _rms_voxels(together, nodes, _incompressible)
    assert filled_together == filled > 0.9
    assert choice[0].weight is not None and e_together < e_apart, (e_together, e_apart)
