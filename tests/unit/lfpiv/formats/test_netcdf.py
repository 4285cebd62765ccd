"""netCDF-4 export, opened by VTK's vtkNetCDFCFReader (ParaView's reader) and by xarray, on a known flow."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.formats import FormatError
from lfpiv.formats.netcdf import time_units, write_netcdf

from .conftest import assert_grid_in_metres, omega, paraview_gradient

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def cf_reader(path):
    """The file as ParaView opens it (its defaults: spherical coordinates on)."""
    r = vtk.vtkNetCDFCFReader()
    r.SetFileName(str(path))
    r.UpdateInformation()
    for k in range(r.GetNumberOfVariableArrays()):
        r.SetVariableArrayStatus(r.GetVariableArrayName(k), 1)
    return r


def test_vtk_reads_an_image_with_si_spacing_times_and_values(rotation, tmp_path):
    path = write_netcdf(tmp_path / "vectors.nc", rotation, source="run.zarr")
    r = cf_reader(path)
    assert r.GetSphericalCoordinates() == 1
    times = r.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    assert times == pytest.approx(rotation.time_s)
    r.UpdateTimeStep(times[1])
    img = r.GetOutput()
    assert_grid_in_metres(img, rotation)
    pd = img.GetPointData()
    nz, ny, nx = rotation.shape
    for c, name in enumerate("uvw"):
        got = vtk_to_numpy(pd.GetArray(name)).reshape(nz, ny, nx)
        assert np.allclose(got, rotation.velocity[1][..., c], rtol=1e-6, atol=1e-7)
    assert np.array_equal(vtk_to_numpy(pd.GetArray("flags")).reshape(nz, ny, nx), rotation.flags[1])


def test_paraviews_gradient_of_the_exported_velocity_is_the_exported_vorticity(rotation, tmp_path):
    r = cf_reader(write_netcdf(tmp_path / "vectors.nc", rotation))
    r.UpdateTimeStep(rotation.time_s[1])
    calc = vtk.vtkArrayCalculator()  # ParaView's Calculator: u, v, w into one vector
    calc.SetInputConnection(r.GetOutputPort())
    calc.SetAttributeTypeToPointData()
    for name in "uvw":
        calc.AddScalarArrayName(name)
    calc.SetFunction("u*iHat + v*jHat + w*kHat")
    calc.SetResultArrayName("velocity")
    pd = paraview_gradient(calc)
    vort = vtk_to_numpy(pd.GetArray("Vorticity"))
    assert np.allclose(vort[:, 2], 2 * omega(2), rtol=1e-5)  # solid-body rotation: 2 Omega everywhere
    assert np.allclose(vort[:, 2], vtk_to_numpy(pd.GetArray("vorticity_z")), rtol=1e-5)
    assert np.allclose(vort[:, :2], 0, atol=1e-5)


def test_xarray_reads_cf_coordinates_units_and_flags(rotation, tmp_path):
    xr = pytest.importorskip("xarray")
    path = write_netcdf(tmp_path / "vectors.nc", rotation, source="run.zarr")
    with xr.open_dataset(path) as ds:
        assert ds["u"].dims == ("time", "z", "y", "x")
        assert ds.attrs["Conventions"] == "CF-1.8" and "run.zarr" in ds.attrs["source"]
        x, y, z = rotation.coords_m()
        assert np.allclose(ds["x"], x) and np.allclose(ds["y"], y) and np.allclose(ds["z"], z)
        assert ds["x"].attrs["units"] == "m" and "axis" not in ds["x"].attrs
        assert ds["u"].attrs["units"] == "m s-1" and ds["vorticity_z"].attrs["units"] == "s-1"
        assert all("long_name" in ds[v].attrs for v in ds.variables)
        # CF time: seconds since the run's start, decoded by xarray to dates
        assert ds["time"].values[1] - np.datetime64("2026-01-02T03:04:05") == np.timedelta64(200, "ms")
        assert ds["pair"].values.tolist() == [0, 2]
        assert np.allclose(ds["vorticity_z"].sel(time=ds["time"][0]), 2 * omega(0))
        assert np.allclose(ds["w"].values, rotation.velocity[..., 2])
        assert ds["flags"].dtype == np.uint8 and ds["flags"].attrs["flag_meanings"] == "outlier replaced"
        assert ds["flags"].attrs["flag_masks"].tolist() == [FLAG_OUTLIER, FLAG_REPLACED]
        assert ds["u"].encoding["zlib"] and ds["u"].encoding["chunksizes"] == (1, *rotation.shape)
    with xr.open_dataset(path, decode_times=False) as ds:
        assert ds["time"].attrs["units"] == "seconds since 2026-01-02 03:04:05"
        assert np.allclose(ds["time"], [0.0, 0.2])


def test_an_earlier_file_stays_whole_until_the_new_one_is_written(rotation, tmp_path, monkeypatch):
    import netCDF4

    path = tmp_path / "vectors.nc"
    path.write_bytes(b"earlier export")

    def fail(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(netCDF4.Dataset, "createVariable", fail)
    with pytest.raises(OSError, match="disk full"):
        write_netcdf(path, rotation)
    assert path.read_bytes() == b"earlier export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vectors.nc"]


def test_time_units():
    assert time_units("2026-01-02T04:04:05+01:00") == "seconds since 2026-01-02 03:04:05"
    assert time_units(None) == "s"
    with pytest.raises(FormatError, match="ISO 8601"):
        time_units("yesterday")
