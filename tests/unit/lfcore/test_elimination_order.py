"""Elimination with the views taking turns (lfcore._kernels.weights.eliminate_turns, ``round_checks``) keeps the
same voxels as one view after another, and MLOS-MART runs coarse-to-fine elimination where asked for.

The scene is benchmarks/recon.py's S2 (the tiny rig's camera and a second one at 90 degrees about y):
the survivors were pinned from the code before the views took turns (26,045 voxels at ``max_dark``
0.01, 60,303 at 0.05)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from lfcore import coarse, metrics
from lfcore import projector as projector_module
from lfcore.plan import coarse_runs, frame_stages, projector_for
from lfcore.reconstruct import FrameReconstructor, ReconSettings, preprocess_images, protocol_settings

#: (max_dark, survivors, the first 12 hex digits of the SHA-1 of their int32 indices) before the change
PINNED = ((0.01, 26_045, "ef0938b0fdb6"), (0.05, 60_303, "70a002fc76af"))


@pytest.fixture(scope="module")
def two_cameras(s2_scene):
    rig, grid, pts, img = s2_scene
    return rig.camera, grid, pts, img


def _survivors(proj, lits, max_dark: float) -> np.ndarray:
    return proj.eliminate(lits, max_dark=max_dark).numpy().copy()


@pytest.mark.parametrize("round_checks", [0, 1, 3, projector_module.ROUND_CHECKS, 64])
def test_the_views_taking_turns_keep_the_same_voxels(two_cameras, device, monkeypatch, round_checks):
    cams, grid, _, img = two_cameras
    proj = projector_for(cams, grid, device=device)
    _, lits, _, _ = preprocess_images(proj, img, ReconSettings())
    monkeypatch.setattr(projector_module, "ROUND_CHECKS", round_checks)  # 0: one view after another
    for max_dark, count, digest in PINNED:
        kept = _survivors(proj, lits, max_dark)
        assert kept.size == count
        assert hashlib.sha1(kept.astype(np.int32).tobytes()).hexdigest()[:12] == digest


def test_within_candidates_the_turns_keep_the_whole_grids_survivors(two_cameras, device):
    cams, grid, _, img = two_cameras
    proj = projector_for(cams, grid, device=device)
    wp = proj.wp
    _, lits, _, _ = preprocess_images(proj, img, ReconSettings())
    whole = _survivors(proj, lits, 0.01)
    candidates = np.sort(np.random.default_rng(0).choice(grid.n_voxels, grid.n_voxels // 3, replace=False))
    within = proj.eliminate(lits, max_dark=0.01, within=wp.array(candidates.astype(np.int32), dtype=wp.int32,
                                                                 device=device)).numpy()
    assert np.array_equal(within, np.intersect1d(whole, candidates))


def test_mlos_mart_takes_the_coarse_grid_when_given(two_cameras, monkeypatch):
    """MLOS-MART after a coarse grid at 2 on S2 (its box lowered under the size rule): fewer voxels are
    eliminated and iterated, nine in ten of the particles' voxels stay active, and Q is MLOS-MART's on
    the whole grid within 0.03."""
    cams, grid, pts, img = two_cameras
    proj = projector_for(cams, grid, device="cpu")
    truth = metrics.truth_volume(grid, pts)
    monkeypatch.setattr(coarse, "COARSE_MIN_VOXELS", 0)
    with pytest.raises(ValueError, match="drt-mart's simultaneous form and mlos-mart's"):
        ReconSettings(method="mart", coarse=2)
    assert protocol_settings("fast", n_cameras=2, method="mlos-mart").coarse == 1  # only where given
    plain = protocol_settings("fast", n_cameras=2, method="mlos-mart", iterations=40, projector="stored")
    given = protocol_settings("fast", n_cameras=2, method="mlos-mart", iterations=40, coarse=2, coarse_iterations=10,
                              projector="stored")
    assert given.coarse == 2 and coarse_runs("light-field", grid, given)
    assert frame_stages("light-field", grid, given)[0].startswith("coarse-to-fine elimination on a 2x coarser grid")
    frames = FrameReconstructor(proj, given)
    assert frames.coarse_applies()
    whole = FrameReconstructor(proj, plain).reconstruct(img)
    res = frames.reconstruct(img)
    assert res.active_voxels < whole.active_voxels
    q_whole, q_coarse = metrics.q_recon(whole.volume, truth), metrics.q_recon(res.volume, truth)
    assert q_whole > 0.6  # a reconstruction worth comparing
    assert q_coarse >= q_whole - 0.03, (q_coarse, q_whole)


def test_a_full_check_table_on_the_cpu_keeps_the_same_voxels(two_cameras, monkeypatch):
    """With every check's pixels in the table (as the live path's weight cache stores them), the CPU's
    elimination takes longer turns (``TABLE_PREFILTER_CHECKS``, ``TABLE_ROUND_CHECKS``) and keeps the
    pinned survivors; so do turns of other lengths."""
    cams, grid, _, img = two_cameras
    proj = projector_for(cams, grid, device="cpu")
    _, lits, _, _ = preprocess_images(proj, img, ReconSettings())
    assert proj.precompute_checks() > 0 and proj._n_checks == proj.max_checks
    for turns in ((projector_module.TABLE_PREFILTER_CHECKS, projector_module.TABLE_ROUND_CHECKS), (1, 3), (12, 64)):
        monkeypatch.setattr(projector_module, "TABLE_PREFILTER_CHECKS", turns[0])
        monkeypatch.setattr(projector_module, "TABLE_ROUND_CHECKS", turns[1])
        for max_dark, count, digest in PINNED:
            kept = _survivors(proj, lits, max_dark)
            assert kept.size == count
            assert hashlib.sha1(kept.astype(np.int32).tobytes()).hexdigest()[:12] == digest
