"""Reading a volume's planes (depth slabs): only the chunks that hold them are read and checked, and a
missing or damaged one is named in one line, never read as zeros."""

from __future__ import annotations

import os

import numpy as np
import pytest

from lfcore.runstore import RunStore, RunStoreError
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(20, 3, 4), voxel_mm=(0.5, 0.5, 1.0), origin_mm=(0.0, 0.0, 0.0))  # z chunks 0-15, 16-19


@pytest.fixture
def run(tiny_rig, tmp_path):
    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 2, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="x")
    s.commit(2)
    s.create_volumes(GRID, method="mart", settings={})
    rng = np.random.default_rng(0)
    vols = {(p, f): rng.random(GRID.shape, dtype=np.float32) for p in (0, 1) for f in (0, 1)}
    for (p, f), v in vols.items():
        s.write_volume(p, f, v)
    s.set_state("complete")
    s.close()
    return path, vols


def test_planes_are_the_volume_s_planes(run):
    path, vols = run
    s = RunStore.open(path)
    for planes in ((0, 20), (0, 1), (3, 17), (16, 20), (19, 20)):
        assert np.array_equal(s.read_volume(1, 0, planes=planes), vols[1, 0][slice(*planes)])


def test_only_the_chunks_of_the_planes_are_needed_and_a_missing_or_damaged_one_is_named(run):
    path, vols = run
    os.remove(path / "volumes/data/c/1/0/1/0/0")  # planes 16-19 of pair 1, frame A
    s = RunStore.open(path)
    assert np.array_equal(s.read_volume(1, 0, planes=(0, 16)), vols[1, 0][:16])
    with pytest.raises(RunStoreError) as err:
        s.read_volume(1, 0, planes=(10, 18))
    assert str(err.value) == (f"{path}: volumes/data pair 1 frame A: chunk c/1/0/1/0/0 is missing; restore it from a "
                              "copy of the run")
    (path / "volumes/data/c/0/1/0/0/0").write_bytes(b"\x00" * 20)  # planes 0-15 of pair 0, frame B
    with pytest.raises(RunStoreError, match=r"pair 0 frame B: chunk c/0/1/0/0/0 is damaged \(its checksum"):
        s.read_volume(0, 1, planes=(2, 4))
    assert np.array_equal(s.read_volume(0, 1, planes=(16, 20)), vols[0, 1][16:])


@pytest.mark.parametrize("planes", [(15, 25), (5, 5), (-1, 3)])
def test_planes_outside_the_volume_are_one_line(run, planes):
    path, _ = run
    with pytest.raises(RunStoreError, match="volumes/data is 20 planes deep: planes .* are not all in it") as err:
        RunStore.open(path).read_volume(0, 0, planes=planes)
    assert "\n" not in str(err.value)
