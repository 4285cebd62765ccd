"""The fine grid's pruning after coarse-to-fine elimination (ReconSettings.coarse_prune, fast's 2%):
the resolved settings, the threshold applied only where the coarse grid ran, fewer voxels there for Q
within a tolerance, no pruning where none is asked for, and older volumes' settings."""

from __future__ import annotations

import pytest

from lfcore import coarse, metrics
from lfcore.plan import projector_for
from lfcore.reconstruct import PROTOCOLS, PRUNE, FrameReconstructor, ReconSettings, protocol_settings
from lfpiv.jobs.reconstruct import _matching, _recorded


def test_the_fast_protocol_prunes_at_two_percent_after_the_coarse_grid_and_the_others_at_the_pruning():
    assert protocol_settings("fast").coarse_prune == 0.02 == protocol_settings("fast", n_cameras=2).coarse_prune
    assert protocol_settings("fast", coarse_prune=0.0).coarse_prune == 0.0  # what the user gives wins
    for name in ("fixed", "chapter"):
        assert protocol_settings(name).coarse_prune == 0.0
    assert ReconSettings().coarse_prune == 0.0 and PRUNE == 0.01
    assert set(PROTOCOLS["fixed"]) == {"iterations"} and "coarse_prune" not in PROTOCOLS["chapter"]
    for bad in (-0.01, 1.0):
        with pytest.raises(ValueError, match="coarse_prune"):
            ReconSettings(coarse_prune=bad)


def test_older_volumes_were_handed_over_at_the_pruning_and_are_made_again():
    """Volumes recorded before coarse_prune count as made with 0 (the pruning's threshold): --skip-done
    and the settings check see older fast volumes as another set, and older fixed ones as the same."""
    fast_now = {**protocol_settings("fast").as_dict(), "protocol": "fast"}
    fast_before = {k: v for k, v in fast_now.items() if k != "coarse_prune"}
    assert _recorded(fast_before)["coarse_prune"] == 0.0
    assert _matching(_recorded(fast_before)) != _matching(_recorded(fast_now))
    fixed_now = {**protocol_settings("fixed").as_dict(), "protocol": "fixed"}
    fixed_before = {k: v for k, v in fixed_now.items() if k != "coarse_prune"}
    assert _matching(_recorded(fixed_before)) == _matching(_recorded(fixed_now))


def _traced(frames: FrameReconstructor, img) -> tuple[object, list[int]]:
    """The frame's result and the voxels each DRT operator of it was made for."""
    made = []
    inner = frames.operator

    def operator(voxels):
        made.append(int(voxels.shape[0]))
        return inner(voxels)

    frames.operator = operator
    return frames.reconstruct([img]), made


def test_a_box_without_the_coarse_grid_prunes_at_the_pruning(small_box):
    """The tiny box is below the coarse grid's size rule: fast traces DRT weights for the voxels its
    line-of-sight passes leave brighter than 1%, as many as with coarse_prune 0, and keeps as many."""
    cams, grid, pts, img = small_box
    proj = projector_for(cams, grid, device="cpu")
    fast = protocol_settings("fast", projector="stored", warm_start=False)
    frames = FrameReconstructor(proj, fast)
    assert not frames.coarse_applies()
    res, made = _traced(frames, img)
    plain, made_plain = _traced(FrameReconstructor(proj, protocol_settings("fast", projector="stored",
                                                                        warm_start=False, coarse_prune=0.0)), img)
    assert made == made_plain and len(made) == 1 and res.final_voxels == plain.final_voxels
    truth = metrics.truth_volume(grid, pts)
    assert abs(metrics.q_recon(res.volume, truth) - metrics.q_recon(plain.volume, truth)) < 0.005


def test_after_the_coarse_grid_fewer_voxels_are_reconstructed_for_the_same_q(small_box, monkeypatch, device):
    """With the coarse grid running (its size rule lowered for this box), pruning the fine grid at 2%
    traces DRT weights for fewer voxels and leaves fewer than 1% does, from the same voxels the coarse
    grid left (its own pruning stays at 1%), and Q stays within 0.02 of it (measured: DRT weights for
    1,097 voxels against 1,568, 561 left against 735, Q 0.713 against 0.715). With no pruning asked for
    (prune 0), none follows the coarse grid either."""
    cams, grid, pts, img = small_box
    proj = projector_for(cams, grid, device=device)
    monkeypatch.setattr(coarse, "COARSE_MIN_VOXELS", 0)
    truth = metrics.truth_volume(grid, pts)
    q, traced, result = {}, {}, {}
    for cut in (0.02, 0.0):
        settings = protocol_settings("fast", projector="stored", warm_start=False, coarse_iterations=5,
                                     coarse_prune=cut)
        frames = FrameReconstructor(proj, settings)
        assert frames.coarse_applies()
        res, made = _traced(frames, img)
        q[cut], traced[cut], result[cut] = metrics.q_recon(res.volume, truth), made[0], res
    assert traced[0.02] < traced[0.0], traced
    assert result[0.02].active_voxels == result[0.0].active_voxels
    assert result[0.02].final_voxels < result[0.0].final_voxels
    assert q[0.02] >= q[0.0] - 0.02, q
    unpruned = protocol_settings("fast", projector="stored", warm_start=False, coarse_iterations=5, prune=0.0,
                                 iterations=40)
    kept, made = _traced(FrameReconstructor(proj, unpruned), img)
    assert kept.final_voxels == made[0] > traced[0.0]  # the hand-over's 1% alone, as before
