"""Store attributes are checked on every read (issue 50, part 2): an edited or damaged attribute
is one line naming the store, the attribute, what it holds and what it should hold, exit 2, no
traceback; nothing derived is replaced from it (a voxel size of the wrong sign never makes
``correlate`` replace good vectors with sign-flipped ones); ``lfpiv check`` lists it."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lfcore.runstore import RunStore, RunStoreError
from lfcore.runstore._schema import describe, problems
from lfpiv.cli import main
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import one_error

TINY = str(EXAMPLES / "tiny.toml")


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run with volumes and vectors (copied for each test)."""
    path = tmp_path_factory.mktemp("made") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "2", "--ppm", "0.2", "--quiet"]) == 0
    assert main(["reconstruct", str(path), "--iterations", "2", "--quiet"]) == 0
    assert main(["correlate", str(path), "--windows", "32x32x16", "--quiet"]) == 0
    return path


def _edit(run: Path, node: str, change: Callable[[dict[str, Any]], None]) -> None:
    f = run / node / "zarr.json"
    meta = json.loads(f.read_text())
    change(meta["attributes"])
    f.write_text(json.dumps(meta))


def _set(key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(a: dict[str, Any]) -> None:
        if "." in key:
            outer, inner = key.split(".")
            a[outer][inner] = value
        else:
            a[key] = value
    return change


# (node, attribute, value, what the line must say it should hold)
CASES = [
    ("", "timing.dt_s", "0.002", "attribute timing.dt_s is '0.002', not a positive, finite time in s"),
    ("", "timing.dt_s", -0.002, "attribute timing.dt_s is -0.002, not a positive"),
    ("", "timing.dt_s", 0, "attribute timing.dt_s is 0, not a positive"),
    ("", "timing", [1, 2], "attribute timing is [1, 2], not a table of the run's timing"),
    ("volumes", "origin_mm", [0.0, 0.0], "volumes/ attribute origin_mm is [0.0, 0.0], not three finite world"),
    ("volumes", "voxel_mm", "0.011", "volumes/ attribute voxel_mm is '0.011', not three positive"),
    ("volumes", "voxel_mm", [-0.011, 0.011, 0.055], "volumes/ attribute voxel_mm is [-0.011, 0.011, 0.055], not three "
                                                    "positive"),
    ("vectors", "correlated_pairs", "0,1", "vectors/ attribute correlated_pairs is '0,1', not a list of pair numbers"),
    ("truth", "flow.radius_mm", "x", "truth/ attribute flow.radius_mm is 'x', not a number"),
    ("truth", "flow.name", "nope", "truth/ attribute flow.name is 'nope', not one of the flows lfpiv knows"),
]
#: The readers that do not read a group's attributes, and may work while they are damaged
UNREAD = {"": ("evaluate",), "volumes": ("export",), "vectors": (), "truth": ("correlate", "export")}


def _vectors(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in (run / "vectors").rglob("*") if p.is_file()
            and "/c/" in f"/{p.relative_to(run).as_posix()}"}


@pytest.mark.parametrize(("node", "key", "value", "said"), CASES, ids=[f"{c[1]}={c[2]!r}" for c in CASES])
def test_a_damaged_attribute_is_one_line_in_every_reader_and_check_lists_it(made, tmp_path, capsys, node, key,
                                                                            value, said):
    run = tmp_path / "run.zarr"
    shutil.copytree(made, run)
    _edit(run, node, _set(key, value))
    vectors = _vectors(run)
    readers = {"info": ["info", run], "correlate": ["correlate", run, "--windows", "16x16x8", "--quiet"],
               "export": ["export", run, "--format", "vtk", "--out", tmp_path / "out"], "evaluate": ["evaluate", run]}
    refused = set()
    for name, argv in readers.items():
        rc, out, err = _run(capsys, *argv)
        assert "Traceback" not in err, (name, err)
        if rc == 0:  # a reader that does not use the attribute (evaluate does not read timing, export not volumes/)
            assert name in UNREAD[node], (name, key)
            continue
        refused.add(name)
        assert rc == 2 and one_error(err) and str(run) in err and said in err, (name, err)
        assert "restore it from a copy of the run" in err
    assert len(refused) >= 2
    if "correlate" in refused:  # refused before writing: the good vectors are kept, never made from a wrong grid
        assert _vectors(run) == vectors
        assert not (run / "vectors.pending").exists()
    rc, out, err = _run(capsys, "check", run)
    assert rc == 1 and said in out and "1 problem(s)" in out, out


def test_a_sign_flip_of_the_voxel_size_never_replaces_the_vectors(made, tmp_path, capsys):
    run = tmp_path / "run.zarr"
    shutil.copytree(made, run)
    u = RunStore.open(run).vectors()["u"]
    _edit(run, "volumes", _set("voxel_mm", [0.011, -0.011, 0.055]))
    rc, _, err = _run(capsys, "correlate", run, "--windows", "16x16x8", "--quiet")
    assert rc == 2 and "voxel_mm" in err and one_error(err), err
    _edit(run, "volumes", _set("voxel_mm", [0.022, 0.011, 0.055]))  # positive, but not the grid the volumes are on
    rc, _, err = _run(capsys, "correlate", run, "--windows", "16x16x8", "--quiet")
    assert rc == 2 and one_error(err) and "volumes/ attribute voxel_mm is [0.022, 0.011, 0.055], but the voxel " \
        "centres of volumes/x are 0.011 mm apart" in err, err
    assert np.array_equal(RunStore.open(run).vectors()["u"], u, equal_nan=True)


def test_the_models_accept_every_store_lfpiv_writes_and_name_every_attribute(made):
    s = RunStore.open(made)
    assert s.verify() == []
    for group, node in (("", s.group), ("volumes", s.group["volumes"]), ("vectors", s.group["vectors"]),
                        ("truth", s.group["truth"])):
        assert problems(made, group, node.attrs) == [], group
    documented = {(g, a) for g, a, _ in describe()}
    assert {("(root)", "timing"), ("volumes", "voxel_mm"), ("vectors", "correlated_pairs"), ("truth", "flow")} \
        <= documented
    # the doc's table of the schema lists every attribute the models name
    text = (Path(__file__).resolve().parents[2] / "docs" / "reference" / "run-store.md").read_text()
    assert all(f"`{a}`" in text for _, a in documented), [a for _, a in documented if f"`{a}`" not in text]


def test_a_run_is_never_created_with_a_timing_no_reader_accepts(tmp_path):
    from lfpiv.rigfile import load_rig

    with pytest.raises(RunStoreError, match=r"timing.dt_s is -1.0, not a positive"):
        RunStore.create(tmp_path / "r.zarr", load_rig(TINY), 1, timing={"dt_s": -1.0}, software_version="x")
    assert not (tmp_path / "r.zarr").exists()
