"""Damage named as damage: every chunk is checksummed and stored, so a missing or changed chunk
of a recorded pair is reported (by verify() and by the reading paths, one line each), never read
as zeros."""

from __future__ import annotations

import json
import os
from pathlib import Path

import google_crc32c
import numcodecs
import numpy as np
import pytest
import zarr

from lfcore.runstore import FrameWriter, RunStore, RunStoreError
from lfcore.volume import VolumeGrid

GRID = VolumeGrid(shape=(20, 3, 4), voxel_mm=(0.5, 0.5, 1.0), origin_mm=(0.0, 0.0, 0.0))  # two chunks along z
LOST = "frame_id gap"


@pytest.fixture
def run(tiny_rig, tmp_path) -> Path:
    """3 committed pairs of cam0 (pair 1 frame B lost), volumes of pairs 0 and 1, vectors of pair 0."""
    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 3, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="x")
    rng = np.random.default_rng(0)
    w = FrameWriter(s.frames("cam0"))
    ids = np.full((3, 2), -1, np.int64)
    for p in range(3):
        for f in (0, 1):
            if (p, f) != (1, 1):
                w.write(p, f, rng.integers(0, 4096, (160, 192), dtype=np.uint16))
                ids[p, f] = 2 * p + f
    s.group["cam0/frame_id"][...] = ids
    s.group["cam0/timestamp_ns"][...] = ids * 1000
    s.add_drop("cam0", 1, 1, 3, 3000, LOST)
    s.commit(3)
    s.write_truth(rng.normal(size=(3, 2, 5, 3)), np.ones((3, 2, 5)), {"name": "uniform"})
    s.create_volumes(GRID, method="mart", settings={})
    for p in (0, 1):
        for f in (0, 1):
            s.write_volume(p, f, rng.random(GRID.shape, dtype=np.float32))
    s.create_vectors(x_mm=[0.0, 1.0], y_mm=[0.0], z_mm=[0.0], dt_s=0.002, windows=[(8, 8, 8)], overlap=(0, 0, 0),
                     settings={})
    s.write_vectors(0, np.ones((1, 1, 2, 3)), np.zeros((1, 1, 2)), np.ones((1, 1, 2)))
    s.set_state("complete")
    s.close()
    return path


def _one(lines: list[str], path: Path) -> str:
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"{path}: ") and "\n" not in lines[0]
    return lines[0]


def test_a_whole_run_verifies_and_reads(run):
    s = RunStore.open(run)
    assert s.verify() == [] and RunStore.check(run) == []
    assert s.read_frame("cam0", 2, 1).shape == (160, 192)
    assert np.array_equal(s.read_frame("cam0", 0, 1), s.frames("cam0")[0, 1])
    assert np.array_equal(s.read_volume(1, 0), s.volumes()[1, 0])
    assert s.read_vectors(0)["u"].tolist() == [[[1.0, 1.0]]]
    # not damage: a frame lost while recording, pairs not recorded, volumes and vectors not made
    with pytest.raises(RunStoreError, match=f"^{run}: cam0 pair 1 frame B was lost while recording \\({LOST}\\); "
                                            "it has no image$"):
        s.read_frame("cam0", 1, 1)
    with pytest.raises(RunStoreError, match="cam0 has pairs 0-2, frames 0 \\(A\\) and 1 \\(B\\): pair 3 frame 0"):
        s.read_frame("cam0", 3, 0)
    with pytest.raises(RunStoreError, match="volumes/ has no volume of pair 2 frame A: it is not reconstructed; run "
                                            "'lfpiv reconstruct"):
        s.read_volume(2, 0)
    with pytest.raises(RunStoreError, match="vectors/ has no vectors of pair 1: it is not correlated"):
        s.read_vectors(1)


def test_frames_of_pairs_not_committed_are_not_recorded(tiny_rig, tmp_path):
    s = RunStore.create(tmp_path / "r.zarr", tiny_rig, 2, timing={}, software_version="x")
    s.write_frame("cam0", 0, 0, np.zeros((160, 192), np.uint16), 0, 0)  # written, not yet committed
    with pytest.raises(RunStoreError, match="cam0 pair 0 frame A is not recorded: the run holds no pairs yet, and is "
                                            "still recording$"):
        s.read_frame("cam0", 0, 0)
    s.write_frame("cam0", 0, 1, np.zeros((160, 192), np.uint16), 1, 1)
    s.commit(1)
    # a black frame is a frame: its chunk is stored like any other
    assert not s.read_frame("cam0", 0, 0).any() and (s.path / "cam0/frames/c/0/0/0/0").exists()
    assert s.verify() == []


def _chunk(run: Path, key: str) -> Path:
    return run / key


def _valid_chunk_of(n_values: int) -> bytes:
    """Blosc-encoded uint16 values with a correct CRC-32C: intact bytes of the wrong size."""
    data = numcodecs.Blosc("lz4", 1, numcodecs.Blosc.BITSHUFFLE).encode(np.arange(n_values, dtype="<u2"))
    return data + google_crc32c.value(data).to_bytes(4, "little")


CHUNK = "cam0/frames/c/2/0/0/0"


@pytest.mark.parametrize("damage, problem", [
    (lambda p: os.remove(p), "is missing"),
    (lambda p: p.write_bytes(np.random.default_rng(1).bytes(p.stat().st_size)),
     r"is damaged \(its checksum does not match its bytes\)"),
    (lambda p: p.write_bytes(p.read_bytes()[:-100]), r"is damaged \(its checksum does not match its bytes\)"),
    (lambda p: p.write_bytes(_valid_chunk_of(100)), r"decodes to the wrong size \(.*\)"),
])
def test_a_damaged_frame_chunk_is_named_by_verify_and_by_reading_it(run, damage, problem):
    damage(_chunk(run, CHUNK))
    line = _one(RunStore.check(run), run)
    assert line.startswith(f"{run}: cam0/frames pair 2 frame A: chunk c/2/0/0/0 ") and line.endswith(
        "; restore it from a copy of the run")
    assert pytest.importorskip("re").search(problem, line)
    s = RunStore.open(run)
    with pytest.raises(RunStoreError) as err:
        s.read_frame("cam0", 2, 0)
    assert str(err.value) == line
    assert np.array_equal(s.read_frame("cam0", 2, 1), s.frames("cam0")[2, 1])  # the rest reads


def test_a_damaged_volume_or_vector_chunk_is_named(run):
    os.remove(run / "volumes/data/c/1/0/1/0/0")  # the second z chunk of pair 1, frame A
    (run / "vectors/v/c/0/0/0/0").write_bytes(b"\x00" * 20)
    lines = RunStore.check(run)
    assert lines == [f"{run}: volumes/data pair 1 frame A: chunk c/1/0/1/0/0 is missing; restore it from a copy of "
                     "the run",
                     f"{run}: vectors/v pair 0: chunk c/0/0/0/0 is damaged (its checksum does not match its bytes); "
                     "restore it from a copy of the run"]
    s = RunStore.open(run)
    with pytest.raises(RunStoreError) as err:
        s.read_volume(1, 0)
    assert str(err.value) == lines[0]
    with pytest.raises(RunStoreError) as err:
        s.read_vectors(0)
    assert str(err.value) == lines[1]
    assert s.read_volume(1, 1).shape == GRID.shape


def _edit_json(path: Path, edit) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def test_an_edited_data_type_is_named(run):
    _edit_json(run / "cam0/frames/zarr.json", lambda d: d.update(data_type="int16"))
    line = _one(RunStore.check(run), run)
    assert line == (f"{run}: cam0/frames holds int16, but the layout says uint16 (its zarr.json was edited or "
                    "damaged); restore it from a copy of the run")
    with pytest.raises(RunStoreError) as err:
        RunStore.open(run).read_frame("cam0", 0, 0)
    assert str(err.value) == line


def test_committed_pairs_beyond_the_arrays_is_named(run):
    _edit_json(run / "zarr.json", lambda d: d["attributes"].update(committed_pairs=7))
    line = _one(RunStore.check(run), run)
    assert line == (f"{run}: committed_pairs is 7, more than the 3 pairs cam0/frames holds (the root zarr.json was "
                    "edited or damaged); restore it from a copy of the run")
    s = RunStore.open(run)
    with pytest.raises(RunStoreError, match=r"committed_pairs is 7, more than the 3 pairs the run's arrays hold "
                                            r"\(the root zarr.json was edited or damaged\)"):
        s.read_frame("cam0", 0, 0)
    _edit_json(run / "zarr.json", lambda d: d["attributes"].update(committed_pairs="3"))
    assert "committed_pairs is '3', not a number of pairs" in _one(RunStore.check(run), run)


def test_a_lost_frame_id_chunk_is_named(run):
    os.remove(run / "cam0/frame_id/c/0/0")
    assert RunStore.check(run) == [f"{run}: cam0/frame_id pairs 0-2: chunk c/0/0 is missing; restore it from a copy "
                                   "of the run"]


def test_a_frame_neither_recorded_nor_dropped_is_named(run):
    s = RunStore.open(run, mode="r+")
    s.group["drops/reason"][0] = ""  # as if the row were never written
    assert s.verify() == [f"{run}: cam0 pair 1 frame B is neither recorded (frame_id -1) nor listed in drops/ as lost: "
                          "cam0/frame_id or drops/ is damaged; restore it from a copy of the run"]


@pytest.mark.parametrize("where", ["zarr.json", "cam0/frames/zarr.json"])
def test_a_truncated_zarr_json_is_one_line(run, where):
    p = run / where
    p.write_text(p.read_text()[:60])
    for mode in ("r", "r+"):
        with pytest.raises(RunStoreError) as err:
            RunStore.open(run, mode=mode)
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(f"{p.parent}/zarr.json is damaged (not valid JSON: ")
        assert msg.endswith("cannot be opened; restore that file from a copy")
    assert RunStore.check(run) == [msg]


def test_a_truncated_zarr_json_of_derived_data_is_named_by_verify(run):
    p = run / "volumes/data/zarr.json"
    p.write_text(p.read_text()[:60])
    line = _one(RunStore.open(run).verify(), run)
    assert line.startswith(f"{run}: volumes/data/zarr.json is damaged (not valid JSON: ")


@pytest.mark.parametrize("version", ["1", 0, -3, True])
def test_a_format_version_lfpiv_never_wrote_is_one_line(run, version):
    _edit_json(run / "zarr.json", lambda d: d["attributes"].update(format_version=version))
    with pytest.raises(RunStoreError) as err:
        RunStore.open(run)
    assert str(err.value) == (f"{run}: format_version is {version!r}, not a format lfpiv writes (its zarr.json was "
                              "edited or damaged); restore it from a copy, or set it to 1")
    assert RunStore.check(run) == [str(err.value)]


def test_stores_made_before_checksums_still_read_and_verify(run):
    """Arrays without the crc32c codec (lfpiv before checksums): still read and written, frame
    by frame as before; a missing frame of a recorded frame id is still named, with the caveat
    that such stores did not store chunks of fill values."""
    g = zarr.open_group(str(run), mode="r+")
    old = g["cam0/frames"]
    data, attrs = old[...], dict(old.attrs)
    codecs = [c for c in old.metadata.codecs if type(c).__name__ != "Crc32cCodec"]
    del g["cam0/frames"]
    new = g.create_array("cam0/frames", shape=data.shape, chunks=(1, 1, 160, 192), dtype=np.uint16, fill_value=0,
                         serializer=codecs[0], compressors=codecs[1:], dimension_names=list(attrs["axes"]))
    new.attrs.update(attrs)
    new[...] = data
    s = RunStore.open(run, mode="r+")
    w = FrameWriter(s.frames("cam0"))
    assert w.direct and s.verify() == []
    w.write(2, 1, data[2, 1] + 1)
    assert np.array_equal(s.read_frame("cam0", 2, 1), data[2, 1] + 1)
    os.remove(run / CHUNK)
    assert s.verify() == [f"{run}: cam0/frames pair 2 frame A: chunk c/2/0/0/0 is missing (or, in a store written "
                          "before lfpiv kept checksums, one that held only its fill value); restore it from a copy of "
                          "the run"]
    (run / CHUNK).write_bytes(b"\x02" * 1000)  # without a checksum, only bytes that do not decode show
    line = _one(s.verify(), run)
    assert line.startswith(f"{run}: cam0/frames pair 2 frame A: chunk c/2/0/0/0 cannot be decoded (")
    with pytest.raises(RunStoreError) as err:
        s.read_frame("cam0", 2, 0)
    assert str(err.value) == line
