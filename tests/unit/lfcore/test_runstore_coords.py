"""Coordinate arrays of volumes/ and vectors/: plain xarray labels every axis in world units."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfcore.volume import VolumeGrid

xr = pytest.importorskip("xarray")

RATE_HZ = 15.0


def _run(rig, path, *, timing=None, pairs=3):
    return RunStore.create(path, rig, pairs, timing={"dt_s": 0.002, "rate_hz": RATE_HZ} if timing is None else timing,
                           software_version="x")


def test_volumes_open_with_voxel_centres_and_pair_times(tiny_rig, tmp_path):
    s = _run(tiny_rig, tmp_path / "run.zarr")
    grid = VolumeGrid(shape=(4, 3, 5), voxel_mm=(0.5, 0.25, 2.0), origin_mm=(-1.0, 2.0, -3.0))
    s.create_volumes(grid, method="drt-mart", settings={})
    s.write_volume(1, 0, np.full(grid.shape, 2.0, np.float32))
    ds = xr.open_zarr(s.path, group="volumes", consolidated=False)
    # the centre of voxel [k, j, i] is origin + (i, j, k) * voxel
    assert np.allclose(ds["x"].values, [-1.0, -0.5, 0.0, 0.5, 1.0])
    assert np.allclose(ds["y"].values, [2.0, 2.25, 2.5])
    assert np.allclose(ds["z"].values, [-3.0, -1.0, 1.0, 3.0])
    for name in "xyz":
        assert ds[name].dims == (name,) and ds[name].attrs["units"] == "mm" and name in ds.indexes
    # time: a non-dimension coordinate along pair, attached through the CF "coordinates" attribute
    assert "time" in ds.coords and ds["time"].dims == ("pair",) and ds["time"].dtype == np.float64
    assert np.allclose(ds["time"].values, np.arange(3) / RATE_HZ) and ds["time"].attrs["units"] == "s"
    data = ds["data"]
    assert data.dims == ("pair", "frame", "z", "y", "x") and set(data.coords) == {"x", "y", "z", "time"}
    # label-based selection in world units: the voxel at x = 0.5 mm, z = 1 mm of pair 1, frame A
    assert float(data.sel(x=0.5, z=1.0, y=2.25).isel(pair=1, frame=0)) == 2.0
    assert float(data.isel(pair=1)["time"]) == pytest.approx(1 / RATE_HZ)


def test_vectors_open_with_window_centres_and_pair_times(tiny_rig, tmp_path):
    s = _run(tiny_rig, tmp_path / "run.zarr")
    s.create_volumes(VolumeGrid.from_rig(tiny_rig), method="drt-mart", settings={})
    x, y, z = [0.0, 1.5], [-2.0], [0.0, 0.5, 1.0]
    s.create_vectors(x_mm=x, y_mm=y, z_mm=z, dt_s=0.002, windows=[(16, 16, 8)], overlap=(0.5, 0.5, 0.5), settings={})
    vel = np.zeros((3, 1, 2, 3), np.float32)
    vel[..., 0] = 1.25
    s.write_vectors(2, vel, np.zeros((3, 1, 2), np.uint8), np.ones((3, 1, 2), np.float32))
    ds = xr.open_zarr(s.path, group="vectors", consolidated=False)
    for name, want in (("x", x), ("y", y), ("z", z)):
        assert ds[name].dims == (name,) and ds[name].attrs["units"] == "mm" and np.allclose(ds[name].values, want)
        assert np.array_equal(ds[f"{name}_mm"].values, ds[name].values)  # the arrays lfpiv has always kept stay
    assert np.allclose(ds["time"].values, np.arange(3) / RATE_HZ) and ds["time"].attrs["units"] == "s"
    for name in ("u", "v", "w", "flags", "peak_ratio"):
        assert ds[name].dims == ("pair", "z", "y", "x") and "time" in ds[name].coords
    assert float(ds["u"].sel(x=1.5, z=0.5).isel(pair=2, y=0)) == 1.25
    assert ds["u"].attrs["units"] == "m/s"
    # lfpiv reads the vectors as before
    assert s.vectors()["x_mm"].tolist() == x and s.vectors()["u"][2, 1, 0, 1] == 1.25


def test_what_decode_coords_does(tiny_rig, tmp_path):
    """The dimension coordinates are xarray's indexes whatever decode_coords says; the CF
    "coordinates" attribute is what makes ``time`` a coordinate, and decode_coords=False leaves
    it a data variable."""
    s = _run(tiny_rig, tmp_path / "run.zarr")
    s.create_volumes(VolumeGrid.from_rig(tiny_rig), method="drt-mart", settings={})
    for decode in (True, "coordinates", "all"):
        ds = xr.open_zarr(s.path, group="volumes", consolidated=False, decode_coords=decode)
        assert set(ds.coords) == {"x", "y", "z", "time"} and list(ds.data_vars) == ["data"]
    ds = xr.open_zarr(s.path, group="volumes", consolidated=False, decode_coords=False)
    assert set(ds.coords) == {"x", "y", "z"} and set(ds.data_vars) == {"data", "time"}
    assert ds["data"].attrs["coordinates"] == "time"


def test_a_run_without_a_rate_has_unknown_times(tiny_rig, tmp_path):
    s = _run(tiny_rig, tmp_path / "run.zarr", timing={}, pairs=2)
    s.create_volumes(VolumeGrid.from_rig(tiny_rig), method="drt-mart", settings={})
    ds = xr.open_zarr(s.path, group="volumes", consolidated=False)
    assert ds["time"].shape == (2,) and np.isnan(ds["time"].values).all()


def test_replacements_get_coordinates_and_keep_them_in_place(tiny_rig, tmp_path):
    s = _run(tiny_rig, tmp_path / "run.zarr", pairs=1)
    old = VolumeGrid(shape=(2, 2, 2), voxel_mm=(1.0, 1.0, 1.0), origin_mm=(0.0, 0.0, 0.0))
    new = VolumeGrid(shape=(2, 2, 3), voxel_mm=(0.5, 1.0, 1.0), origin_mm=(-1.0, 0.0, 0.0))
    s.create_volumes(old, method="mart", settings={})
    for f in (0, 1):
        s.write_volume(0, f, np.ones(old.shape, np.float32))
    s.create_volumes(new, method="mart", settings={})  # old volumes exist: made in volumes.pending/
    s.create_vectors(x_mm=[0.0], y_mm=[0.0], z_mm=[0.0], dt_s=0.002, windows=[(8, 8, 8)], overlap=(0, 0, 0),
                     settings={})
    s.write_vectors(0, np.zeros((1, 1, 1, 3)), np.zeros((1, 1, 1)), np.ones((1, 1, 1)))
    s.create_vectors(x_mm=[5.0, 6.0], y_mm=[0.0], z_mm=[0.0], dt_s=0.002, windows=[(8, 8, 8)], overlap=(0, 0, 0),
                     settings={})
    pending = xr.open_zarr(s.path, group="volumes.pending", consolidated=False)
    assert np.allclose(pending["x"].values, [-1.0, -0.5, 0.0]) and "time" in pending["data"].coords
    assert xr.open_zarr(s.path, group="vectors.pending", consolidated=False)["x"].values.tolist() == [5.0, 6.0]
    assert xr.open_zarr(s.path, group="volumes", consolidated=False)["x"].values.tolist() == [0.0, 1.0]
    for f in (0, 1):
        s.write_volume(0, f, np.ones(new.shape, np.float32))
    s.write_vectors(0, np.zeros((1, 1, 2, 3)), np.zeros((1, 1, 2)), np.ones((1, 1, 2)))
    assert s.finish("volumes") and s.finish("vectors")
    vol = xr.open_zarr(s.path, group="volumes", consolidated=False)
    assert np.allclose(vol["x"].values, [-1.0, -0.5, 0.0]) and vol["time"].values.tolist() == [0.0]
    assert xr.open_zarr(s.path, group="vectors", consolidated=False)["x"].values.tolist() == [5.0, 6.0]


def test_stores_made_before_the_coordinates_still_work(tiny_rig, tmp_path):
    s = _run(tiny_rig, tmp_path / "run.zarr", pairs=1)
    grid = VolumeGrid.from_rig(tiny_rig)
    s.create_volumes(grid, method="mart", settings={})
    s.create_vectors(x_mm=[0.0, 1.0], y_mm=[0.0], z_mm=[0.0], dt_s=0.002, windows=[(8, 8, 8)], overlap=(0, 0, 0),
                     settings={})
    for group in ("volumes", "vectors"):  # as an older lfpiv left them
        g = s.group[group]
        for name in ("x", "y", "z", "time"):
            del g[name]
        for name in g.array_keys():
            if "coordinates" in g[name].attrs:
                del g[name].attrs["coordinates"]
    r = RunStore.open(s.path, mode="r+")
    assert r.volume_grid() == grid
    r.write_volume(0, 0, np.ones(grid.shape, np.float32))
    r.write_volume(0, 1, np.ones(grid.shape, np.float32))
    r.write_vectors(0, np.ones((1, 1, 2, 3)), np.zeros((1, 1, 2)), np.ones((1, 1, 2)))
    r = RunStore.open(s.path)
    assert r.reconstructed_pairs() == [0] and r.correlated_pairs() == [0] and r.vectors()["u"][0].min() == 1
    ds = xr.open_zarr(s.path, group="vectors", consolidated=False)
    assert "time" not in ds.coords and ds["u"].dims == ("pair", "z", "y", "x")
    # a new set made in place of the old one has them
    r = RunStore.open(s.path, mode="r+")
    r.create_volumes(grid, method="mart", settings={})
    for f in (0, 1):
        r.write_volume(0, f, np.ones(grid.shape, np.float32))
    assert r.finish("volumes")
    assert "time" in xr.open_zarr(s.path, group="volumes", consolidated=False).coords


def test_a_time_resolved_timing_is_told_by_its_rate_and_dt():
    from lfcore.runstore import is_time_resolved

    assert is_time_resolved({"dt_s": 0.002, "rate_hz": 250.0})  # a pair every 2 dt
    assert is_time_resolved({"dt_s": 0.002, "rate_hz": 250.0 * 1.009})  # within 1%
    assert not is_time_resolved({"dt_s": 0.002, "rate_hz": 250.0 * 1.02})
    assert not is_time_resolved({"dt_s": 0.002, "rate_hz": 10.0})  # double-frame pairs at 10 Hz
    assert not is_time_resolved({"dt_s": 0.002, "rate_hz": None})
    assert not is_time_resolved({"dt_s": 0.002})
    assert not is_time_resolved({})
