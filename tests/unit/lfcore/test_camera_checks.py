"""The checks before recording (lfcore.camera_checks) against rendered images of known seeding."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.camera_checks import (
    RECOMMENDED_PPM,
    background_noise,
    check_image,
    particle_density_ppp,
    view_samples_per_particle,
    visible_share,
)
from lfcore.particles import particle_count, seed_particles
from lfcore.render import LightFieldRenderer, PinholeRenderer
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES


def _deeper_rig():
    """The one-camera example's optics on a 512 x 384 crop of its sensor, seeded 3 mm deep
    (+-1.8 lenslets of blur)."""
    rig = load_rig(EXAMPLES / "one_camera.toml")
    cam = rig.camera[0].model_copy(update={"sensor_px": (512, 384)})
    return rig.model_copy(update={"camera": (cam,),
                                  "volume": rig.volume.model_copy(update={"size_mm": (4.0, 3.0, 3.0)})})


def _frame(rig, ppm, *, rays=3000, counts=50_000.0, seed=3):
    cam = rig.camera[0]
    cfg = rig.render.model_copy(update={"rays_per_particle": rays})
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(seed))
    return LightFieldRenderer(cam, cfg, wavelength_nm=532.0, device="cpu").frame(pts, counts, seed=1)


def test_background_and_noise_of_a_dark_frame() -> None:
    img = np.random.default_rng(0).normal(100.0, 4.0, (200, 200))
    b, s = background_noise(img)
    assert b == pytest.approx(100.0, abs=0.5)
    assert s == pytest.approx(4.0, rel=0.1)


@pytest.mark.parametrize("which", ["tiny", "deeper"])
@pytest.mark.parametrize("ppm", [0.1, 0.3, 0.5])
def test_seeding_density_from_the_raw_image(tiny_rig, which, ppm) -> None:
    rig = tiny_rig if which == "tiny" else _deeper_rig()
    img = _frame(rig, ppm)
    c = check_image(img, rig.camera[0], full_scale=2**rig.render.bit_depth - 1, volume=rig.volume)
    assert c.ppm == pytest.approx(ppm, rel=0.2)


def test_the_model_behind_the_estimate(tiny_rig) -> None:
    cam = tiny_rig.camera[0]
    assert visible_share(cam, tiny_rig.volume) == 1.0  # the tiny rig sees its whole volume
    # a volume as thin as the focal plane: one view sample per particle
    thin = tiny_rig.volume.model_copy(update={"size_mm": (0.9, 0.75, 1e-6)})
    assert view_samples_per_particle(cam, thin) == pytest.approx(1.0, abs=1e-3)
    assert view_samples_per_particle(cam, tiny_rig.volume) > 1.0
    far = tiny_rig.volume.model_copy(update={"centre_mm": (50.0, 0.0, 0.0)})
    assert visible_share(cam, far) == 0.0


def test_saturation_fill_histogram_and_verdicts(tiny_rig) -> None:
    rig = tiny_rig
    full = 2**rig.render.bit_depth - 1
    img = _frame(rig, RECOMMENDED_PPM)
    c = check_image(img, rig.camera[0], full_scale=full, volume=rig.volume)
    assert c.saturated_fraction == 0.0
    assert c.histogram.sum() == img.size
    assert c.fill == pytest.approx(1.0, abs=0.1)  # matched f-numbers: the micro-images touch
    assert all(ok for _, ok in c.verdicts())
    assert c.preview.ndim == 2 and c.preview.size > 0 and "refocused" in c.preview_label
    # a frame a tenth of which is clipped: saturated, marked
    hot = img.copy()
    hot[: img.shape[0] // 10] = full
    c2 = check_image(hot, rig.camera[0], full_scale=full, volume=rig.volume)
    assert c2.saturated_fraction == pytest.approx(np.mean(hot >= full))
    sat = [ok for line, ok in c2.verdicts() if line.startswith("saturated")]
    assert sat == [False]
    # a main lens stopped down two stops: micro-images half the pitch across
    small = rig.camera[0].model_copy(update={"f_number": 4.0})
    r = LightFieldRenderer(small, rig.render.model_copy(update={"rays_per_particle": 3000}), wavelength_nm=532.0,
                           device="cpu")
    pts = seed_particles(rig.volume, particle_count(rig, ppm=1.0), np.random.default_rng(1))
    c3 = check_image(r.frame(pts, 50_000.0, seed=1), small, full_scale=full, volume=rig.volume)
    assert c3.fill == pytest.approx(0.5, abs=0.12)
    assert [ok for line, ok in c3.verdicts() if line.startswith("micro-image")] == [False]


def test_particles_per_pixel_of_a_pinhole_camera() -> None:
    rig = load_rig(EXAMPLES / "tomo_4_cameras.toml")
    cam = rig.camera[0]
    cols, rows = cam.sensor_px
    ppp = 0.01  # sparse enough that particle images rarely merge
    pts = seed_particles(rig.volume, int(ppp * cols * rows), np.random.default_rng(2))
    img = PinholeRenderer(cam, rig.render, wavelength_nm=532.0, device="cpu").frame(pts, 5000.0, seed=1)
    assert particle_density_ppp(img) == pytest.approx(ppp * visible_share(cam, rig.volume), rel=0.15)
    c = check_image(img, cam, full_scale=2**rig.render.bit_depth - 1, volume=rig.volume)
    assert c.ppm is None and c.fill is None and c.ppp == pytest.approx(particle_density_ppp(img))
