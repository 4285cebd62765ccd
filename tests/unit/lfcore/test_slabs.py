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
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import ReconSettings, reconstruct
from lfcore.render import LightFieldRenderer
from lfcore.slabs import SlabReconstructor, plan_slabs, slab_halo, slabs_for_budget
from lfcore.volume import VolumeGrid


def _images(rig, ppm=0.3, device="cpu"):
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(5))
    cfg = rig.render.model_copy(update={"rays_per_particle": 20_000})
    return [LightFieldRenderer(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(
                pts, 50_000.0, seed=1 + i)
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
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
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
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    images = _images(tiny_rig, device=device)
    for smooth in (1.0, 0.0):  # a halo of 3 planes over slabs of 1 to 2; none at all
        settings = ReconSettings(iterations=10, smooth=smooth)
        want = reconstruct(proj, images, settings).volume
        got, _ = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 20))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))


@pytest.mark.parametrize(("rig_file", "method"), [("mixed_cameras.toml", "drt-mart"),
                                                 ("tomo_4_cameras.toml", "mlos-smart")])
def test_pinhole_and_mixed_rigs_by_slabs(device, rig_file, method):
    from lfcore.plan import projector_for
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
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    images = _images(tiny_rig, device=device)
    settings = ReconSettings(iterations=5, **options)
    want = reconstruct(proj, images, settings)
    got, res = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 3))
    assert res.projector == want.projector and res.on_the_fly_voxels == want.on_the_fly_voxels
    # the operator's memory as in memory: the templates (one set for every slab) counted once
    assert abs(res.weight_bytes - want.weight_bytes) <= 0.01 * want.weight_bytes, (res.weight_bytes, want.weight_bytes)
    assert want.volume.max() > 0
    np.testing.assert_allclose(got, want.volume, rtol=1e-5, atol=1e-5 * float(want.volume.max()))


def _slab_rows(weights, first: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each voxel's (pixels, weights) row, keyed by its box index (``first`` added to a slab's)."""
    offs, pix, w = weights.to_numpy()
    vox = weights.voxels.numpy()
    return {int(v) + first: (pix[a:b], w[a:b]) for v, a, b in zip(vox, offs[:-1], offs[1:], strict=True)}


@pytest.mark.parametrize("kind", ["drt", "los", "templates", "pinhole"])
def test_a_slabs_voxels_are_the_boxs_to_the_bit(tiny_rig, device, kind):
    """Projector.planes numbers a slab's voxels from its first plane; each has the box voxel's centre
    to the bit, so its weights (ray-traced, line of sight, the templates' images, a pinhole camera's)
    and its elimination are the box's."""
    from lfcore.matrix_free import DrtTemplates, TemplateOperator
    from lfcore.plan import projector_for
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    if kind == "pinhole":
        rig = load_rig(EXAMPLES / "tomo_4_cameras.toml")
        rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (0.8, 0.8, 0.8)})})
    else:
        d = tiny_rig.to_dict()
        d["volume"].update(size_mm=[0.5, 0.4, 1.2])
        d["camera"][0].update(mla_rotation_deg=2.5, mla_offset_um=[6.0, -9.0])
        rig = type(tiny_rig).from_dict(d)
    grid = VolumeGrid.from_rig(rig)
    box = projector_for(rig.camera, grid, device=device)
    wp = box.wp
    z0, z1 = 4, 9
    slab = box.planes(z0, z1)
    plane = grid.shape[1] * grid.shape[2]
    assert slab.grid.shape == (z1 - z0, *grid.shape[1:]) and slab.grid.n_voxels == (z1 - z0) * plane
    assert slab.box is box.box and slab.z0 == z0 and box.planes(1, 10).planes(3, 8).z0 == z0  # slabs of slabs
    local = np.arange(0, slab.grid.n_voxels, 7, dtype=np.int32)
    vox_slab = wp.array(local, dtype=wp.int32, device=device)
    vox_box = wp.array(local + z0 * plane, dtype=wp.int32, device=device)
    if kind == "templates":
        t_box = DrtTemplates(box)
        a = TemplateOperator(t_box, vox_box).expanded()
        b = TemplateOperator(t_box.on(slab), vox_slab).expanded()
        with pytest.raises(ValueError, match="another box"):
            t_box.on(LightFieldProjector(rig.camera, grid.planes(0, 5), device=device))
    else:
        method = "los" if kind in ("los", "pinhole") else "drt"
        a, b = box.weights(vox_box, method=method), slab.weights(vox_slab, method=method)
    rows_a, rows_b = _slab_rows(a, 0), _slab_rows(b, z0 * plane)
    assert rows_a.keys() == rows_b.keys() and a.nnz == b.nnz > 0
    for v, (pix, w) in rows_a.items():
        np.testing.assert_array_equal(rows_b[v][0], pix)
        np.testing.assert_array_equal(rows_b[v][1], w)
    # the slab's elimination keeps the box's voxels of its planes
    rng = np.random.default_rng(4)
    lit = [rng.random((c.sensor_px[1], c.sensor_px[0])) < 0.6 for c in rig.camera]
    kept_box = box.eliminate(lit).numpy()
    kept_box = kept_box[(kept_box >= z0 * plane) & (kept_box < z1 * plane)]
    np.testing.assert_array_equal(slab.eliminate(lit).numpy() + z0 * plane, kept_box)
    with pytest.raises(ValueError, match="not a range"):
        box.planes(5, 5)


def test_a_box_past_the_index_limit_is_reconstructed_in_slabs(tiny_rig, device, monkeypatch):
    """A box of more voxels than int32 indices number (the chapter's 5.5-G-voxel dual-camera box;
    here the limit lowered to 12 planes of the tiny box) has no in-memory reconstruction, while its
    slabs, each numbering its own voxels, give the volume the box gives below the limit."""
    import lfcore.operator as projector_module
    from lfcore.reconstruct import FrameReconstructor
    from lfcore.slabs import deepest_slab

    grid = VolumeGrid.from_rig(tiny_rig)  # 82 x 68 x 29 voxels
    images = _images(tiny_rig, device=device)
    settings = ReconSettings(iterations=10, projector="matrix-free")
    want = reconstruct(LightFieldProjector(tiny_rig.camera, grid, device=device), images, settings)
    plane = grid.shape[1] * grid.shape[2]
    monkeypatch.setattr(projector_module, "INDEX_LIMIT", 12 * plane + 1)
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)  # the box's projector still serves its slabs
    with pytest.raises(MemoryBudgetError, match="depth slabs"):
        FrameReconstructor(proj, settings)
    with pytest.raises(MemoryBudgetError, match="depth slabs"):
        proj.eliminate([np.ones((c.sensor_px[1], c.sensor_px[0]), bool) for c in tiny_rig.camera])
    assert deepest_slab(grid, halo=2) == 8
    assert slabs_for_budget(grid, 10**12, halo=2) == 4  # whatever the memory: slabs of 8 planes at most
    with pytest.raises(ValueError, match="int32"):  # 10 planes and a halo of 2 + 2 are 14 > 12
        SlabReconstructor(proj, settings, slabs=plan_slabs(grid.shape[0], 3))
    got, res = _by_slabs(proj, images, settings, plan_slabs(grid.shape[0], 4))
    assert res.slabs == 4 and res.active_voxels == want.active_voxels and res.projector == "matrix-free"
    np.testing.assert_allclose(got, want.volume, rtol=1e-5, atol=1e-5 * float(want.volume.max()))
