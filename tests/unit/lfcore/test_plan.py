"""The planner (lfcore.plan): which operator, whether a weight cache serves, how many depth slabs,
and why; every operator it makes is the one protocol the algorithms iterate over."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lfcore import metrics
from lfcore.operator import ALL_KINDS, JOINT, PINHOLE, TEMPLATE_IMAGES, TEMPLATES, TRACED, Operator
from lfcore.pinhole_projector import JointProjector, PinholeProjector
from lfcore.plan import (
    BYTES_PER_BOX_VOXEL,
    AutoSource,
    Plan,
    PlanError,
    TemplateSource,
    WeightSource,
    build_reconstructor,
    frame_stages,
    operator_source,
    plan_reconstruction,
    projector_for,
)
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import FrameReconstructor, ReconSettings, protocol_settings
from lfcore.rig import Rig
from lfcore.slabs import SlabReconstructor
from lfcore.volume import VolumeGrid
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES
from tests.helpers import lightfield_scene, tomo_arc_small

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def small() -> Rig:
    """The chapter's 4-camera arc on a 2 x 2 x 1.5 mm box, one camera distorted."""
    return tomo_arc_small()


def _crop(rig: Rig, size_mm=(0.5, 0.4, 1.2)) -> Rig:
    return rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": size_mm})})


def test_projector_for_picks_the_cameras_kind(small):
    tiny = load_rig(EXAMPLES / "tiny.toml")
    grid = VolumeGrid.from_rig(small)
    assert isinstance(projector_for(small.camera, grid, device="cpu"), PinholeProjector)
    lf = projector_for(tiny.camera, VolumeGrid.from_rig(tiny), device="cpu")
    assert type(lf) is LightFieldProjector
    assert isinstance(projector_for([*small.camera, tiny.camera[0]], grid, device="cpu"), JointProjector)


def test_the_plan_of_each_camera_kind_says_its_operator_cache_and_why(tiny_rig, small):
    mixed = load_rig(EXAMPLES / "mixed_cameras.toml")
    lf = plan_reconstruction(tiny_rig.camera, VolumeGrid.from_rig(tiny_rig), ReconSettings(), device="cpu")
    assert (lf.cameras, lf.operator, lf.cache, lf.slabs) == ("light-field", "auto", True, 1)
    assert lf.summary() == "auto on cpu, weight cache, in memory"
    assert any("--projector auto" in r for r in lf.reasons) and any("weight cache" in r for r in lf.reasons)
    stored = plan_reconstruction(tiny_rig.camera, VolumeGrid.from_rig(tiny_rig), ReconSettings(projector="stored"),
                                 device="cpu")
    assert stored.operator == TRACED and stored.cache
    ph = plan_reconstruction(small.camera, VolumeGrid.from_rig(small), ReconSettings(method="mlos-smart"),
                             device="cpu")
    assert (ph.cameras, ph.operator, ph.cache) == ("pinhole", PINHOLE, False)
    assert any("pinhole cameras have a handful of weights per voxel" in r for r in ph.reasons)
    joint = plan_reconstruction(mixed.camera, VolumeGrid.from_rig(_crop(mixed, (0.3, 0.3, 0.3))), ReconSettings(),
                                device="cpu")
    assert (joint.cameras, joint.operator, joint.cache) == ("joint", JOINT, True)
    mart = plan_reconstruction(tiny_rig.camera, VolumeGrid.from_rig(tiny_rig), ReconSettings(method="mart"),
                               device="cpu")
    assert mart.operator == "line-of-sight weights" and not mart.cache
    assert any("MART baseline" in r for r in mart.reasons)
    fly = plan_reconstruction(tiny_rig.camera, VolumeGrid.from_rig(tiny_rig),
                              ReconSettings(projector="matrix-free", weight_storage="on-the-fly"), device="cpu")
    assert fly.operator == TEMPLATES and not fly.cache
    # what the run store records, read back
    assert Plan.from_dict(lf.as_dict()) == lf
    with pytest.raises(PlanError, match="not a recorded plan"):
        Plan.from_dict({"device": "cpu"})


def test_the_plan_says_what_each_frame_runs(tiny_rig, small):
    """Plan.stages: the coarse grid where it applies (or why not), the line-of-sight iterations first, the
    ordered subsets and the stopping rule; depth slabs run the plain form; older records read as none."""
    grid = VolumeGrid.from_rig(tiny_rig)  # 82 x 68 x 29 voxels: under COARSE_MIN_VOXELS
    fast = plan_reconstruction(tiny_rig.camera, grid, protocol_settings("fast"), device="cpu")
    assert fast.stages == ("elimination on the whole grid (no coarse grid for a box of fewer than 1,000,000 voxels)",
                           "20 iterations on line-of-sight weights, then DRT weights for the voxels still bright",
                           "6 ordered subsets a pass",
                           "frames B warm-started from frame A carried along their own pair's displacement, at most 80 "
                           "iterations", "at most 400 iterations by the stopping rule")
    assert fast.describe_stages() == "; ".join(fast.stages) and "stages: " in fast.lines()[1]
    big = VolumeGrid(shape=(120, 100, 100), voxel_mm=grid.voxel_mm, origin_mm=grid.origin_mm)  # 1.2 M voxels
    assert frame_stages("light-field", big, protocol_settings("fast"))[0] == \
        "coarse-to-fine elimination on a 3x coarser grid (30 line-of-sight iterations; the fine grid's voxels pruned " \
        "at 2%)"
    assert "cameras other than light-field ones" in frame_stages("joint", big, protocol_settings("fast"))[0]
    assert frame_stages("light-field", big, protocol_settings("fast"), slabs=2) == frame_stages(
        "light-field", big, protocol_settings("fast", warm_start=False))  # depth slabs run the in-memory plan
    assert "warm-started" not in " ".join(frame_stages("light-field", big, protocol_settings("fast", warm_start=True),
                                                       slabs=2))  # but not the warm start
    assert frame_stages("light-field", grid, ReconSettings()) == ("50 iterations",)
    warm = frame_stages("light-field", grid, protocol_settings("fixed", warm_start=True))
    assert warm[0].startswith("frames B warm-started from frame A")
    assert "the last pair's" in frame_stages("light-field", grid, protocol_settings("fixed", warm_start=True,
                                                                                    warm_predictor="last"))[0]
    ph = plan_reconstruction(small.camera, VolumeGrid.from_rig(small), protocol_settings("fast", method="mlos-smart"),
                             device="cpu")
    assert ph.stages[0] == "6 ordered subsets a pass" and ph.stages[-1] == "at most 400 iterations by the stopping rule"
    assert Plan.from_dict(fast.as_dict()) == fast
    old = {k: v for k, v in fast.as_dict().items() if k != "stages"}  # recorded before December 2026
    assert Plan.from_dict(old).stages == () and Plan.from_dict(old).describe_stages() == ""


def test_the_plan_splits_what_does_not_fit_and_refuses_in_one_line(tiny_rig):
    grid = VolumeGrid.from_rig(tiny_rig)  # 82 x 68 x 29 voxels
    need = BYTES_PER_BOX_VOXEL * grid.n_voxels
    settings = ReconSettings()
    assert plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu", slabs="auto", free_bytes=need).slabs == 1
    split = plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu", slabs="auto", free_bytes=2_400_000)
    assert split.slabs == 5 and not split.cache  # 6 planes a slab, as `lfpiv reconstruct --slabs auto` says
    assert any("5 depth slabs, since its buffers" in r for r in split.reasons)
    assert plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu", slabs=3).slabs == 3
    with pytest.raises(PlanError, match=r"more than it has free; use a coarser --pvr, or --slabs auto") as not_given:
        plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu", free_bytes=need - 1)
    assert "\n" not in str(not_given.value)
    with pytest.raises(PlanError, match="the sequential form cannot be split"):
        plan_reconstruction(tiny_rig.camera, grid, ReconSettings(form="sequential", relaxation=1.0), device="cpu",
                            slabs="auto", free_bytes=need - 1)
    with pytest.raises(PlanError, match="the box is 29 voxels deep; give from 1 to 29 slabs, or auto"):
        plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu", slabs=30)
    # the plan made: slabs of their own projectors, or the in-memory reconstructor with its cache
    built = build_reconstructor(split, tiny_rig.camera, grid, settings)
    assert built.in_slabs and isinstance(built, SlabReconstructor) and len(built.slabs) == 5
    frames = build_reconstructor(plan_reconstruction(tiny_rig.camera, grid, settings, device="cpu"),
                                 tiny_rig.camera, grid, settings, checks=0)
    assert not frames.in_slabs and frames.cache is not None and frames.cache.checks_bytes == 0


def test_the_operator_sources_of_the_settings(tiny_rig, small):
    grid = VolumeGrid.from_rig(_crop(tiny_rig))
    lf = LightFieldProjector(tiny_rig.camera, grid, device="cpu")
    assert isinstance(operator_source(lf, ReconSettings()), AutoSource)
    assert isinstance(operator_source(lf, ReconSettings(projector="stored")), WeightSource)
    assert isinstance(operator_source(lf, ReconSettings(projector="matrix-free")), TemplateSource)
    assert isinstance(operator_source(lf, ReconSettings(method="mlos-mart")), WeightSource)
    ph = PinholeProjector(small.camera, VolumeGrid.from_rig(small), device="cpu")
    assert isinstance(operator_source(ph, ReconSettings(method="mlos-smart")), WeightSource)


@pytest.fixture(scope="module")
def scene(tiny_rig):
    return lightfield_scene(_crop(tiny_rig))


@pytest.mark.parametrize(("settings", "kind"), [
    (ReconSettings(iterations=10, projector="stored"), TRACED),
    (ReconSettings(iterations=10, projector="matrix-free", weight_storage="stored"), TEMPLATE_IMAGES),
    (ReconSettings(iterations=10, projector="matrix-free", weight_storage="on-the-fly"), TEMPLATES),
    (ReconSettings(iterations=10, method="mlos-mart"), "line-of-sight weights"),
])
def test_every_operator_is_the_protocol_and_reconstructs_the_particles(scene, settings, kind):
    """The algorithms see one protocol whichever operator the plan chooses: the same loop reconstructs
    the known particles through each (Q against the truth), and each says what it is."""
    rig, grid, pts, img = scene
    frames = FrameReconstructor(LightFieldProjector(rig.camera, grid, device="cpu"), settings)
    res = frames.reconstruct([img])
    assert res.operator == kind and kind in ALL_KINDS
    assert res.projector == ("matrix-free" if kind in (TEMPLATE_IMAGES, TEMPLATES) else "stored")
    q = metrics.q_recon(res.volume, metrics.truth_volume(grid, pts))
    assert q > 0.5, q
    voxels = frames.eliminate([img > np.median(img)])
    assert isinstance(frames.operator(voxels), Operator)


def test_no_module_but_the_planner_tests_a_concrete_operator_type():
    """The operator is chosen in one place: nothing else asks which concrete class it holds."""
    concrete = r"(LightFieldProjector|PinholeProjector|JointProjector|Projector|Weights|TemplateOperator|" \
               r"MatrixFreeWeights|WeightCache|DrtTemplates)"
    pattern = re.compile(rf"(type\([^)]*\)\s+is\s+(not\s+)?{concrete}\b|isinstance\([^)]*\b{concrete}\b)")
    found = []
    for package in ("lfcore", "lfpiv", "realtime", "calibration", "acquisition", "sim"):
        for path in (ROOT / package).rglob("*.py"):
            if path.name == "plan.py" and path.parent.name == "lfcore":
                continue
            for n, line in enumerate(path.read_text().splitlines(), 1):
                if pattern.search(line):
                    found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert found == []


def test_the_projectors_old_operator_methods_give_the_operators_results(scene):
    """Scripts that called ``projector.forward(weights, e)`` and the like keep their results, warned."""
    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device="cpu")
    wp = proj.wp
    w = proj.weights(proj.all_voxels()[:200], method="drt")
    e = wp.array(np.linspace(0.5, 1.5, 200).astype(np.float32), dtype=float, device="cpu")
    with pytest.warns(DeprecationWarning, match=r"forward\(\) is deprecated since lfpiv 0.1.0: use weights.forward"):
        old = proj.forward(w, e).numpy()
    np.testing.assert_array_equal(old, w.forward(e).numpy())
    with pytest.warns(DeprecationWarning, match="use weights.scatter"):
        np.testing.assert_array_equal(proj.to_volume(w, e), w.to_volume(e))


@pytest.mark.parametrize("kind", ["stored", "templates", "on-the-fly"])
def test_an_operator_restricted_to_some_rows_is_those_rows(scene, device, kind):
    """``restrict``: the operator of some of its voxels projects and updates as the whole one does with
    the other voxels dark (the rows are copied whole; rows made on the fly stay so)."""
    from lfcore.matrix_free import DrtTemplates, TemplateOperator
    from tests.helpers import smart_update

    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    wp = proj.wp
    rng = np.random.default_rng(2)
    vox = wp.array(np.sort(rng.choice(grid.n_voxels, 3000, replace=False)).astype(np.int32), device=device)
    if kind == "stored":
        op = proj.weights(vox, method="drt")
    elif kind == "templates":
        op = TemplateOperator(DrtTemplates(proj), vox)
    else:  # a third of the line-of-sight rows stored, the rest made on the fly
        full = proj.weights(vox, method="los")
        op = proj.weights(vox, method="los", storage="auto", budget_bytes=full.nbytes // 3)
        assert 0 < op.n_stored < op.n_voxels
    keep = np.sort(rng.choice(3000, 700, replace=False)).astype(np.int32)
    sub = op.restrict(wp.array(keep, dtype=wp.int32, device=device))
    assert sub.kind == op.kind and sub.n_voxels == 700
    np.testing.assert_array_equal(sub.voxels.numpy(), vox.numpy()[keep])
    e_full = np.zeros(3000, np.float32)
    e_full[keep] = rng.random(700).astype(np.float32) + 0.1
    a = op.forward(wp.array(e_full, device=device)).numpy()
    b = sub.forward(wp.array(e_full[keep], device=device)).numpy()
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6 * a.max())
    image = wp.array((a * rng.uniform(0.5, 1.5, a.size)).astype(np.float32), device=device)
    ea, eb = wp.array(e_full, device=device), wp.array(e_full[keep], device=device)
    smart_update(op, image, wp.array(a, device=device), ea, 1.0, 1e-3)
    smart_update(sub, image, wp.array(a, device=device), eb, 1.0, 1e-3)
    np.testing.assert_allclose(eb.numpy(), ea.numpy()[keep], rtol=1e-5)
    np.testing.assert_allclose(sub.scatter(eb).numpy(), op.scatter(ea).numpy(), rtol=1e-5)  # the others stay 0


def test_dark_voxels_leave_the_operator_at_the_same_quality(scene, device):
    """Pruning (ReconSettings.prune): the voxels MART leaves dark stop being iterated; the known
    particles are reconstructed as well as with every voxel to the end, by far fewer voxels."""
    rig, grid, pts, img = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    truth = metrics.truth_volume(grid, pts)
    every = FrameReconstructor(proj, ReconSettings.chapter(iterations=60, projector="stored")).reconstruct([img])
    pruned = FrameReconstructor(proj, ReconSettings(iterations=60, projector="stored")).reconstruct([img])
    assert every.final_voxels == every.active_voxels == pruned.active_voxels
    assert pruned.final_voxels < 0.5 * pruned.active_voxels
    q_every, q_pruned = metrics.q_recon(every.volume, truth), metrics.q_recon(pruned.volume, truth)
    assert q_every > 0.5 and q_pruned >= q_every - 0.01, (q_every, q_pruned)
    # the voxels left are the bright ones: what pruning took held under 1% of the light
    assert pruned.volume.sum() == pytest.approx(every.volume.sum(), rel=0.02)
    with pytest.raises(ValueError, match="prune must be from 0"):
        ReconSettings(prune=1.5)
    with pytest.raises(ValueError, match="prune_every must be 1 or more"):
        ReconSettings(prune_every=0)
