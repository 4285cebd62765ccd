"""The run store round trip and its guards."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from lfcore.runstore import FRAME_CODEC, FrameWriter, RunStore, RunStoreError


def test_drops_of_a_run_killed_while_appending_them(tiny_rig, tmp_path):
    s = RunStore.create(tmp_path / "run.zarr", tiny_rig, 4, timing={}, software_version="test")
    s.add_drop("cam0", 0, 1, 2, 10, "frame_id gap")
    s.commit(1)
    # killed between two resizes (the one window left): some columns grew, the rest did not
    for name in ("camera", "pair", "frame"):
        s.group[f"drops/{name}"].resize((2,))
    want = [{"camera": "cam0", "pair": 0, "frame": 1, "frame_id": 2, "timestamp_ns": 10, "reason": "frame_id gap"}]
    assert RunStore.open(tmp_path / "run.zarr").drops() == want
    # every column appended, the pair not committed: still only committed pairs
    for name, value in (("camera", "cam0"), ("pair", 1), ("frame", 0), ("frame_id", 5), ("timestamp_ns", 5),
                        ("reason", "lost")):
        a = s.group[f"drops/{name}"]
        a.resize((2,))
        a[1:] = np.asarray([value], dtype=object if isinstance(value, str) else np.int64)
    assert RunStore.open(tmp_path / "run.zarr").drops() == want
    s.commit(2)
    assert len(RunStore.open(tmp_path / "run.zarr").drops()) == 2


def test_a_kill_while_adding_drops_leaves_columns_of_one_length(tiny_rig, tmp_path, monkeypatch):
    """The columns all grow before any row is written, so plain readers (xarray needs one
    length per dimension) can read the drops of a recorder killed while adding them, and lfpiv
    leaves the rows that were never finished out."""
    import xarray as xr

    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 4, timing={}, software_version="test")
    s.add_drop("cam0", 0, 1, 2, 10, "frame_id gap")
    s.commit(3)
    writes = 0
    real_setitem = zarr.Array.__setitem__

    def killed_after_three_columns(self, key, value):
        nonlocal writes
        writes += 1
        if writes > 3:
            raise SystemExit("killed")
        real_setitem(self, key, value)

    monkeypatch.setattr(zarr.Array, "__setitem__", killed_after_three_columns)
    with pytest.raises(SystemExit):
        s.add_drops([{"camera": "cam1", "pair": 2, "frame": 0, "frame_id": 7, "timestamp_ns": 11, "reason": "timeout"}])
    monkeypatch.undo()
    ds = xr.open_zarr(path, group="drops", consolidated=False)
    assert ds.sizes == {"drop": 2}
    assert list(ds["camera"].values) == ["cam0", "cam1"] and list(ds["reason"].values) == ["frame_id gap", ""]
    assert RunStore.open(path).drops() == [{"camera": "cam0", "pair": 0, "frame": 1, "frame_id": 2,
                                            "timestamp_ns": 10, "reason": "frame_id gap"}]
    with pytest.raises(RunStoreError, match="needs a reason"):
        s.add_drop("cam0", 1, 0, 3, 12, "")


def test_round_trip(tiny_rig, tmp_path):
    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 3, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="9.9")
    assert s.state == "recording" and s.committed_pairs == 0
    img = np.random.default_rng(0).integers(0, 65535, (160, 192), dtype=np.uint16)
    s.write_frame("cam0", 1, 1, img, frame_id=3, timestamp_ns=123)
    s.commit(2)
    s.add_drop("cam0", 2, 0, 4, 456, "frame_id gap")
    p = np.random.default_rng(1).normal(size=(3, 2, 7, 3))
    s.write_truth(p, np.ones((3, 2, 7)), {"name": "uniform", "velocity_m_s": [1, 0, 0]}, ppm=0.5, seed=4)
    s.set_state("complete")

    r = RunStore.open(path)
    assert r.rig == tiny_rig
    assert r.cameras == ["cam0"] and r.n_pairs == 3
    assert (r.state, r.committed_pairs) == ("complete", 2)
    assert r.attrs["software_version"] == "9.9" and r.timing == {"dt_s": 0.002, "rate_hz": 10.0}
    f = r.frames("cam0")
    assert f.shape == (3, 2, 160, 192) and f.dtype == np.uint16 and f.chunks == (1, 1, 160, 192)
    assert np.array_equal(f[1, 1], img) and not f[0, 0].any()
    assert r.frame_ids("cam0")[1, 1] == 3 and r.frame_ids("cam0")[0, 0] == -1
    assert r.timestamps_ns("cam0")[1, 1] == 123
    assert r.drops() == [{"camera": "cam0", "pair": 2, "frame": 0, "frame_id": 4, "timestamp_ns": 456,
                          "reason": "frame_id gap"}]
    t = r.truth()
    assert np.array_equal(t["particles"], p) and t["attrs"]["flow"]["name"] == "uniform"
    assert t["attrs"]["ppm"] == 0.5
    assert np.allclose(t["t0_s"], [0.0, 0.1, 0.2])  # pair / rate_hz unless the writer gives the times
    # a user with plain zarr sees units and axes
    g = zarr.open_group(str(path), mode="r")
    assert g["cam0/frames"].attrs["axes"] == ["pair", "frame", "row", "column"]
    assert g["truth/particles"].attrs["units"] == "mm"


def test_truth_times_kept_and_read_from_older_stores(tiny_rig, tmp_path):
    s = RunStore.create(tmp_path / "run.zarr", tiny_rig, 3, timing={"dt_s": 0.002, "rate_hz": 5.0},
                        software_version="x")
    flow = {"name": "uniform", "velocity_m_s": [1, 0, 0]}
    s.write_truth(np.zeros((3, 2, 1, 3)), np.ones((3, 2, 1)), flow, t0_s=[0.0, 0.2, 0.0])  # a pool of two pairs
    assert RunStore.open(s.path).truth()["t0_s"].tolist() == [0.0, 0.2, 0.0]
    assert zarr.open_group(str(s.path), mode="r")["truth/t0_s"].attrs["units"] == "s"
    del s.group["truth/t0_s"]  # written before the times were kept
    assert np.allclose(RunStore.open(s.path).truth()["t0_s"], [0.0, 0.2, 0.4])
    with pytest.raises(ValueError, match="one time per pair"):
        s.write_truth(np.zeros((3, 2, 1, 3)), np.ones((3, 2, 1)), flow, t0_s=[0.0, 0.2])


def test_guards(tiny_rig, tmp_path):
    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 1, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="x")
    s.write_frame("cam0", 0, 0, np.full((160, 192), 7, np.uint16), 0, 0)
    with pytest.raises(RunStoreError, match="already exists; choose another output path or pass --overwrite"):
        RunStore.create(path, tiny_rig, 1, timing={}, software_version="x")
    assert RunStore.open(path).frames("cam0")[0, 0, 0, 0] == 7  # untouched
    with pytest.raises(RunStoreError, match="uint16"):
        s.write_frame("cam0", 0, 1, np.zeros((160, 192), np.float32), 1, 1)
    with pytest.raises(RunStoreError, match="does not exist"):
        RunStore.open(tmp_path / "nope.zarr")
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w")
    with pytest.raises(RunStoreError, match="not an lfpiv run store"):
        RunStore.open(tmp_path / "plain.zarr")
    newer = zarr.open_group(str(path), mode="r+")
    newer.attrs["format_version"] = 99
    with pytest.raises(RunStoreError, match=r"newer lfpiv \(format_version 99\); upgrade lfpiv"):
        RunStore.open(path)
    newer.attrs["format_version"] = 1
    bad = zarr.open_group(str(path), mode="r+")
    bad.attrs["rig"] = {"camera": []}
    with pytest.raises(RunStoreError):
        _ = RunStore.open(path).rig
    with pytest.raises(RunStoreError, match="at least one pair"):
        RunStore.create(tmp_path / "zero.zarr", tiny_rig, 0, timing={}, software_version="x")
    with pytest.raises(RunStoreError, match="state must be one of"):
        s.set_state("finished")


@pytest.mark.parametrize("damage, missing", [
    (lambda g: g["cam0"].__delitem__("frames"), "cam0/frames"),
    (lambda g: g["drops"].__delitem__("reason"), "drops/reason"),
    (lambda g: g.attrs.__delitem__("state"), "the root attribute 'state'"),
])
def test_a_damaged_store_is_named_not_a_key_error(tiny_rig, tmp_path, damage, missing):
    path = tmp_path / "run.zarr"
    RunStore.create(path, tiny_rig, 1, timing={}, software_version="x")
    damage(zarr.open_group(str(path), mode="r+"))
    with pytest.raises(RunStoreError, match=f"^{path} is incomplete: {missing} is missing .*cannot be read"):
        RunStore.open(path)


def test_a_half_made_volumes_group_counts_as_none_and_is_made_again(tiny_rig, tmp_path):
    from lfcore.volume import VolumeGrid

    s = RunStore.create(tmp_path / "v.zarr", tiny_rig, 1, timing={}, software_version="x")
    s.group.create_group("volumes")  # a reconstruction killed between the group and its array
    r = RunStore.open(tmp_path / "v.zarr", mode="r+")
    assert not r.has_volumes and r.reconstructed_pairs() == []
    with pytest.raises(RunStoreError, match="no reconstructed volumes; run 'lfpiv reconstruct"):
        r.volumes()
    r.create_volumes(VolumeGrid.from_rig(tiny_rig), method="drt-mart", settings={})
    assert RunStore.open(tmp_path / "v.zarr").volumes().shape[:2] == (1, 2)


def test_volumes_round_trip(tiny_rig, tmp_path):
    from lfcore.volume import VolumeGrid

    s = RunStore.create(tmp_path / "v.zarr", tiny_rig, 2, timing={}, software_version="x")
    assert not s.has_volumes and s.reconstructed_pairs() == []
    with pytest.raises(RunStoreError, match="no reconstructed volumes; run 'lfpiv reconstruct"):
        s.volumes()
    grid = VolumeGrid.from_rig(tiny_rig)
    s.create_volumes(grid, method="drt-mart", settings={"iterations": 3})
    vol = np.random.default_rng(0).random(grid.shape, dtype=np.float32)
    s.write_volume(1, 0, vol)
    assert s.reconstructed_pairs() == []  # frame B still missing
    s.write_volume(1, 1, 2 * vol)
    r = RunStore.open(tmp_path / "v.zarr")
    assert r.reconstructed_pairs() == [1]
    assert r.volume_grid() == grid
    v = r.volumes()
    assert v.shape == (2, 2, *grid.shape) and v.dtype == np.float32
    assert np.array_equal(v[1, 1], 2 * vol) and not v[0].any()
    assert r.group["volumes"].attrs["method"] == "drt-mart"


def test_volumes_are_replaced_only_once_the_new_ones_are_finished(tiny_rig, tmp_path):
    from lfcore.volume import VolumeGrid

    path = tmp_path / "v.zarr"
    s = RunStore.create(path, tiny_rig, 2, timing={}, software_version="x")
    grid = VolumeGrid.from_rig(tiny_rig)
    s.create_volumes(grid, method="mart", settings={"iterations": 1})
    old = np.ones(grid.shape, np.float32)
    for f in (0, 1):
        s.write_volume(0, f, old)
    s.finish("volumes")  # nothing pending: nothing to do
    old_id = s.volumes_id
    s.create_volumes(grid, method="drt-mart", settings={"iterations": 2})
    # a second process (a Dask worker) writes into the same replacement
    w = RunStore.open(path, mode="r+")
    w.resume("volumes")
    w.write_volume(1, 0, 3 * old, record=False)
    s.write_volume(1, 1, 3 * old, record=False)
    # further attributes in the same write, made from the current ones (the operator figures)
    s.record_volumes([(1, 0)], attrs=lambda now: {"frames": now.get("frames", 0) + 1})
    s.record_volumes([(1, 1)], attrs=lambda now: {"frames": now.get("frames", 0) + 1})
    r = RunStore.open(path)
    assert r.volumes_id == old_id and r.reconstructed_pairs() == [0] and r.volumes()[0, 1].min() == 1
    assert r.pending("volumes").attrs["reconstructed_pairs"] == [1] and r.pending("volumes").attrs["frames"] == 2
    s.finish("volumes")
    r = RunStore.open(path)
    assert r.pending("volumes") is None and r.volumes_id != old_id and r.reconstructed_pairs() == [1]
    assert r.group["volumes"].attrs["method"] == "drt-mart" and r.volumes()[1, 0].max() == 3
    assert sorted(p.name for p in path.iterdir() if p.name.startswith("volumes")) == ["volumes"]
    with pytest.raises(RunStoreError, match="no volumes.pending/ to resume"):
        r.resume("volumes")


def test_a_replacement_killed_as_it_is_put_in_place_is_settled_on_the_next_write(tiny_rig, tmp_path):
    import os

    from lfcore.volume import VolumeGrid

    path = tmp_path / "v.zarr"
    s = RunStore.create(path, tiny_rig, 1, timing={}, software_version="x")
    grid = VolumeGrid.from_rig(tiny_rig)
    for iterations in (1, 2):
        s.create_volumes(grid, method="mart", settings={"iterations": iterations})
        s.plan("volumes", [0])
        assert s.unfinished("volumes") == ([0] if iterations == 2 else [])
        s.write_volume(0, 0, np.full(grid.shape, iterations, np.float32))
        s.write_volume(0, 1, np.full(grid.shape, iterations, np.float32))
        assert s.unfinished("volumes") == []
        if iterations == 1:
            assert not s.finish("volumes")  # written in place: nothing to put there
    # killed between the two renames of finish: no volumes/, the old set aside, the new one pending
    os.replace(path / "volumes", path / "volumes.replaced")
    r = RunStore.open(path)
    assert not r.has_volumes and r.replaced_left("volumes")
    assert RunStore.open(path, mode="r+").group["volumes"].attrs["settings"] == {"iterations": 2}
    r = RunStore.open(path)
    assert r.volumes()[0, 1].min() == 2 and r.pending("volumes") is None and not r.replaced_left("volumes")
    # killed while the old set was deleted: what is left of it goes
    (path / "volumes.replaced" / "c").mkdir(parents=True)
    assert RunStore.open(path, mode="r+").recover() == [] and not (path / "volumes.replaced").exists()


def test_frame_writer_writes_the_chunks_zarr_writes(tiny_rig, tmp_path):
    rng = np.random.default_rng(2)
    frames = (rng.normal(100, 5, (3, 2, 160, 192)) + (rng.random((3, 2, 160, 192)) < 0.02) * 3000).astype(np.uint16)
    ours = RunStore.create(tmp_path / "ours.zarr", tiny_rig, 4, timing={}, software_version="0")
    ref = RunStore.create(tmp_path / "ref.zarr", tiny_rig, 4, timing={}, software_version="0")
    w = FrameWriter(ours.frames("cam0"))
    assert w.direct
    w.write_pairs(0, frames[:2])
    w.write(3, 1, frames[2, 1])
    ref.frames("cam0")[0:2] = frames[:2]
    ref.frames("cam0")[3, 1] = frames[2, 1]
    back = RunStore.open(tmp_path / "ours.zarr").frames("cam0")
    assert np.array_equal(back[0:2], frames[:2]) and np.array_equal(back[3, 1], frames[2, 1])
    assert not back[2].any() and not back[3, 0].any()  # never written: the fill value
    for key in ("c/0/0/0/0", "c/1/1/0/0", "c/3/1/0/0"):  # byte for byte what zarr writes
        a = (tmp_path / "ours.zarr" / "cam0" / "frames" / key).read_bytes()
        assert a == (tmp_path / "ref.zarr" / "cam0" / "frames" / key).read_bytes() and len(a) < frames[0, 0].nbytes
    assert not (tmp_path / "ours.zarr" / "cam0" / "frames" / "c" / "2").exists()


def test_frame_writer_goes_through_zarr_for_other_layouts(tmp_path):
    g = zarr.open_group(tmp_path / "g.zarr", mode="w")
    plain = g.create_array("plain", shape=(2, 2, 8, 8), chunks=(1, 1, 8, 8), dtype=np.uint16, fill_value=0)
    wide = g.create_array("wide", shape=(2, 2, 8, 8), chunks=(1, 2, 8, 8), dtype=np.uint16, fill_value=0,
                          compressors=FRAME_CODEC)
    img = np.arange(64, dtype=np.uint16).reshape(8, 8)
    for arr in (plain, wide):
        w = FrameWriter(arr)
        assert not w.direct
        w.write(1, 1, img)
        w.write_pairs(0, np.stack([[img, img]]))
        assert np.array_equal(arr[1, 1], img) and np.array_equal(arr[0, 0], img)


def test_every_group_reads_with_xarray(tiny_rig, tmp_path):
    """The run-store layout (docs/reference/run-store.md): a user with plain zarr or xarray reads a
    run without lfpiv. xarray needs each array's axes as zarr v3 dimension_names, with one size per
    name across a group."""
    xr = pytest.importorskip("xarray")
    from lfcore.volume import VolumeGrid

    path = tmp_path / "run.zarr"
    s = RunStore.create(path, tiny_rig, 2, timing={}, software_version="x")
    s.write_frame("cam0", 1, 0, np.full((160, 192), 7, np.uint16), 5, 123)
    s.add_drops([{"camera": "cam0", "pair": 0, "frame": 1, "frame_id": 2, "timestamp_ns": 9, "reason": "test"}])
    s.write_truth(np.zeros((2, 2, 3, 3)), np.ones((2, 2, 3)), flow={"name": "uniform"})
    grid = VolumeGrid.from_rig(tiny_rig)
    s.create_volumes(grid, method="drt-mart", settings={})
    s.create_vectors(x_mm=[0.0, 1.0], y_mm=[0.0], z_mm=[0.0, 0.5, 1.0], dt_s=0.002, windows=[(16, 16, 8)],
                     overlap=(0.5, 0.5, 0.5), settings={})
    cam = xr.open_zarr(path, group="cam0", consolidated=False)
    assert cam["frames"].dims == ("pair", "frame", "row", "column") and cam["frames"].attrs["units"] == "counts"
    assert int(cam["frames"][1, 0, 3, 4]) == 7 and int(cam["timestamp_ns"][1, 0]) == 123
    drops = xr.open_zarr(path, group="drops", consolidated=False)
    assert drops["reason"].dims == ("drop",) and drops["reason"].values.tolist() == ["test"]
    truth = xr.open_zarr(path, group="truth", consolidated=False)
    assert truth["particles"].dims == ("pair", "frame", "particle", "xyz")
    vol = xr.open_zarr(path, group="volumes", consolidated=False)
    assert vol["data"].dims == ("pair", "frame", "z", "y", "x") and vol["data"].shape[2:] == grid.shape
    vec = xr.open_zarr(path, group="vectors", consolidated=False)
    assert vec["u"].dims == ("pair", "z", "y", "x") and vec["u"].shape == (2, 3, 1, 2)
    assert vec["x_mm"].dims == ("x",) and vec["u"].attrs["units"] == "m/s"
