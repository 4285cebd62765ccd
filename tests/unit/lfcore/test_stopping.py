"""The stopping rule (ReconSettings.stop_tolerance) and the named protocols (lfcore.reconstruct.PROTOCOLS):
a frame of few isolated particles stops early, a denser one runs longer, and without the rule a
frame runs exactly its count."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import metrics
from lfcore.device import warp
from lfcore.particles import particle_count, seed_particles
from lfcore.plan import projector_for
from lfcore.reconstruct import (
    CAPPED,
    CONVERGED,
    FIXED,
    MASKED,
    PROTOCOLS,
    STOP_TOLERANCE,
    FrameReconstructor,
    ReconSettings,
    StoppingRule,
    protocol_settings,
    relative_residual,
    stop_interval,
)
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid


def _scene(rig: Rig, ppm: float, size_mm=(0.5, 0.4, 1.2)):
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": size_mm})})
    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(3))
    cfg = rig.render.model_copy(update={"rays_per_particle": 5_000})
    img = LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, 50_000.0, seed=1)
    return projector_for(rig.camera[:1], grid, device="cpu"), metrics.truth_volume(grid, pts), img


@pytest.fixture(scope="module")
def sparse(tiny_rig):
    return _scene(tiny_rig, 0.2)


@pytest.fixture(scope="module")
def dense(tiny_rig):
    return _scene(tiny_rig, 1.0)


def test_the_relative_residual_of_known_projections():
    wp = warp()
    b = wp.array(np.array([3.0, 4.0, 0.0, MASKED], np.float32), dtype=float, device="cpu")

    def r(p):
        return relative_residual(b, wp.array(np.array(p, np.float32), dtype=float, device="cpu"))

    assert r([3.0, 4.0, 0.0, 7.0]) == pytest.approx(0.0)  # a masked pixel measured nothing
    assert r([0.0, 0.0, 0.0, 0.0]) == pytest.approx(1.0)  # an empty volume
    assert r([3.0, 4.0, 5.0, 0.0]) == pytest.approx(1.0)  # a ghost's light on an unlit pixel counts
    assert r([6.0, 8.0, 0.0, 0.0]) == pytest.approx(1.0)


def test_the_rule_stops_when_the_residual_and_the_voxels_settle():
    rule = StoppingRule(0.01, voxels=0.02, every=10)
    assert rule.on and rule.due(0) and rule.due(20) and not rule.due(15)
    assert not rule.converged(0, 0.5, 1000)  # the first measurement: nothing to compare with
    assert not rule.converged(10, 0.3, 1000)  # the residual fell by 40%
    assert not rule.converged(20, 0.299, 900)  # 0.3%, but 10% of the voxels left
    assert rule.converged(30, 0.2985, 895)  # 0.2% and 0.6%
    assert not StoppingRule(0.0).on and not StoppingRule(0.0).due(10)


def test_the_settings_and_protocols_are_checked():
    with pytest.raises(ValueError, match="stop_tolerance"):
        ReconSettings(stop_tolerance=1.0)
    with pytest.raises(ValueError, match="stop_every"):
        ReconSettings(stop_every=0)
    with pytest.raises(ValueError, match="protocol must be one of"):
        protocol_settings("slow")
    chapter = ReconSettings.chapter(iterations=100)
    assert chapter.prune == 0 and not chapter.stopping and chapter.iterations == 100 and not chapter.warm_start
    assert protocol_settings("chapter").iterations == 400 and protocol_settings("chapter").relaxation == 1.0
    assert protocol_settings("fixed") == ReconSettings()  # lfpiv reconstruct's settings before the protocols
    fast = protocol_settings("fast")
    assert fast.stop_tolerance == STOP_TOLERANCE and fast.los_iterations and fast.prune > 0
    # frame B warm-started by its own pair: a volume depends on its pair alone, not on the pairs made before
    assert fast.warm_start and fast.warm_predictor == "own"
    # another method or form keeps what applies to it
    assert protocol_settings("fast", method="mart").los_iterations == 0
    assert not protocol_settings("fast", form="sequential", relaxation=2.0).warm_start
    assert protocol_settings("fast", iterations=15).los_iterations == 0  # too few for DRT's weights to take over
    assert set(PROTOCOLS) >= {"chapter", "fixed", "fast"}


def test_without_the_rule_a_frame_runs_exactly_its_count(sparse):
    proj, _, img = sparse
    counts = []
    res = FrameReconstructor(proj, ReconSettings(iterations=37, projector="stored")).reconstruct(
        [img], progress=counts.append)
    assert res.iterations == 37 and res.stopped == FIXED and sum(counts) == 37


def test_a_converged_frame_stops_early_and_a_harder_one_runs_longer(sparse, dense):
    rule = ReconSettings(iterations=300, projector="stored", stop_tolerance=STOP_TOLERANCE)
    done = {}
    for name, (proj, truth, img) in (("sparse", sparse), ("dense", dense)):
        counts = []
        res = FrameReconstructor(proj, rule).reconstruct([img], progress=counts.append)
        assert sum(counts) == 300  # the bar sized for the most is filled
        done[name] = res, metrics.q_recon(res.volume, truth)
    (easy, q_easy), (hard, _) = done["sparse"], done["dense"]
    assert easy.stopped == CONVERGED and easy.iterations < 250, easy.iterations
    assert hard.iterations > easy.iterations + 30, (hard.iterations, easy.iterations)
    assert hard.stopped in (CONVERGED, CAPPED)
    # stopping early lost nothing: the sparse frame is where 200 fixed iterations take it
    proj, truth, img = sparse
    fixed = FrameReconstructor(proj, ReconSettings(iterations=200, projector="stored")).reconstruct([img])
    assert q_easy >= metrics.q_recon(fixed.volume, truth) - 0.01


def test_the_rule_after_line_of_sight_iterations_counts_them(sparse):
    proj, _, img = sparse
    res = FrameReconstructor(proj, protocol_settings("fast", projector="stored")).reconstruct([img])
    assert res.operator == "line-of-sight weights, then traced weights"
    assert res.stopped in (CONVERGED, CAPPED) and 20 < res.iterations <= 400


def test_every_measurement_window_holds_a_pruning():
    """The rule's voxel test sees voxels leave only at the prunings: with them every 30 iterations it
    measures every 30 (the least common multiple), not every 10, where two windows in three would hold
    none and pass the voxel test whatever the ghosts do."""
    assert stop_interval(ReconSettings(), prune=True) == 10
    assert stop_interval(ReconSettings(prune_every=30), prune=True) == 30
    assert stop_interval(ReconSettings(prune_every=4), prune=True) == 20
    assert stop_interval(ReconSettings(prune_every=30), prune=False) == 10
