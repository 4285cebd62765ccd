"""``lfpiv particles --skip-done`` on ``particles/`` groups written before today's IPR settings existed:
a missing setting reads as the value that reproduced the old code's particles."""

from __future__ import annotations

import pytest

from lfcore.ipr import IprSettings
from lfpiv.jobs.particles import same_settings

#: The first ``particles/`` groups' settings (lfcore.ipr at the first particles commit): no
#: ``split_intensity``, ``model``, ``point_sub_apertures``, ``particle_image_px``, ``wavelength_nm``,
#: ``relocate_depth`` nor ``max_position_std``.
FIRST = {"method": "drt-mart", "candidate_iterations": 50, "candidate_threshold": 0.05, "shakes": 12,
         "max_step_voxels": 0.5, "min_intensity": 0.5, "merge_voxels": 1.0, "rounds": 3, "cameras": ["cam0"]}


def meta(**settings) -> dict:
    """What ``particles_run`` records for these settings (method and cameras as the first group's)."""
    return {**IprSettings(**settings).as_dict(), "method": "drt-mart", "cameras": ["cam0"]}


def test_an_old_group_matches_the_settings_that_reproduce_it() -> None:
    old = meta(model="voxels", split_intensity=0.0, relocate_depth=0, candidate_protocol="fixed", local_refit_share=0.0)
    assert same_settings(FIRST, old)
    # the point model's own settings do not change the voxels model's particles
    assert same_settings(FIRST, meta(model="voxels", split_intensity=0.0, wavelength_nm=633.0, point_sub_apertures=40,
                                     particle_image_px=2.0, relocate_depth=3, candidate_protocol="fixed",
                                     local_refit_share=0.0))
    # a group written after split_intensity, before the point model
    assert same_settings({**FIRST, "split_intensity": 1.4}, meta(model="voxels", split_intensity=1.4,
                                                                  candidate_protocol="fixed", local_refit_share=0.0))
    # a group written after the point model, before max_position_std
    point = {k: v for k, v in meta().items() if k != "max_position_std"}
    assert same_settings(point, meta())
    # a group written before candidate_protocol: its candidates came from plain DRT-MART (fixed)
    before = {k: v for k, v in meta(candidate_protocol="fixed").items() if k != "candidate_protocol"}
    assert same_settings(before, meta(candidate_protocol="fixed"))
    assert not same_settings(before, meta())


def test_an_old_group_does_not_match_other_settings() -> None:
    assert not same_settings(FIRST, meta())  # today's defaults: the point model, splitting, moves
    assert not same_settings(FIRST, meta(model="voxels"))  # splitting (1.4) the old code did not do
    assert not same_settings(FIRST, meta(model="voxels", split_intensity=0.0, max_position_std=0.1))
    assert not same_settings(FIRST, meta(model="voxels", split_intensity=0.0, shakes=6))
    point = {k: v for k, v in meta().items() if k != "max_position_std"}
    assert not same_settings(point, meta(max_position_std=0.05))
    assert not same_settings(point, meta(relocate_depth=2))
    # today's groups compare every setting as before
    assert same_settings(meta(), meta())
    assert not same_settings(meta(), meta(wavelength_nm=633.0))


def test_a_group_written_before_candidate_source_had_the_reconstructions_candidates() -> None:
    before = {k: v for k, v in meta().items() if k != "candidate_source"}
    assert same_settings(before, meta(candidate_source="reconstruction"))
    assert not same_settings(before, meta(candidate_source="rays"))
    assert same_settings(meta(candidate_source="rays"), meta(candidate_source="rays"))


def test_a_group_written_before_intensity_axis_judged_by_the_frames_median() -> None:
    before = {k: v for k, v in meta().items() if k not in ("intensity_axis", "intensity_share")}
    assert same_settings(before, meta())
    assert same_settings(before, meta(intensity_share=0.3))  # the window is not used without an axis
    assert not same_settings(before, meta(intensity_axis="z"))
    assert same_settings(meta(intensity_axis="z"), meta(intensity_axis="z"))
    assert not same_settings(meta(intensity_axis="z"), meta(intensity_axis="z", intensity_share=0.3))


def test_a_group_written_before_noise_model_was_fitted_by_plain_least_squares() -> None:
    before = {k: v for k, v in meta().items() if k != "noise_model"}
    assert same_settings(before, meta(noise_model="flat")) and same_settings(before, meta())  # flat: the default
    assert not same_settings(before, meta(noise_model="shot"))
    assert same_settings(meta(noise_model="shot"), meta(noise_model="shot"))


def test_the_min_intensity_is_judged_along_an_uneven_sheet_by_default(tiny_rig) -> None:
    from lfpiv.errors import UsageError
    from lfpiv.jobs.particles import intensity_axis

    even = tiny_rig  # sheet_profile "uniform"
    gaussian = tiny_rig.model_copy(update={"laser": tiny_rig.laser.model_copy(
        update={"sheet_profile": "gaussian", "sheet_axis": "y"})})
    assert intensity_axis(even) is None and intensity_axis(even, "sheet") == even.laser.sheet_axis
    assert intensity_axis(gaussian) == "y" and intensity_axis(gaussian, "frame") is None
    with pytest.raises(UsageError, match="min-intensity-of"):
        intensity_axis(even, "volume")


def test_a_group_written_before_noise_floor_had_no_floor() -> None:
    before = {k: v for k, v in meta(noise_model="shot").items() if k != "noise_floor"}
    assert same_settings(before, meta(noise_model="shot", noise_floor=0.0))
    assert not same_settings(before, meta(noise_model="shot", noise_floor=0.1))


def test_particles_made_along_the_pairs_match_only_along_the_pairs() -> None:
    """--along-pairs is recorded only where on (settings.along_pairs): groups written before it, or
    without it, match today's frame-by-frame settings; along the pairs only the same searches match."""
    from lfpiv.jobs.particles import AlongPairs

    along = {**meta(), "along_pairs": AlongPairs().as_dict()}
    assert same_settings(meta(), meta())
    assert not same_settings(meta(), along) and not same_settings(along, meta())
    assert same_settings(along, {**meta(), "along_pairs": AlongPairs().as_dict()})
    assert not same_settings(along, {**meta(), "along_pairs": AlongPairs(search_voxels=(4, 4, 4)).as_dict()})


def test_the_prediction_along_the_pairs_reads_only_the_last_frames() -> None:
    """A uniform flow of 30 particles through 14 frames: the prediction from the whole history
    equals the one from its last frames, and is where the particles go next (so a long series
    may let its early frames go)."""
    import numpy as np

    from lfcore.volume import VolumeGrid
    from lfpiv.jobs.particles import AlongPairs

    grid = VolumeGrid(shape=(20, 64, 64), voxel_mm=(0.01, 0.01, 0.05), origin_mm=(-0.315, -0.315, -0.475))
    rng = np.random.default_rng(3)
    start = np.asarray(grid.origin_mm) + np.asarray(grid.voxel_mm) * (8 + rng.random((30, 3)) * [20, 20, 4])
    step = np.asarray(grid.voxel_mm) * [1.5, -0.5, 0.3]  # voxels a frame (x, y, z)
    frames = [start + k * step for k in range(14)]
    along = AlongPairs()
    whole = along.predict(frames, grid)
    last = along.predict(frames[-along.frames_read:], grid)
    assert along.frames_read < len(frames)
    np.testing.assert_allclose(np.sort(whole, axis=0), np.sort(last, axis=0), atol=1e-9)
    np.testing.assert_allclose(np.sort(whole, axis=0), np.sort(start + 14 * step, axis=0), atol=1e-6)


def test_a_group_written_before_residual_mask_masked_nothing() -> None:
    before = {k: v for k, v in meta().items() if k != "residual_mask"}
    assert same_settings(before, meta(residual_mask=0.0))
    assert not same_settings(before, meta(residual_mask=3.0))


def test_a_group_written_before_box_margin_voxels_kept_only_the_box() -> None:
    before = {k: v for k, v in meta().items() if k != "box_margin_voxels"}
    assert same_settings(before, meta(box_margin_voxels=0.0))
    assert not same_settings(before, meta())  # today's default keeps particles 2 voxels outside: remade
    # the voxels' model has no image outside the box: the margin changes nothing there
    voxels = {k: v for k, v in meta(model="voxels").items() if k != "box_margin_voxels"}
    assert same_settings(voxels, meta(model="voxels"))
    with pytest.raises(ValueError, match="box_margin_voxels"):
        IprSettings(box_margin_voxels=-1.0)


def test_a_group_written_before_local_refit_share_refitted_every_particle() -> None:
    before = {k: v for k, v in meta().items() if k != "local_refit_share"}
    assert same_settings(before, meta(local_refit_share=0.0))
    assert not same_settings(before, meta())  # today's residual rounds of few candidates refit locally: remade


def test_a_group_written_before_relocate_screen_traced_every_move_in_full() -> None:
    before = {k: v for k, v in meta().items() if k != "relocate_screen"}
    assert same_settings(before, meta(relocate_screen=0.0))
    assert not same_settings(before, meta(relocate_screen=0.5))  # screened moves: other particles, remade
    # the voxels' model makes no moves: the screen changes nothing there
    assert same_settings(meta(model="voxels"), meta(model="voxels", relocate_screen=0.5))


def test_a_group_written_before_candidate_weights_had_the_protocols_weights_unsmoothed() -> None:
    before = {k: v for k, v in meta().items() if k not in ("candidate_weights", "candidate_smoothing")}
    assert same_settings(before, meta())  # the protocol's weights, no smoothing: today's default
    assert not same_settings(before, meta(candidate_weights="line-of-sight"))  # other candidates: remade
    assert not same_settings(before, meta(candidate_smoothing=2.0))
    with pytest.raises(ValueError, match="candidate_smoothing"):
        IprSettings(candidate_smoothing=-1.0)


def test_a_group_written_before_jacobian_reuse_traced_every_jacobian() -> None:
    before = {k: v for k, v in meta().items() if k != "jacobian_reuse"}
    assert same_settings(before, meta(jacobian_reuse=0.0))
    assert not same_settings(before, meta(jacobian_reuse=0.05))  # an inexact Jacobian: other particles, remade
    # the voxels' model traces no point: the reuse changes nothing there
    assert same_settings(meta(model="voxels"), meta(model="voxels", jacobian_reuse=0.05))
