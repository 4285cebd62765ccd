"""`lfpiv reconstruct --projector matrix-free` end to end: the volumes, their recorded settings,
`lfpiv info`, and the one-line error of a method it does not apply to."""

from __future__ import annotations

import pytest

from lfcore.runstore import RunStore
from lfpiv.cli import main
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run

TINY = str(EXAMPLES / "tiny.toml")


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("mf") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--ppm", "0.1", "--flow", "uniform",
                 "--quiet"]) == 0
    return path


def test_matrix_free_from_the_command(capsys, synthetic_run):
    rc, out, err = _run(capsys, "reconstruct", str(synthetic_run), "--projector", "matrix-free", "--iterations", "2",
                        "--quiet")
    assert rc == 0, err
    assert "with drt-mart" in out and "matrix-free templates" in out and "ms per iteration" in out
    s = RunStore.open(synthetic_run)
    assert s.reconstructed_pairs() == [0]
    assert s.volumes()[0].max() > 0
    assert s.group["volumes"].attrs["settings"]["projector"] == "matrix-free"
    rc, out, err = _run(capsys, "info", str(synthetic_run))
    assert rc == 0, err
    assert "projector matrix-free" in out
    # the same settings again: nothing to do
    rc, out, _ = _run(capsys, "reconstruct", str(synthetic_run), "--projector", "matrix-free", "--iterations", "2",
                      "--quiet", "--skip-done")
    assert rc == 0 and "nothing to do" in out


def test_matrix_free_needs_drt_mart(capsys, synthetic_run):
    rc, out, err = _run(capsys, "reconstruct", str(synthetic_run), "--projector", "matrix-free", "--method", "mart",
                        "--iterations", "2", "--quiet")
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "drt-mart" in err


def test_a_camera_off_the_grid_axes_is_one_line(capsys, tmp_path):
    rig_path = tmp_path / "tilted.toml"
    text = (EXAMPLES / "tiny.toml").read_text()
    rig_path.write_text(text.replace("rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [0.0, 20.0, 0.0]"))
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", str(rig_path), "--out", str(run), "--pairs", "1", "--ppm", "0.1", "--quiet"]) == 0
    capsys.readouterr()
    rc, out, err = _run(capsys, "reconstruct", str(run), "--projector", "matrix-free", "--iterations", "2", "--quiet")
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "grid axis" in err
