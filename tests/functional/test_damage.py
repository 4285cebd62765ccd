"""One writer per store, and damage named as damage: the reliability issue's repros, each as a test.

A second writer is refused in one line naming the process that holds the store; a missing or
damaged chunk of a committed pair is an error naming the array, pair and chunk, never zeros, and
nothing derived is replaced from damaged input; ``lfpiv check`` lists every problem."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.cli import main
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import chunk_file, damage_chunk, one_error, store_held

TINY = str(EXAMPLES / "tiny.toml")


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run with volumes and vectors (copied for each test)."""
    path = tmp_path_factory.mktemp("made") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "2", "--ppm", "0.2", "--quiet"]) == 0
    assert main(["reconstruct", str(path), "--iterations", "2", "--quiet"]) == 0
    assert main(["correlate", str(path), "--windows", "32x32x16", "--quiet"]) == 0
    return path


def _copy(made: Path, tmp_path: Path) -> Path:
    shutil.copytree(made, tmp_path / "run.zarr")
    return tmp_path / "run.zarr"


def test_a_missing_frame_chunk_is_named_and_nothing_is_replaced(made, tmp_path, capsys):
    run = _copy(made, tmp_path)
    before = RunStore.open(run).volumes()[...]
    chunk_file(run, "cam0/frames", 1).unlink()
    rc, out, err = _run(capsys, "check", run)
    assert rc == 1 and "cam0/frames pair 1 frame A: chunk c/1/0/0/0 is missing" in out, out
    rc, out, err = _run(capsys, "info", run, "--check")
    assert rc == 1 and "complete (2 of 2 pairs committed)" in out and "1 problem(s)" in out
    rc, out, err = _run(capsys, "reconstruct", run, "--iterations", "3", "--quiet")
    assert rc == 2 and one_error(err) and "cam0/frames pair 1 frame A: chunk c/1/0/0/0 is missing" in err, err
    assert "the volumes made before with other settings are unchanged" in err
    s = RunStore.open(run)
    assert np.array_equal(s.volumes()[...], before)  # the volumes made before are whole
    assert s.group["volumes"].attrs["settings"]["iterations"] == 2


def test_damaged_or_missing_volume_chunks_are_named_and_the_vectors_kept(made, tmp_path, capsys):
    run = _copy(made, tmp_path)
    v_before = RunStore.open(run).vectors()["u"][...]
    chunk = chunk_file(run, "volumes/data", 1)
    damage_chunk(chunk, "random")  # random bytes in place of the chunk
    rc, out, err = _run(capsys, "correlate", run, "--windows", "16x16x8", "--quiet")
    assert rc == 2 and one_error(err) and "volumes/data pair 1" in err, err
    assert np.array_equal(RunStore.open(run).vectors()["u"][...], v_before, equal_nan=True)
    chunk.unlink()
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 2 and err.count("\n") == 1 and "volumes/data pair 1" in err and "missing" in err, err


def test_a_truncated_chunk_and_edited_metadata_are_one_line(made, tmp_path, capsys):
    run = _copy(made, tmp_path)
    chunk = chunk_file(run, "cam0/frames", 0)
    damage_chunk(chunk, "truncated")
    rc, out, _ = _run(capsys, "check", run)
    assert rc == 1 and "cam0/frames pair 0 frame A" in out
    rc, _, err = _run(capsys, "reconstruct", run, "--quiet")
    assert rc == 2 and one_error(err) and "cam0/frames pair 0 frame A" in err, err
    (run / "zarr.json").write_text((run / "zarr.json").read_text()[:40])  # a truncated root zarr.json
    for argv in (["info", run], ["reconstruct", run], ["check", run], ["export", run, "--format", "mat", "--out",
                                                                         tmp_path / "x"]):
        rc, out, err = _run(capsys, *argv)
        assert rc in (1, 2) and "Traceback" not in err and (out + err).count("\n") <= 2, (argv, out, err)


def test_a_second_writer_is_refused_naming_the_first(made, tmp_path, capsys):
    run = _copy(made, tmp_path)
    with store_held(run) as holder:
        before = RunStore.open(run).volumes()[...]  # readers keep working
        for argv in (["reconstruct", run, "--iterations", "5", "--quiet"],
                     ["correlate", run, "--windows", "16x16x8", "--quiet"],
                     ["synth", "--rig", TINY, "--out", run, "--overwrite", "--quiet"]):
            rc, out, err = _run(capsys, *argv)
            assert rc == 2 and err.count("\n") == 1 and f"pid {holder.pid}" in err, (argv, err)
        rc, out, _ = _run(capsys, "info", run)
        assert rc == 0 and f"being written by pid {holder.pid}" in out
        assert np.array_equal(RunStore.open(run).volumes()[...], before)
    # a killed holder leaves nothing held
    t = time.monotonic()
    while time.monotonic() - t < 10:
        if _run(capsys, "reconstruct", run, "--iterations", "3", "--quiet")[0] == 0:
            break
        time.sleep(0.2)
    assert RunStore.open(run).group["volumes"].attrs["settings"]["iterations"] == 3


@pytest.mark.parametrize("how", ["random", "truncated"])
def test_a_damaged_vectors_chunk_is_one_line_in_export_and_evaluate(made, tmp_path, capsys, how):
    """The adversarial sweep's find: export and evaluate read every vector field whole first, and
    a damaged chunk was zarr's checksum ValueError in a traceback."""
    run = _copy(made, tmp_path)
    damage_chunk(chunk_file(run, "vectors/u", 1), how)
    for argv in (["export", run, "--format", "vtk", "--out", tmp_path / "x"], ["evaluate", run]):
        rc, out, err = _run(capsys, *argv)
        assert rc == 2 and one_error(err) and "vectors/u pair 1: chunk c/1/0/0/0 is damaged" in err, (argv, err)
    assert not list((tmp_path / "x").glob("*.vti"))  # nothing exported from damaged vectors


@pytest.mark.parametrize("damage", ["volumes/zarr.json", "volumes/data"])
def test_volumes_without_their_record_or_data_are_named_not_a_traceback(made, tmp_path, capsys, damage):
    """The adversarial sweep's find: volumes/zarr.json deleted was a KeyError traceback in info,
    evaluate and reconstruct and 'whole' to check; volumes/data deleted was 'whole' too."""
    run = _copy(made, tmp_path)
    (run / damage).unlink() if damage.endswith(".json") else shutil.rmtree(run / damage)
    want = "volumes/zarr.json is missing" if damage.endswith(".json") else "volumes/data is missing, though"
    rc, out, _ = _run(capsys, "check", run)
    assert rc == 1 and want in out, out
    for argv in (["info", run], ["evaluate", run], ["reconstruct", run, "--iterations", "1", "--quiet"]):
        rc, out, err = _run(capsys, *argv)
        assert rc == 2 and one_error(err) and want in err and f"remove {run}/volumes" in err, (argv, err)


def test_a_state_of_no_kind_is_named(made, tmp_path, capsys):
    run = _copy(made, tmp_path)
    meta = run / "zarr.json"
    meta.write_text(meta.read_text().replace('"state": "complete"', '"state": "weird"'))
    rc, out, err = _run(capsys, "info", run)
    assert rc == 2 and one_error(err) and "state is 'weird', not one of recording, complete, aborted" in err, err
