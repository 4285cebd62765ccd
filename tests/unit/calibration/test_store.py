"""The calibration store: layout, attributes, grid round trip, planes and resume bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from calibration.mla_grid import detect_grid
from calibration.store import CalibrationStore, CalibrationStoreError
from lfcore.runstore import RunStore, RunStoreError
from lfcore.white import WhiteImageConfig, white_image
from tests.conftest import tiny_variant


def test_round_trip_and_plain_zarr_layout(tiny_rig, tmp_path):
    rig = tiny_variant(tiny_rig, mla_rotation_deg=0.2)
    cam = rig.camera[0]
    img = white_image(cam, render=rig.render, config=WhiteImageConfig())
    grid = detect_grid(img)
    path = tmp_path / "calib.zarr"
    s = CalibrationStore.create(path, rig, software_version="test")
    s.write_white("cam0", img, frames_averaged=3)
    s.write_grid("cam0", grid, mla=grid.to_mla(cam))
    s.init_planes(np.arange(5) * 0.5, step_mm=0.5)
    s.write_plane("cam0", 2, img, 1.0001)
    with pytest.raises(CalibrationStoreError, match="exists"):
        CalibrationStore.create(path, rig)

    back = CalibrationStore.open(path)
    assert np.array_equal(back.white("cam0"), img)
    g = back.grid("cam0")
    assert g.pitch_px == grid.pitch_px and np.array_equal(g.centres_px, grid.centres_px)
    assert np.array_equal(back.planes_done(), [False, False, True, False, False])
    assert back.stage_mm("cam0")[2] == pytest.approx(1.0001)
    text = "\n".join(back.summary())
    assert "pitch" in text and "planes 1 of 5" in text

    # a user with plain zarr: every array says its units, axes and what it is
    root = zarr.open_group(str(path), mode="r")
    assert root.attrs["format"] == "lfpiv-calibration" and root.attrs["format_version"] == 1
    for name in ("cam0/white", "cam0/mla/centres_px", "cam0/mla/residuals_px", "cam0/planes/frames",
                 "cam0/planes/stage_mm", "cam0/planes/target_mm"):
        assert {"units", "axes", "description"} <= set(root[name].attrs), name
    assert root["cam0/mla/centres_px"].shape == (grid.n_lenslets, 2)
    assert root["cam0/planes/frames"].shape == (5, 160, 192)
    m = root["cam0/mla"].attrs
    assert m["grid"] == "hex" and m["rotation_deg"] == pytest.approx(0.2, abs=0.01) and len(m["offset_px"]) == 2

    xr = pytest.importorskip("xarray")  # and a user with xarray
    mla = xr.open_zarr(path, group="cam0/mla", consolidated=False)
    assert mla["centres_px"].dims == ("lenslet", "column_row") and mla["inliers"].dims == ("lenslet",)
    planes = xr.open_zarr(path, group="cam0/planes", consolidated=False)
    assert planes["frames"].dims == ("plane", "row", "column") and float(planes["stage_mm"][2]) == 1.0001

    # a new grid removes the model fitted through the old one
    s.write_model("cam0", {"name": "cam0"}, {"rms_px": 0.1})
    assert s.model("cam0") is not None
    assert s.write_grid("cam0", grid, mla=grid.to_mla(cam)) is True
    assert s.model("cam0") is None and s.write_grid("cam0", grid) is False


def test_resume_needs_the_same_planes_and_cameras(tiny_rig, tmp_path):
    path = tmp_path / "c.zarr"
    s = CalibrationStore.open_or_create(path, tiny_rig)
    s.init_planes(np.arange(4) * 0.5, step_mm=0.5)
    s = CalibrationStore.open_or_create(path, tiny_rig)
    s.init_planes(np.arange(4) * 0.5, step_mm=0.5)  # same: fine
    with pytest.raises(CalibrationStoreError, match="other stage positions"):
        s.init_planes(np.arange(6) * 0.5, step_mm=0.5)
    other = tiny_variant(tiny_rig, name="camX")
    with pytest.raises(CalibrationStoreError, match="other cameras"):
        CalibrationStore.open_or_create(path, other)
    # the same camera with other optics: its planes would be named with the wrong model
    zoomed = tiny_variant(tiny_rig, magnification=-1.1, serial="123")
    with pytest.raises(CalibrationStoreError, match=r"made with another rig \(camera 'cam0' magnification "
                                                    r"-1\.0 in the store, -1\.1 now\); give a new --out path"):
        CalibrationStore.open_or_create(path, zoomed)
    assert CalibrationStore.open_or_create(path, tiny_variant(tiny_rig, serial="123"))  # a serial is no optics
    with pytest.raises(CalibrationStoreError, match="does not exist"):
        CalibrationStore.open(tmp_path / "nope.zarr")


def test_a_store_of_the_other_kind_is_named(tiny_rig, tmp_path):
    CalibrationStore.create(tmp_path / "calib.zarr", tiny_rig)
    RunStore.create(tmp_path / "run.zarr", tiny_rig, 1, timing={}, software_version="x")
    with pytest.raises(RunStoreError, match=r"calib.zarr is an lfpiv calibration store, not an lfpiv run store; give"):
        RunStore.open(tmp_path / "calib.zarr")
    with pytest.raises(CalibrationStoreError, match=r"run.zarr is an lfpiv run store, not an lfpiv calibration store"):
        CalibrationStore.open(tmp_path / "run.zarr")
