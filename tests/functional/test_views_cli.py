"""``lfpiv views`` and ``lfpiv check-camera`` end to end: a synthetic run's frame, a raw image file
with a calibration fitted to a white image of an MLA that is not where the rig file says, the
simulated lab, and bad input (one line, exit code 2, nothing written)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile

import lfpiv
from lfcore.render import LightFieldRenderer
from lfcore.views import focus_measure, nominal_lattice
from lfcore.volume import VolumeGrid
from lfcore.white import WhiteImageConfig, white_image
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES, run_cli
from tests.helpers import one_error

TINY = EXAMPLES / "tiny.toml"


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("views") / "run.zarr"
    from lfpiv.cli import main

    assert main(["synth", "--rig", str(TINY), "--out", str(path), "--pairs", "1", "--ppm", "0.3", "--quiet"]) == 0
    return path


def test_views_of_a_runs_frame(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "looks"
    rc, text, _ = run_cli(capsys, "views", run, "--frame", "B", "--depths=-0.4:0.4:0.4", "--upsample", "2",
                          "--out", out)
    assert rc == 0
    assert "nominal MLA" in text and "refocused at z = -0.4, 0, 0.4 mm" in text
    views = sorted(out.glob("view_u*_v*.png"))
    res = lfpiv.views(run, frame="B", depths_mm=[0.0])
    assert len(views) == len(res.views.offsets_px) > 50
    for name in ("mosaic.png", "centre.png", "views.png", "refocus_z-0.400mm.png", "refocus_z+0.400mm.png"):
        assert (out / name).is_file()
    centre = iio.imread(out / "centre.png")
    assert centre.dtype == np.uint16 and centre.shape == res.centre_view.shape
    # the API's planes: 0 where no view reaches, the views' mean on the focal plane
    v = res.views
    assert np.allclose(res.planes[0][v.inside], v.images.mean(axis=0)[v.inside], rtol=1e-4, atol=1e-3)


def test_views_of_an_image_file_on_the_calibrated_lattice(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # The real MLA is rotated 0.5 degrees and offset by 0.3 lenslet from the rig file's.
    nominal = load_rig(TINY)
    true_cam = nominal.camera[0].model_copy(update={"mla_rotation_deg": 0.5, "mla_offset_um": (16.5, -5.0)})
    white = white_image(true_cam, render=nominal.render, config=WhiteImageConfig(level_counts=30000.0))
    tifffile.imwrite(tmp_path / "white.tif", white)
    cal = tmp_path / "cal.zarr"
    rc, _, _ = run_cli(capsys, "calibrate", "mla", "--rig", TINY, "--white", f"cam0={tmp_path / 'white.tif'}",
                       "--out", cal)
    assert rc == 0
    z = 0.45
    cfg = nominal.render.model_copy(update={"rays_per_particle": 200_000})
    point = LightFieldRenderer(true_cam, cfg, wavelength_nm=532.0, device="cpu").frame(
        np.array([[0.02, 0.01, z]]), 50_000.0, seed=2)
    tifffile.imwrite(tmp_path / "point.tif", point)
    dz = VolumeGrid.from_rig(nominal).voxel_mm[2]
    depths = np.arange(-0.8, 0.8 + 1e-9, dz)
    res = lfpiv.views(image=tmp_path / "point.tif", calibration=cal, depths_mm=depths, out=tmp_path / "d",
                      fmt="tiff", every_view=False)
    # the lattice is the true one, not the rig file's
    truth, fitted = nominal_lattice(true_cam), res.views.lattice
    assert fitted.pitch_px == pytest.approx(truth.pitch_px, abs=0.01)
    n = np.stack(np.meshgrid(np.arange(-8, 9), np.arange(-8, 9)), axis=-1).reshape(-1, 2)
    nodes = np.asarray(fitted.origin_px) + n @ fitted.basis_px  # every fitted node is a true one
    idx = (nodes - truth.origin_px) @ np.linalg.inv(truth.basis_px)
    assert np.abs(idx - np.rint(idx)).max() * truth.pitch_px < 0.05
    wrong = (nodes - nominal_lattice(nominal.camera[0]).origin_px) @ np.linalg.inv(truth.basis_px)
    assert np.abs(wrong - np.rint(wrong)).max() * truth.pitch_px > 1.0  # the rig file's lattice is off
    sharp = focus_measure(res.planes)
    assert abs(depths[np.argmax(sharp)] - z) <= dz + 1e-9
    assert "fitted grid" in res.lattice_source
    assert any("divided by the white image" in n for n in res.notes)
    planes = sorted((tmp_path / "d").glob("refocus_z*.tif"))
    assert len(planes) == len(depths) and tifffile.imread(planes[0]).dtype == np.float32
    # the command prints where the lattice came from
    rc, text, _ = run_cli(capsys, "views", "--image", tmp_path / "point.tif", "--calibration", cal, "--depths", "0",
                          "--no-each-view", "--out", tmp_path / "e")
    assert rc == 0 and "fitted grid" in text and not list((tmp_path / "e").glob("view_u*"))


@pytest.mark.parametrize("argv, words", [
    ([], "give a run"),
    (["--image", "x.tif"], "--calibration"),
    (["RUN", "--camera", "nope"], "not in run"),
    (["RUN", "--pair", "7"], "pair 7"),
    (["RUN", "--depths", "1:0:0.1"], "not depths"),
])
def test_views_bad_input(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture, argv, words) -> None:
    out = tmp_path / "never"
    argv = [str(run) if a == "RUN" else a for a in argv]
    rc, _, err = run_cli(capsys, "views", *argv, "--out", out)
    assert rc == 2 and one_error(err) and words in err
    assert not out.exists()


def test_views_image_of_another_size(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    iio.imwrite(tmp_path / "small.png", np.zeros((50, 60), dtype=np.uint8))
    rc, _, err = run_cli(capsys, "views", "--image", tmp_path / "small.png", "--rig", TINY, "--out", tmp_path / "o")
    assert rc == 2 and one_error(err) and "60 x 50" in err
    assert not (tmp_path / "o").exists()


def test_check_camera_on_the_simulated_lab(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rc, text, _ = run_cli(capsys, "check-camera", "--rig", TINY, "--sim-ppm", "0.5", "--sim-flow", "uniform",
                          "--plot", tmp_path / "checks.png")
    assert rc == 0, text
    assert "ok   seeding" in text and "PPM (recommended 0.5" in text and "ok   saturated 0.000%" in text
    assert (tmp_path / "checks.png").is_file()
    ppm = float(text.split("seeding ")[1].split(" PPM")[0])
    assert ppm == pytest.approx(0.5, rel=0.3)
    rc, text, _ = run_cli(capsys, "check-camera", "--rig", TINY, "--sim-ppm", "5", "--sim-flow", "uniform")
    assert rc == 1 and "FIX  seeding" in text and "seed less" in text


def test_check_camera_of_a_run_and_of_files(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rc, text, _ = run_cli(capsys, "check-camera", "--rig", TINY, "--run", run)
    assert rc == 0
    assert float(text.split("seeding ")[1].split(" PPM")[0]) == pytest.approx(0.3, rel=0.25)
    frame = lfpiv.open_run(run).read_frame("cam0", 0, 0)
    tifffile.imwrite(tmp_path / "f.tif", frame)
    checks, _ = lfpiv.check_camera(TINY, images={"cam0": tmp_path / "f.tif"})
    direct, _ = lfpiv.check_camera(TINY, frames={"cam0": frame})
    assert checks[0].ppm == pytest.approx(direct[0].ppm) == pytest.approx(0.3, rel=0.25)
    rc, _, err = run_cli(capsys, "check-camera", "--rig", TINY, "--image", f"cam9={tmp_path / 'f.tif'}")
    assert rc == 2 and one_error(err) and "cam9" in err
