"""`lfpiv reconstruct --projector matrix-free` end to end: the volumes, their recorded settings,
`lfpiv info`, the one-line error of a method it does not apply to, and a camera off the grid axes."""

from __future__ import annotations

import shutil

import numpy as np
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


def test_a_tilted_camera_reconstructs_matrix_free_as_on_its_stored_weights(capsys, tmp_path):
    """A camera off the grid axes (here 20 degrees about y; a fitted pose is a fraction of a degree)
    takes the templates of its sampled depths: the command runs matrix-free, and the volume is the
    stored weights' to the fidelity of its voxels' images."""
    rig_path = tmp_path / "tilted.toml"
    text = (EXAMPLES / "tiny.toml").read_text()
    rig_path.write_text(text.replace("rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [0.0, 20.0, 0.0]"))
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", str(rig_path), "--out", str(run), "--pairs", "1", "--ppm", "0.1", "--quiet"]) == 0
    stored = tmp_path / "stored.zarr"
    shutil.copytree(run, stored)
    capsys.readouterr()
    rc, out, err = _run(capsys, "reconstruct", str(run), "--projector", "matrix-free", "--iterations", "10", "--quiet")
    assert rc == 0, err
    rc, out, err = _run(capsys, "reconstruct", str(stored), "--projector", "stored", "--iterations", "10", "--quiet")
    assert rc == 0, err
    a, b = RunStore.open(stored).volumes()[0].ravel(), RunStore.open(run).volumes()[0].ravel()
    assert a.max() > 0
    assert np.corrcoef(a, b)[0, 1] >= 0.999 and abs(b.sum() / a.sum() - 1.0) <= 0.01
    rc, out, _ = _run(capsys, "info", str(run))
    assert rc == 0 and "projector matrix-free" in out


def test_matrix_free_on_a_mixed_rig_is_refused_before_the_store_is_touched(capsys, tmp_path):
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", str(EXAMPLES / "mixed_cameras.toml"), "--out", str(run), "--pairs", "1",
                 "--ppm", "0.05", "--quiet"]) == 0
    capsys.readouterr()
    rc, out, err = _run(capsys, "reconstruct", str(run), "--projector", "matrix-free", "--iterations", "2", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "is a pinhole camera, and the templates are for light-field cameras alone; use --projector auto" in err
    assert "volumes" not in RunStore.open(run).group and "volumes.pending" not in RunStore.open(run).group
