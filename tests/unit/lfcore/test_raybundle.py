"""Ray-bundling candidates (lfcore.raybundle) on the tiny rig focused beyond its box, from known truths.

Particles rendered by the Monte-Carlo renderer at known points: their bright pixels' rays must bundle
where they are (within a voxel), two well-separated particles give two candidates, a blank image none;
a pixel's ray must pass the particle that lit it; and IPR with ``candidate_source="rays"`` must find
isolated particles as it does from the reconstruction's peaks.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import ipr
from lfcore.plan import projector_for
from lfcore.raybundle import camera_rays, ray_candidates
from lfcore.render import LightFieldRenderer
from lfcore.volume import VolumeGrid


def _image(rig, pts, seed=1):
    cfg = rig.render.model_copy(update={"rays_per_particle": 40_000})
    return LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, 50_000.0, seed=seed)


@pytest.fixture(scope="module")
def setup():
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    # focused 0.2 mm beyond the box (the way to focus for particles): every particle's light spreads over
    # lenslets, which see it from different directions (on the focal plane one lenslet sees it all)
    rig = load_rig(EXAMPLES / "one_camera_off_focus.toml")
    return rig, VolumeGrid.from_rig(rig)


def _err(grid, found, truth_u):
    """Each true point's largest per-axis distance (voxels) to the nearest candidate."""
    return np.array([np.min(np.max(np.abs(found - t), axis=1)) for t in truth_u])


def test_a_pixels_ray_passes_the_particle_that_lit_it(setup):
    rig, grid = setup
    truth = ipr.to_mm(grid, np.array([[15.3, 30.2, 40.6]]))
    rays = camera_rays(rig.camera[0], _image(rig, truth), threshold_sigma=4.0)
    assert rays.n > 20
    rel = truth[0] - rays.origin
    dist = np.linalg.norm(rel - np.sum(rel * rays.direction, axis=1, keepdims=True) * rays.direction, axis=1)
    # each ray stands for a tube an object-side lenslet wide (the ray was taken through the lenslet's
    # centre, the light passed anywhere in its cell): half the rays within half of it, three in four
    # within its width (the rest: the diffraction blur's tails and noise pixels)
    print("distances / tube: percentiles 50, 75, 90", (np.percentile(dist, [50, 75, 90]) / rays.tube_mm).round(2))
    assert np.median(dist) < 0.5 * rays.tube_mm
    assert np.percentile(dist, 75) < rays.tube_mm
    assert np.allclose(np.linalg.norm(rays.direction, axis=1), 1.0)


@pytest.mark.parametrize("u", [[15.3, 30.2, 40.6], [22.6, 47.7, 28.2], [5.4, 20.7, 60.1]])
def test_a_single_particles_rays_bundle_within_a_voxel_of_it(setup, u):
    rig, grid = setup
    truth_u = np.array([u])
    found, scores = ray_candidates(grid, rig.camera, [_image(rig, ipr.to_mm(grid, truth_u))])
    assert len(found) >= 1
    print("candidates", found.round(2), scores.round(0))
    # the strongest candidate is the particle, within a voxel on every axis
    assert np.all(np.abs(found[0] - truth_u[0]) < 1.0)


def test_two_separated_particles_give_two_candidates(setup):
    rig, grid = setup
    truth_u = np.array([[15.3, 30.2, 40.6], [22.6, 47.7, 20.2]])
    found, _ = ray_candidates(grid, rig.camera, [_image(rig, ipr.to_mm(grid, truth_u))])
    print("candidates", found.round(2))
    assert len(found) == 2
    assert np.all(_err(grid, found, truth_u) < 1.0)


def test_a_blank_image_gives_no_candidates(setup):
    rig, grid = setup
    blank = _image(rig, np.zeros((0, 3)))
    found, scores = ray_candidates(grid, rig.camera, [blank])
    assert found.shape == (0, 3) and scores.shape == (0,)


def test_ipr_from_ray_candidates_finds_isolated_particles(setup):
    rig, grid = setup
    u = np.array([[5.3, 20.25, 24.65], [22.6, 47.7, 28.2], [23.2, 24.4, 59.3], [6.75, 49.15, 56.55]])
    truth = ipr.to_mm(grid, u)
    proj = projector_for(rig.camera, grid, device="cpu")
    settings = ipr.IprSettings(candidate_source="rays", wavelength_nm=rig.laser.wavelength_nm)
    res = ipr.ParticleReconstructor(proj, settings=settings).reconstruct([_image(rig, truth)])
    err = np.array([np.min(np.max(np.abs(res.positions_mm - t) / grid.voxel_mm, axis=1)) for t in truth])
    print("particles", res.n, "largest error per particle (voxels)", err.round(3))
    assert res.n == len(truth)  # no ghost, none missed
    assert np.all(err < 0.1)


def test_the_candidate_source_is_checked():
    with pytest.raises(ValueError, match="source"):
        ipr.IprSettings(candidate_source="voxels")
    assert ipr.IprSettings().candidate_source == "reconstruction"


@pytest.mark.parametrize("kind", ["pinhole", "mixed"])
def test_pinhole_and_mixed_rigs_candidates_by_rays(kind):
    from lfcore.render import renderer_for
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES
    from tests.helpers import four_particles, tomo_arc_small

    # four pinhole cameras, or the mixed rig (a light-field camera and two pinhole ones, focused on the
    # box's middle: near its focal plane the light-field camera abstains and the pinhole ones decide)
    rig = tomo_arc_small() if kind == "pinhole" else load_rig(EXAMPLES / "mixed_cameras.toml")
    grid = VolumeGrid.from_rig(rig)
    u = four_particles(grid)
    truth = ipr.to_mm(grid, u)
    cfg = rig.render.model_copy(update={"rays_per_particle": 40_000})
    counts = 50_000.0 if kind == "pinhole" else 10_000.0  # the mixed rig's 12-bit pinhole cameras saturate
    images = [renderer_for(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(truth, counts, seed=3 + i)
              for i, c in enumerate(rig.camera)]
    found, _ = ray_candidates(grid, rig.camera, images)
    print(kind, "candidates", len(found), "nearest to each particle (voxels)", _err(grid, found, u).round(2))
    assert np.all(_err(grid, found, u) < 1.0)
    settings = ipr.IprSettings(candidate_source="rays", wavelength_nm=rig.laser.wavelength_nm,
                               particle_image_px=rig.render.particle_image_px)
    proj = projector_for(rig.camera, grid, device="cpu")
    res = ipr.ParticleReconstructor(proj, settings=settings).reconstruct(images)
    err = np.array([np.min(np.max(np.abs(res.positions_mm - t) / grid.voxel_mm, axis=1)) for t in truth])
    print(kind, "particles", res.n, "largest error per particle (voxels)", err.round(3))
    assert res.n == len(truth)
    assert np.all(err < 0.05)
