"""The volumetric calibration fit on the simulated lab (issue 6, step 5).

The lab renders the TRUE cameras (MLA rotated 0.2 degrees and offset by 0.3 lenslet,
magnification 1% high, the second camera's pose 0.5 degree off about world y); the calibration
starts from the NOMINAL rig file and must recover each. The tiny rig (about 19 x 16 lenslets per
camera, 1 mm field of view) is the hardest case for the pose: a handful of dots per plane, and
a field of view a hundredth of the working distance, so tolerances here are looser than a real
rig's (hundreds of lenslets, many dots).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.store import CalibrationStore
from lfcore.rig import Rig
from lfpiv.cli import main
from lfpiv.jobs.calibrate import calibrate_fit, calibrate_mla, calibrate_volume, default_board
from sim.lab import SimLab
from tests.helpers import fast_rig_text

PITCH_UM = 55.0


def _true_rig(nominal: Rig) -> Rig:
    cams = []
    for i, c in enumerate(nominal.camera):
        upd = {"mla_rotation_deg": 0.2, "mla_offset_um": (0.3 * PITCH_UM, 0.0), "magnification": 1.01 * c.magnification}
        if i == 1:
            upd["rotation_deg"] = (0.0, 90.5, 0.0)
        cams.append(c.model_copy(update=upd))
    return nominal.model_copy(update={"camera": tuple(cams)})


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(a.T @ b).as_rotvec())))


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Rig, Rig]:
    nominal = Rig.from_dict(tomllib.loads(fast_rig_text()))
    true = _true_rig(nominal)
    out = tmp_path_factory.mktemp("fit") / "calib.zarr"
    board = default_board(nominal, spacing_mm=0.3)
    assert board.tilt_deg == pytest.approx(45.0)
    with SimLab(true, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        calibrate_mla(nominal, out, frames=2, sim_options={"lab": lab})
        calibrate_volume(nominal, out, planes=5, step_mm=0.1, board=board, sim_options={"lab": lab},
                         sim_target={"rays_per_point": 8})
    return out, nominal, true


def test_fit_recovers_the_true_cameras(calibrated: tuple[Path, Rig, Rig]) -> None:
    out, nominal, true = calibrated
    fits = calibrate_fit(out)
    for fit, tru in zip(fits, true.camera, strict=True):
        c = fit.camera
        assert c.mla_rotation_deg == pytest.approx(0.2, abs=0.02)
        assert np.allclose(c.mla_offset_um, (0.3 * PITCH_UM, 0.0), atol=0.1)  # 0.2% of a lenslet
        assert c.magnification == pytest.approx(tru.magnification, rel=0.005)  # the 1% error, to half a percent
        assert np.allclose(c.focus_mm, tru.focus_mm, atol=0.02)
        assert _angle_deg(c.rotation, tru.rotation) < 0.3  # from 0.5 (cam1) off
        assert fit.rms_px < 0.2
        assert fit.lattice_rms_px < 0.03
    assert _angle_deg(fits[1].camera.rotation, true.camera[1].rotation) < _angle_deg(
        nominal.camera[1].rotation, true.camera[1].rotation)
    store = CalibrationStore.open(out)
    rig = store.fitted_rig()
    assert rig.camera[0].magnification == fits[0].camera.magnification
    assert store.model("cam1")["plane_dots"] and store.model("cam1")["rms_px"] == pytest.approx(fits[1].rms_px)


def test_fit_and_report_cli(calibrated: tuple[Path, Rig, Rig], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out, _, _ = calibrated
    assert main(["calibrate", "fit", str(out)]) == 0
    text = capsys.readouterr().out
    assert "cam0: RMS" in text and "cam1: RMS" in text and "magnification" in text
    png = tmp_path / "rms.png"
    assert main(["calibrate", "report", str(out), "--rms-plot", str(png)]) == 0
    rep = capsys.readouterr().out
    assert "reprojection RMS" in rep and "plane  stage_mm  dots  rms_px" in rep and png.stat().st_size > 5_000
    # the rig file's cam1 is 0.5 deg off the truth the fit finds; cam0 is right
    found = re.findall(r"(cam\d): fitted model: .*\(([\d.]+) deg from the rig file's\)", rep)
    turn = {cam: float(deg) for cam, deg in found}
    assert turn["cam0"] < 0.2 and 0.3 < turn["cam1"] < 0.7
    # lfpiv info describes a calibration store too, with the report's summary
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "lfpiv calibration" in info and info.strip() in rep


def test_a_plane_without_dots_is_one_line_naming_camera_and_plane(calibrated: tuple[Path, Rig, Rig],
                                                                    tmp_path: Path) -> None:
    import shutil

    out, _, _ = calibrated
    bad = tmp_path / "bad.zarr"
    shutil.copytree(out, bad)
    store = CalibrationStore.open(bad, mode="r+")
    frames = store.plane_frames("cam1")
    frames[2] = np.full(frames.shape[1:], 100, dtype=np.uint16)  # the target fell off: a dark plane
    from lfpiv.errors import UsageError

    with pytest.raises(UsageError, match=r"^camera 'cam1', plane 3 of 5 \(stage") as info:
        calibrate_fit(bad)
    assert "\n" not in str(info.value)


@pytest.fixture(scope="module")
def recorded_run(calibrated: tuple[Path, Rig, Rig]) -> Path:
    """One pair recorded with the NOMINAL rig file in the lab that renders the TRUE cameras."""
    from lfpiv.jobs.acquire import record
    from sim.world import SimWorld

    out, nominal, true = calibrated
    run = out.parent / "run.zarr"
    with SimLab(true, world=SimWorld(true, ppm=0.1), pool_pairs=1, reply_latency_s=0.0005) as lab:
        assert record(nominal, run, 1, sim_options={"lab": lab}).state == "complete"
    return run


def test_reconstruction_with_the_calibrated_models(calibrated: tuple[Path, Rig, Rig], recorded_run: Path,
                                                   capsys: pytest.CaptureFixture) -> None:
    """Q with the calibrated models is close to Q with the true ones, far above the nominal rig's."""
    from lfcore.reconstruct import ReconSettings
    from lfcore.runstore import RunStore
    from lfpiv.jobs.evaluate import evaluate_run
    from lfpiv.jobs.reconstruct import reconstruct_run

    out, _, true = calibrated
    if CalibrationStore.open(out).model("cam1") is None:
        calibrate_fit(out)
    run = str(recorded_run)
    q = {}
    for name, extra in (("nominal", []), ("calibrated", ["--calibration", str(out)])):
        assert main(["reconstruct", run, "--iterations", "20", "--quiet", *extra]) == 0
        q[name] = np.mean([e.q for e in evaluate_run(RunStore.open(run))])
    assert "and the models of" in capsys.readouterr().out
    store = RunStore.open(run, mode="r+")
    used = store.group["volumes"].attrs["settings"]["calibration"]
    assert used["store"] == str(out.resolve()) and set(used["rms_px"]) == {"cam0", "cam1"}
    reconstruct_run(store, ReconSettings(iterations=20), rig=store.rig.model_copy(update={"camera": true.camera}),
                    progress=False)
    assert store.group["volumes"].attrs["settings"]["calibration"] is None
    q["true"] = np.mean([e.q for e in evaluate_run(store)])
    print("Q (mean of frames A and B):", {k: round(float(v), 4) for k, v in q.items()})
    assert q["true"] > 0.5
    assert q["calibrated"] >= 0.93 * q["true"]  # the issue's goal is 95%; see the module docstring
    assert q["nominal"] < 0.5 * q["calibrated"]  # 0.5 degree and 1% off: the nominal rig is useless


def test_reconstruct_with_an_unfitted_calibration_is_one_line(calibrated: tuple[Path, Rig, Rig], recorded_run: Path,
                                                               tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _, nominal, _ = calibrated
    empty = tmp_path / "empty.zarr"
    CalibrationStore.create(empty, nominal)
    assert main(["reconstruct", str(recorded_run), "--calibration", str(empty), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith("lfpiv: error: camera 'cam0': no fitted model in") and "lfpiv calibrate fit" in err


def test_a_fit_started_at_the_truth_stays_there(tmp_path: Path) -> None:
    """The demo rig (two 256 x 256 cameras at 90 degrees) whose nominal cameras ARE the true ones.

    Its tilted board spans depths where the centroids of dots are biased (sharply focused dots
    sampled by a couple of lenslets; far from focus, neighbours' blur discs overlapping); a fit
    that trusted them all moved cam0's rotation 0.42 degree off the truth, at 0.48 px RMS.
    """
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / "demo.toml")
    out = tmp_path / "demo.zarr"
    calibrate_mla(rig, out, frames=2)
    calibrate_volume(rig, out, planes=5, step_mm=0.2)
    for fit, tru in zip(calibrate_fit(out), rig.camera, strict=True):
        c = fit.camera
        assert _angle_deg(c.rotation, tru.rotation) < 0.06, fit.camera.name
        assert c.magnification == pytest.approx(tru.magnification, rel=1e-3)
        assert np.allclose(c.focus_mm, tru.focus_mm, atol=0.02)  # about a voxel (16.5 um), along the optical axis
        assert np.allclose(c.mla_offset_um, (0.0, 0.0), atol=0.05) and abs(c.mla_rotation_deg) < 0.005
        assert fit.rms_px < 0.1
        assert fit.set_aside > 0


def test_issue_acceptance_on_the_demo_rig(tmp_path: Path) -> None:
    """The issue's test on the demo rig (two 256 x 256 cameras at 90 degrees, 1.2 mm cube).

    The lab renders the TRUE cameras (:func:`_true_rig`), the calibration and the recording use the
    NOMINAL rig file; 7 planes 0.2 mm apart span the cube. Measured (20 iterations, 2026-11-24):
    MLA rotation within 0.005 degree, offset within 0.002 um, magnification within 0.05%, pose
    within 0.023 / 0.041 degree, focus within 0.003 mm (0.012 before the views' geometry was
    modelled), RMS 0.057 and 0.053 px; Q nominal 0.053, calibrated 0.851, true 0.851.
    """
    from lfcore.reconstruct import ReconSettings
    from lfcore.runstore import RunStore
    from lfpiv.jobs.acquire import record
    from lfpiv.jobs.calibrate import calibrated_rig
    from lfpiv.jobs.evaluate import evaluate_run
    from lfpiv.jobs.reconstruct import reconstruct_run
    from lfpiv.rigfile import load_rig
    from sim.world import SimWorld
    from tests.conftest import EXAMPLES

    nominal = load_rig(EXAMPLES / "demo.toml")
    true = _true_rig(nominal)
    out = tmp_path / "calib.zarr"
    with SimLab(true, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0005) as lab:
        calibrate_mla(nominal, out, frames=2, sim_options={"lab": lab})
        calibrate_volume(nominal, out, planes=7, step_mm=0.2, sim_options={"lab": lab})
    fits = calibrate_fit(out)
    for fit, tru in zip(fits, true.camera, strict=True):
        c = fit.camera
        print(f"{c.name}: pose {_angle_deg(c.rotation, tru.rotation):.4f} deg off, magnification "
              f"{c.magnification / tru.magnification - 1:+.2e}, focus {np.subtract(c.focus_mm, tru.focus_mm)} mm, "
              f"MLA {c.mla_rotation_deg - 0.2:+.4f} deg {np.subtract(c.mla_offset_um, (0.3 * PITCH_UM, 0.0))} um, "
              f"RMS {fit.rms_px:.3f} px")
        assert c.mla_rotation_deg == pytest.approx(0.2, abs=0.02), c.name  # a tenth of the 0.2 degree error
        assert np.allclose(c.mla_offset_um, (0.3 * PITCH_UM, 0.0), atol=0.1), c.name  # 0.2% of a lenslet
        assert c.magnification == pytest.approx(tru.magnification, rel=0.002), c.name  # a fifth of the 1% error
        assert np.allclose(c.focus_mm, tru.focus_mm, atol=0.02), c.name  # about a voxel (16.5 um)
        assert _angle_deg(c.rotation, tru.rotation) < 0.1, c.name  # a fifth of cam1's 0.5 degree error
        assert fit.rms_px < 0.1, c.name  # the issue's goal
        assert fit.lattice_rms_px < 0.03, c.name

    run = tmp_path / "run.zarr"
    with SimLab(true, world=SimWorld(true, ppm=0.1), pool_pairs=1, reply_latency_s=0.0005) as lab:
        assert record(nominal, run, 1, sim_options={"lab": lab}).state == "complete"
    store = RunStore.open(run, mode="r+")
    calibrated, info = calibrated_rig(store.rig, out)
    q = {}
    for name, rig, cal in (("nominal", None, None), ("calibrated", calibrated, info),
                           ("true", store.rig.model_copy(update={"camera": true.camera}), None)):
        reconstruct_run(store, ReconSettings(iterations=20), rig=rig, calibration=cal, progress=False)
        q[name] = np.mean([e.q for e in evaluate_run(store)])
    print("Q (mean of frames A and B):", {k: round(float(v), 4) for k, v in q.items()})
    assert q["true"] > 0.7
    assert q["calibrated"] >= 0.95 * q["true"]  # the issue's goal
    assert q["nominal"] < 0.3 * q["calibrated"]
