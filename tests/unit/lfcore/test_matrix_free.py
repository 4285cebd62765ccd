"""The matrix-free DRT operator against the stored DRT weights (the reference), on every Warp device.

Per voxel, the image the templates make agrees with the stored weights' (correlation >= 0.999,
total light within 0.1%, and within 2e-4 where the cut spots' bilinear shares keep it) on random
voxels of small rigs: hexagonal and square lenslets, a
rotated and offset (fitted) MLA, a fitted camera pose (a fraction of a degree off the grid's z), a
tilted and an oblique camera, and two cameras at 90 degrees (one looking along the grid's x).
Forward projections of random volumes agree within 1e-3, and so do the SMART updates; a
reconstruction's Q_recon is within 0.005 of the stored path's at the same iterations.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import metrics
from lfcore.matrix_free import (
    CUT_SPOT_BYTES,
    IMAGE_FLOOR,
    RIGID_SPOT_BYTES,
    DrtTemplates,
    MatrixFreeUnsupported,
    TemplateOperator,
    applied_by,
    fidelity,
    template_count,
)
from lfcore.projector import LightFieldProjector, MemoryBudgetError
from lfcore.reconstruct import FrameReconstructor, ReconSettings, reconstruct
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from tests.helpers import lightfield_scene, smart_update


def _small(rig: Rig, size_mm=(0.5, 0.4, 1.2), cameras: list | None = None, **camera_changes) -> Rig:
    """The tiny rig's optics around a smaller box (a few thousand voxels), cameras changed."""
    d = rig.to_dict()
    d["volume"].update(size_mm=list(size_mm))
    d["camera"][0].update(camera_changes)
    if cameras:
        d["camera"] += [dict(d["camera"][0], **c) for c in cameras]
    return Rig.from_dict(d)


VARIANTS = {
    "hex": {},
    "square": {"mla_grid": "square"},
    "fitted": {"mla_rotation_deg": 2.5, "mla_offset_um": [6.0, -9.0]},
    "dual": {"cameras": [{"name": "cam1", "rotation_deg": [0.0, 90.0, 0.0]}], "size_mm": (0.3, 0.4, 0.5)},
    # a fitted pose: the optical axis a fraction of a degree off the grid's z, the MLA rotated and offset
    "fitted-pose": {"rotation_deg": [0.3, -0.2, 0.1], "mla_rotation_deg": 1.5, "mla_offset_um": [-4.0, 7.0]},
    # tilted and rolled: a voxel's depth moves by about half its extent across the box
    "tilted": {"rotation_deg": [3.0, 2.0, 10.0]},
    "oblique": {"rotation_deg": [20.0, 0.0, 0.0]},
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_voxel_images_match_the_stored_weights(tiny_rig, device, variant):
    opts = dict(VARIANTS[variant])
    rig = _small(tiny_rig, **opts)
    grid = VolumeGrid.from_rig(rig)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    templates = DrtTemplates(proj)
    assert template_count(proj) == templates.n_templates
    vox = np.random.default_rng(7).choice(grid.n_voxels, 60, replace=False)
    f = fidelity(proj, vox, templates)
    assert f["correlation"].min() >= 0.999, f["correlation"].min()
    assert np.abs(f["light"] - 1.0).max() <= 1e-3, np.abs(f["light"] - 1.0).max()


def test_templates_keep_each_voxels_light(tiny_rig, device):
    """A cut spot's share is bilinear in probes whose sum over a sub-aperture's parts is its whole
    light, so a voxel's light is kept far closer than the 0.1% goal (the fixed-point probes and
    the spots crossing the sensor's edges are what is left)."""
    rig = _small(tiny_rig, **VARIANTS["fitted"])
    grid = VolumeGrid.from_rig(rig)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    t = DrtTemplates(proj)
    assert t.n_rigid > 0 and t.n_cut > 0 and t.n_rigid + t.n_cut == t.n_spots
    assert t.tables.rigid.numpy().itemsize == RIGID_SPOT_BYTES and t.tables.cut.numpy().itemsize == CUT_SPOT_BYTES
    assert t.nbytes == RIGID_SPOT_BYTES * t.n_rigid + CUT_SPOT_BYTES * t.n_cut + 8 * (t.n_templates + 1)
    vox = np.random.default_rng(11).choice(grid.n_voxels, 40, replace=False)
    f = fidelity(proj, vox, t)
    assert np.abs(f["light"] - 1.0).max() <= 2e-4, np.abs(f["light"] - 1.0).max()


@pytest.fixture(scope="module")
def scene(tiny_rig):
    """A small tiny-rig box, its particles and image (rendered on the CPU)."""
    return lightfield_scene(_small(tiny_rig))


def test_forward_projection_and_update_match_the_stored_weights(scene, device):
    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    wp = proj.wp
    rng = np.random.default_rng(1)
    vox_np = np.sort(rng.choice(grid.n_voxels, grid.n_voxels // 3, replace=False)).astype(np.int32)
    vox = wp.array(vox_np, dtype=wp.int32, device=device)
    stored = proj.weights(vox, method="drt")
    mf = TemplateOperator(DrtTemplates(proj), vox)
    e_np = rng.random(len(vox_np)).astype(np.float32)
    a = stored.forward(wp.array(e_np, device=device)).numpy()
    b = mf.forward(wp.array(e_np, device=device)).numpy()
    assert np.linalg.norm(b - a) <= 1e-3 * np.linalg.norm(a)
    # one SMART update from the same projection: the same steps (the weighted mean log ratios)
    image = wp.array((a * rng.uniform(0.5, 1.5, a.size)).astype(np.float32), device=device)
    proj_a = wp.array(a, device=device)
    ea, eb = wp.array(e_np, device=device), wp.array(e_np, device=device)
    smart_update(stored, image, proj_a, ea, 1.0, 1e-3)
    smart_update(mf, image, proj_a, eb, 1.0, 1e-3)
    step_a, step_b = np.log(ea.numpy() / e_np), np.log(eb.numpy() / e_np)
    assert np.linalg.norm(step_b - step_a) <= 1e-2 * np.linalg.norm(step_a)


def _same_operator(proj, reference, other, rng) -> None:
    """``other`` projects random intensities and updates them (one SMART step) as ``reference``
    does, up to float summation order."""
    wp, device = proj.wp, proj.device
    e_np = rng.random(reference.n_voxels).astype(np.float32)
    a = reference.forward(wp.array(e_np, device=device)).numpy()
    b = other.forward(wp.array(e_np, device=device)).numpy()
    np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6 * a.max())
    image = wp.array((a * rng.uniform(0.5, 1.5, a.size)).astype(np.float32), device=device)
    proj_a = wp.array(a, device=device)
    ea, eb = wp.array(e_np, device=device), wp.array(e_np, device=device)
    smart_update(reference, image, proj_a, ea, 1.0, 1e-3)
    smart_update(other, image, proj_a, eb, 1.0, 1e-3)
    np.testing.assert_allclose(eb.numpy(), ea.numpy(), rtol=1e-5)


def test_launches_visit_the_voxels_of_one_template_together(scene, device):
    """The launch order is a permutation that groups the voxels by their template in the first
    view; projections and updates do not depend on it (up to float summation order)."""
    from lfcore._kernels import matrix_free as km

    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    wp = proj.wp
    rng = np.random.default_rng(5)
    vox_np = np.sort(rng.choice(grid.n_voxels, grid.n_voxels // 4, replace=False)).astype(np.int32)
    vox = wp.array(vox_np, dtype=wp.int32, device=device)
    t = DrtTemplates(proj)
    mf = TemplateOperator(t, vox)
    order = mf.order().numpy()
    assert np.array_equal(np.sort(order), np.arange(len(vox_np)))
    key = wp.empty(len(vox_np), dtype=wp.int32, device=device)
    wp.launch(km.template_key, dim=len(vox_np), inputs=[proj._grid, proj.views, t.plans, t.tables, vox, key],
              device=device)
    k = key.numpy()[order]
    assert np.all(np.diff(k) >= 0) and k.max() >= 0
    own = TemplateOperator(t, vox)
    own._order = wp.array(np.arange(len(vox_np), dtype=np.int32), dtype=wp.int32, device=device)
    _same_operator(proj, own, mf, rng)


def test_reconstruction_quality_matches_the_stored_path(scene, device):
    rig, grid, pts, img = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    truth = metrics.truth_volume(grid, pts)
    base = ReconSettings(iterations=20)
    stored = reconstruct(proj, [img], base)
    mf = reconstruct(proj, [img], ReconSettings(iterations=20, projector="matrix-free", weight_storage="on-the-fly"))
    assert stored.projector == "stored" and mf.projector == "matrix-free"
    assert mf.active_voxels == stored.active_voxels  # the same elimination
    assert mf.nnz == 0 and 0 < mf.weight_bytes < 64 * 2**20
    q_stored, q_mf = metrics.q_recon(stored.volume, truth), metrics.q_recon(mf.volume, truth)
    assert q_stored > 0.3
    assert abs(q_mf - q_stored) <= 0.005, (q_mf, q_stored)
    # the templates' images stored (where they fit: here) reconstruct the same volume as the templates
    # applied in every iteration, with as many entries as the ray-traced weights give, to a few percent
    ex = reconstruct(proj, [img], ReconSettings(iterations=20, projector="matrix-free"))
    assert ex.projector == "matrix-free" and abs(ex.nnz - stored.nnz) <= 0.1 * stored.nnz, (ex.nnz, stored.nnz)
    assert np.abs(ex.volume - mf.volume).max() <= 1e-3 * mf.volume.max()


def test_the_templates_images_stored_apply_the_same_operator(scene, device):
    """The expansion (once per frame, no ray tracing) gives stored weights whose projection and
    update are the templates' own, and its images are the stored weights' to the fidelity goals."""
    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    wp = proj.wp
    rng = np.random.default_rng(2)
    vox_np = np.sort(rng.choice(grid.n_voxels, grid.n_voxels // 3, replace=False)).astype(np.int32)
    vox = wp.array(vox_np, dtype=wp.int32, device=device)
    mf = TemplateOperator(DrtTemplates(proj), vox)
    ex = mf.expanded(floor=0.0)  # no faint entries dropped: the templates' operator exactly
    assert ex.from_templates and applied_by(ex) == "matrix-free" and applied_by(proj.weights(vox[:5])) == "stored"
    assert ex.n_voxels == len(vox_np) and ex.nnz <= mf.entries_per_voxel() * len(vox_np) * 1.2
    _same_operator(proj, mf, ex, rng)
    # each voxel's merged entries are its image (the dense check's own)
    offs, pix, w = ex.to_numpy()
    dense = np.zeros((len(vox_np), proj.n_pixels), dtype=np.float64)
    np.add.at(dense, (np.repeat(np.arange(len(vox_np)), np.diff(offs)), pix), w)
    np.testing.assert_allclose(dense[:50], mf.images()[:50], rtol=1e-5, atol=1e-7)
    # merged (one entry per pixel) and sorted by pixel, as the stored build leaves its own
    assert all(np.all(np.diff(pix[offs[i]:offs[i + 1]]) > 0) for i in range(len(vox_np)))


def _rows(w) -> list[tuple[np.ndarray, np.ndarray]]:
    offs, pix, val = w.to_numpy()
    return [(pix[offs[i]:offs[i + 1]], val[offs[i]:offs[i + 1]].astype(np.float64)) for i in range(len(offs) - 1)]


def test_the_stored_images_drop_their_faint_entries_and_keep_each_voxels_light(scene, device):
    """By default the images lose their merged entries at or below IMAGE_FLOOR; each voxel's
    others are its exact image's, scaled so that its light is kept. The GPU's form of the merge
    (raw entries sorted and merged, run here on this device) gives the CPU's entries."""
    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    rng = np.random.default_rng(4)
    vox_np = np.sort(rng.choice(grid.n_voxels, grid.n_voxels // 3, replace=False)).astype(np.int32)
    mf = TemplateOperator(DrtTemplates(proj), proj.wp.array(vox_np, dtype=proj.wp.int32, device=device))
    exact = mf.expanded(floor=0.0)
    floor = 1e-4  # above IMAGE_FLOOR, so that this small box's voxels lose some entries
    assert IMAGE_FLOOR < floor
    pruned = mf.expanded(floor=floor)
    assert 0.5 * exact.nnz < pruned.nnz < exact.nnz, (pruned.nnz, exact.nnz)
    assert pruned.nnz <= mf.expanded().nnz <= exact.nnz
    lost = 0
    for (pe, we), (pp, wq) in zip(_rows(exact), _rows(pruned), strict=True):
        keep = we > floor
        np.testing.assert_array_equal(pp, pe[keep])
        if keep.any():
            np.testing.assert_allclose(wq.sum(), we.sum(), rtol=1e-5)  # the voxel's light kept
            np.testing.assert_allclose(wq, we[keep] * (we.sum() / we[keep].sum()), rtol=1e-5)
        lost += (~keep).sum()
    assert lost == exact.nnz - pruned.nnz
    # the raw entries sorted and merged per voxel (the GPU's expansion), here on this device
    merged = proj.builder.merged(mf.voxels, mf._trace, floor=floor)
    assert merged.nnz == pruned.nnz
    for (pa, wa), (pb, wb) in zip(_rows(pruned), _rows(merged), strict=True):
        np.testing.assert_array_equal(pb, pa)
        np.testing.assert_allclose(wb, wa, rtol=1e-5, atol=1e-9)


def test_the_templates_images_are_stored_only_where_they_fit(scene, monkeypatch):
    rig, grid, _, img = scene
    proj = LightFieldProjector(rig.camera, grid, device="cpu")
    big = FrameReconstructor(proj, ReconSettings(iterations=3, projector="matrix-free"))
    fits = big.reconstruct([img])
    assert fits.nnz > 0 and fits.weight_bytes > big._templates.nbytes
    # a budget that holds the templates but not their images: applied from the templates instead
    small = FrameReconstructor(proj, ReconSettings(iterations=3, projector="matrix-free"),
                               budget_bytes=big._templates.nbytes + 12 * proj.n_pixels + 8 * grid.n_voxels
                               + 4 * fits.active_voxels + fits.nnz)
    slow = small.reconstruct([img])
    assert slow.nnz == 0 and slow.projector == "matrix-free"
    assert np.abs(slow.volume - fits.volume).max() <= 1e-3 * fits.volume.max()
    with pytest.raises(MemoryBudgetError):
        FrameReconstructor(proj, ReconSettings(iterations=3, projector="matrix-free", weight_storage="stored"),
                           budget_bytes=small.budget_bytes).reconstruct([img])
    with pytest.raises(ValueError, match="matrix-free projector alone"):
        ReconSettings(weight_storage="on-the-fly", projector="stored")


def test_auto_takes_the_templates_where_stored_weights_do_not_fit(scene, device, monkeypatch):
    rig, grid, _, img = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    frames = FrameReconstructor(proj, ReconSettings(iterations=2))
    assert frames.reconstruct([img]).projector == "stored"

    def too_large(*args, **kwargs):
        raise MemoryBudgetError("the weights need 1 TiB")

    monkeypatch.setattr(proj, "weights", too_large)
    done = frames.reconstruct([img])
    assert done.projector == "matrix-free" and done.volume.max() > 0
    # stored weights asked for are refused as before
    with pytest.raises(MemoryBudgetError):
        FrameReconstructor(proj, ReconSettings(iterations=2, projector="stored")).reconstruct([img])


def test_auto_takes_the_templates_images_where_they_cost_less_than_tracing(scene, device, monkeypatch):
    """projector auto per frame: the small box's few thousand active voxels cost less to trace
    than its templates to build; with templates made cheap (a frame of many more voxels than
    templates, as on the Mc crop) the templates' images; with the weight cache holding the
    frame's voxels nothing is left to trace, so its stored weights."""
    import lfcore.plan as recon
    from lfcore.weight_cache import WeightCache

    rig, grid, _, img = scene
    proj = LightFieldProjector(rig.camera, grid, device=device)
    settings = ReconSettings(iterations=2)
    frames = FrameReconstructor(proj, settings)
    traced = frames.reconstruct([img])
    n, n_templates = traced.active_voxels, template_count(proj)
    assert n < recon.TEMPLATE_TRACES * n_templates  # so tracing pays here
    assert traced.projector == "stored" and frames._templates is None
    # templates that cost nothing to build: the images are cheaper than tracing every voxel
    monkeypatch.setattr(recon, "TEMPLATE_TRACES", 0.0)
    imager = FrameReconstructor(proj, settings)
    imaged = imager.reconstruct([img])
    assert imaged.projector == "matrix-free" and imaged.nnz > 0  # the images stored, not applied
    assert imaged.active_voxels == n
    assert np.abs(imaged.volume - traced.volume).max() <= 0.05 * traced.volume.max()
    # room for the templates but not their images beside them: the templates let go, the traced weights
    held = imager._templates.nbytes
    assert traced.weight_bytes < held
    tight = FrameReconstructor(proj, settings, budget_bytes=12 * proj.n_pixels + 4 * n + 8 * grid.n_voxels + held
                               + (imaged.weight_bytes - held) // 2)
    assert tight.reconstruct([img]).projector == "stored" and tight._templates is None
    # and the next frame does not build the templates again only to find their images too big
    built = []
    monkeypatch.setattr(recon, "DrtTemplates", lambda *a, **k: built.append(1))
    assert tight.reconstruct([img]).projector == "stored" and not built
    # the same frame again with its weights cached: no voxel left to trace, so the cache serves
    cache = WeightCache(proj)
    cached = FrameReconstructor(proj, settings, cache=cache)
    monkeypatch.setattr(recon, "TEMPLATE_TRACES", 1e9)
    served = cached.reconstruct([img])
    assert served.projector == "stored" and cache.n_cached >= n
    # its memory counts the cache's pool, which keeps a second copy of every traced row
    assert cache.device_bytes >= 8 * served.nnz and served.weight_bytes >= 8 * served.nnz + cache.device_bytes
    monkeypatch.setattr(recon, "TEMPLATE_TRACES", 0.0)
    vox = proj.wp.array(np.arange(grid.n_voxels, dtype=np.int32), device=device)
    assert cache.uncached(vox) == grid.n_voxels - cache.n_cached
    again = cached.reconstruct([img])
    assert again.projector == "stored" and cached._templates is None
    # cameras with no templates (a pinhole camera's) never take them
    def no_templates(projector):
        raise MatrixFreeUnsupported("pinhole cameras have no templates")

    monkeypatch.setattr(recon, "template_count", no_templates)
    assert not FrameReconstructor(proj, settings).templates_pay(vox)


def test_the_template_count_is_the_builds(scene):
    rig, grid, _, _ = scene
    proj = LightFieldProjector(rig.camera, grid, device="cpu")
    assert template_count(proj) == DrtTemplates(proj).n_templates


def test_settings_and_geometry_that_have_no_matrix_free_form(tiny_rig):
    with pytest.raises(ValueError, match="drt-mart"):
        ReconSettings(method="mart", projector="matrix-free")
    with pytest.raises(ValueError, match="simultaneous"):
        ReconSettings(form="sequential", relaxation=1.0, projector="matrix-free")
    with pytest.raises(ValueError, match="projector must be"):
        ReconSettings(projector="fast")


def test_a_camera_off_the_grid_axes_takes_the_sampled_depth_nearest_its_voxels(tiny_rig):
    """Off the grid axes, a depth plane of the grid is no depth of the camera: the templates are made
    at DEPTH_SAMPLES_PER_VOXEL evenly spaced camera depths per voxel depth extent over the box, and
    a voxel takes the nearest (a grid-aligned camera keeps one template depth per grid plane)."""
    from lfcore.matrix_free import DEPTH_SAMPLES_PER_VOXEL

    aligned = _small(tiny_rig)
    grid = VolumeGrid.from_rig(aligned)
    flat = DrtTemplates(LightFieldProjector(aligned.camera, grid, device="cpu"))
    assert len(flat.depth_phase) == grid.shape[0]
    rig = _small(tiny_rig, rotation_deg=[0.3, -0.2, 0.1])
    t = DrtTemplates(LightFieldProjector(rig.camera, grid, device="cpu"))
    # the box's depth range, a little deeper for the tilt, sampled DEPTH_SAMPLES_PER_VOXEL times finer
    assert DEPTH_SAMPLES_PER_VOXEL * (grid.shape[0] - 1) < len(t.depth_phase) <= DEPTH_SAMPLES_PER_VOXEL * (
        grid.shape[0] + 1) + 1


def test_pinhole_and_mixed_rigs_have_no_matrix_free_form():
    from pathlib import Path

    from lfcore.plan import projector_for
    from lfpiv.rigfile import load_rig

    # a mixed rig's joint projector is a Projector too, but its pinhole cameras have no lenslets
    rig = load_rig(Path(__file__).resolve().parents[3] / "examples" / "mixed_cameras.toml")
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (0.3, 0.3, 0.3)})})
    grid = VolumeGrid.from_rig(rig)
    for cams in (rig.camera, [c for c in rig.camera if c.kind == "pinhole"]):
        with pytest.raises(MatrixFreeUnsupported, match="light-field cameras alone"):
            DrtTemplates(projector_for(cams, grid, device="cpu"))
        with pytest.raises(MatrixFreeUnsupported, match="light-field cameras alone"):
            template_count(projector_for(cams, grid, device="cpu"))
