"""Depth-slab reconstruction (lfcore.slabs) against the in-memory path, on every device Warp finds.

Known truth: the in-memory FrameReconstructor's volume. A box split into slabs, each eliminated,
weighted and written on its own while every iteration sums all the slabs' projections, must give
the same volume to float round-off (the sum over voxels only reordered).
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.device import MemoryBudgetError
from lfcore.particles import particle_count, seed_particles
from lfcore.projector import Projector
from lfcore.reconstruct import ReconSettings, reconstruct
from lfcore.render import LightFieldRenderer
from lfcore.slabs import SlabReconstructor, plan_slabs, slab_halo, slabs_for_budget
from lfcore.volume import VolumeGrid


def _images(rig, ppm=0.3, device="cpu"):
    pts = seed_particles(rig.volume, particle_count(rig, ppm), np.random.default_rng(5))
    cfg = rig.render.model_copy(update={"rays_per_particle": 20_000})
    return [LightFieldRenderer(c, cfg, rig.laser.wavelength_nm, device=device).frame(pts, 50_000.0, seed=1 + i)
            for i, c in enumerate(rig.camera)]


def _by_slabs(proj, images, settings, slabs):
    out = np.full(proj.grid.shape, np.nan, np.float32)
    written, lines = [], []

    def write(z0, z1, planes):
        written.append((z0, z1))
        out[z0:z1] = planes

    res = SlabReconstructor(proj, settings, slabs=slabs).reconstruct(images, write=write, log=lines.append)
    assert written == [(s.z0, s.z1) for s in slabs]  # front to back, each slab once
    # one line per stage: each slab's elimination and operator, the start, the iterations, the writing
    n = len(slabs)
    assert [f"slab {i + 1}/{n} (planes {s.z0}-{s.z1 - 1})" in line for i, (s, line) in
            enumerate(zip(slabs, lines, strict=False))] == [True] * n, lines
    if res.active_voxels:
        assert lines[n].startswith("start (one projection of") and f"iteration {settings.iterations}/" in lines[-2]
    assert lines[-1].startswith("volume smoothed and written"), lines
    return out, res


@pytest.mark.parametrize("method", ["drt-mart", "mlos-mart", "mart"])
def test_three_slabs_give_the_in_memory_volume(tiny_rig, device, method):
    grid = VolumeGrid.from_rig(tiny_rig)  # 82 x 68 x 29 voxels
    proj = Projector(tiny_rig.camera, grid, device=device)
    images = _images(tiny_rig, device=device)
    settings = ReconSettings(method=method, iterations=8 if method == "mart" else 20)
    want = reconstruct(proj, images, settings)
    slabs = plan_slabs(grid.shape[0], 3)
    assert [s.nz for s in slabs] == [10, 9, 10]
    got, res = _by_slabs(proj, images, settings, slabs)
    assert res.slabs == 3 and res.volume.size == 0 and res.peak_bytes > 0
    assert res.active_voxels == want.active_voxels and res.nnz == want.nnz  # the same voxels and weights
    assert want.volume.max() > 0
    np.testing.assert_allclose(got, want.volume, rtol=1e-5, atol=1e-5 * float(want.volume.max()))


def test_slabs_thinner_than_the_smoothing_halo_and_no_smoothing(tiny_rig, device):
    grid = VolumeGrid.from_rig(tiny_rig)
    proj = Projector(tiny_rig.camera, grid, device=device)
    images = _images(tiny_rig, device=device)
    for smooth in (1.0, 0.0):  # a halo of 3 planes over slabs of 1 to 2; none at all
        settings = ReconSettings(iterations=10, smooth=smooth)
        want = reconstruct(proj, images, settings).volume
        got, _ = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 20))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))


@pytest.mark.parametrize(("rig_file", "method"), [("mixed_cameras.toml", "drt-mart"),
                                                 ("tomo_4_cameras.toml", "mlos-smart")])
def test_pinhole_and_mixed_rigs_by_slabs(device, rig_file, method):
    from lfcore.pinhole_projector import projector_for
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / rig_file)
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (0.3, 0.3, 0.3)})})
    grid = VolumeGrid.from_rig(rig)
    proj = projector_for(rig.camera, grid, device=device)
    rng = np.random.default_rng(2)
    images = [(100 + rng.poisson(3.0, (c.sensor_px[1], c.sensor_px[0]))).astype(np.uint16) for c in rig.camera]
    for im in images:  # a few bright spots, so something survives elimination
        im[70:90, 70:90] += 400
    settings = ReconSettings(method=method, iterations=5)
    want = reconstruct(proj, images, settings).volume
    assert want.max() > 0
    got, _ = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 3))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))


def test_planning():
    grid = VolumeGrid(shape=(29, 68, 82), voxel_mm=(0.01, 0.01, 0.05), origin_mm=(0.0, 0.0, 0.0))
    plane = 20 * 68 * 82
    assert slab_halo(ReconSettings(smooth=0.6)) == 2 and slab_halo(ReconSettings(smooth=0.0)) == 0
    assert slabs_for_budget(grid, 10**9, halo=2) == 1
    assert slabs_for_budget(grid, plane * 14, halo=2) == 3  # slabs of 10 planes and their halo of 2 + 2
    with pytest.raises(MemoryBudgetError, match="even a slab one plane deep needs"):
        slabs_for_budget(grid, plane * 4, halo=2)
    assert [(s.z0, s.z1) for s in plan_slabs(5, 2)] == [(0, 2), (2, 5)]
    with pytest.raises(ValueError, match="slabs must be from 1 to 5"):
        plan_slabs(5, 6)
    with pytest.raises(ValueError, match="simultaneous form"):
        SlabReconstructor(None, ReconSettings(form="sequential", relaxation=1.0), slabs=plan_slabs(5, 1))


@pytest.mark.parametrize("options", [{"projector": "matrix-free"},
                                     {"method": "mlos-mart", "weight_storage": "on-the-fly"}])
def test_slabs_with_matrix_free_templates_and_weights_made_on_the_fly(tiny_rig, device, options):
    grid = VolumeGrid.from_rig(tiny_rig)
    proj = Projector(tiny_rig.camera, grid, device=device)
    images = _images(tiny_rig, device=device)
    settings = ReconSettings(iterations=5, **options)
    want = reconstruct(proj, images, settings)
    got, res = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 3))
    assert res.projector == want.projector and res.on_the_fly_voxels == want.on_the_fly_voxels
    # the operator's memory as in memory: the templates (one set for every slab) counted once
    assert abs(res.weight_bytes - want.weight_bytes) <= 0.01 * want.weight_bytes, (res.weight_bytes, want.weight_bytes)
    assert want.volume.max() > 0
    np.testing.assert_allclose(got, want.volume, rtol=1e-5, atol=1e-5 * float(want.volume.max()))
