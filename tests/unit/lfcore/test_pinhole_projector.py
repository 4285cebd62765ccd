"""MLOS-SMART's operator: pinhole cameras' line-of-sight weights, MLOS elimination, reconstruction."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import pinhole
from lfcore.pinhole_projector import PinholeProjector, footprint_sigma_px
from lfcore.reconstruct import FrameReconstructor, ReconSettings
from lfcore.render import PinholeRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES
from tests.helpers import tomo_arc_small


@pytest.fixture(scope="module")
def small() -> Rig:
    """The chapter's 4-camera arc on a 2 x 2 x 1.5 mm box (27 x 27 x 20 voxels at PVR 1), one
    camera with radial and tangential distortion and an off-centre principal point."""
    return tomo_arc_small()


def _centres(grid: VolumeGrid, voxels: np.ndarray) -> np.ndarray:
    z, r = np.divmod(voxels, grid.shape[1] * grid.shape[2])
    y, x = np.divmod(r, grid.shape[2])
    return np.asarray(grid.origin_mm) + np.stack([x, y, z], axis=-1) * np.asarray(grid.voxel_mm)


def test_weights_are_centred_on_each_cameras_image_of_the_voxel_centre(small, device):
    grid = VolumeGrid.from_rig(small)
    p = PinholeProjector(small.camera, grid, device=device)
    rng = np.random.default_rng(2)
    voxels = np.sort(rng.choice(grid.n_voxels, 40, replace=False)).astype(np.int32)
    w = p.weights(p.wp.array(voxels, dtype=p.wp.int32, device=device))
    offsets, pix, wt = w.to_numpy()
    assert w.nnz == len(pix) and offsets[-1] == w.nnz
    centres = _centres(grid, voxels)
    for j in range(len(voxels)):
        sl = slice(offsets[j], offsets[j + 1])
        assert wt[sl].sum() == pytest.approx(1.0, abs=1e-4)  # divided by the sum over all cameras
        cam_of = np.searchsorted(p.pixel_offsets, pix[sl], side="right") - 1
        for k, cam in enumerate(small.camera):
            mine = cam_of == k
            local = pix[sl][mine] - p.pixel_offsets[k]
            row, col = np.divmod(local, cam.sensor_px[0])
            share = wt[sl][mine]
            assert share.sum() == pytest.approx(0.25, abs=4e-3)  # each camera sees the box (cut at 2.5 sigma)
            got = np.array([(share * (col + 0.5)).sum(), (share * (row + 0.5)).sum()]) / share.sum()
            want = pinhole.project(cam, centres[j])
            assert got == pytest.approx(want, abs=0.02)  # distortion included


def test_the_footprint_follows_the_voxels_projected_width(small):
    cam = small.camera[0]
    assert footprint_sigma_px(cam, VolumeGrid.from_rig(small)) == pytest.approx(0.5, rel=1e-3)
    assert footprint_sigma_px(cam, VolumeGrid.from_rig(small, pvr=(2.0, 2.0, 2.0))) == pytest.approx(1.0, rel=1e-3)
    with pytest.raises(ValueError, match="light-field camera"):
        PinholeProjector(list(small.camera) + [load_rig(EXAMPLES / "tiny.toml").camera[0]],
                         VolumeGrid.from_rig(small), device="cpu")
    with pytest.raises(ValueError, match="dense ray tracing"):
        p = PinholeProjector(small.camera, VolumeGrid.from_rig(small), device="cpu")
        p.weights(p.all_voxels(), method="drt")


def test_mlos_keeps_a_voxel_only_where_every_camera_is_lit(small, device):
    grid = VolumeGrid.from_rig(small)
    p = PinholeProjector(small.camera, grid, device=device)
    target = int(np.ravel_multi_index((10, 13, 12), grid.shape))
    point = _centres(grid, np.array([target]))[0]
    lits = []
    for cam in small.camera:
        lit = np.zeros((cam.sensor_px[1], cam.sensor_px[0]), bool)
        u, v = pinhole.project(cam, point)
        # the pixels around the image (a voxel centre of PVR 1 may image on a pixel's edge)
        lit[int(v - 0.5):int(v + 0.5) + 1, int(u - 0.5):int(u + 0.5) + 1] = True
        lits.append(lit)
    kept = p.eliminate(lits).numpy()
    assert target in kept and len(kept) < 0.005 * grid.n_voxels  # the lines of sight cross at the voxel
    lits[3][:] = False  # one camera sees nothing: nothing can be there
    assert len(p.eliminate(lits).numpy()) == 0
    assert len(p.eliminate([np.ones_like(m) for m in lits]).numpy()) == grid.n_voxels


def test_a_point_source_reconstructs_at_its_voxel(small, device):
    grid = VolumeGrid.from_rig(small)
    p = PinholeProjector(small.camera, grid, device=device)
    target = (8, 14, 11)
    point = _centres(grid, np.array([np.ravel_multi_index(target, grid.shape)]))
    images = [PinholeRenderer(cam, small.render, device=device).frame(point, 10000.0, seed=k)
              for k, cam in enumerate(small.camera)]
    res = FrameReconstructor(p, ReconSettings(method="mlos-smart", iterations=20)).reconstruct(images)
    assert np.unravel_index(np.argmax(res.volume), grid.shape) == target
    assert res.active_fraction < 0.02
    near = res.volume[target[0] - 2:target[0] + 3, target[1] - 2:target[1] + 3, target[2] - 2:target[2] + 3].sum()
    assert near > 0.9 * res.volume.sum()  # the light is where the particle is, not along its lines of sight


def test_a_mixed_rig_joins_both_kinds_weights_and_eliminations(device):
    from lfcore.pinhole_projector import JointProjector
    from lfcore.plan import projector_for

    rig = load_rig(EXAMPLES / "mixed_cameras.toml")  # lf0, then the pinhole cameras tomo0 and tomo1
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (0.3, 0.3, 0.3)})})
    grid = VolumeGrid.from_rig(rig)
    joint = projector_for(rig.camera, grid, device=device)
    assert isinstance(joint, JointProjector) and joint.n_pixels == 192 * 160 + 2 * 160 * 160
    voxels = joint.wp.array(np.arange(0, grid.n_voxels, 97, dtype=np.int32), dtype=joint.wp.int32, device=device)
    offs, pix, w = joint.weights(voxels, method="los").to_numpy()
    lo, lp, lw = joint.lf.weights(voxels, method="los").to_numpy()
    po, pp, pw = joint.ph.weights(voxels).to_numpy()
    for j in range(voxels.shape[0]):
        row = slice(offs[j], offs[j + 1])
        n_lf = lo[j + 1] - lo[j]
        # the light-field camera's pixels first, as they are (it is camera 0), then the pinhole ones after them
        np.testing.assert_array_equal(pix[row][:n_lf], lp[lo[j]:lo[j + 1]])
        np.testing.assert_array_equal(pix[row][n_lf:], pp[po[j]:po[j + 1]] + 192 * 160)
        np.testing.assert_allclose(w[row][:n_lf], lw[lo[j]:lo[j + 1]] / 3, rtol=1e-6)  # 1 camera of 3
        np.testing.assert_allclose(w[row][n_lf:], pw[po[j]:po[j + 1]] * 2 / 3, rtol=1e-6)  # 2 of 3
    lits = [np.ones((c.sensor_px[1], c.sensor_px[0]), bool) for c in rig.camera]
    lits[2][:, :80] = False  # tomo1 sees nothing on its left half: the voxels imaged there go
    kept = joint.eliminate(lits).numpy()
    assert 0 < len(kept) < grid.n_voxels
    np.testing.assert_array_equal(kept, np.intersect1d(joint.lf.eliminate(lits[:1]).numpy(),
                                                       joint.ph.eliminate(lits[1:]).numpy()))
