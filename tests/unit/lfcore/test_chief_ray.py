"""lfcore.chief_ray against the renderer: a point source's light, summed per lenslet and
centred over the micro-image centres, lands where ``project`` says."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcore.chief_ray import project
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.white import micro_image_centres

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def _centroid(img: np.ndarray, centres: np.ndarray, pitch_px: float) -> np.ndarray:
    rows, cols = img.shape
    r, c = np.mgrid[0:rows, 0:cols]
    xy = np.stack([c.ravel() + 0.5, r.ravel() + 0.5], axis=-1)
    dist, idx = cKDTree(centres).query(xy, distance_upper_bound=0.6 * pitch_px)
    ok = np.isfinite(dist)
    sums = np.bincount(idx[ok], weights=img.ravel()[ok], minlength=len(centres))
    return (sums[:, None] * centres).sum(axis=0) / sums.sum()


@pytest.mark.parametrize("pose", [(0.0, 0.0, 0.0), (3.0, 30.0, -10.0)])
@pytest.mark.parametrize("dz", [-0.5, 0.4])
def test_project_is_the_centroid_of_a_defocused_point(pose: tuple[float, float, float], dz: float) -> None:
    rig = Rig.from_dict(tomllib.loads((EXAMPLES / "tiny.toml").read_text()))
    cam = rig.camera[0].model_copy(update={"rotation_deg": pose, "mla_rotation_deg": 0.3,
                                           "mla_offset_um": (12.0, -7.0), "magnification": -1.02})
    render = rig.render.model_copy(update={"rays_per_particle": 400_000, "diffraction": False})
    point = cam.camera_to_world(np.array([[0.12, -0.08, dz]]))
    img = LightFieldRenderer(cam, render, device="cpu").irradiance(point, 1e6, seed=1)
    got = _centroid(img, micro_image_centres(cam), cam.pixels_per_lenslet)
    want = project(cam, point)[0]
    # Pixels. The disc of light (2 to 3 lenslets wide) is sampled once per lenslet, which biases
    # its centroid by up to about 0.02 lenslet (0.2 px here): the floor of the dot fit too.
    assert np.hypot(*(got - want)) < 0.25
    assert np.allclose(project(cam, point, pupil_mm=(0.0, 0.0)), want)


def test_points_behind_the_lens_project_to_nan() -> None:
    rig = Rig.from_dict(tomllib.loads((EXAMPLES / "tiny.toml").read_text()))
    cam = rig.camera[0]
    p = project(cam, np.array([[0.0, 0.0, 500.0], [0.0, 0.0, 0.0]]))
    assert np.all(np.isnan(p[0])) and np.allclose(p[1], [96.0, 80.0])
