"""The white-image model (lfcore.white) and the microlens grid detected from it (calibration.mla_grid)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from calibration.mla_grid import GridError, check_white, detect_grid
from lfcore.mla import lenslet_centers, sensor_to_pixel
from lfcore.white import WhiteImageConfig, micro_image_centres, micro_image_scale, white_image, white_irradiance
from tests.conftest import tiny_variant

ROT, OFF_LENSLETS = 0.2, 0.3  # the perturbation of the issue: MLA rotated 0.2 deg, offset 0.3 lenslet


def _camera(tiny_rig, grid: str, **changes):
    pitch = tiny_rig.camera[0].mla_pitch_um
    return tiny_variant(tiny_rig, mla_grid=grid, mla_rotation_deg=ROT,
                        mla_offset_um=[OFF_LENSLETS * pitch, 0.0], **changes).camera[0]


def test_micro_images_sit_on_the_chief_rays_not_under_the_lenslets(tiny_rig):
    # f/3 instead of f/2: discs smaller than the lenslets, so each can be measured alone
    cam = _camera(tiny_rig, "hex", f_number=3.0)
    img = white_irradiance(cam)
    k = micro_image_scale(cam)
    assert k == pytest.approx(1 + 0.22 / 100.0)
    truth = micro_image_centres(cam)
    lenslets = sensor_to_pixel(cam, lenslet_centers(cam))
    labels, n = ndimage.label(img > 0.01 * img.max())
    cents = np.array(ndimage.center_of_mass(img, labels, range(1, n + 1)))[:, ::-1] + 0.5  # (column, row)
    sizes = ndimage.sum(np.ones_like(img), labels, range(1, n + 1))
    whole = (sizes > 0.9 * np.median(sizes)) & np.all((cents > 5) & (cents < [187, 155]), axis=1)
    cents = cents[whole]
    d_truth, i = cKDTree(truth).query(cents)
    assert np.max(d_truth) < 0.02
    # the outermost whole discs are measurably away from their lenslet centres
    far = np.hypot(*(truth[i] - [96, 80]).T) > 70
    assert np.all(np.hypot(*(cents[far] - lenslets[i][far]).T) > 0.15)
    # disc radius f_ml D / (2 si): 0.22 * (50 / 3) / 200 mm = 3.33 px, area 34.9 px^2
    assert np.median(ndimage.sum(img, labels, range(1, n + 1))) / 20000 == pytest.approx(
        np.pi * (0.22 * 50 / 3 / 200 / 0.0055) ** 2, rel=0.02)


def test_white_image_noise_vignetting_and_dead_lenslets(tiny_rig):
    cam = _camera(tiny_rig, "square")
    render = tiny_rig.render
    cfg = WhiteImageConfig(level_counts=20000, vignetting=0.5, dead_lenslets=4, seed=3)
    img = white_image(cam, render=render, config=cfg)
    assert img.dtype == np.uint16 and img.shape == (160, 192)
    truth = np.rint(micro_image_centres(cam) - 0.5).astype(int)
    inside = (truth[:, 0] >= 0) & (truth[:, 0] < 192) & (truth[:, 1] >= 0) & (truth[:, 1] < 160)
    at = img[truth[inside, 1], truth[inside, 0]].astype(float)
    assert np.sum(at < 0.05 * at.max()) == 4  # the dead ones
    centre = img[75:85, 90:100].max()
    assert 19000 < centre < 21500
    corner_lit = np.sort(at[at > 1000])
    assert corner_lit[0] < 0.62 * centre  # corners darker by about half (cos^4 profile)
    assert np.array_equal(img, white_image(cam, render=render, config=cfg))  # reproducible


@pytest.mark.parametrize("grid", ["hex", "square"])
def test_grid_recovers_rotation_offset_and_pitch(tiny_rig, grid):
    cam = _camera(tiny_rig, grid)
    img = white_image(cam, render=tiny_rig.render, config=WhiteImageConfig(vignetting=0.5, dead_lenslets=4, seed=1))
    g = detect_grid(img)
    k = micro_image_scale(cam)
    assert g.grid == grid
    assert g.pitch_px == pytest.approx(cam.pixels_per_lenslet * k, abs=0.003)
    assert g.rotation_deg == pytest.approx(ROT, abs=0.01)
    # the node nearest the sensor centre: the lenslet 0.3 pitch off axis, scaled by k, x mirrored
    off = OFF_LENSLETS * cam.pixels_per_lenslet * k
    assert np.allclose(g.offset_px, [-off, 0.0], atol=0.02)
    mla = g.to_mla(cam)
    assert mla["mla_pitch_um"] == pytest.approx(cam.mla_pitch_um, rel=3e-4)
    assert np.allclose(mla["mla_offset_um"], cam.mla_offset_um, atol=0.02 * 5.5)
    # every inlier centre is on its true micro-image centre
    truth = micro_image_centres(cam)
    d, _ = cKDTree(truth).query(g.centres_px[g.inliers])
    assert g.rms_px < 0.04 and np.sqrt(np.mean(d**2)) < 0.04 and d.max() < 0.15
    assert g.inliers.sum() >= 0.9 * g.n_lenslets >= 0.7 * len(truth)
    # the fitted lattice predicts the centres
    assert np.allclose(g.lattice_px() + g.residuals_px, g.centres_px)


def test_dead_lenslets_are_not_detected(tiny_rig):
    cam = _camera(tiny_rig, "hex")
    cfg = WhiteImageConfig(dead_lenslets=6, dead_at_edge=False, seed=5)
    img = white_image(cam, render=tiny_rig.render, config=cfg)
    g = detect_grid(img, grid="hex")
    truth = micro_image_centres(cam)
    lit = np.asarray(white_irradiance(cam, config=cfg))
    cr = np.rint(truth - 0.5).astype(int)
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < 192) & (cr[:, 1] >= 0) & (cr[:, 1] < 160)
    dead = truth[ok][lit[cr[ok, 1], cr[ok, 0]] < 1.0]
    assert len(dead) == 6
    d, _ = cKDTree(g.centres_px).query(dead)
    assert np.all(d > 3.0)
    assert g.rotation_deg == pytest.approx(ROT, abs=0.01)


def test_bad_white_images_are_refused():
    rng = np.random.default_rng(0)
    with pytest.raises(GridError, match="too dark"):
        check_white(rng.normal(100, 3, (64, 64)).clip(0), 65535)
    with pytest.raises(GridError, match="saturated"):
        check_white(np.full((64, 64), 4095), 4095)
    with pytest.raises(GridError, match="no periodic"):
        detect_grid(rng.normal(20000, 150, (96, 96)))


@pytest.mark.parametrize(("grid", "f_number"), [("hex", 2.0), ("square", 1.6)])
def test_splatted_white_image_equals_every_disc_summed_at_every_subsample(tiny_rig, grid, f_number):
    # The known truth, by brute force: at every sub-sample, the ramped coverage of EVERY
    # lenslet's disc (on or off the sensor), weighted by its cos^4 falloff. f/1.6 over-fills the
    # lenslets, so neighbouring discs overlap and edge discs of off-sensor lenslets show.
    cam = _camera(tiny_rig, grid, f_number=f_number, sensor_px=[40, 30])
    cfg = WhiteImageConfig(vignetting=0.4, supersample=3, level_counts=1.0)
    k = micro_image_scale(cam)
    r_px = cam.mla_focal_length_mm * 0.5 * cam.aperture_mm / cam.image_distance_mm / cam.pixel_mm
    lenslets = lenslet_centers(cam, margin_mm=5 * cam.mla_pitch_mm)
    centres = sensor_to_pixel(cam, k * lenslets)
    corner = 0.5 * np.hypot(*cam.sensor_size_mm)
    length = corner / np.sqrt((1 - cfg.vignetting) ** -0.5 - 1)
    weight = 1.0 / (1.0 + np.sum(lenslets**2, axis=1) / length**2) ** 2
    nc, nr = cam.sensor_px
    sub = (np.arange(3) + 0.5) / 3
    x = (np.arange(nc)[:, None] + sub).ravel()
    y = (np.arange(nr)[:, None] + sub).ravel()
    d = np.hypot(x[None, None, :] - centres[:, 0, None, None], y[None, :, None] - centres[:, 1, None, None])
    cover = np.clip((r_px - d) * 3 + 0.5, 0.0, 1.0)  # (lenslet, sub-row, sub-column)
    truth = np.einsum("l,lrc->rc", weight, cover).reshape(nr, 3, nc, 3).mean(axis=(1, 3))
    img = white_irradiance(cam, config=cfg)
    assert np.allclose(img, truth, rtol=0, atol=1e-9)
    if f_number < 2:
        assert img.max() > 1.2  # overlapping discs add up


def test_grid_centring_in_parallel_blocks_equals_one_block(tiny_rig):
    from calibration.mla_grid import _flat_field, _symmetric_centres

    cam = _camera(tiny_rig, "hex")
    img = white_image(cam, render=tiny_rig.render, config=WhiteImageConfig(vignetting=0.3, seed=2)).astype(np.float64)
    start = micro_image_centres(cam)
    start = start[np.all((start > 8) & (start < np.array(cam.sensor_px) - 8), axis=1)] + 0.3
    flat = _flat_field(img, cam.pixels_per_lenslet)
    one = _symmetric_centres(flat, start, cam.pixels_per_lenslet, block=len(start))
    many = _symmetric_centres(flat, start, cam.pixels_per_lenslet, block=5)  # several blocks, a thread pool
    assert len(start) > 20 and np.array_equal(one, many)
    d, _ = cKDTree(micro_image_centres(cam)).query(one)
    assert np.sqrt(np.mean(d**2)) < 0.05  # and they moved 0.42 px onto the true centres
