"""DRT-MART and the MART baseline on the tiny rig, on every device Warp finds.

Known truths: a single particle must come back where it was; a voxel's weights must spread its
light as the optics (the Monte-Carlo renderer) does; dual cameras at 90 degrees must resolve
depth better than one; nothing may appear outside the seeded region.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lfcore import metrics
from lfcore.particles import particle_count, seed_particles
from lfcore.projector import LightFieldProjector, MemoryBudgetError
from lfcore.reconstruct import ReconSettings, estimate_background, reconstruct
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from tests.conftest import tiny_variant
from tests.helpers import smart_update


def _render(rig, pts, seed=1, rays=20_000, device="cpu"):
    cfg = rig.render.model_copy(update={"rays_per_particle": rays})
    return [LightFieldRenderer(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(
                pts, 50_000.0, seed=seed + i)
            for i, c in enumerate(rig.camera)]


def _voxel_index(grid, ix, iy, iz):
    return (iz * grid.shape[1] + iy) * grid.shape[2] + ix


def _voxel_images(proj, renderer, grid, ix, iy, iz, rng, method="drt"):
    """A voxel's projection through its weights, and the renderer's image of the voxel filled
    uniformly with points, both as fractions of its light."""
    w = proj.weights(proj.wp.array([_voxel_index(grid, ix, iy, iz)], dtype=proj.wp.int32, device=proj.device),
                     method=method)
    f = w.forward(proj.wp.array([1.0], dtype=float, device=proj.device)).numpy()
    centre = np.asarray(grid.origin_mm) + np.array([ix, iy, iz]) * np.asarray(grid.voxel_mm)
    pts = centre + (rng.random((100, 3)) - 0.5) * np.asarray(grid.voxel_mm)
    return f, renderer.irradiance(pts, 1000.0, seed=2).ravel() / (100 * 1000.0)


def _seeded_scene(tiny_rig, device):
    """The tiny rig at 0.3 PPM: grid, true particles, image, projector and truth volume."""
    grid = VolumeGrid.from_rig(tiny_rig)
    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.3), np.random.default_rng(3))
    (img,) = _render(tiny_rig, pts, device=device)
    return grid, pts, img, LightFieldProjector(tiny_rig.camera, grid, device=device), metrics.truth_volume(grid, pts)


def _dual_rig(tiny_rig) -> Rig:
    d = tiny_rig.to_dict()
    d["volume"].update(size_mm=[0.8, 0.7, 0.8], pvr=[2.0, 2.0, 2.0])
    side = dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0])
    d["camera"].append(side)
    return Rig.from_dict(d)


@pytest.mark.parametrize("grid_kind", ["hex", "square"])
@pytest.mark.parametrize("point", [(0.05, -0.03, 0.31), (-0.12, 0.08, -0.55), (0.2, 0.1, 0.7)])
def test_single_particle_comes_back_in_place(tiny_rig, device, grid_kind, point):
    rig = tiny_variant(tiny_rig, mla_grid=grid_kind)
    grid = VolumeGrid.from_rig(rig)
    (img,) = _render(rig, np.array([point]), device=device)
    res = reconstruct(LightFieldProjector(rig.camera, grid, device=device), [img], ReconSettings(iterations=30))
    pos, peaks, idx = metrics.detect_particles(res.volume, grid, threshold=0.5)
    assert len(pos) == 1  # one particle, no ghost above half its intensity
    err = np.abs(pos[0] - point) / np.asarray(grid.voxel_mm)
    elong = metrics.particle_diameters(res.volume, idx)[0]
    assert err[0] < 1.0 and err[1] < 1.0  # within a voxel laterally
    assert err[2] < max(1.0, 0.5 * elong[2])  # within the elongation in depth
    assert res.active_fraction < 0.01  # elimination keeps a handful of voxels


def test_weights_spread_light_as_the_optics_do(tiny_rig, device):
    grid = VolumeGrid.from_rig(tiny_rig)
    cam = tiny_rig.camera[0]
    proj = LightFieldProjector([cam], grid, device=device)
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000, "diffraction": False})
    r = LightFieldRenderer(cam, cfg, device=device)
    rng = np.random.default_rng(0)
    for ix, iy, iz in [(41, 34, 14), (45, 30, 20), (41, 34, 2), (60, 50, 26), (81, 67, 0)]:
        f, img = _voxel_images(proj, r, grid, ix, iy, iz, rng)
        assert f.sum() == pytest.approx(img.sum(), abs=0.02)  # the share of light on the sensor
        assert np.corrcoef(f, img)[0, 1] > 0.97  # spread over the same pixels
        assert np.abs(f - img).sum() < 0.25 * img.sum()
        if ix < 80:
            assert f.sum() == pytest.approx(1.0, abs=1e-4)  # inside the field of view: all light arrives
    assert f.sum() < 0.95  # the last, defocused at the corner of the box, loses some off the sensor


def test_baseline_weights_reach_the_sensor_at_every_depth(tiny_rig, device):
    # The baseline must be honest at the focal plane too, where every line of sight of a lenslet
    # passes through the same conjugate point (its search once left three layers without weights).
    grid = VolumeGrid.from_rig(tiny_rig)
    cam = tiny_rig.camera[0]
    proj = LightFieldProjector([cam], grid, device=device)
    nz, ny, nx = grid.shape
    column = [_voxel_index(grid, ix, iy, iz) for iz in range(nz) for ix in (40, 41, 42) for iy in (33, 34, 35)]
    w = proj.weights(proj.wp.array(column, dtype=proj.wp.int32, device=proj.device), method="los")
    offsets, _, values = w.to_numpy()
    assert np.all(np.diff(offsets) > 0)
    np.testing.assert_allclose(np.add.reduceat(values, offsets[:-1]), 1.0, atol=1e-4)
    # the focal-plane voxel lights the pixels its image does
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000, "diffraction": False})
    iz = int(np.argmin(np.abs(np.asarray(grid.origin_mm)[2] + np.arange(nz) * grid.voxel_mm[2] - cam.focus_mm[2])))
    f, img = _voxel_images(proj, LightFieldRenderer(cam, cfg, device=device), grid, 41, 34, iz,
                           np.random.default_rng(0), "los")
    assert np.corrcoef(f, img)[0, 1] > 0.95


@pytest.mark.parametrize(("r_cyl", "r_sph"), [(27.5, 5.5), (1.0, 1.0), (0.5, 2.0)])
def test_tabulated_line_of_sight_overlap_is_the_circles_shared_area(r_cyl, r_sph):
    from lfcore._kernels.weights import OVERLAP_SAMPLES, overlap_table

    table = overlap_table(r_cyl, r_sph)
    d0, d1 = abs(r_cyl - r_sph), r_cyl + r_sph
    assert table[0] == pytest.approx(min(r_cyl, r_sph) ** 2 / r_sph**2) and table[-1] == 0.0
    assert np.all(np.diff(table) <= 0)  # less overlap the farther apart
    # the share of the sphere's disc inside the cylinder's, counted on a fine grid of the disc
    g = (np.arange(2000) + 0.5) / 1000.0 - 1.0
    x, y = np.meshgrid(g * r_sph, g * r_sph)
    disc = x**2 + y**2 <= r_sph**2
    for frac in (0.1, 0.37, 0.5, 0.83, 0.97):
        d = d0 + frac * (d1 - d0)
        inside = ((x - d) ** 2 + y**2 <= r_cyl**2) & disc
        looked_up = np.interp(frac * OVERLAP_SAMPLES, np.arange(OVERLAP_SAMPLES + 1), table)
        assert looked_up == pytest.approx(inside.sum() / disc.sum(), abs=2e-3)
    if r_cyl == r_sph:  # two unit circles one radius apart share 2 pi / 3 - sqrt(3) / 2
        assert np.interp(OVERLAP_SAMPLES / 2, np.arange(OVERLAP_SAMPLES + 1), table) == pytest.approx(
            (2 * np.pi / 3 - np.sqrt(3) / 2) / np.pi, abs=1e-5)


def test_drt_mart_beats_mart_at_equal_work(tiny_rig, device):
    grid, pts, img, proj, e0 = _seeded_scene(tiny_rig, device)
    drt = reconstruct(proj, [img], ReconSettings(method="drt-mart", iterations=20))
    # the baseline gets as many passes over its stored weights as DRT-MART streams
    mart_its = max(1, round(20 * drt.nnz / proj.weights(proj.all_voxels(), method="los").nnz))
    mart = reconstruct(proj, [img], ReconSettings(method="mart", iterations=mart_its))
    assert 0.0 < drt.eliminate_s < drt.weights_s and mart.eliminate_s == 0.0  # elimination timed apart
    out = {}
    tol = 2 * np.asarray(grid.voxel_mm)
    for name, res in (("drt", drt), ("mart", mart)):
        pos, _, idx = metrics.detect_particles(res.volume, grid, threshold=0.1)
        m = metrics.match_particles(pos, pts, tol)
        real = np.linalg.norm((pos[:, None] - pts[None]) / tol, axis=-1).min(axis=1) <= 1  # not ghosts
        depth = np.median(metrics.particle_diameters(res.volume, idx[real])[:, 2])
        out[name] = (metrics.q_recon(res.volume, e0), depth, m.ghosts)
    assert out["drt"][0] > out["mart"][0]  # Q
    assert out["drt"][1] < out["mart"][1]  # depth elongation
    assert out["drt"][2] < out["mart"][2]  # ghosts


def test_mlos_mart_is_the_baseline_on_the_surviving_voxels(tiny_rig, device):
    # Eliminated voxels hold no particle, so MART on the survivors with the baseline's weights
    # must reconstruct what the baseline does on the whole box.
    _, _, img, proj, e0 = _seeded_scene(tiny_rig, device)
    mlos = reconstruct(proj, [img], ReconSettings(method="mlos-mart", iterations=20))
    drt = reconstruct(proj, [img], ReconSettings(method="drt-mart", iterations=20))
    mart = reconstruct(proj, [img], ReconSettings(method="mart", iterations=20))
    assert mlos.active_voxels == drt.active_voxels < 0.25 * mart.active_voxels
    assert mlos.nnz < 0.25 * mart.nnz
    q_mlos, q_mart = metrics.q_recon(mlos.volume, e0), metrics.q_recon(mart.volume, e0)
    assert q_mlos == pytest.approx(q_mart, abs=0.01)


def test_two_cameras_at_90_degrees_beat_one(tiny_rig, device):
    rig = _dual_rig(tiny_rig)
    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=0.2), np.random.default_rng(4))
    imgs = _render(rig, pts, device=device)
    e0 = metrics.truth_volume(grid, pts)
    tol = 2 * np.asarray(grid.voxel_mm)
    one = reconstruct(LightFieldProjector(rig.camera[:1], grid, device=device), imgs[:1], ReconSettings(iterations=30))
    two = reconstruct(LightFieldProjector(rig.camera, grid, device=device), imgs, ReconSettings(iterations=30))
    q1, q2 = metrics.q_recon(one.volume, e0), metrics.q_recon(two.volume, e0)
    m1 = metrics.match_particles(metrics.detect_particles(one.volume, grid)[0], pts, tol)
    m2 = metrics.match_particles(metrics.detect_particles(two.volume, grid)[0], pts, tol)
    assert q2 > q1 + 0.1
    assert m2.recall > m1.recall
    # camera 0 looks along z: its depth error shrinks once camera 1 sees z sideways
    assert m2.rms_error_mm[2] < 0.7 * m1.rms_error_mm[2]
    assert two.active_fraction < one.active_fraction


def test_no_intensity_outside_the_seeded_region(tiny_rig, device):
    grid = VolumeGrid.from_rig(tiny_rig, margin_mm=(0.0, 0.0, 0.4))
    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.2), np.random.default_rng(5))
    (img,) = _render(tiny_rig, pts, device=device)
    res = reconstruct(LightFieldProjector(tiny_rig.camera, grid, device=device), [img], ReconSettings(iterations=30))
    v = tiny_rig.volume
    # a particle at the boundary keeps its depth elongation: allow it three depth voxels
    reach = np.asarray(v.size_mm) + [0.0, 0.0, 6 * grid.voxel_mm[2]]
    assert metrics.outside_fraction(res.volume, grid, v.centre_mm, reach) < 0.002
    assert metrics.outside_fraction(res.volume, grid, v.centre_mm, v.size_mm) < 0.05
    assert res.volume.sum() > 0


def test_sequential_form_finds_the_particle_too(tiny_rig):
    grid = VolumeGrid.from_rig(tiny_rig)
    point = np.array([[0.05, -0.03, 0.31]])
    (img,) = _render(tiny_rig, point)
    res = reconstruct(LightFieldProjector(tiny_rig.camera, grid, device="cpu"), [img],
                      ReconSettings(iterations=10, form="sequential", relaxation=2.5))
    pos, _, _ = metrics.detect_particles(res.volume, grid, threshold=0.5)
    assert len(pos) == 1 and np.all(np.abs(pos[0] - point[0])[:2] < np.asarray(grid.voxel_mm)[:2])


def test_background_estimate(tiny_rig):
    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.5), np.random.default_rng(6))
    (img,) = _render(tiny_rig, pts)
    level, sigma = estimate_background(img)
    assert level == pytest.approx(100.0, abs=2.0)  # the rig's background_counts
    assert sigma == pytest.approx(np.sqrt(100.0 + 9.0), rel=0.15)  # shot and read noise


@pytest.mark.parametrize("seed", range(6))
def test_background_estimate_of_narrow_integer_counts(seed):
    # Low noise in whole counts spans few values: the histogram's bins must not be narrower than
    # a count (they once were, and the level came out NaN for some images).
    rng = np.random.default_rng(seed)
    img = rng.normal(100.0, 3.0, size=(160, 192))
    img[rng.random(img.shape) < 0.05] += 400.0  # particle light
    for im in (img.round().astype(np.uint16), img.round().astype(np.float32)):
        level, sigma = estimate_background(im)
        assert level == pytest.approx(100.0, abs=0.5) and sigma == pytest.approx(3.0, rel=0.2)


def test_weights_that_do_not_fit_are_refused(tiny_rig):
    proj = LightFieldProjector(tiny_rig.camera, VolumeGrid.from_rig(tiny_rig), device="cpu")
    with pytest.raises(MemoryBudgetError, match=r"the weights need .* GiB .* use a coarser --pvr"):
        proj.weights(proj.all_voxels(), method="los", budget_bytes=1000)


def _scene_images(rig, ppm, device):
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(5))
    return pts, _render(rig, pts, device=device)


@pytest.mark.parametrize("dual", [False, True])
def test_weights_made_on_the_fly_project_and_update_as_stored_ones(tiny_rig, device, dual):
    rig = _dual_rig(tiny_rig) if dual else tiny_rig
    proj = LightFieldProjector(rig.camera, VolumeGrid.from_rig(rig), device=device)
    wp = proj.wp
    rng = np.random.default_rng(4)
    voxels = wp.array(np.sort(rng.choice(proj.grid.n_voxels, 4000, replace=False)).astype(np.int32), device=device)
    stored = proj.weights(voxels, method="los")
    fly = proj.weights(voxels, method="los", storage="on-the-fly")
    split = proj.weights(voxels, method="los", storage="auto", budget_bytes=stored.nbytes // 3)
    assert stored.stored and not fly.stored and not split.stored
    assert fly.n_on_the_fly == 4000 and 0 < split.n_stored < 4000 and split.n_stored + split.n_on_the_fly == 4000
    assert fly.nnz == split.nnz == stored.nnz and fly.nbytes < stored.nbytes / 50
    e = rng.random(4000).astype(np.float32)
    e[rng.random(4000) < 0.3] = 0.0  # dead voxels are skipped
    ref = stored.forward(wp.array(e, dtype=float, device=device)).numpy().copy()
    image = wp.array((ref * rng.uniform(0.5, 1.5, ref.size)).astype(np.float32), dtype=float, device=device)
    ref_e = wp.array(e, dtype=float, device=device)
    smart_update(stored, image, wp.array(ref, dtype=float, device=device), ref_e, 1.0, 0.01)
    for w in (fly, split):
        got = w.forward(wp.array(e, dtype=float, device=device)).numpy()
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6 * ref.max())
        upd = wp.array(e, dtype=float, device=device)
        smart_update(w, image, wp.array(ref, dtype=float, device=device), upd, 1.0, 0.01)
        np.testing.assert_allclose(upd.numpy(), ref_e.numpy(), rtol=1e-5)
    with pytest.raises(ValueError, match="made on the fly, not stored"):
        fly.to_numpy()


@pytest.mark.parametrize("method", ["mlos-mart", "mart"])
def test_weights_that_do_not_fit_are_made_on_the_fly(tiny_rig, device, method):
    grid = VolumeGrid.from_rig(tiny_rig)
    pts, images = _scene_images(tiny_rig, 0.3, device)
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    its = 10 if method == "mlos-mart" else 3
    stored = reconstruct(proj, images, ReconSettings(method=method, iterations=its, weight_storage="stored"))
    assert stored.on_the_fly_voxels == 0
    # a budget that holds some of the weights: the rest are made on the fly, and the volume is the same
    small = stored.weight_bytes // 2 + 12 * proj.n_pixels + 12 * grid.n_voxels
    tight = reconstruct(proj, images, ReconSettings(method=method, iterations=its), budget_bytes=small)
    fly = reconstruct(proj, images, ReconSettings(method=method, iterations=its, weight_storage="on-the-fly"))
    assert 0 < tight.on_the_fly_voxels < stored.active_voxels and fly.on_the_fly_voxels == stored.active_voxels
    assert tight.weight_bytes < stored.weight_bytes and fly.weight_bytes < stored.weight_bytes / 20
    truth = metrics.truth_volume(grid, pts)
    for res in (tight, fly):
        np.testing.assert_allclose(res.volume, stored.volume, rtol=1e-3, atol=1e-4 * stored.volume.max())
        assert metrics.q_recon(res.volume, truth) == pytest.approx(metrics.q_recon(stored.volume, truth), abs=1e-4)
    with pytest.raises(MemoryBudgetError, match="the weights need"):
        reconstruct(proj, images, ReconSettings(method=method, iterations=1, weight_storage="stored"),
                    budget_bytes=small)


def test_bad_settings():
    with pytest.raises(ValueError, match="method must be one of"):
        ReconSettings(method="sart")
    with pytest.raises(ValueError, match="relaxation must be positive"):
        ReconSettings(relaxation=0.0)
    with pytest.raises(ValueError, match="diverge; use at most 2, or the sequential form"):
        ReconSettings(relaxation=2.5)
    assert ReconSettings(relaxation=2.5, form="sequential").relaxation == 2.5
    with pytest.raises(ValueError, match="weight_storage must be one of auto, stored, on-the-fly"):
        ReconSettings(method="mlos-mart", weight_storage="disk")
    with pytest.raises(ValueError, match="made on the fly by the matrix-free projector alone"):
        ReconSettings(weight_storage="on-the-fly")
    with pytest.raises(ValueError, match="the sequential form needs stored weights"):
        ReconSettings(method="mlos-mart", form="sequential", weight_storage="on-the-fly")


def test_a_frame_reconstructor_keeps_its_buffers_and_gives_reconstruct_s_volumes(tiny_rig, device):
    """Frames of few, many, then few particles through one reconstructor: each volume is the
    one-frame reconstruction's, its intensities and volume stay in the same device buffers, and
    a result's volume is not overwritten by the next frame."""
    from lfcore.reconstruct import FrameReconstructor

    grid = VolumeGrid.from_rig(tiny_rig)
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    settings = ReconSettings(iterations=5)
    scenes = [(7, 0.1), (8, 0.4), (7, 0.1)]  # the third repeats the first
    images = [_render(tiny_rig, seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=ppm),
                                               np.random.default_rng(seed)), device=device)
              for seed, ppm in scenes]
    frames = FrameReconstructor(proj, settings)
    results, e_ptr, vol_ptr = [], [], []
    for imgs in images:
        results.append(frames.reconstruct(imgs))
        e_ptr.append(frames._e.ptr)
        vol_ptr.append(frames._volume.ptr)
    assert results[0].active_voxels < results[1].active_voxels  # the second frame grows the intensities
    assert e_ptr[1] == e_ptr[2] and vol_ptr[0] == vol_ptr[1] == vol_ptr[2]
    for imgs, res in zip(images, results, strict=True):
        ref = reconstruct(proj, imgs, settings)
        assert res.active_voxels == ref.active_voxels and res.nnz == ref.nnz and ref.volume.max() > 0
        np.testing.assert_allclose(res.volume, ref.volume, rtol=1e-5, atol=1e-6 * float(ref.volume.max()))
    np.testing.assert_allclose(results[2].volume, results[0].volume, rtol=1e-5,
                               atol=1e-6 * float(results[0].volume.max()))
    assert not np.allclose(results[1].volume, results[0].volume)
    with pytest.raises(ValueError, match="got 2 images for 1 cameras"):
        frames.reconstruct(images[0] * 2)


def test_frame_reconstructor_stages_on_device_images(tiny_rig, device):
    """The stages one by one, from a device signal and lit mask (as the live path has them),
    with iterations and relaxation given per call, equal the settings' own reconstruction."""
    from lfcore.reconstruct import FrameReconstructor, preprocess

    grid = VolumeGrid.from_rig(tiny_rig)
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.3), np.random.default_rng(9))
    (img,) = _render(tiny_rig, pts, device=device)
    level, sigma = estimate_background(img)
    signal, lit = preprocess(img, level, sigma, 2.0)
    wp = proj.wp
    frames = FrameReconstructor(proj, ReconSettings(iterations=50, relaxation=1.5))
    w = frames.operator(frames.eliminate(wp.array(lit.ravel().astype(np.uint8), device=device)))
    done = frames.iterate(w, wp.array(signal.ravel(), dtype=float, device=device), [sigma], iterations=8,
                          relaxation=1.0)
    assert done.iterate_s > 0 and done.start_s > 0
    got = frames.volume(w, done.e).numpy()
    ref = reconstruct(proj, [img], ReconSettings(iterations=8, relaxation=1.0)).volume
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6 * float(ref.max()))


def test_a_frame_reconstructor_s_own_buffers_do_not_shrink_the_weights_budget(tiny_rig, device, monkeypatch):
    """On a device with a fixed amount of memory, less what the reconstructor holds, the same
    frame twice makes (nearly) the same share of its weights on the fly: the buffers kept from
    the first frame serve the second, so they are not set aside for it again."""
    from lfcore import reconstruct as recon_module
    from lfcore.reconstruct import FrameReconstructor

    grid = VolumeGrid.from_rig(tiny_rig)
    _, images = _scene_images(tiny_rig, 0.3, device)
    proj = LightFieldProjector(tiny_rig.camera, grid, device=device)
    settings = ReconSettings(method="mlos-mart", iterations=2)
    stored = reconstruct(proj, images, dataclasses.replace(settings, weight_storage="stored"))
    total = stored.weight_bytes // 2 + 12 * proj.n_pixels + 12 * grid.n_voxels
    frames = FrameReconstructor(proj, settings)
    buffers = ("_image", "_proj", "_e", "_volume")

    def free(_device: str) -> int:
        held = sum(getattr(frames, b).capacity for b in buffers if getattr(frames, b) is not None)
        return total - held - (frames.ops._tmp.capacity if frames.ops._tmp is not None else 0)

    monkeypatch.setattr(recon_module, "available_bytes", free)
    first, second = frames.reconstruct(images), frames.reconstruct(images)
    assert 0 < first.on_the_fly_voxels < first.active_voxels
    assert abs(second.on_the_fly_voxels - first.on_the_fly_voxels) <= 0.01 * first.active_voxels
    np.testing.assert_allclose(second.volume, first.volume, rtol=1e-3, atol=1e-4 * float(first.volume.max()))
