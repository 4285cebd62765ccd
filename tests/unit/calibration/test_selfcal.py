"""Volume self-calibration (Wieneke 2008): particles, matches, disparity maps, the correction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from calibration.selfcal import SelfCalError, find_particles, match_particles, self_calibrate
from lfcore import pinhole
from lfcore.render import PinholeRenderer
from lfcore.rig import Rig
from lfcore.soloff import SoloffMap
from lfcore.world import ParticleWorld
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig(EXAMPLES / "tomo_4_cameras.toml")


@pytest.fixture(scope="module")
def recording(rig):
    """Eight frames (four pairs) of the 4-camera arc at the chapter's 0.05 ppp, and their truth."""
    world = ParticleWorld(rig, flow="uniform", ppp=0.05, seed=3)
    renderers = [PinholeRenderer(c, rig.render, device="cpu") for c in rig.camera]
    frames, truth = [[] for _ in rig.camera], []
    for k in range(4):
        parts, bright = world.pair(k)
        for f in range(2):
            truth.append(parts[f])
            for ci, r in enumerate(renderers):
                frames[ci].append(r.frame(parts[f], bright[f], seed=100 * k + 10 * f + ci))
    return [np.stack(f) for f in frames], truth


def _off_by_a_pixel(rig: Rig) -> list:
    """The rig's cameras with a 1 px calibration error injected: camera 0 turned so that its image
    moves a pixel down the sensor, camera 2's principal point a pixel off along the diagonal."""
    cams = list(rig.camera)
    turn = np.degrees(1.0 / cams[0].focal_length_px)
    rx, ry, rz = cams[0].rotation_deg
    cams[0] = cams[0].model_copy(update={"rotation_deg": (rx + turn, ry, rz)})
    cams[2] = cams[2].model_copy(update={"principal_point_px": (np.sqrt(0.5), -np.sqrt(0.5))})
    return cams


def _true_disparity(rig: Rig, cams, truth) -> np.ndarray:
    """Per camera, the RMS disparity of the true particles' images triangulated through ``cams``."""
    p = np.concatenate(truth)
    px = np.stack([pinhole.project(c, p) for c in rig.camera])
    x = pinhole.triangulate(cams, px)
    d = px - np.stack([pinhole.project(c, x) for c in cams])
    return np.sqrt(np.mean(np.sum(d**2, axis=-1), axis=1))


def test_isolated_particles_are_centred_to_hundredths_of_a_pixel(rig):
    cam = rig.camera[1]
    pts = np.random.default_rng(0).uniform(-4.0, 4.0, (40, 3)) * [1.0, 1.0, 0.4]
    img = PinholeRenderer(cam, rig.render, device="cpu").frame(pts, 10000.0, seed=1)
    found = find_particles(img)
    dist, _ = cKDTree(pinhole.project(cam, pts)).query(found)
    # (a pair whose images touch pulls each other by a tenth or two)
    assert len(found) >= 36 and np.median(dist) < 0.03 and np.percentile(dist, 90) < 0.05


def test_true_models_match_every_sparse_particle_without_disparity(rig):
    pts = np.random.default_rng(1).uniform(*rig.volume.bounds_mm, (60, 3))
    particles = [pinhole.project(c, pts) for c in rig.camera]
    x, d = match_particles(rig.camera, particles, rig.volume.bounds_mm, radius_px=1.0)
    near, _ = cKDTree(x).query(pts)
    assert near.max() < 1e-6  # every particle found, at its place
    true = cKDTree(pts).query(x)[0] < 1e-6
    assert np.abs(d[:, true]).max() < 1e-6  # with no disparity
    assert true.sum() == 60 and (~true).sum() < 20  # and a few ghosts: particles that happen to line up


def test_an_injected_pixel_of_calibration_error_is_brought_below_a_tenth(rig, recording):
    frames, truth = recording
    cams = _off_by_a_pixel(rig)
    assert _true_disparity(rig, cams, truth).max() > 0.5
    # each camera's Soloff polynomial, as fitted to the same (wrong) calibration
    lo, hi = rig.volume.bounds_mm
    grid = np.stack(np.meshgrid(*[np.linspace(a, b, 6) for a, b in zip(lo, hi, strict=True)], indexing="ij"),
                    axis=-1).reshape(-1, 3)
    soloff = [SoloffMap.fit(grid, pinhole.project(c, grid)) for c in cams]
    res = self_calibrate(cams, frames, rig.volume.bounds_mm, soloff=soloff)
    assert res.frames == 8 and len(res.rms_px) == 4  # before, and after each of 3 corrections
    # what it measured: the injected error, then disparity maps below a tenth of a pixel
    assert res.max_px[0] > 0.5 and res.rms_px[0] > 0.25
    assert res.rms_px[-1] < 0.1
    # what is true: the particles' own images agree through the corrected models to hundredths
    assert _true_disparity(rig, res.cameras, truth).max() < 0.05
    # the Soloff polynomials were corrected by the same maps: they map as the corrected models do
    for cam, m in zip(res.cameras, res.soloff, strict=True):
        assert np.hypot(*(m.project(grid) - pinhole.project(cam, grid)).T).max() < 0.1


def test_too_few_cameras_or_particles_say_what_to_do(rig, recording):
    frames, _ = recording
    with pytest.raises(SelfCalError, match="1 pinhole camera"):
        self_calibrate(rig.camera[:1], frames[:1], rig.volume.bounds_mm)
    dark = [np.full((2, 160, 160), 100, dtype=np.uint16) for _ in rig.camera]
    with pytest.raises(SelfCalError, match="no sub-volume has 20 matched particles"):
        self_calibrate(rig.camera, dark, rig.volume.bounds_mm, iterations=0)
