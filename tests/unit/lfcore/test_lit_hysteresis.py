"""The lit mask's hysteresis (ReconSettings.lit_hysteresis): a pixel next to a lit one is lit above a lower
threshold, so that noise darkening the dim rim of a particle's spot does not drop the particle's voxels in a
strict elimination (``max_dark`` 0), while a lone pixel of the background still needs the full threshold.

Scenes: a hand-made image with known signals, and benchmarks/recon.py's S2 (two light-field cameras) rendered
with three times the renderer's shot and read noise, whose particles' voxels are the known truth."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.plan import projector_for
from lfcore.reconstruct import ReconSettings, preprocess, preprocess_images
from lfcore.render import LightFieldRenderer


def _image(sigma: float = 4.0, level: float = 100.0) -> np.ndarray:
    """A 16 x 16 frame at ``level``: a spot (centre 10 sigmas, its four neighbours 1 sigma, one diagonal
    neighbour 0.3 sigma) and a lone pixel at 1 sigma far from it."""
    img = np.full((16, 16), level, np.float32)
    img[5, 5] = level + 10 * sigma
    for r, c in ((4, 5), (6, 5), (5, 4), (5, 6)):
        img[r, c] = level + 1.0 * sigma
    img[4, 4] = level + 0.3 * sigma
    img[12, 12] = level + 1.0 * sigma
    return img


def test_hysteresis_lights_the_spots_rim_not_a_lone_pixel_and_keeps_the_signal():
    img, sigma = _image(), 4.0
    plain_signal, plain = preprocess(img, 100.0, sigma, 2.0)
    signal, lit = preprocess(img, 100.0, sigma, 2.0, hysteresis=0.5)
    assert np.argwhere(plain).tolist() == [[5, 5]]
    assert sorted(map(tuple, np.argwhere(lit).tolist())) == [(4, 5), (5, 4), (5, 5), (5, 6), (6, 5)]
    assert not lit[12, 12] and not lit[4, 4]  # a lone 1-sigma pixel; a rim pixel below 0.5 sigma
    np.testing.assert_array_equal(signal, plain_signal)  # the iterations fit the same signal
    # at the full threshold the hysteresis lights nothing more; growing comes after it
    assert np.array_equal(preprocess(img, 100.0, sigma, 2.0, hysteresis=2.0)[1], plain)
    grown = preprocess(img, 100.0, sigma, 2.0, hysteresis=0.5, grow=1)[1]
    assert grown.sum() == 21 and grown[4, 4] and not grown[12, 12]  # the 5 pixels' 3 x 3 neighbourhoods


def test_lit_hysteresis_is_checked():
    assert ReconSettings().lit_hysteresis is None
    for bad in (-0.5, 2.5):
        with pytest.raises(ValueError, match="lit_hysteresis must be from 0 to threshold_sigma"):
            ReconSettings(lit_hysteresis=bad)
    assert ReconSettings(lit_hysteresis=3.0, threshold_sigma=3.0).lit_hysteresis == 3.0


@pytest.fixture(scope="module")
def noisy_s2(s2_scene):
    """S2's particles rendered with three times the renderer's shot and read noise, the projector, and the
    particles' voxels (flat indices of the voxels their centres fall in)."""
    rig, grid, pts, _ = s2_scene
    r = rig.render
    render = r.model_copy(update={"rays_per_particle": 5_000, "read_noise_counts": 3 * r.read_noise_counts,
                                  "gain_e_per_count": r.gain_e_per_count / 9})
    img = [LightFieldRenderer(c, render, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, render.particle_counts, seed=1 + k) for k, c in enumerate(rig.camera)]
    zyx = np.rint(grid.world_to_index(pts)).astype(int)
    inside = np.all((zyx >= 0) & (zyx < np.array(grid.shape)), axis=1)
    particles = np.ravel_multi_index(tuple(zyx[inside].T), grid.shape)
    return projector_for(rig.camera, grid, device="cpu"), img, particles


def test_a_strict_elimination_with_hysteresis_keeps_every_particle_of_a_noisy_frame(noisy_s2):
    """S2 at 3x noise, no dark check allowed: with the hysteresis every particle's voxel survives (without
    it noise darkens a check of some), and the survivors hold every one of the plain mask's."""
    proj, img, particles = noisy_s2
    kept = {}
    for hysteresis in (None, 0.5):
        _, lits, _, _ = preprocess_images(proj, img, ReconSettings(lit_hysteresis=hysteresis))
        kept[hysteresis] = proj.eliminate(lits, max_dark=0.0).numpy().copy()
    assert particles.size > 150
    assert np.isin(particles, kept[0.5]).all()
    assert np.isin(particles, kept[None]).mean() < 1.0  # the loss the hysteresis avoids
    assert np.isin(kept[None], kept[0.5]).all()  # more pixels lit: a superset
    assert kept[0.5].size < 3 * kept[None].size  # still an elimination
