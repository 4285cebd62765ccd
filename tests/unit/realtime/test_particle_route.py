"""The live particle route's pieces: its settings, the tracks' field as the view takes it, and the
particles drawn into a volume, from known displacements and positions."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.ipr import to_mm
from lfcore.track import track_pair
from lfcore.volume import VolumeGrid
from realtime.processing import HostVolumeOps, particle_volume, tracks_as_field
from realtime.settings import LIVE_ROUTES, check_live_route, default_windows, monitoring_ipr, monitoring_tracking


def test_routes_and_monitoring_settings() -> None:
    assert LIVE_ROUTES == ("voxels", "particles")
    check_live_route("particles")
    with pytest.raises(ValueError, match="voxels or particles, not 'volume'"):
        check_live_route("volume")
    ipr = monitoring_ipr()
    assert ipr.candidate_iterations == 20 and ipr.rounds == 2
    # the live route keeps every pixel alike and no residual mask on every rig, light-field ones included
    # (lfpiv particles chooses shot + 3 there: 3.1x the CPU on the live route, fewer found)
    assert ipr.noise_model == "flat" and ipr.residual_mask == 0.0
    with pytest.raises(ValueError, match="at least 1"):
        monitoring_ipr(rounds=0)
    # the bins: the voxel route's last window; the first search an eighth of its first window, at least 4
    shape = (131, 1000, 1000)
    t = monitoring_tracking(shape)
    assert t.bin_voxels == default_windows(shape)[-1] == (32, 32, 32)
    assert t.search_voxels == (8.0, 8.0, 8.0)
    assert monitoring_tracking((29, 68, 82)).search_voxels == (4.0, 4.0, 4.0)


def test_a_uniform_displacement_becomes_the_views_field_in_voxels(tiny_rig) -> None:
    grid = VolumeGrid.from_rig(tiny_rig)
    rng = np.random.default_rng(3)
    nz, ny, nx = grid.shape
    u = rng.uniform([1, 1, 1], [nz - 3, ny - 3, nx - 3], size=(400, 3))  # (z, y, x) voxel coordinates
    shift = np.array([0.5, -1.0, 2.25])  # (z, y, x) voxels
    a, b = to_mm(grid, u), to_mm(grid, u + shift)
    bins = (16, 16, 8)
    tracks = track_pair(a, b, grid, settings=monitoring_tracking(grid.shape))
    vf = tracks_as_field(tracks, grid, bins)
    assert vf.displacement.shape == (len(vf.z), len(vf.y), len(vf.x), 3) == (*vf.shape, 3)
    filled = ~vf.outlier
    assert filled.sum() >= 0.5 * filled.size
    # (x, y, z) voxels of B relative to A, every filled bin
    np.testing.assert_allclose(vf.displacement[filled], np.broadcast_to(shift[::-1], (int(filled.sum()), 3)),
                               atol=1e-9)
    assert np.all(np.isnan(vf.displacement[~filled]))
    # the bin centres in voxel coordinates: the first bin's centre half a bin from the grid's first voxel edge
    assert vf.x[0] == pytest.approx((bins[0] - 1) / 2) and vf.z[1] - vf.z[0] == pytest.approx(bins[2])
    assert vf.grid.window == bins == vf.grid.step


def test_particles_drawn_into_the_volume_keep_their_light_at_their_place(tiny_rig) -> None:
    grid = VolumeGrid.from_rig(tiny_rig)
    u = np.array([[10.0, 20.0, 30.0], [5.25, 40.5, 60.75]])  # (z, y, x)
    vol = particle_volume(grid, to_mm(grid, u), np.array([2.0, 4.0]))
    assert vol.shape == grid.shape and vol.dtype == np.float32
    assert vol.sum() == pytest.approx(6.0, rel=1e-6)
    assert vol[10, 20, 30] == pytest.approx(2.0)  # at a voxel centre: all of it in that voxel
    block = vol[5:7, 40:42, 60:62]
    assert block.sum() == pytest.approx(4.0, rel=1e-6)
    centroid = np.array([(block * g).sum() / block.sum() for g in np.meshgrid(*(np.arange(2),) * 3, indexing="ij")])
    np.testing.assert_allclose(centroid + [5, 40, 60], u[1], atol=1e-6)  # the trilinear spread keeps the centroid
    ops = HostVolumeOps()
    assert ops.projection(vol, 0).shape == grid.shape[1:] and ops.plane(vol, 0, 10)[20, 30] == vol[10, 20, 30]
    with pytest.raises(IndexError, match="outside"):
        ops.plane(vol, 0, grid.shape[0])
    assert particle_volume(grid, np.zeros((0, 3)), np.zeros(0)).sum() == 0


def test_particles_outside_the_box_draw_only_their_light_inside_it(tiny_rig) -> None:
    """IPR keeps particles up to lfcore.ipr.BOX_MARGIN_VOXELS outside the box: drawn, they add the
    share of their light that falls on the box's voxels and index nothing out of it."""
    from lfcore.ipr import BOX_MARGIN_VOXELS

    grid = VolumeGrid.from_rig(tiny_rig)
    nz, ny, nx = grid.shape
    far = -0.5 - BOX_MARGIN_VOXELS + 0.1  # -2.4 voxels: no corner inside
    u = np.array([[far, 20.0, 30.0], [10.0, far, 30.0], [10.0, 20.0, nx - 0.6 + BOX_MARGIN_VOXELS],
                  [-0.7, 20.0, 30.0]])  # (z, y, x); the last 0.3 of its light on plane 0
    vol = particle_volume(grid, to_mm(grid, u), np.array([1.0, 1.0, 1.0, 2.0]))
    assert vol.sum() == pytest.approx(0.6, rel=1e-5) and vol[0, 20, 30] == pytest.approx(0.6, rel=1e-5)

