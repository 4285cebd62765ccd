"""Depth slabs run the in-memory path's whole plan: the ``fast`` protocol's coarse-to-fine elimination,
line-of-sight first iterations and ordered subsets, each alone and all together, on every device Warp finds.

Known truth: the in-memory FrameReconstructor's volume with the same settings. The slabs reorder only
the sums over voxels (each slab's projection summed into the whole volume's), so the volume, the voxels
kept at every stage, the iterations the stopping rule runs and the operators are the in-memory ones
(volumes to float round-off).
"""

from __future__ import annotations

import numpy as np
import pytest

import lfcore.coarse as coarse_grids
from lfcore.particles import particle_count, seed_particles
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import CONVERGED, FrameReconstructor, protocol_settings
from lfcore.render import LightFieldRenderer
from lfcore.slabs import SlabReconstructor, plan_slabs
from lfcore.volume import VolumeGrid

#: Below the tiny rig's 161,704 voxels, so that coarse-to-fine elimination runs on its box.
SMALL_BOX = 100_000
#: Each stage of the ``fast`` protocol alone over the plain plan (elimination, one operator, SMART with
#: the pruning and the stopping rule), and all of them. No warm start: depth slabs leave it out.
STAGES = {
    "fast": {},
    "subsets": {"los_iterations": 0, "coarse": 1},
    "line-of-sight first": {"subsets": 1, "coarse": 1},
    "coarse": {"subsets": 1, "los_iterations": 0},
    "plain": {"subsets": 1, "los_iterations": 0, "coarse": 1},
}
RTOL = 1e-4


def _settings(stage: str):
    # at most 60 iterations: the whole plan stops by the rule at about 50 on this scene
    return protocol_settings("fast", iterations=60, warm_start=False, **STAGES[stage])


@pytest.fixture(scope="module")
def scene(tiny_rig):
    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.3), np.random.default_rng(5))
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000})
    images = [LightFieldRenderer(c, cfg, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu").frame(
        pts, 50_000.0, seed=1 + i) for i, c in enumerate(tiny_rig.camera)]
    return tiny_rig, VolumeGrid.from_rig(tiny_rig), images


_IN_MEMORY: dict = {}


def _in_memory(scene, device, stage):
    rig, grid, images = scene
    if (device, stage) not in _IN_MEMORY:
        proj = LightFieldProjector(rig.camera, grid, device=device)
        _IN_MEMORY[device, stage] = FrameReconstructor(proj, _settings(stage)).reconstruct(images)
    return _IN_MEMORY[device, stage]


def _by_slabs(scene, device, stage, n):
    rig, grid, images = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    out = np.full(grid.shape, np.nan, np.float32)
    lines = []

    def write(z0, z1, planes):
        out[z0:z1] = planes

    slabs = plan_slabs(grid.shape[0], n)
    res = SlabReconstructor(proj, _settings(stage), slabs=slabs).reconstruct(images, write=write, log=lines.append)
    return out, res, lines


@pytest.mark.parametrize("n_slabs", [2, 3])
@pytest.mark.parametrize("stage", ["fast", "subsets", "line-of-sight first", "coarse"])
def test_slabs_run_the_fast_plan_to_the_in_memory_volume(scene, device, monkeypatch, stage, n_slabs):
    monkeypatch.setattr(coarse_grids, "COARSE_MIN_VOXELS", SMALL_BOX)
    want = _in_memory(scene, device, stage)
    got, res, _ = _by_slabs(scene, device, stage, n_slabs)
    assert want.volume.max() > 0 and not np.isnan(got).any()
    # the same voxels at every stage, the same operators, the same iterations and reason to stop
    assert (res.slabs, res.active_voxels, res.final_voxels, res.nnz) == (
        n_slabs, want.active_voxels, want.final_voxels, want.nnz)
    assert (res.iterations, res.stopped, res.operator) == (want.iterations, want.stopped, want.operator)
    np.testing.assert_allclose(got, want.volume, rtol=RTOL, atol=RTOL * float(want.volume.max()))


@pytest.mark.parametrize("stage", ["fast", "subsets", "line-of-sight first", "coarse"])
def test_each_stage_changes_the_volume(scene, device, monkeypatch, stage):
    """The known truth above is not the plain plan's volume: each stage ran (in memory as in slabs)."""
    monkeypatch.setattr(coarse_grids, "COARSE_MIN_VOXELS", SMALL_BOX)
    plain, want = _in_memory(scene, device, "plain"), _in_memory(scene, device, stage)
    assert np.abs(want.volume - plain.volume).max() > 100 * RTOL * float(want.volume.max())
    if stage in ("fast", "coarse"):  # the coarse grid's bright voxels only: fewer tested and kept
        assert want.active_voxels < 0.8 * plain.active_voxels, (want.active_voxels, plain.active_voxels)
    if stage in ("fast", "line-of-sight first"):
        assert want.operator == "line-of-sight weights, then traced weights"
        assert want.nnz < 0.8 * plain.nnz  # DRT weights for the voxels still bright
    assert want.stopped == CONVERGED or want.iterations == 60


def test_the_stage_log_of_the_fast_plan(scene, device, monkeypatch):
    monkeypatch.setattr(coarse_grids, "COARSE_MIN_VOXELS", SMALL_BOX)
    _, res, lines = _by_slabs(scene, device, "fast", 3)
    assert lines[0].startswith("coarse grid (3x coarser, 6,440 voxels): "), lines
    assert all(line.startswith(f"slab {i}/3 (planes ") for i, line in zip((1, 2, 3), lines[1:4], strict=True)), lines
    assert lines[4].startswith(f"start (one projection of {res.active_voxels:,} voxels)"), lines
    assert "iteration 1/60" in lines[5] and "iteration 3/60" in lines[7], lines
    # the DRT stage's start and first iterations, and every tenth, are logged too (an L frame runs for hours)
    assert sum(line.startswith("start (one projection of") for line in lines) == 2, lines
    assert "iteration 21/60" in " ".join(lines) and "iteration 10/60" in " ".join(lines), lines
    drt = [line for line in lines if "still bright" in line]
    assert len(drt) == 3 and all("traced" in line for line in drt), lines
    assert any(line.startswith(f"{res.iterations} iterations ({res.stopped}), {res.final_voxels:,} voxels left")
               for line in lines), lines
    assert lines[-1].startswith("volume smoothed and written"), lines
    assert res.peak_bytes > 0


def test_a_slabs_coarse_children_and_parents_are_the_boxs():
    """The children of coarse voxels in a slab, numbered from its first plane, are the box's children in
    its planes; their parents are the box's."""
    grid = VolumeGrid(shape=(29, 17, 13), voxel_mm=(0.1, 0.1, 0.1), origin_mm=(0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    coarse = np.unique(rng.integers(0, 10 * 6 * 5, 60))
    whole = coarse_grids.children(coarse, grid, 3)
    plane = 17 * 13
    parts = []
    for z0, z1 in ((0, 7), (7, 8), (8, 20), (20, 29)):
        mine = coarse_grids.children(coarse, grid, 3, z0=z0, z1=z1)
        assert mine.dtype == np.int32 and (mine < (z1 - z0) * plane).all()
        np.testing.assert_array_equal(coarse_grids.parents(mine, grid, 3, z0=z0),
                                      coarse_grids.parents(mine.astype(np.int64) + z0 * plane, grid, 3))
        parts.append(mine.astype(np.int64) + z0 * plane)
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_the_slab_budget_holds_the_coarse_grid():
    """--slabs auto's slabs fit the budget, and so must the coarse grid's elimination buffers (20 bytes a
    coarse voxel), which exist before the slabs' own: a deep box whose thin slabs fit but whose coarse grid
    does not is refused in one line that names the fix."""
    from lfcore.device import MemoryBudgetError
    from lfcore.slabs import BYTES_PER_SLAB_VOXEL, slabs_for_budget

    grid = VolumeGrid(shape=(400, 100, 100), voxel_mm=(0.1, 0.1, 0.1), origin_mm=(0.0, 0.0, 0.0))
    budget = 5_000_000  # slabs of a few planes fit; the coarse grid at 2 (500,000 voxels: 10 MB) does not
    n = slabs_for_budget(grid, budget, halo=2)
    assert n == slabs_for_budget(grid, budget, halo=2, coarse=3)  # at 3: 20 * 34 * 34 * 134 bytes = 3.1 MB fit
    assert BYTES_PER_SLAB_VOXEL * (-(-400 // 2)) * 50 * 50 > budget
    with pytest.raises(MemoryBudgetError, match="the coarse grid of --coarse 2 .* use --coarse 1 or a coarser --pvr"):
        slabs_for_budget(grid, budget, halo=2, coarse=2)
