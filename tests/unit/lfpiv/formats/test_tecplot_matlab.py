"""Tecplot ASCII export read back by VTK's vtkTecplotReader (ParaView's), MATLAB export by scipy.io.loadmat.

meshio's Tecplot reader reads only finite-element zones, not the ordered (I, J, K) zones that
PIV vector fields are written as, so VTK's reader is the one used here.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.io import loadmat

from lfcore.vectors import FLAG_OUTLIER
from lfpiv.formats import FormatError
from lfpiv.formats.fields import fields_of
from lfpiv.formats.matlab import to_meshgrid, write_mat
from lfpiv.formats.tecplot import write_tecplot

from .conftest import RATE_HZ, omega, rotation_vectors


def test_tecplot_zones_read_back_by_vtk(rotation, tmp_path):
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    path = write_tecplot(tmp_path / "vectors.dat", rotation)
    text = path.read_text()
    assert "SOLUTIONTIME=0.2, STRANDID=1" in text and "ZONETYPE=ORDERED, DATAPACKING=POINT" in text
    assert "u: m/s" in text
    vtk.vtkObject.GlobalWarningDisplayOff()  # VTK's reader warns that it ignores SOLUTIONTIME and STRANDID
    try:
        r = vtk.vtkTecplotReader()
        r.SetFileName(str(path))
        r.Update()
    finally:
        vtk.vtkObject.GlobalWarningDisplayOn()
    out = r.GetOutput()
    assert out.GetNumberOfBlocks() == 2
    assert [out.GetMetaData(i).Get(vtk.vtkCompositeDataSet.NAME()) for i in range(2)] == ["pair 0", "pair 2"]
    x, y, z = rotation.coords_m()
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    for i, pair in enumerate(rotation.pairs):
        grid = out.GetBlock(i)
        assert grid.IsA("vtkStructuredGrid")
        pts = vtk_to_numpy(grid.GetPoints().GetData())
        assert np.allclose(pts, np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]))  # metres, x fastest
        pd = grid.GetPointData()
        for c, name in enumerate("uvw"):
            assert np.allclose(vtk_to_numpy(pd.GetArray(name)), rotation.velocity[i][..., c].ravel(), rtol=1e-6)
        assert np.allclose(vtk_to_numpy(pd.GetArray("vorticity_z")), 2 * omega(pair), rtol=1e-6)
        assert np.array_equal(vtk_to_numpy(pd.GetArray("flags")), rotation.flags[i].ravel())


def test_tecplot_writes_a_missing_vector_as_zero_with_its_outlier_flag(tmp_path):
    v = rotation_vectors()
    v["u"][0, 1, 1, 1] = np.nan
    v["flags"][0, 1, 1, 1] = FLAG_OUTLIER
    text = write_tecplot(tmp_path / "v.dat", fields_of(v, [0], RATE_HZ)).read_text()
    assert "nan" not in text.lower()


def test_matlab_file_in_meshgrid_order(rotation, tmp_path):
    m = loadmat(write_mat(tmp_path / "vectors.mat", rotation))
    nz, ny, nx = rotation.shape
    x, y, z = rotation.coords_m()
    for name in ("x", "y", "z"):
        assert m[name].shape == (ny, nx, nz)
    # what MATLAB's [X, Y, Z] = meshgrid(x, y, z) gives: X(i, j, k) = x(j), Y(i, j, k) = y(i), Z(i, j, k) = z(k)
    assert np.allclose(m["x"], x[None, :, None] + 0 * m["x"])
    assert np.allclose(m["y"], y[:, None, None] + 0 * m["y"])
    assert np.allclose(m["z"], z[None, None, :] + 0 * m["z"])
    for name in ("u", "v", "w", "vorticity_z", "flags", "peak_ratio"):
        assert m[name].shape == (ny, nx, nz, 2)
    # u(i, j, k, p) is the velocity at (x(j), y(i), z(k)) of pair p: -Omega y for the rotation
    for p, pair in enumerate(rotation.pairs):
        assert np.allclose(m["u"][..., p], -omega(pair) * m["y"])
        assert np.allclose(m["v"][..., p], omega(pair) * m["x"])
        assert np.allclose(m["vorticity_z"][..., p], 2 * omega(pair))
    # flags[pair 0, z 1, y 2, x 3] is at (y, x, z, pair) in the file
    assert m["flags"].dtype == np.uint8 and m["flags"][2, 3, 1, 0] == FLAG_OUTLIER
    assert np.allclose(m["t"], [[0.0, 0.2]]) and m["pair"].tolist() == [[0, 2]]
    units = m["units"][0, 0]
    assert units["u"][0] == "m/s" and units["x"][0] == "m" and units["q_criterion"][0] == "1/s^2"
    assert m["info"][0, 0]["start"][0] == rotation.start


def test_to_meshgrid_refuses_other_shapes():
    with pytest.raises(FormatError, match=r"\(pairs, z, y, x\)"):
        to_meshgrid(np.zeros((2, 3)))
