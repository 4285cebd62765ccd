"""``lfpiv calibrate`` on the simulated lab: white images through the real pulse-generator driver
(camera output only), microlens grids recovered against the known, perturbed MLA; the volumetric
run through the real stage driver on the emulated stage, interrupted and resumed."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from calibration.store import CalibrationStore
from lfcore.rig import Rig
from lfcore.white import WhiteImageConfig, micro_image_scale
from lfpiv.cli import main
from lfpiv.jobs.calibrate import calibrate_mla
from lfpiv.rigfile import load_rig
from sim.lab import SimLab
from tests.helpers import fast_rig_text

PITCH_UM = 55.0


def _perturbed_rig_text(cameras: int = 2) -> str:
    # The perturbation: MLA rotated 0.2 degrees and offset by 0.3 lenslet.
    return fast_rig_text(cameras=cameras).replace(
        "focus_mm = [0.0, 0.0, 0.0]",
        f"focus_mm = [0.0, 0.0, 0.0]\nmla_rotation_deg = 0.2\nmla_offset_um = [{0.3 * PITCH_UM}, 0.0]")


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "perturbed.toml"
    path.write_text(_perturbed_rig_text())
    return path


def _check_grid(store: CalibrationStore, rig: Rig) -> None:
    for cam in rig.camera:
        g = store.grid(cam.name)
        k = micro_image_scale(cam)
        assert g.grid == "hex"
        assert g.pitch_px == pytest.approx(cam.pixels_per_lenslet * k, abs=0.003)
        assert g.rotation_deg == pytest.approx(0.2, abs=0.01)
        assert np.allclose(g.offset_px, [-0.3 * cam.pixels_per_lenslet * k, 0.0], atol=0.02)
        assert g.rms_px < 0.04


def test_calibrate_mla_two_cameras_and_report(rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "calib.zarr"
    assert main(["calibrate", "mla", "--rig", str(rig_file), "--out", str(out), "--frames", "3"]) == 0
    text = capsys.readouterr().out
    assert "cam0: hex grid" in text and "cam1: hex grid" in text and "rotation +0.20" in text
    store = CalibrationStore.open(out)
    rig = load_rig(rig_file)
    _check_grid(store, rig)
    assert store.white("cam0").shape == (160, 192)
    assert store.group["cam0/white"].attrs["frames_averaged"] == 3

    png = tmp_path / "grid.png"
    assert main(["calibrate", "report", str(out), "--plot", str(png)]) == 0
    rep = capsys.readouterr().out
    assert "cam1: MLA hex, pitch 10.02" in rep and "RMS" in rep and png.stat().st_size > 10_000
    # running mla again updates the same store
    assert main(["calibrate", "mla", "--rig", str(rig_file), "--out", str(out), "--frames", "1"]) == 0
    assert CalibrationStore.open(out).group["cam0/white"].attrs["frames_averaged"] == 1


def test_calibration_never_enables_a_laser_output(rig_file: Path, tmp_path: Path) -> None:
    rig = load_rig(rig_file)
    seen: list[set[int]] = []
    with SimLab(rig, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        lab.pulse_generator.add_listener(lambda tick, t0, outputs: seen.append(set(outputs)))
        calibrate_mla(rig, tmp_path / "c.zarr", frames=4, sim_options={"lab": lab},
                      white=WhiteImageConfig(vignetting=0.5, dead_lenslets=4))
        assert not lab.pulse_generator.firing and not lab.pulse_generator.outputs_enabled()
    assert len(seen) == 4
    assert all(s == {rig.pulse_generator.channels["camera"]} for s in seen)
    _check_grid(CalibrationStore.open(tmp_path / "c.zarr"), rig)


@pytest.mark.parametrize(("level", "what"), [("5", "too dark"), ("300000", "saturated")])
def test_a_white_image_that_is_not_white_is_one_line_naming_the_camera(
        rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture, level: str, what: str) -> None:
    code = main(["calibrate", "mla", "--rig", str(rig_file), "--out", str(tmp_path / "x.zarr"), "--frames", "1",
                 "--sim-level", level])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("lfpiv: error: camera 'cam0'") and what in err and "\n" not in err
    assert not (tmp_path / "x.zarr").exists()


def test_report_of_a_missing_store_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["calibrate", "report", str(tmp_path / "none.zarr")]) == 2
    err = capsys.readouterr().err.strip()
    assert "does not exist" in err and "\n" not in err


def test_volume_run_resumes_without_repeating_planes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from lfpiv.jobs.calibrate import calibrate_volume

    rig = Rig.from_dict(tomllib.loads(fast_rig_text(cameras=1)))
    out = tmp_path / "vol.zarr"

    def stop_after_3(plane: int, done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with SimLab(rig, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        with pytest.raises(KeyboardInterrupt):
            calibrate_volume(rig, out, planes=7, step_mm=0.2, sim_options={"lab": lab}, progress=stop_after_3)
        assert lab.pulse_generator.ticks_fired == 3 and not lab.pulse_generator.outputs_enabled()
    assert CalibrationStore.open(out).planes_done().sum() == 3
    with SimLab(rig, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        res = calibrate_volume(rig, out, planes=7, step_mm=0.2, sim_options={"lab": lab})
        moves = [c for c in lab.stage.commands if "move abs" in c]
        assert lab.pulse_generator.ticks_fired == 4  # one trigger per remaining plane, none repeated
    assert res.skipped == (0, 1, 2) and res.taken == (3, 4, 5, 6) and len(moves) == 4
    store = CalibrationStore.open(out)
    stage = store.stage_mm("cam0")
    assert np.allclose(np.diff(stage), 0.2, atol=1e-3) and np.all(np.isfinite(stage))
    frames = store.plane_frames("cam0")[...]
    # each plane was taken at its own stage position, in order: the dot images of neighbouring
    # planes (0.2 mm apart) resemble each other, those 0.6 mm apart hardly, and no plane repeats
    # another (0.82-0.87 and 0.20-0.31 measured). The brightest pixel is no focus measure in a
    # light-field image (a dot in focus spreads over a whole lenslet image) and its order changes
    # with the render's random stream.
    c = np.corrcoef(frames.reshape(7, -1).astype(np.float64))
    assert all(0.6 < c[k, k + 1] < 0.98 for k in range(6)), np.round(c, 3)
    assert all(c[k, k + 3] < 0.5 for k in range(4)), np.round(c, 3)
    # the same command again: nothing left to do
    assert main(["calibrate", "volume", "--rig", str(_write(tmp_path)), "--out", str(out), "--planes", "7",
                 "--step-mm", "0.2", "--quiet"]) == 0
    assert "took 0 plane(s) (7 already done)" in capsys.readouterr().out


def _write(tmp_path: Path) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(fast_rig_text(cameras=1))
    return path


def test_a_stage_that_misses_a_plane_is_one_line_naming_it(tmp_path: Path) -> None:
    from acquisition.protocols import DeviceError
    from lfpiv.jobs.calibrate import calibrate_volume

    rig = Rig.from_dict(tomllib.loads(fast_rig_text(cameras=1)))
    with SimLab(rig, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        def slip_after_2(plane: int, done: int, total: int) -> None:
            if done == 2:
                lab.stage.inject("slip")  # the next move ends 50 um short

        with pytest.raises(DeviceError, match=r"^plane 3 of 5 \(target") as info:
            calibrate_volume(rig, tmp_path / "s.zarr", planes=5, step_mm=0.2, sim_options={"lab": lab},
                             progress=slip_after_2)
    assert "\n" not in str(info.value) and "2 plane(s) are stored" in str(info.value)
    assert CalibrationStore.open(tmp_path / "s.zarr").planes_done().sum() == 2
