"""DRT-MART's first iterations on line-of-sight weights (ReconSettings.los_iterations): DRT weights then
built only for the voxels still bright, to the quality of DRT weights from the start."""

from __future__ import annotations

import pytest

from lfcore import metrics
from lfcore.plan import projector_for
from lfcore.reconstruct import FrameReconstructor, ReconSettings
from lfcore.rig import Rig
from tests.helpers import lightfield_scene


def _crop(rig: Rig, size_mm=(0.5, 0.4, 1.2)) -> Rig:
    return rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": size_mm})})


@pytest.fixture(scope="module")
def scene(tiny_rig):
    return lightfield_scene(_crop(tiny_rig))


def test_the_settings_are_checked():
    with pytest.raises(ValueError, match="fewer than the iterations"):
        ReconSettings(iterations=20, los_iterations=20)
    with pytest.raises(ValueError, match="drt-mart's simultaneous form"):
        ReconSettings(method="mlos-mart", los_iterations=5)
    with pytest.raises(ValueError, match="0 or more"):
        ReconSettings(los_iterations=-1)


def test_line_of_sight_first_reaches_the_drt_quality_on_a_fraction_of_the_voxels(scene):
    rig, grid, pts, img = scene
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(rig.camera[:1], grid, device="cpu")
    plain = FrameReconstructor(proj, ReconSettings(iterations=50, projector="stored")).reconstruct([img])
    los = FrameReconstructor(proj, ReconSettings(iterations=50, projector="stored", los_iterations=20)
                             ).reconstruct([img])
    q_plain, q_los = metrics.q_recon(plain.volume, truth), metrics.q_recon(los.volume, truth)
    assert q_los >= q_plain - 0.01, (q_los, q_plain)
    assert los.operator == "line-of-sight weights, then traced weights" and los.iterations == 50
    assert los.active_voxels == plain.active_voxels
    # the DRT weights were built for the voxels the line-of-sight iterations left bright: fewer rows
    assert los.nnz < 0.8 * plain.nnz, (los.nnz, plain.nnz)


def test_the_bright_voxels_are_what_the_pruning_keeps_read_without_copying_weights(scene, device):
    """bright_voxels gives the voxels and intensities prune_dark keeps, with one threshold over several
    operators (the depth slabs'); a SlabOperators restricted lets go of each slab's operator."""
    import numpy as np

    from lfcore.device import warp
    from lfcore.reconstruct import bright_voxels, prune_dark
    from lfcore.slabs import SlabOperators

    wp = warp()
    rig, grid, _, _ = scene
    proj = projector_for(rig.camera[:1], grid, device=device)
    frames = FrameReconstructor(proj, ReconSettings(iterations=5, projector="stored"))
    rng = np.random.default_rng(7)
    picked = np.sort(rng.choice(grid.n_voxels, 4000, replace=False)).astype(np.int32)
    ops = [frames.los_operator(wp.array(v, dtype=wp.int32, device=device)) for v in (picked[:2500], picked[2500:])]
    es = [wp.array((rng.random(op.n_voxels) * [1.0, 0.6][i]).astype(np.float32), device=device)
          for i, op in enumerate(ops)]
    kept_ops, kept_es = prune_dark(ops, es, 0.3)
    voxels, values = bright_voxels(ops, es, 0.3)
    assert 0 < voxels[1].size < voxels[0].size < 2500  # one threshold: the dimmer operator keeps fewer
    for op, e, v, x in zip(kept_ops, kept_es, voxels, values, strict=True):
        np.testing.assert_array_equal(op.voxels.numpy()[:op.n_voxels], v)
        np.testing.assert_allclose(e.numpy()[:op.n_voxels], x)
    joint = SlabOperators(ops, scratch=wp.zeros(proj.n_pixels, dtype=float, device=device))
    rows = np.arange(0, joint.n_voxels, 2, dtype=np.int32)
    small = joint.restrict(wp.array(rows, dtype=wp.int32, device=device))
    assert joint.parts == [None, None] and small.n_voxels == rows.size
    np.testing.assert_array_equal(np.concatenate([w.voxels.numpy()[:w.n_voxels] for w in small.parts]), picked[rows])
