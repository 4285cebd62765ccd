"""VTK ImageData series export, read back by VTK's own vtkXMLImageDataReader, on a known flow."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from lfpiv.formats import FormatError
from lfpiv.formats.fields import fields_of
from lfpiv.formats.vti import write_vti_series

from .conftest import RATE_HZ, assert_grid_in_metres, omega, paraview_gradient, rotation_vectors

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def read_vti(path):
    r = vtk.vtkXMLImageDataReader()
    r.SetFileName(str(path))
    r.Update()
    assert r.GetErrorCode() == 0
    return r


def test_series_in_si_units_read_back_by_vtk(rotation, tmp_path):
    files = write_vti_series(tmp_path, rotation)
    assert [f.name for f in files] == ["vectors_pair0000.vti", "vectors_pair0002.vti", "vectors.pvd"]
    steps = ET.parse(tmp_path / "vectors.pvd").getroot().findall("./Collection/DataSet")
    assert [(float(d.get("timestep")), d.get("file")) for d in steps] == [
        (0.0, "vectors_pair0000.vti"), (pytest.approx(2 / RATE_HZ), "vectors_pair0002.vti")]
    reader = read_vti(files[1])
    img = reader.GetOutput()
    assert_grid_in_metres(img, rotation)
    pd = img.GetPointData()
    nz, ny, nx = rotation.shape
    vel = vtk_to_numpy(pd.GetArray("velocity")).reshape(nz, ny, nx, 3)
    assert np.allclose(vel, rotation.velocity[1], rtol=1e-6, atol=1e-7)
    assert np.array_equal(vtk_to_numpy(pd.GetArray("flags")).reshape(nz, ny, nx), rotation.flags[1])
    assert vtk_to_numpy(img.GetFieldData().GetArray("TimeValue"))[0] == pytest.approx(0.2)
    assert pd.GetVectors().GetName() == "velocity"


def test_paraviews_gradient_of_the_velocity_is_the_exported_vorticity(rotation, tmp_path):
    """The 1000x mismatch of the old mm export is gone: ParaView's Gradient filter (vorticity on) gives 2 Omega."""
    files = write_vti_series(tmp_path, rotation)
    for i, pair in enumerate(rotation.pairs):
        reader = read_vti(files[i])  # kept: the filter's input
        pd = paraview_gradient(reader)
        theirs, ours = vtk_to_numpy(pd.GetArray("Vorticity")), vtk_to_numpy(pd.GetArray("vorticity"))
        assert np.allclose(theirs[:, 2], 2 * omega(pair), rtol=1e-5)
        assert np.allclose(theirs, ours, rtol=1e-5, atol=1e-4)


def test_an_earlier_series_is_replaced_whole_and_other_files_kept(rotation, tmp_path):
    (tmp_path / "vectors_pair0007.vti").write_text("from an earlier export")
    (tmp_path / "notes.txt").write_text("keep")
    write_vti_series(tmp_path, rotation)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "notes.txt", "vectors.pvd", "vectors_pair0000.vti", "vectors_pair0002.vti"]


def test_an_uneven_grid_is_refused_with_the_way_out(tmp_path):
    v = rotation_vectors()
    v["x_mm"] = v["x_mm"] ** 3 / 25.0
    with pytest.raises(FormatError, match="not evenly spaced.*export netcdf"):
        write_vti_series(tmp_path, fields_of(v, [0], RATE_HZ))
    assert list(tmp_path.iterdir()) == []
