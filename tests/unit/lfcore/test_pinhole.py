"""Pinhole (Tomo-PIV) cameras: the rig file, the camera model, its Warp twin and the renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from lfcore import pinhole
from lfcore._kernels.pinhole import PinholeParams, pinhole_params, pinhole_project, pinhole_ray
from lfcore.chief_ray import chief_ray_mla
from lfcore.mla import sensor_to_pixel
from lfcore.particles import particle_count
from lfcore.render import LightFieldRenderer, PinholeRenderer, renderer_for
from lfcore.rig import NotLightFieldError, PinholeCamera, Rig, RigError, camera_from_dict
from lfcore.white import white_image
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES


@pytest.fixture(scope="module")
def tomo4() -> Rig:
    return load_rig(EXAMPLES / "tomo_4_cameras.toml")


def _pinhole(**changes) -> PinholeCamera:
    table = {"kind": "pinhole", "name": "t", "sensor_px": [160, 120], "pixel_pitch_um": 7.4, "focal_length_mm": 85.0,
             "object_distance_mm": 946.5, **changes}
    return camera_from_dict(table)


# --- the rig file ---------------------------------------------------------------------------

def test_chapter_arcs_load_with_the_chapter_optics():
    for n in (4, 6, 8):
        rig = load_rig(EXAMPLES / f"tomo_{n}_cameras.toml")
        assert len(rig.camera) == n and all(c.kind == "pinhole" for c in rig.camera)
        ry = [c.rotation_deg[1] for c in rig.camera]
        assert ry == pytest.approx([-90 + (k + 0.5) * 180 / n for k in range(n)])  # equally spaced on the arc
        cam = rig.camera[0]
        # f 85 mm, image and object distances 93.4 and 946.5 mm, 0.075 mm per pixel
        assert cam.image_distance_mm == pytest.approx(93.4, abs=0.05)
        assert cam.object_distance_mm == pytest.approx(946.5, abs=1e-9)
        assert cam.object_pixel_mm == pytest.approx(0.075, rel=1e-4)
        assert np.linalg.norm(cam.lens_centre_mm) == pytest.approx(946.5)
        assert rig.optics_warnings() == []


def test_light_field_is_the_default_kind_and_kinds_mix():
    rig = load_rig(EXAMPLES / "mixed_cameras.toml")
    assert [c.kind for c in rig.camera] == ["lightfield", "pinhole", "pinhole"]
    assert [c.name for c in rig.lightfield_cameras] == ["lf0"] and len(rig.pinhole_cameras) == 2
    assert Rig.from_dict(rig.to_dict()) == rig
    assert load_rig(EXAMPLES / "tiny.toml").camera[0].kind == "lightfield"


@pytest.mark.parametrize(("change", "message"), [
    ({"mla_pitch_um": 55.0}, 'camera[0].mla_pitch_um: a pinhole camera (kind = "pinhole") has no mla_pitch_um'),
    ({"kind": "tomo"}, "camera[0]: kind must be 'lightfield' (the default) or 'pinhole'"),
    ({"focal_lenth_mm": 85.0}, "camera[0].focal_lenth_mm: unknown key (did you mean focal_length_mm?)"),
    ({"magnification": -0.1}, "camera[0]: give magnification or object_distance_mm, not both"),
    ({"object_distance_mm": 50.0}, "object_distance_mm must be beyond the focal length (85 mm), got 50"),
    ({"k1": "0.1"}, "camera[0].k1: input should be a valid number"),
])
def test_pinhole_keys_are_checked_in_one_line(change, message):
    table = {"kind": "pinhole", "name": "t", "sensor_px": [160, 160], "pixel_pitch_um": 7.4, "focal_length_mm": 85.0,
             "object_distance_mm": 946.5, **change}
    with pytest.raises(RigError, match=None) as err:
        Rig.from_dict({"volume": {"size_mm": [10, 10, 4]}, "camera": [table]})
    assert message in str(err.value) and "\n" not in str(err.value)


def test_pinhole_keys_on_a_light_field_camera_say_which_kind(tiny_rig):
    d = tiny_rig.to_dict()
    d["camera"][0]["k1"] = 0.01
    with pytest.raises(RigError, match=r'camera\[0\].k1: k1 is a key of pinhole cameras; set kind = "pinhole"'):
        Rig.from_dict(d)


def test_light_field_code_refuses_a_pinhole_camera_naming_it(tomo4):
    cam = tomo4.camera[0]
    with pytest.raises(NotLightFieldError, match="camera 'cam0' is a pinhole camera: a white image needs"):
        white_image(cam)
    with pytest.raises(NotLightFieldError, match="camera 'cam0' is a pinhole camera: the light-field renderer"):
        LightFieldRenderer(cam, tomo4.render, device="cpu")
    with pytest.raises(NotLightFieldError, match="camera 'cam0' is a pinhole camera: it has no mla_pitch_mm"):
        _ = cam.mla_pitch_mm
    assert not hasattr(cam, "pixels_per_lenslet")  # still an AttributeError for hasattr
    with pytest.raises(ValueError, match="only pinhole cameras, which have no microlenses; give the seeding in "
                                         "particles per pixel"):
        particle_count(tomo4, ppm=0.5)


def test_seeding_in_particles_per_pixel(tomo4):
    assert particle_count(tomo4, ppp=0.05) == 1280  # 0.05 x 160 x 160
    assert particle_count(tomo4) == 1280  # a rig of pinhole cameras only: 0.05 ppp by default
    mixed = load_rig(EXAMPLES / "mixed_cameras.toml")
    assert particle_count(mixed, ppp=0.1) == 2560  # on the first pinhole camera
    with pytest.raises(ValueError, match="beyond 1 particles per pixel"):
        particle_count(tomo4, ppp=2.0)


# --- the camera model -----------------------------------------------------------------------

def test_a_point_projects_to_the_pixel_the_pinhole_puts_it():
    cam = _pinhole()
    f_px = cam.image_distance_mm / 7.4e-3
    assert cam.focal_length_px == pytest.approx(f_px)
    # the focus point images on the sensor centre; a point 1 mm right and 2 mm up, 10 mm nearer
    assert pinhole.project(cam, [0.0, 0.0, 0.0]) == pytest.approx([80.0, 60.0])
    col, row = pinhole.project(cam, [1.0, 2.0, 10.0])
    d = 946.5 - 10.0
    assert col == pytest.approx(80.0 + f_px * 1.0 / d, abs=1e-9)  # upright: +x to the right
    assert row == pytest.approx(60.0 - f_px * 2.0 / d, abs=1e-9)  # +y toward row 0
    assert np.isnan(pinhole.project(cam, [0.0, 0.0, 2000.0])).all()  # behind the lens


def test_pinhole_and_light_field_cameras_share_one_world_frame(tiny_rig):
    lf = tiny_rig.camera[0].model_copy(update={"rotation_deg": (10.0, -30.0, 5.0), "focus_mm": (0.1, -0.2, 0.3)})
    ph = camera_from_dict({"kind": "pinhole", "name": "p", "sensor_px": list(lf.sensor_px),
                           "pixel_pitch_um": lf.pixel_pitch_um, "focal_length_mm": lf.main_focal_length_mm,
                           "magnification": lf.magnification, "rotation_deg": list(lf.rotation_deg),
                           "focus_mm": list(lf.focus_mm)})
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    # the pinhole image is where the light-field camera's chief ray meets its image plane
    assert pinhole.project(ph, pts) == pytest.approx(sensor_to_pixel(lf, chief_ray_mla(lf, pts)), abs=1e-9)


def test_distortion_round_trip_and_lines_of_sight():
    cam = _pinhole(k1=0.8, k2=-3.0, p1=0.004, p2=-0.003, principal_point_px=[4.5, -3.0],
                   rotation_deg=[5.0, 30.0, -10.0], focus_mm=[1.0, 0.5, -2.0])
    xy = np.random.default_rng(1).uniform(-0.06, 0.06, (200, 2))
    assert pinhole.undistort(pinhole.distort(xy, cam.distortion), cam.distortion) == pytest.approx(xy, abs=1e-14)
    pts = np.random.default_rng(2).uniform(-5.0, 5.0, (200, 3))
    px = pinhole.project(cam, pts)
    origin, direction = pinhole.line_of_sight(cam, px)
    assert np.linalg.norm(direction, axis=-1) == pytest.approx(1.0)
    along = np.einsum("ij,ij->i", pts - origin, direction)
    assert np.all(along > 0)  # into the scene
    miss = np.linalg.norm(origin + along[:, None] * direction - pts, axis=-1)
    assert miss.max() < 1e-9


def test_projection_matrix_is_the_undistorted_model():
    cam = _pinhole(principal_point_px=[2.0, 1.0], rotation_deg=[3.0, -40.0, 2.0])
    pts = np.random.default_rng(3).uniform(-5, 5, (20, 3))
    h = np.concatenate([pts, np.ones((20, 1))], axis=1) @ pinhole.projection_matrix(cam).T
    assert h[:, :2] / h[:, 2:] == pytest.approx(pinhole.project(cam, pts), abs=1e-9)


def test_triangulation_recovers_points_from_the_arc(tomo4):
    pts = np.random.default_rng(4).uniform(-4, 4, (30, 3))
    px = np.stack([pinhole.project(c, pts) for c in tomo4.camera])
    assert pinhole.triangulate(tomo4.camera, px) == pytest.approx(pts, abs=1e-9)
    px[0, :5] = np.nan  # a camera that missed a point is left out of its fit
    px[1:, 5] = np.nan  # seen by one camera only: no point
    out = pinhole.triangulate(tomo4.camera, px)
    assert out[:5] == pytest.approx(pts[:5], abs=1e-9) and np.isnan(out[5]).all()


@wp.kernel
def _project_and_ray(cam: PinholeParams, pts: wp.array(dtype=wp.vec3), px: wp.array(dtype=wp.vec3),
                     dirs: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    q = pinhole_project(cam, pts[i])
    px[i] = q
    dirs[i] = pinhole_ray(cam, q[0], q[1])


def test_warp_twin_matches_the_model(device):
    cam = _pinhole(k1=0.5, k2=-2.0, p1=0.002, p2=0.001, principal_point_px=[3.0, -1.5],
                   rotation_deg=[2.0, 35.0, -4.0], focus_mm=[0.5, 0.0, -1.0])
    pts = np.random.default_rng(5).uniform(-5, 5, (64, 3))
    p_dev = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device)
    px = wp.zeros(64, dtype=wp.vec3, device=device)
    dirs = wp.zeros(64, dtype=wp.vec3, device=device)
    wp.launch(_project_and_ray, dim=64, inputs=[pinhole_params(cam), p_dev, px, dirs], device=device)
    got = px.numpy()
    assert got[:, :2] == pytest.approx(pinhole.project(cam, pts), abs=2e-3)  # float32 on the device
    depth = cam.object_distance_mm - cam.world_to_camera(pts)[:, 2]
    assert got[:, 2] == pytest.approx(depth, rel=1e-5)
    _, want = pinhole.line_of_sight(cam, got[:, :2].astype(np.float64))
    assert dirs.numpy() == pytest.approx(want, abs=1e-5)


# --- synthetic Tomo-PIV images --------------------------------------------------------------

def test_a_point_source_is_a_gaussian_of_the_particle_image_size(tomo4, device):
    cam = tomo4.camera[1].model_copy(update={"k1": 0.5, "principal_point_px": (2.0, -1.0)})
    r = renderer_for(cam, tomo4.render, device=device)
    assert isinstance(r, PinholeRenderer) and r.shape == (160, 160)
    p = np.array([[1.3, -0.7, 0.9]])
    img = r.irradiance(p, 10000.0)
    rows, cols = np.indices(img.shape) + 0.5
    total = img.sum()
    assert total == pytest.approx(10000.0, rel=1e-4)
    centre = np.array([(img * cols).sum(), (img * rows).sum()]) / total
    assert centre == pytest.approx(pinhole.project(cam, p)[0], abs=2e-3)
    # 1/e^2 diameter 3 px: sigma 0.75 px, widened by the pixel's own width (1/12 px^2)
    var = (img * (cols - centre[0]) ** 2).sum() / total
    assert math.sqrt(var) == pytest.approx(math.sqrt(0.75**2 + 1 / 12), rel=0.01)


def test_frames_are_seeded_noisy_and_saturate_at_the_bit_depth(device):
    rig = load_rig(EXAMPLES / "mixed_cameras.toml")
    cam = rig.camera_named("tomo0")  # a 12-bit camera
    r = PinholeRenderer(cam, rig.render, device=device)
    assert r.full_scale == 4095.0
    pts = np.zeros((1, 3))
    a, b = r.frame(pts, 1e6, seed=3), r.frame(pts, 1e6, seed=3)
    assert np.array_equal(a, b) and a.dtype == np.uint16
    assert a.max() == 4095  # a particle brighter than the sensor clips at 2**12 - 1
    dark = r.frame(np.zeros((0, 3)), 0.0, seed=4)
    bg = rig.render.background_counts
    assert dark.mean() == pytest.approx(bg, abs=0.5)
    assert dark.std() == pytest.approx(math.sqrt(bg + rig.render.read_noise_counts**2), rel=0.1)
