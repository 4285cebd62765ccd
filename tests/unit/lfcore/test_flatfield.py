"""The flat field from known truths: identity, a vignetted image corrected back, masked pixels."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from lfcore.flatfield import correct, flat_field, sensor_response
from lfcore.reconstruct import MASKED, preprocess
from lfcore.rig import Rig
from lfcore.white import white_irradiance

TINY = Path(__file__).resolve().parents[3] / "examples" / "tiny.toml"


def tiny():
    return Rig.from_dict(tomllib.loads(TINY.read_text()))


def test_flat_white_and_zero_dark_are_the_identity():
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 4000, size=(40, 50)).astype(np.uint16)
    flat = flat_field(np.zeros((40, 50)), np.full((40, 50), 1000.0))
    assert not flat.mask.any()
    np.testing.assert_allclose(correct(raw, flat), raw.astype(np.float32), rtol=1e-6)


def test_dark_level_is_subtracted():
    flat = flat_field(np.full((8, 8), 100.0), np.full((8, 8), 1100.0))
    np.testing.assert_allclose(correct(np.full((8, 8), 600, np.uint16), flat), 500.0, rtol=1e-6)


def test_vignetted_image_corrects_back_to_the_clean_one():
    rig = tiny()
    cam = rig.camera[0]
    resp = rig.render.model_copy(update={"lens_falloff": 0.4, "micro_vignetting": 0.3, "dust_spots": 2,
                                         "dark_fpn_counts": 5.0})
    r = sensor_response(cam, resp)
    clean = white_irradiance(cam)  # any image the optics form: a uniformly lit scene here
    ref = white_irradiance(cam)
    white = 0.8 * ref * r.gain + r.dark
    flat = flat_field(r.dark, white, reference=ref)
    scene = 3000.0 * clean
    raw = scene * r.gain + r.dark
    got = correct(raw, flat)
    keep = ~flat.mask
    assert flat.mask.mean() < 0.2
    ratio = got[keep] / scene[keep]
    # one scale for every pixel (the gain is normalised), within 0.1%
    np.testing.assert_allclose(ratio / np.median(ratio), 1.0, atol=1e-3)
    assert np.isnan(got[flat.mask]).all()


def test_dust_and_dead_pixels_are_masked():
    white = np.full((20, 20), 1100.0)
    white[5, 5] = 100.0  # dead: no more than the dark
    white[10:12, 10:12] = 200.0  # under dense dust: a tenth of the light
    flat = flat_field(np.full((20, 20), 100.0), white)
    assert flat.mask[5, 5] and flat.mask[10:12, 10:12].all() and flat.mask.sum() == 5


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="same camera"):
        flat_field(np.zeros((4, 4)), np.ones((5, 4)))
    with pytest.raises(ValueError, match="nowhere brighter"):
        flat_field(np.full((4, 4), 10.0), np.full((4, 4), 5.0))
    flat = flat_field(0.0, np.ones((4, 4)))
    with pytest.raises(ValueError, match="this camera"):
        correct(np.ones((3, 3)), flat)


def test_masked_pixels_leave_the_update():
    """A masked pixel gives the signal MASKED and counts as lit; its log ratio is 0, so the voxels it
    sees do not change (where a measured zero would pull them dark)."""
    from lfcore.device import warp
    from lfcore.operator import log_ratio

    img = np.array([[np.nan, 0.0, 50.0]], dtype=np.float32)
    sig, lit = preprocess(img, 0.0, 1.0, 3.0)
    assert sig[0, 0] == MASKED and lit[0, 0] and not lit[0, 1] and lit[0, 2]
    wp = warp()
    image = wp.array(sig.ravel(), dtype=float, device="cpu")
    proj = wp.array(np.array([10.0, 10.0, 10.0], np.float32), dtype=float, device="cpu")
    out = wp.zeros(3, dtype=float, device="cpu")
    r = log_ratio(image, proj, 1.0, out).numpy()
    assert r[0] == 0.0 and r[1] < -2.0 and r[2] == pytest.approx(np.log(5.0), rel=1e-5)


def test_masked_pixels_are_left_out_of_the_start():
    """The uniform start carries the measured signal: a masked pixel adds nothing to it."""
    from lfcore.device import warp
    from lfcore.reconstruct import _total_measured

    wp = warp()
    masked = wp.array(np.array([MASKED, 40.0], np.float32), dtype=float, device="cpu")
    assert _total_measured(masked) == pytest.approx(40.0)


def test_response_off_by_default_and_on_when_asked():
    rig = tiny()
    assert not rig.render.has_response
    cam = rig.camera[0]
    r = sensor_response(cam, rig.render)
    assert np.all(r.gain == 1.0) and np.all(r.dark == rig.render.background_counts)
    on = sensor_response(cam, rig.render.model_copy(update={"lens_falloff": 0.4}))
    # the corners get 60% (cos^4 profile through the corner pixel centres: within a pixel of it)
    assert on.gain[0, 0] == pytest.approx(0.6, abs=0.01) and on.gain.max() == pytest.approx(1.0, abs=1e-3)


def test_live_preprocessor_corrects_as_the_batch_path():
    """The device preprocessor with a flat field gives what preprocess(correct(raw)) gives."""
    from lfcore.device import warp
    from lfcore.device_ops import ImagePreprocessor

    rig = tiny()
    cam = rig.camera[0]
    rng = np.random.default_rng(2)
    shape = (cam.sensor_px[1], cam.sensor_px[0])
    white = rng.uniform(500, 1000, shape)
    white[3, 4] = 100.0  # dead
    dark = np.full(shape, 100.0) + rng.normal(0, 2, shape)
    flat = flat_field(dark, white)
    raw = (rng.uniform(90, 400, shape)).astype(np.uint16)
    sig, lit = preprocess(correct(raw, flat), 5.0, 10.0, 3.0)
    wp = warp()
    pre = ImagePreprocessor([cam], device="cpu", flats=[flat])
    signal = wp.zeros(raw.size, dtype=float, device="cpu")
    lit_d = wp.zeros(raw.size, dtype=wp.uint8, device="cpu")
    pre(wp.array(raw.ravel(), dtype=wp.uint16, device="cpu"), [5.0], [30.0], signal, lit_d)
    np.testing.assert_allclose(signal.numpy().reshape(shape), sig, rtol=1e-5, atol=1e-3)
    assert np.array_equal(lit_d.numpy().reshape(shape).astype(bool), lit)
    assert sig[3, 4] == MASKED
