"""``lfpiv study`` end to end: the CSV, the PNG and the report, resuming, workers, bad input."""

from __future__ import annotations

import csv

from tests.conftest import EXAMPLES, run_cli


def test_study_writes_table_figure_and_report(tmp_path, capsys):
    rc, out, err = run_cli(capsys, "study", "iterations", "--scale", "tiny", "--out", tmp_path, "--device", "cpu")
    assert rc == 0, err
    folder = tmp_path / "iterations"
    rows = list(csv.DictReader((folder / "table.csv").open()))
    assert len(rows) == 7 and rows[0]["method"] == "truth" and float(rows[0]["Q"]) == 1.0
    assert (folder / "figure.png").read_bytes()[:4] == b"\x89PNG"
    report = (folder / "report.md").read_text()
    assert "Fig. 4.6" in report and "![figure](figure.png)" in report and "| Chapter |" in report
    assert "study iterations: 6 cases (6 run now)" in out and "Fig. 4.6:" in out
    assert "case drt-mart_mu1 done" in err
    # again: refused in one line, nothing lost; resumed with --skip-done
    rc, out, err = run_cli(capsys, "study", "iterations", "--scale", "tiny", "--out", tmp_path)
    assert rc == 2 and err.count("\n") == 1 and "--skip-done" in err
    rc, out, err = run_cli(capsys, "study", "iterations", "--scale", "tiny", "--out", tmp_path, "--skip-done",
                           "--quiet")
    assert rc == 0 and "(0 run now, 6 kept)" in out and err == ""


def test_study_lf_vs_tomo_compares_by_ltpr(tmp_path, capsys):
    rc, out, err = run_cli(capsys, "study", "lf-vs-tomo", "--scale", "tiny", "--out", tmp_path, "--device", "cpu",
                           "--quiet")
    assert rc == 0, err
    folder = tmp_path / "lf-vs-tomo"
    rows = list(csv.DictReader((folder / "table.csv").open()))
    assert {r["kind"] for r in rows} == {"tomo", "lf"} and "disp_rms_z_um" in rows[0]
    assert (folder / "figure.png").read_bytes()[:4] == b"\x89PNG"
    report = (folder / "report.md").read_text()
    assert "Figs. 4.23 and 4.24" in report and "LTPR" in report and "Scaled down" in report
    assert "study lf-vs-tomo: 6 cases (6 run now)" in out


def test_study_on_workers_and_a_users_rig(tmp_path, capsys):
    rc, out, err = run_cli(capsys, "study", "iterations", "--scale", "tiny", "--out", tmp_path, "--device", "cpu",
                           "--workers", "2", "--rig", EXAMPLES / "tiny.toml", "--quiet")
    assert rc == 0, err
    assert "6 cases (6 run now)" in out
    assert "`tiny.toml` rig" in (tmp_path / "iterations" / "report.md").read_text()


def test_study_bad_input(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "study", "nope", "--out", tmp_path)
    assert rc == 2 and "invalid choice" in err
    rc, _, err = run_cli(capsys, "study", "dual", "--out", tmp_path, "--rig", tmp_path / "missing.toml")
    assert rc == 2 and err.count("\n") == 1
    rc, _, err = run_cli(capsys, "study", "dual", "--out", tmp_path, "--workers", "0")
    assert rc == 2 and "at least 1" in err
    # the studies are of light-field PIV: a rig of pinhole cameras only is refused in one line
    rc, _, err = run_cli(capsys, "study", "iterations", "--out", tmp_path, "--rig", EXAMPLES / "tomo_4_cameras.toml")
    assert rc == 2 and err.count("\n") == 1 and "only pinhole cameras" in err


def test_study_on_a_mixed_rig_uses_its_light_field_cameras():
    from lfpiv.jobs.study import study_setup

    setup = study_setup(scale="tiny", rig=EXAMPLES / "mixed_cameras.toml")
    assert len(setup.rig["camera"]) == 1 and setup.rig["camera"][0].get("kind", "lightfield") == "lightfield"
    assert "light-field cameras" in setup.rig_name
