"""Rig files: validation that names the key, the derived optics, poses and the voxel grid."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcore.rig import Rig, RigError, rotation_angle_deg, voxel_shape_warnings
from lfcore.volume import VolumeGrid
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES, tiny_variant


@pytest.mark.parametrize("name", ["tiny", "one_camera", "two_cameras", "two_cameras_off_focus",
                                  "one_camera_off_focus"])
def test_examples_load_with_matched_optics(name):
    rig = load_rig(EXAMPLES / f"{name}.toml")
    assert rig.optics_warnings() == []
    for cam in rig.camera:
        assert cam.image_side_f_number == pytest.approx(cam.lenslet_f_number)


def test_two_camera_example_is_29mp_at_90_degrees():
    rig = load_rig(EXAMPLES / "two_cameras.toml")
    a, b = rig.camera
    assert a.sensor_px[0] * a.sensor_px[1] == pytest.approx(29e6, rel=0.01)
    assert (a.pixel_pitch_um, a.mla_pitch_um, a.mla_focal_length_um, a.mla_grid) == (5.5, 77.0, 308.0, "hex")
    cos = float(a.optical_axis @ b.optical_axis)
    assert math.degrees(math.acos(cos)) == pytest.approx(90.0)


def test_off_focus_example_keeps_both_focal_planes_out_of_the_box():
    # particles near a light-field camera's focal plane are not located: the example focuses beyond the box
    rig = load_rig(EXAMPLES / "two_cameras_off_focus.toml")
    grid = VolumeGrid.from_rig(rig)
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T
    corners = np.asarray(rig.volume.centre_mm) + corners * np.asarray(rig.volume.size_mm)
    a, b = rig.camera
    assert math.degrees(math.acos(abs(float(a.optical_axis @ b.optical_axis)))) == pytest.approx(90.0)
    for cam in rig.camera:
        depth = cam.world_to_camera(corners)[:, 2]  # + toward the camera from its focal plane
        assert depth.min() >= 10 * max(grid.voxel_mm)  # the whole box in front of the focal plane, 10 voxels clear


def test_one_camera_off_focus_example_is_the_tiny_rig_focused_beyond_its_box():
    # one light-field camera cannot place the particles within ~3 of its 55 um depth voxels of its focal
    # plane, nor ~174 um in front of it: the example moves the focal plane 0.2 mm beyond the box
    rig = load_rig(EXAMPLES / "one_camera_off_focus.toml")
    tiny = load_rig(EXAMPLES / "tiny.toml")
    (cam,), (cam0,) = rig.camera, tiny.camera
    assert rig.volume == tiny.volume
    assert cam.model_copy(update={"focus_mm": cam0.focus_mm}) == cam0  # only the focus differs
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T
    corners = np.asarray(rig.volume.centre_mm) + corners * np.asarray(rig.volume.size_mm)
    depth = cam.world_to_camera(corners)[:, 2]  # + toward the camera from its focal plane
    assert depth.min() == pytest.approx(0.2)  # the whole box in front of the focal plane, 0.2 mm clear
    assert depth.min() > max(3 * VolumeGrid.from_rig(rig).voxel_mm[2], 0.174)


def test_m512_off_focus_rig_is_issue_48s_512_rig_focused_beyond_its_box():
    # benchmarks/rigs/m512_off_focus.toml is benchmarks/recon.py's Mc (the M camera cropped to 512 x 512 px,
    # a 4.5 x 4.5 x 12 mm box) with the focus moved 6.8 mm away from the camera, as benchmarks/particles.py's
    # Mcoff: 245 x 245 x 131 voxels, the focal plane 0.8 mm beyond the far face of the box
    rig = load_rig(EXAMPLES.parent / "benchmarks" / "rigs" / "m512_off_focus.toml")
    m = load_rig(EXAMPLES / "one_camera.toml")
    (cam,), (cam0,) = rig.camera, m.camera
    assert rig.optics_warnings() == []
    assert rig.volume == m.volume.model_copy(update={"size_mm": (4.5, 4.5, 12.0)})
    assert cam.model_copy(update={"focus_mm": cam0.focus_mm, "sensor_px": cam0.sensor_px}) == cam0
    assert tuple(cam.sensor_px) == (512, 512)
    np.testing.assert_allclose(np.asarray(cam.focus_mm), np.asarray(cam0.focus_mm) - 6.8 * cam0.optical_axis)
    assert VolumeGrid.from_rig(rig).shape == (131, 245, 245)  # z, y, x
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T
    corners = np.asarray(rig.volume.centre_mm) + corners * np.asarray(rig.volume.size_mm)
    depth = cam.world_to_camera(corners)[:, 2]  # + toward the camera from its focal plane
    assert depth.min() == pytest.approx(0.8) and depth.max() == pytest.approx(12.8)


def _benchmark(name: str):
    """benchmarks/NAME.py as a module (the benchmarks are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"bench_{name}", EXAMPLES.parent / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_lc_cases_are_ls_optics_on_a_hundredth_of_its_box():
    # benchmarks/particles.py's Lc is benchmarks/recon.py's: camera 0 of the chapter's 29 MP rig on a
    # 660 x 440 crop of its sensor, 330 x 220 x 182 voxels of 11 x 11 x 55 um, 878 particles at 0.5 PPM
    # (85,578 in L's box); Lcoff the same focused 5.3 mm away from the camera, its focal plane 0.295 mm
    # beyond the far face of the 10.01 mm deep box
    from lfcore.particles import particle_count

    particles = _benchmark("particles")
    rig, shift = particles.case_rig("Lc")
    (cam,), cam0 = rig.camera, load_rig(EXAMPLES / "two_cameras.toml").camera[0]
    assert shift == 0.0 and rig.optics_warnings() == []
    assert cam.model_copy(update={"sensor_px": cam0.sensor_px}) == cam0
    assert tuple(cam.sensor_px) == (660, 440)
    assert VolumeGrid.from_rig(rig).shape == (182, 220, 330)  # z, y, x
    np.testing.assert_allclose(VolumeGrid.from_rig(rig).voxel_mm, (0.011, 0.011, 0.055))
    assert particle_count(rig, ppm=0.5) == 878
    off, shift = particles.case_rig("Lcoff")
    assert shift == -5.3 and off.volume == rig.volume
    np.testing.assert_allclose(np.asarray(off.camera[0].focus_mm), np.asarray(cam.focus_mm) - 5.3 * cam.optical_axis)
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T
    corners = np.asarray(rig.volume.centre_mm) + corners * np.asarray(rig.volume.size_mm)
    depth = off.camera[0].world_to_camera(corners)[:, 2]  # + toward the camera from its focal plane
    assert depth.min() == pytest.approx(0.295) and depth.max() == pytest.approx(10.305)
    assert particles.case_rig("Lc", focus_shift=-1.0)[1] == -1.0


def test_derived_distances_follow_thin_lens(tiny_rig):
    cam = tiny_rig.camera[0]  # F = 50 mm, M = -1, N = 2
    assert cam.image_distance_mm == pytest.approx(100.0)
    assert cam.object_distance_mm == pytest.approx(100.0)
    assert cam.aperture_mm == pytest.approx(25.0)
    assert 1 / cam.object_distance_mm + 1 / cam.image_distance_mm == pytest.approx(1 / cam.main_focal_length_mm)
    assert cam.pixels_per_lenslet == pytest.approx(10.0)


def test_f_number_mismatch_warns_with_the_fix(tiny_rig):
    rig = tiny_variant(tiny_rig, f_number=4.0)
    (msg,) = rig.optics_warnings()
    assert "cam0" in msg and "N(1-M) = 8.00" in msg and "set f_number = 2 " in msg


@pytest.mark.parametrize(
    ("second", "pvr", "warns"),
    [
        (None, (2, 2, 10), False),  # one camera: deep voxels are what it resolves
        ((0, 90, 0), (2, 2, 10), True),
        ((0, -60, 0), (2, 2, 10), True),
        ((0, 90, 0), (2, 2, 2), False),
        ((0, 90, 0), (3, 3, 5), False),  # less than 2x: left to the user
        ((0, 30, 0), (2, 2, 10), False),  # close views share most of their depth axis
        ((0, 180, 0), (2, 2, 10), False),  # facing cameras share it entirely
    ],
)
def test_crossed_cameras_on_deep_voxels_warn_with_the_fix(tiny_rig, second, pvr, warns):
    cams = [tiny_rig.camera[0]]
    if second is not None:
        cams.append(cams[0].model_copy(update={"name": "cam1", "rotation_deg": second}))
    msgs = voxel_shape_warnings(cams, pvr)
    assert len(msgs) == int(warns)
    if warns:
        angle = abs(second[1])
        assert f"'cam0' and 'cam1' view the volume {angle} degrees apart" in msgs[0]
        assert "5x longer than wide (PVR 2, 2, 10)" in msgs[0] and "--pvr 2,2,2" in msgs[0]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"f_nmber": 2.0}, "camera[0].f_nmber: unknown key"),
        ({"f_number": -2.0}, "camera[0].f_number: input should be greater than 0"),
        ({"magnification": 0.5}, "camera[0].magnification: input should be less than 0"),
        ({"mla_grid": "triangle"}, "camera[0].mla_grid: input should be 'hex' or 'square'"),
        ({"mla_pitch_um": 5.0}, "camera[0]: mla_pitch_um must cover at least 2 pixels"),
        ({"sensor_px": [192]}, "camera[0].sensor_px"),
        ({"name": "truth"}, "camera[0].name: 'truth' is reserved"),
        ({"main_focal_length_mm": 0.7}, "the volume reaches within the focal length of camera 'cam0'"),
        ({"focus_mm": [0.0, 0.0, 1e9]}, "the volume lies 1e+09 mm from the focal plane of camera 'cam0'"),
    ],
)
def test_bad_camera_values_name_their_key(tiny_rig, change, expected):
    d = tiny_rig.to_dict()
    d["camera"][0].update(change)
    with pytest.raises(RigError) as err:
        Rig.from_dict(d, source="rig.toml")
    msg = str(err.value)
    assert msg.startswith("rig.toml: ") and expected in msg and "\n" not in msg


def test_bad_tables_name_their_key(tiny_rig):
    d = tiny_rig.to_dict()
    d["laser"]["sheet_profile"] = "gaussian"
    with pytest.raises(RigError, match=r"laser: sheet_thickness_mm is required"):
        Rig.from_dict(d)
    d = tiny_rig.to_dict()
    d["volume"]["pvr"] = [2, 0, 10]
    with pytest.raises(RigError, match=r"volume.pvr\[1\]: input should be greater than 0"):
        Rig.from_dict(d)
    d = tiny_rig.to_dict()
    d["camera"].append(dict(d["camera"][0]))
    with pytest.raises(RigError, match="'cam0' appears twice"):
        Rig.from_dict(d)
    d = tiny_rig.to_dict()
    d["lazer"] = {}
    with pytest.raises(RigError, match="lazer: unknown key"):
        Rig.from_dict(d)
    del d["lazer"], d["volume"]
    with pytest.raises(RigError, match="volume: required key is missing"):
        Rig.from_dict(d)


EXAMPLE = EXAMPLES / "one_camera.toml"


@pytest.mark.parametrize("old, new, message", [
    # a misspelt key is named, with the key it meant, not the key it leaves missing
    ("pixel_pitch_um", "pixel_pich_um", r"camera\[0\]\.pixel_pich_um: unknown key \(did you mean pixel_pitch_um\?\)"),
    ("dt_us", "dt_uss", r"timing\.dt_uss: unknown key \(did you mean dt_us\?\)"),
    ("[laser]", "[lazer]", r"lazer: unknown key \(did you mean laser\?\)"),
    ("[[camera]]", "[camera]", r"camera: write each camera as an array of tables, \[\[camera\]\], not \[camera\]"),
    # a quoted number is refused rather than converted
    ("pixel_pitch_um = 5.5", 'pixel_pitch_um = "5.5"',
     r"camera\[0\]\.pixel_pitch_um: input should be a valid number \(got '5\.5'\); write numbers .* without quotes"),
    ("sensor_px = [2048, 2048]", "sensor_px = [2048.5, 2048]",
     r"camera\[0\]\.sensor_px\[0\]: input should be a valid integer"),
    # a pitch in millimetres leaves a sensor a fraction of a lenslet wide
    ("pixel_pitch_um = 5.5", "pixel_pitch_um = 0.0055",
     r"camera\[0\]: the sensor is only 0\.146 x 0\.146 lenslets .* check the units"),
])
def test_rig_file_slips_are_named(tmp_path, old, new, message):
    text = EXAMPLE.read_text()
    assert old in text
    path = tmp_path / "rig.toml"
    path.write_text(text.replace(old, new))
    with pytest.raises(RigError, match=f"^{path}: {message}"):
        load_rig(path)


def test_whole_numbers_written_as_floats_and_numpy_values_load(tiny_rig, tmp_path):
    path = tmp_path / "rig.toml"
    text = (EXAMPLES / "tiny.toml").read_text()
    assert "sensor_px = [192, 160]" in text and "rays_per_particle = 4000" in text
    path.write_text(text.replace("sensor_px = [192, 160]", "sensor_px = [192.0, 160.0]")
                    .replace("rays_per_particle = 4000", "rays_per_particle = 4e3"))
    rig = load_rig(path)
    assert rig.camera[0].sensor_px == (192, 160) and rig.render.rays_per_particle == 4000
    d = tiny_rig.to_dict()
    d["camera"][0]["sensor_px"] = np.array([192, 160])
    d["camera"][0]["f_number"] = np.float32(2.0)
    assert Rig.from_dict(d) == tiny_rig


def test_a_sensor_a_few_lenslets_wide_loads_with_a_warning(tiny_rig):
    # stores made before the unit check may hold such small test cameras: they must still open
    cam = tiny_variant(tiny_rig, sensor_px=[32, 32]).camera[0]
    assert any("only 3.2 x 3.2 lenslets" in w for w in cam.optics_warnings())


def test_many_pixels_per_lenslet_is_suspected(tiny_rig):
    cam = tiny_variant(tiny_rig, mla_pitch_um=tiny_rig.camera[0].pixel_pitch_um * 80,
                       sensor_px=[800, 800]).camera[0]
    assert any("spans 80 pixels" in w for w in cam.optics_warnings())
    assert not any("spans" in w for w in tiny_rig.camera[0].optics_warnings())


def test_stage_address_and_microstep(tiny_rig):
    d = tiny_rig.to_dict()
    assert d["stage"] == {"port": None, "baud": 115200, "device": 1, "axis": 1, "microstep_um": 0.1}
    d["stage"].update(device=2, axis=1, microstep_um=0.047625)
    assert Rig.from_dict(d).stage.microstep_um == 0.047625
    d["stage"]["device"] = 0
    with pytest.raises(RigError, match=r"stage\.device: input should be greater than or equal to 1"):
        Rig.from_dict(d)


def test_rig_file_errors(tmp_path):
    with pytest.raises(RigError, match="not found"):
        load_rig(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[volume\nsize_mm = 1\n")
    with pytest.raises(RigError, match=r"bad.toml: invalid TOML: .*line 1"):
        load_rig(bad)


def test_rig_round_trips_through_its_dict(tiny_rig):
    assert Rig.from_dict(tiny_rig.to_dict()) == tiny_rig


def test_pose_convention(tiny_rig):
    # Identity pose: the camera is on world +z; depth dz is positive toward it.
    cam = tiny_rig.camera[0]
    assert np.allclose(cam.optical_axis, [0, 0, 1])
    assert np.allclose(cam.world_to_camera([[0.1, 0.2, 0.3]]), [[0.1, 0.2, 0.3]])
    # Rotated 90 degrees about y, it sits on world +x; a world point toward +x is closer to it.
    side = tiny_variant(tiny_rig, rotation_deg=[0, 90, 0], focus_mm=[0.0, 0.1, 0.0]).camera[0]
    assert np.allclose(side.optical_axis, [1, 0, 0])
    p = np.array([[0.3, 0.1, 0.0]])
    assert side.world_to_camera(p)[0, 2] == pytest.approx(0.3)
    # R = Rz Ry Rx: an x rotation applied first, then z.
    rot = tiny_variant(tiny_rig, rotation_deg=[90, 0, 90]).camera[0]
    assert np.allclose(rot.rotation @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    assert np.allclose(rot.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    q = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(rot.camera_to_world(rot.world_to_camera(q)), q)


def test_volume_grid_from_pvr(tiny_rig):
    g = VolumeGrid.from_rig(tiny_rig)
    pix = 5.5e-3  # object-side pixel at |M| = 1
    assert g.voxel_mm == pytest.approx((2 * pix, 2 * pix, 10 * pix))
    assert g.shape == (29, 68, 82)  # (z, y, x) of 1.6 x 0.75 x 0.9 mm
    assert g.axis_mm("x").mean() == pytest.approx(0.0)
    assert g.world_to_index([g.origin_mm]) == pytest.approx(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="pvr must be three positive"):
        VolumeGrid.from_rig(tiny_rig, pvr=(2, 2, 0))


def test_rotation_angle_between_poses_is_small_where_euler_angles_jump():
    assert rotation_angle_deg((0, 30, 0), (0, 30, 0)) == 0.0
    assert rotation_angle_deg((10, 20, 30), (10, 20, 30.25)) == pytest.approx(0.25, abs=1e-9)
    assert rotation_angle_deg((0, 90, 0), (0, 90, 0.001)) == pytest.approx(0.001, rel=1e-6)
    # at gimbal lock (ry = 90) rx and rz turn about one axis: only rz - rx counts
    assert rotation_angle_deg((0, 90, 0), (-108.0, 90.0, -108.0)) == pytest.approx(0.0, abs=1e-6)
    assert rotation_angle_deg((0, 90, 0), (-108.0107, 89.9861, -108.0168)) < 0.02
    assert rotation_angle_deg((0, 0, 0), (0, 180, 0)) == pytest.approx(180.0)
