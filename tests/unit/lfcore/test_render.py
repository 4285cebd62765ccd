"""The renderer against thin-lens optics, on every device Warp finds.

Known truths: a point on the focal plane images to a single lenslet whose aperture image it
fills; off focus, its blur on the MLA is a disc of diameter D |M| |dz| / (so - dz), and each lit
lenslet sees it through one sub-aperture only; no ray inside the aperture is lost.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcore import mla
from lfcore.render import LightFieldRenderer
from tests.conftest import DEVICES, tiny_variant

GRIDS = ["hex", "square"]


def _renderer(rig, device, **render):
    cfg = rig.render.model_copy(update={"diffraction": False, "rays_per_particle": 100_000, **render})
    return LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device=device)


def _cell_second_moment(cam) -> float:
    """Polar second moment per area of one lenslet cell about its centre (mm^2)."""
    p = cam.mla_pitch_mm
    return 5 * p * p / 36 if cam.mla_grid == "hex" else p * p / 6


def _defocus_geometry(cam, point_cam):
    """Blur diameter and centre on the MLA, and the aperture-to-MLA scale a (q = a A + g)."""
    x, y, dz = point_cam
    so_p = cam.object_distance_mm - dz
    si_p = 1.0 / (1.0 / cam.main_focal_length_mm - 1.0 / so_p)
    a = 1.0 - cam.image_distance_mm / si_p
    g = -np.array([x, y]) * cam.image_distance_mm / so_p
    return cam.aperture_mm * abs(a), g, a


@pytest.mark.parametrize("grid", GRIDS)
def test_focal_point_fills_exactly_one_lenslet(tiny_rig, device, grid):
    rig = tiny_variant(tiny_rig, mla_grid=grid)
    cam = rig.camera[0]
    centres = mla.lenslet_centers(cam)
    c = centres[np.argmin(np.linalg.norm(centres - [0.12, -0.08], axis=1))]  # an off-axis lenslet
    m = cam.magnification
    img = _renderer(rig, device).irradiance(cam.camera_to_world([[c[0] / m, c[1] / m, 0.0]]), 1000.0, seed=3)
    pix = mla.pixel_centers_sensor(cam)
    dist = np.linalg.norm(pix - c, axis=-1) / cam.pixel_mm  # pixel centre to lenslet centre, px
    half = 0.5 * cam.pixels_per_lenslet  # matched optics: the aperture image just fills the lenslet
    lit = img > 0
    assert dist[lit].max() <= half + 0.75  # nothing outside this lenslet's aperture image
    owned = np.all(np.isclose(mla.nearest_lenslet(cam, pix), c), axis=-1)
    assert img[owned].sum() / img.sum() > 0.97
    inner = dist <= half - 0.75
    assert inner.sum() > 40 and lit[inner].all()  # every pixel inside the main-lens image is lit
    assert img[inner].std() / img[inner].mean() < 0.1  # evenly: the aperture is uniformly lit


@pytest.mark.parametrize("grid", GRIDS)
def test_defocus_disc_grows_with_the_thin_lens_slope(tiny_rig, device, grid):
    rig = tiny_variant(tiny_rig, mla_grid=grid)
    cam = rig.camera[0]
    r = _renderer(rig, device)
    owner = mla.nearest_lenslet(cam, mla.pixel_centers_sensor(cam))
    dzs = np.array([-1.6, -1.2, -0.8, -0.4, 0.4, 0.8, 1.2, 1.6])
    diam = []
    for i, dz in enumerate(dzs):
        p = np.array([0.013, -0.021, dz])
        img = r.irradiance(cam.camera_to_world([p]), 1000.0, seed=10 + i).astype(np.float64)
        w = img / img.sum()
        centroid = np.einsum("rc,rck->k", w, owner)
        m2 = np.einsum("rc,rc->", w, ((owner - centroid) ** 2).sum(-1))
        # Energy binned on lenslet centres: a uniform disc of diameter B has <rho^2> = B^2 / 8,
        # plus the spread of positions within one cell (Sheppard's correction).
        diam.append(math.sqrt(8.0 * (m2 - _cell_second_moment(cam))))
        expected, g, _ = _defocus_geometry(cam, p)
        assert diam[-1] == pytest.approx(expected, rel=0.07), f"dz = {dz}"
        assert np.linalg.norm(centroid - g) < 0.25 * cam.mla_pitch_mm
    slope, intercept = np.polyfit(np.abs(dzs), diam, 1)
    assert slope == pytest.approx(cam.aperture_mm * cam.magnification**2 / cam.image_distance_mm, rel=0.03)
    assert abs(intercept) < 0.2 * cam.mla_pitch_mm


@pytest.mark.parametrize("grid", GRIDS)
@pytest.mark.parametrize("dz", [-1.2, 1.4])
def test_each_lenslet_sees_one_sub_aperture(tiny_rig, device, grid, dz):
    rig = tiny_variant(tiny_rig, mla_grid=grid)
    cam = rig.camera[0]
    p = np.array([0.02, 0.01, dz])
    img = _renderer(rig, device, rays_per_particle=400_000).irradiance(cam.camera_to_world([p]), 1000.0, seed=7)
    pix = mla.pixel_centers_sensor(cam)
    blur, g, a = _defocus_geometry(cam, p)
    f_ml, si = cam.mla_focal_length_mm, cam.image_distance_mm
    # A ray through aperture point A meets the MLA at q = a A + g and lands at
    # c + f_ml (q - A) / si; over one cell that is the cell scaled by f_ml |1 - 1/a| / si.
    circumradius = cam.mla_pitch_mm / (math.sqrt(3) if grid == "hex" else math.sqrt(2))
    spot_r = min(circumradius * f_ml * abs(1 - 1 / a) / si, 0.5 * cam.mla_pitch_mm) / cam.pixel_mm
    centres = mla.lenslet_centers(cam)
    inside = centres[np.linalg.norm(centres - g, axis=1) < 0.5 * blur - cam.mla_pitch_mm]
    assert len(inside) >= 3
    centred = 0
    for c in inside:
        # A pixel that straddles two lenslet images may take light from both, so judge the
        # pixels well inside this lenslet's cell.
        mine = np.linalg.norm(pix - c, axis=-1) < 0.5 * cam.mla_pitch_mm - cam.pixel_mm
        w = np.where(mine, img, 0.0)
        predicted = c + f_ml * (c - (c - g) / a) / si  # spot of the sub-aperture A = (c - g) / a
        d = np.linalg.norm(pix - predicted, axis=-1) / cam.pixel_mm
        assert w.sum() > 0 and w[d > spot_r + 0.75].sum() == 0.0  # the lenslet's other pixels stay dark
        if np.linalg.norm(predicted - c) < 0.5 * cam.mla_pitch_mm - (spot_r + 1.0) * cam.pixel_mm:
            centroid = np.einsum("rc,rck->k", w, pix) / w.sum()  # whole spot inside: it is centred
            assert np.linalg.norm(centroid - predicted) / cam.pixel_mm < 0.35
            centred += 1
    assert centred >= 1


@pytest.mark.parametrize("f_number", [2.0, 1.6])  # matched, and a wider aperture with crosstalk
def test_energy_is_conserved(tiny_rig, device, f_number):
    rig = tiny_variant(tiny_rig, f_number=f_number)
    cam = rig.camera[0]
    pts = cam.camera_to_world([[0.0, 0.0, 0.0], [0.05, -0.03, 0.5], [-0.04, 0.02, -0.7]])
    counts = np.array([1000.0, 2500.0, 400.0])
    for diameter in (0.0, 20.0):
        r = _renderer(rig, device, rays_per_particle=20_000, particle_diameter_um=diameter, diffraction=True)
        assert r.irradiance(pts, counts, seed=1).sum() == pytest.approx(counts.sum(), rel=1e-5)


def test_same_seed_same_frame(tiny_rig, device):
    r = _renderer(tiny_rig, device, rays_per_particle=5000, diffraction=True, particle_diameter_um=10.0)
    pts = np.random.default_rng(0).uniform(-0.3, 0.3, (40, 3))
    a = r.frame(pts, 50000.0, seed=11)
    b = r.frame(pts, 50000.0, seed=11)
    c = r.frame(pts, 50000.0, seed=12)
    assert a.dtype == np.uint16 and a.shape == (160, 192)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.skipif("cuda:0" not in DEVICES, reason="needs a CUDA GPU")
def test_cpu_and_gpu_agree_statistically(tiny_rig):
    pts = np.random.default_rng(1).uniform(-0.3, 0.3, (20, 3))
    cpu = _renderer(tiny_rig, "cpu", diffraction=True).irradiance(pts, 1000.0, seed=2)
    gpu = _renderer(tiny_rig, "cuda:0", diffraction=True).irradiance(pts, 1000.0, seed=2)
    assert gpu.sum() == pytest.approx(cpu.sum(), rel=1e-5)
    cam = tiny_rig.camera[0]
    owner = mla.nearest_lenslet(cam, mla.pixel_centers_sensor(cam)).reshape(-1, 2)
    _, idx = np.unique(np.round(owner / cam.mla_pitch_mm * 2), axis=0, return_inverse=True)
    e_cpu = np.bincount(idx.ravel(), cpu.ravel())
    e_gpu = np.bincount(idx.ravel(), gpu.ravel())
    big = e_cpu > 0.01 * e_cpu.max()
    assert np.allclose(e_gpu[big], e_cpu[big], rtol=0.05, atol=0.002 * e_cpu.max())


def test_sensor_noise_background_and_saturation(tiny_rig, device):
    r = _renderer(tiny_rig, device, background_counts=100.0, gain_e_per_count=1.0, read_noise_counts=3.0)
    dark = r.frame(np.zeros((0, 3)), 0.0, seed=4).astype(np.float64)
    assert dark.mean() == pytest.approx(100.0, abs=0.2)
    assert dark.std() == pytest.approx(math.sqrt(100.0 + 3.0**2), rel=0.05)  # shot + read noise
    bright = r.frame(np.zeros((1, 3)), 1e9, seed=4)
    assert bright.max() == 65535
    r12 = _renderer(tiny_rig, device, bit_depth=12)
    assert r12.frame(np.zeros((1, 3)), 1e9, seed=4).max() == 4095


def test_diffraction_blur_is_the_airy_core(tiny_rig):
    r = LightFieldRenderer(tiny_rig.camera[0], tiny_rig.render, wavelength_nm=532.0, device="cpu")
    lam = 532e-6
    assert r.params.sigma_sensor == pytest.approx(0.42 * lam * 4.0)  # f/4 lenslets
    assert r.params.sigma_mla == pytest.approx(0.42 * lam * 4.0)  # N (1 - M) = 4


def test_a_particle_far_off_the_axis_lights_nothing(tiny_rig, device):
    """Rays landing beyond any int index of the sensor are dropped (their conversion to an index
    is undefined, and crashed the kernel)."""
    r = _renderer(tiny_rig, device, rays_per_particle=2000)
    cam = tiny_rig.camera[0]
    far = cam.camera_to_world([[3e7, 0.0, 0.0], [0.0, -3e9, 0.2], [0.0, 0.0, 0.0]])
    img = r.irradiance(far, np.array([1000.0, 1000.0, 1000.0]), seed=1)
    assert img.sum() == pytest.approx(1000.0, rel=1e-5)  # only the particle at the focus


def test_bad_particles_are_rejected(tiny_rig):
    r = _renderer(tiny_rig, "cpu")
    with pytest.raises(ValueError, match="finite"):
        r.irradiance(np.array([[0.0, np.nan, 0.0]]), 1.0)
    with pytest.raises(ValueError, match="inside the focal length"):
        r.irradiance(np.array([[0.0, 0.0, 60.0]]), 1.0)
