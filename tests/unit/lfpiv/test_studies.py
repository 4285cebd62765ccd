"""The chapter's studies at ``--scale tiny``: what each must show from known truths, and the runner
(resume, refusal, rigs)."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from lfcore.rig import Rig
from lfpiv.errors import UsageError
from lfpiv.jobs.study import run_studies, study_setup
from lfpiv.studies import STUDY_NAMES, dual, rigs, study_named
from lfpiv.studies.runner import Setup, run_study


@pytest.fixture(scope="module")
def tiny_all(tmp_path_factory):
    """Every study at the tiny scale, once (``lfpiv study all --scale tiny``)."""
    out = tmp_path_factory.mktemp("studies")
    outcomes = run_studies(["all"], Setup(scale="tiny", device="cpu"), out)
    return out, {o.name: o for o in outcomes}


def _results(out, name):
    return {p.stem: json.loads(p.read_text())["result"] for p in (out / name / "cases").glob("*.json")}


def _rows(out, name):
    with (out / name / "table.csv").open() as fh:
        return list(csv.DictReader(fh))


def test_all_writes_every_study_and_an_index(tiny_all):
    out, outcomes = tiny_all
    assert list(outcomes) == list(STUDY_NAMES)
    for o in outcomes.values():
        assert o.table.stat().st_size > 0 and o.figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        report = o.report.read_text()
        assert "The chapter's claim" in report and "--scale tiny" in report and o.findings
        assert all(f.verdict in ("reproduced", "partly", "not reproduced", "not measured") for f in o.findings)
        assert o.done_now == o.cases
    index = (out / "README.md").read_text()
    assert all(f"[{n}]({n}/report.md)" in index for n in STUDY_NAMES)


def test_iterations_truth_q_is_one_and_q_grows_with_iterations(tiny_all):
    out, _ = tiny_all
    r = _results(out, "iterations")
    assert r["truth"]["q"] == [pytest.approx(1.0, abs=1e-12)]
    for m in ("drt-mart", "mart", "mlos-mart"):
        q = r[f"{m}_mu1"]["q"]
        assert all(0.0 < v < 1.0 for v in q)
        assert q[-1] > q[0]  # 5 iterations reconstruct better than 2
    assert 0 < r["drt-mart_mu1"]["active_fraction"] < 1 == r["mart_mu1"]["active_fraction"]


def test_diameters_of_the_truth_are_three_voxels(tiny_all):
    out, _ = tiny_all
    truth = np.asarray(_results(out, "diameters")["truth"]["diameters_vox"])
    # E0's blobs are 3 voxels across at exp(-2) of their peak, on every axis
    np.testing.assert_allclose(np.median(truth, axis=0), 3.0, atol=0.15)
    rows = {r["method"] + r["iterations"]: r for r in _rows(out, "diameters")}
    assert float(rows["truth0"]["dz_median_px"]) == pytest.approx(3.0 * 10, rel=0.05)  # PVR 10 in z


def test_density_ratios_are_timed_in_the_same_run(tiny_all):
    out, _ = tiny_all
    r = _results(out, "density")
    for key in ("ppm0.25", "ppm1"):
        runs = r[key]["runs"]
        # the chapter's protocol (5 against 3 iterations at tiny) and equal time (5 against 2)
        assert r[key]["ratio_protocol"] == pytest.approx(runs["mart_3"]["seconds"] / runs["drt-mart_5"]["seconds"])
        assert r[key]["ratio_equal_time"] == pytest.approx(runs["mart_2"]["seconds"] / runs["drt-mart_5"]["seconds"])
        assert all(run["seconds"] >= run["weights_s"] + run["iterate_s"] > 0 for run in runs.values())
    g = r["ghosts"]
    assert 0 <= g["outside_fraction"] < 1 and np.asarray(g["xz"]).shape == (len(g["z_mm"]), len(g["x_mm"]))


def test_oscillatory_zero_displacement_gives_zero_error(tiny_all):
    out, _ = tiny_all
    r = _results(out, "oscillatory")
    # the same image as both frames: the whole chain (reconstruction, correlation, truth) gives nothing
    assert max(r["still"]["same_image_rms"]) < 1e-4
    # the same particles with new noise: a small noise floor
    assert max(r["still"]["rms"][next(iter(r["still"]["rms"]))]) < 0.15
    # true particles as volumes, correlated alike, measure the known flow closely
    assert max(r["goal_single"]["bound_rms"]) < 0.1 and max(r["goal_dual"]["bound_rms"]) < 0.1
    # the flow keeps the chapter's proportions: 25/160 of the final window along u
    w = r["A1_w1_drt"]["windows"][-1][0] * r["A1_w1_drt"]["voxel_px"][0]
    assert r["A1_w1_drt"]["displacement_px"] == pytest.approx(w * 25 / 160)


def test_dual_resolution_of_one_view_twice_is_one_cameras():
    rig = rigs.dual_rig(None, "tiny")
    one = dual.resolution_map(rigs.one_camera(rig), 2, 2000, "cpu")
    same = dual.resolution_map(rigs.with_angle(rig, 0.0), 2, 2000, "cpu")
    crossed = dual.resolution_map(rigs.with_angle(rig, 90.0), 2, 2000, "cpu")
    np.testing.assert_allclose(same["resolution_mm"], one["resolution_mm"], rtol=1e-5)
    assert same["angle_deg"] == pytest.approx(0.0, abs=1e-6) and crossed["angle_deg"] == pytest.approx(90.0)
    assert np.nanmedian(crossed["resolution_mm"]) < 0.5 * np.nanmedian(one["resolution_mm"])


def test_dual_two_cameras_beat_one(tiny_all):
    out, _ = tiny_all
    r = _results(out, "dual")
    assert r["cams2_ppm0.5"]["q"][-1] > r["cams1_ppm0.5"]["q"][-1]
    assert r["angle90"]["q"]["0.5"] > r["angle0"]["q"]["0.5"]


def test_vortex_ring_truth_field_is_nearly_divergence_free(tiny_all):
    out, _ = tiny_all
    r = _results(out, "vortex-ring")
    for cams in ("cams1", "cams2", "cams2_faces", "cams2_faces_ppm1"):
        truth = np.nanmedian(r[cams]["truth"]["divergence"])
        assert truth < np.nanmedian(r[cams]["none"]["divergence"])
        assert 0 < r[cams]["none"]["of_peak"] < 1
    rows = _rows(out, "vortex-ring")
    assert {row["vectors"] for row in rows} == {"none", "median", "truth field"}


def test_resume_keeps_cases_and_a_second_run_must_say_how(tmp_path):
    study = study_named("iterations")
    setup = Setup(scale="tiny", device="cpu")
    cases = tmp_path / "iterations" / "cases"
    first = run_study(study, setup, tmp_path)
    stamp = {p.name: p.stat().st_mtime_ns for p in cases.glob("*.json")}
    with pytest.raises(UsageError, match="--skip-done"):
        run_study(study, setup, tmp_path)
    again = run_study(study, setup, tmp_path, skip_done=True)
    assert (first.done_now, again.done_now) == (6, 0)
    assert {p.name: p.stat().st_mtime_ns for p in cases.glob("*.json")} == stamp
    # another rig makes the cases another study's: done again
    other = Setup(scale="tiny", device="cpu", rig=rigs.single_rig(None, "tiny").to_dict(), rig_name="mine")
    assert run_study(study, other, tmp_path, skip_done=True).done_now == 6
    # a damaged case file counts as not done
    (cases / "truth.json").write_text("{")
    assert run_study(study, other, tmp_path, skip_done=True).done_now == 1


def test_a_users_rig_is_cropped_below_chapter_scale(tiny_rig):
    big = Rig.from_dict({**tiny_rig.to_dict(), "camera": [dict(tiny_rig.to_dict()["camera"][0],
                                                               sensor_px=[400, 300])],
                         "volume": dict(tiny_rig.to_dict()["volume"], size_mm=[2.0, 1.5, 1.6])})
    q = rigs.cropped(big, "quick")
    assert q.camera[0].sensor_px == (192, 160)
    assert q.volume.size_mm[0] == pytest.approx(0.9 * 192 * 0.0055) and q.volume.size_mm[2] == 1.6
    assert rigs.cropped(big, "chapter") == big
    two = rigs.dual_rig(big.to_dict(), "tiny")  # one camera: a second is added at 90 degrees
    assert len(two.camera) == 2 and two.camera[1].rotation_deg == (0.0, 90.0, 0.0)


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, 150.0, 180.0])
def test_a_second_camera_is_the_first_turned_about_y(tiny_rig, angle):
    d = tiny_rig.to_dict()
    d["camera"][0].update(rotation_deg=[10.0, -20.0, 5.0], focus_mm=[0.1, 0.0, 0.2])
    rig = rigs.with_angle(Rig.from_dict(d), angle)
    a = math.radians(angle)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    np.testing.assert_allclose(rig.camera[1].rotation, turn @ rig.camera[0].rotation, atol=1e-9)
    np.testing.assert_allclose(rig.camera[1].focus_mm, turn @ np.array([0.1, 0.0, 0.2]), atol=1e-9)


def test_setup_refuses_bad_input_in_one_line(tmp_path):
    with pytest.raises(UsageError, match="--scale"):
        study_setup(scale="huge")
    with pytest.raises(UsageError, match="no study 'nope'"):
        run_studies(["nope"], Setup(scale="tiny"), tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(UsageError, match="is a file"):
        run_studies(["dual"], Setup(scale="tiny"), tmp_path / "file")


def test_ltpr_is_the_chapters_eq_4_5():
    from lfpiv.studies.lf_vs_tomo import ltpr

    got = sorted(round(ltpr(px, n), 2) for px in (800, 1600) for n in (4, 6, 8))
    assert got == [3.12, 4.17, 6.25, 12.5, 16.67, 25.0]  # the chapter's six ratios (3.125 rounds to even)


def test_lf_vs_tomo_rigs_keep_the_chapters_pixels_in_a_smaller_field_of_view():
    from lfpiv.studies.lf_vs_tomo import lf_rig, tomo_rig

    for scale, f in (("tiny", 0.125), ("chapter", 1.0)):
        t = tomo_rig(6, scale)
        assert len(t.camera) == 6 and t.camera[0].sensor_px == (round(160 * f),) * 2
        assert t.camera[0].object_pixel_mm == pytest.approx(0.075, rel=1e-3)
        lf = lf_rig(1600, 14, scale)
        cam = lf.camera[0]
        assert cam.pixels_per_lenslet == pytest.approx(14.0) and cam.sensor_px[0] == pytest.approx(1600 * f, abs=1)
        # the light-field sensor spans the Tomo-PIV cameras' field of view
        assert cam.sensor_px[0] * cam.object_pixel_mm == pytest.approx(t.camera[0].sensor_px[0] * 0.075, rel=0.01)
        assert lf.volume.size_mm == t.volume.size_mm


def test_lf_vs_tomo_measures_both_kinds_against_ltpr(tiny_all):
    out, outcomes = tiny_all
    r = _results(out, "lf-vs-tomo")
    assert set(r) == {"tomo4_ppp0.05", "tomo8_ppp0.05", "lf800_pmr7", "lf800_pmr14", "lf1600_pmr7", "lf1600_pmr14"}
    for key in ("tomo4_ppp0.05", "tomo8_ppp0.05"):
        assert r[key]["q"] > 0.75  # MLOS-SMART of the 4- and 8-camera arcs at 0.05 ppp
        # the shift is known: (0.8, 0.5, 0.33) of 0.15 mm, and the error is a fraction of it
        assert np.linalg.norm(r[key]["shift_um"]) == pytest.approx(150.0, rel=1e-6)
        assert max(r[key]["displacement_rms_um"]) < 0.5 * 150.0
    rows = _rows(out, "lf-vs-tomo")
    lf = [row for row in rows if row["kind"] == "lf"]
    assert len(lf) == 8 and sorted({float(row["LTPR"]) for row in lf}) == [3.125, 6.25, 12.5, 25.0]
    assert any("LTPR" in f.claim for f in outcomes["lf-vs-tomo"].findings)
