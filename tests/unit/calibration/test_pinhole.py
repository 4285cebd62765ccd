"""Calibrating pinhole cameras: blobs, the pinhole fit with distortion, the Soloff polynomial."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.board import default_board
from calibration.dots import match_dots
from calibration.fit import FitError
from calibration.pinhole import detect_blobs, fit_pinhole, refine_pinhole
from calibration.planes import fit_from_planes
from lfcore import pinhole
from lfcore.rig import Rig, camera_from_dict, rotation_angle_deg
from lfcore.soloff import SOLOFF_TERMS, SoloffMap
from lfpiv.rigfile import load_rig
from sim.scenes import dot_target_scene
from tests.conftest import EXAMPLES

STAGE_MM = np.array([-1.5, -0.5, 0.5, 1.5])


@pytest.fixture(scope="module")
def nominal() -> Rig:
    return load_rig(EXAMPLES / "tomo_4_cameras.toml")


@pytest.fixture(scope="module")
def truth(nominal) -> Rig:
    """The rig as built: every camera a little off the rig file's (turned, moved, its principal
    point off centre)."""
    d = nominal.to_dict()
    for k, c in enumerate(d["camera"]):
        c["rotation_deg"] = [v + dv for v, dv in zip(c["rotation_deg"], (0.2, -0.3 + 0.1 * k, 0.15), strict=True)]
        c["focus_mm"] = [0.2, -0.1, 0.15 * k]
        c["principal_point_px"] = [1.5, -1.0]
    return Rig.from_dict(d)


@pytest.fixture(scope="module")
def planes(nominal, truth):
    """The board and each camera's images of it at the stage positions, rendered with the true rig."""
    board = dataclasses.replace(default_board(nominal), stage_centre_mm=0.0)
    images = []
    for z in STAGE_MM:
        scene, _ = dot_target_scene(truth, board.centre_mm[2] + z, board=board, points_per_dot=512)
        images.append([scene(ci) for ci in range(len(truth.camera))])
    return board, [np.stack([im[ci] for im in images]) for ci in range(len(truth.camera))]


def _volume_points(rig: Rig, n: int = 400) -> np.ndarray:
    lo, hi = rig.volume.bounds_mm
    return np.random.default_rng(7).uniform(lo, hi, (n, 3))


def test_blobs_are_centred_on_the_dots(truth, planes):
    board, frames = planes
    cam = truth.camera[1]
    dots = detect_blobs(frames[1][0])
    assert dots.views_px.shape[1] == 1 and len(dots) > 15
    ij = board.indices(6)
    found, which = match_dots(dots, pinhole.project(cam, board.dot_centres(ij, STAGE_MM[0])), ij)
    assert len(found) == len(dots)  # every whole dot is one of the board's
    err = dots.centres_px[found] - pinhole.project(cam, board.dot_centres(which, STAGE_MM[0]))
    assert np.abs(err).max() < 0.02
    marker = np.flatnonzero(np.all(which == 0, axis=1))
    assert len(marker) == 1 and dots.flux[found][marker[0]] > 2.0 * np.median(dots.flux)  # the larger marker dot


def test_a_blob_cut_by_the_edge_is_left_out():
    img = np.full((40, 40), 100, dtype=np.uint16)
    rows, cols = np.indices(img.shape) + 0.5
    for cx, cy in ((20.3, 19.6), (1.0, 30.0)):  # the second is cut by the left edge
        img += (5000 * np.exp(-((cols - cx) ** 2 + (rows - cy) ** 2) / (2 * 1.5**2))).astype(np.uint16)
    dots = detect_blobs(img)
    assert len(dots) == 1 and dots.centres_px[0] == pytest.approx([20.3, 19.6], abs=0.01)


def test_the_fit_recovers_each_true_camera(nominal, truth, planes):
    board, frames = planes
    pts = _volume_points(nominal)
    for ci, (start, true) in enumerate(zip(nominal.camera, truth.camera, strict=True)):
        fit = fit_from_planes(start, board, frames[ci], STAGE_MM, None, wavelength_nm=532.0)
        assert fit.rms_px < 0.02 and fit.dropped == 0 and np.all(fit.plane_dots > 10)
        assert np.all(fit.plane_rms_px < 0.03)
        # where it puts the volume's points: the true camera's image, to a hundredth of a pixel
        miss = np.hypot(*(pinhole.project(fit.camera, pts) - pinhole.project(true, pts)).T)
        assert miss.max() < 0.02, ci
        # the pose: over a 12 mm field a principal point 1.8 px off centre looks like a turn of
        # 1.8 / f_px rad = 0.008 degree, which is all the fit leaves
        assert rotation_angle_deg(fit.camera.rotation_deg, true.rotation_deg) < 0.02
        # the Soloff polynomial fitted to the same dots maps as well
        assert fit.soloff is not None and fit.soloff_rms_px < 0.02
        assert np.hypot(*(fit.soloff.project(pts) - pinhole.project(true, pts)).T).max() < 0.02


def test_too_few_dots_is_a_one_line_error(nominal, planes):
    board, frames = planes
    with pytest.raises(FitError, match=r"camera 'cam0': 0 dot\(s\) on 0 plane\(s\)"):
        fit_pinhole(nominal.camera[0], board, [])


def test_distortion_is_recovered_where_the_field_of_view_shows_it():
    # a wide-angle camera: 12 mm lens, 1024 px of 5.5 um, 300 mm away
    true = camera_from_dict({"kind": "pinhole", "name": "wide", "sensor_px": [1024, 1024], "pixel_pitch_um": 5.5,
                             "focal_length_mm": 12.0, "object_distance_mm": 300.0, "rotation_deg": [1.0, 20.0, -2.0],
                             "principal_point_px": [6.0, -4.0], "k1": -0.12, "k2": 0.05, "p1": 1e-3, "p2": -6e-4})
    half = 0.45 * true.field_of_view_mm[0]
    g = np.linspace(-half, half, 15)
    x, y, z = np.meshgrid(g, g, [-40.0, 0.0, 40.0], indexing="ij")
    world = true.camera_to_world(np.stack([x, y, z], axis=-1).reshape(-1, 3))
    px = pinhole.project(true, world)
    start = true.model_copy(update={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "principal_point_px": (0.0, 0.0),
                                    "rotation_deg": (0.0, 19.0, 0.0)})
    fitted, sol = refine_pinhole(start, world, px + np.random.default_rng(0).normal(0, 0.02, px.shape))
    assert sol.success
    assert fitted.k1 == pytest.approx(-0.12, abs=0.003) and fitted.k2 == pytest.approx(0.05, abs=0.01)
    assert fitted.p1 == pytest.approx(1e-3, abs=1e-4) and fitted.p2 == pytest.approx(-6e-4, abs=1e-4)
    assert fitted.principal_point_px == pytest.approx((6.0, -4.0), abs=0.5)
    assert np.hypot(*(pinhole.project(fitted, world) - px).T).max() < 0.02


def test_soloff_polynomial_fits_its_own_terms_exactly():
    rng = np.random.default_rng(1)
    pts = np.concatenate([np.column_stack([rng.uniform(-5, 5, (60, 2)), np.full(60, z)]) for z in (-2.0, 0.0, 2.0)])
    centre, scale = np.array([0.0, 0.0, 0.0]), np.array([5.0, 5.0, 2.0])
    coef = rng.normal(0, 1, (2, len(SOLOFF_TERMS)))
    u = (pts - centre) / scale
    px = np.prod(u[:, None, :] ** SOLOFF_TERMS, axis=-1) @ coef.T
    m = SoloffMap.fit(pts, px)
    assert m.z_order == 2 and m.project(pts) == pytest.approx(px, abs=1e-9)
    back = SoloffMap.from_dict(m.to_dict())
    assert back.project(pts) == pytest.approx(px, abs=1e-9) and len(m.to_dict()["terms"]) == 19
    one_plane = SoloffMap.fit(pts[:60], px[:60])  # one depth: no term in z
    assert one_plane.z_order == 0 and one_plane.coefficients.shape == (2, 10)
    with pytest.raises(ValueError, match="cannot fit the 19 terms"):
        SoloffMap.fit(pts[::10], px[::10])
