"""Particle tracks as VTK PolyData (read back by VTK's vtkXMLPolyDataReader) and CSV, on known tracks."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from lfpiv.formats.tracks import CSV_HEADER, write_tracks_csv, write_tracks_vtp_series

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def known_tracks() -> np.ndarray:
    """(m, 11) rows: pairs 0 and 2, tracks of a rotation about z over dt = 1 ms (positions mm, m/s)."""
    rng = np.random.default_rng(0)
    rows = []
    for pair, n in ((0, 5), (2, 3)):
        a = rng.uniform(-1, 1, (n, 3))
        b = a + np.column_stack([-a[:, 1], a[:, 0], np.zeros(n)]) * 0.01
        vel = (b - a) * 1e-3 / 1e-3
        rows.append(np.column_stack([np.full(n, pair), a, b, vel, (np.arange(n) == 1).astype(float)]))
    return np.concatenate(rows)


def test_tracks_read_back_by_vtk_as_lines_in_metres(tmp_path):
    rows = known_tracks()
    files = write_tracks_vtp_series(tmp_path, rows, rate_hz=10.0)
    assert [f.name for f in files] == ["tracks_pair0000.vtp", "tracks_pair0002.vtp", "tracks.pvd"]
    steps = ET.parse(tmp_path / "tracks.pvd").getroot().findall("./Collection/DataSet")
    assert [(float(d.get("timestep")), d.get("file")) for d in steps] == [
        (0.0, "tracks_pair0000.vtp"), (pytest.approx(0.2), "tracks_pair0002.vtp")]
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(files[0]))
    r.Update()
    assert r.GetErrorCode() == 0
    poly = r.GetOutput()
    mine = rows[rows[:, 0] == 0]
    assert poly.GetNumberOfPoints() == 2 * len(mine) and poly.GetNumberOfLines() == len(mine)
    pts = vtk_to_numpy(poly.GetPoints().GetData())
    assert np.allclose(pts[0::2], mine[:, 1:4] * 1e-3, atol=1e-12) and np.allclose(pts[1::2], mine[:, 4:7] * 1e-3,
                                                                                    atol=1e-12)
    # each line joins its track's two ends
    for k in range(len(mine)):
        ids = poly.GetCell(k).GetPointIds()
        assert (ids.GetNumberOfIds(), ids.GetId(0), ids.GetId(1)) == (2, 2 * k, 2 * k + 1)
    vel = vtk_to_numpy(poly.GetPointData().GetArray("velocity"))
    assert np.allclose(vel[0::2], mine[:, 7:10], rtol=1e-6) and np.allclose(vel[1::2], mine[:, 7:10], rtol=1e-6)
    assert vtk_to_numpy(poly.GetCellData().GetArray("outlier")).tolist() == [0, 1, 0, 0, 0]
    assert poly.GetFieldData().GetArray("TimeValue").GetValue(0) == 0.0
    # a later export of fewer pairs replaces the series whole
    write_tracks_vtp_series(tmp_path, rows[rows[:, 0] == 2], rate_hz=10.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tracks.pvd", "tracks_pair0002.vtp"]


def test_a_pair_without_tracks_is_a_file_without_lines(tmp_path):
    files = write_tracks_vtp_series(tmp_path, np.zeros((0, 11)), rate_hz=None, pairs=[3])
    assert [f.name for f in files] == ["tracks_pair0003.vtp", "tracks.pvd"]
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(files[0]))
    r.Update()
    assert r.GetErrorCode() == 0 and r.GetOutput().GetNumberOfPoints() == 0


def test_csv_reads_back(tmp_path):
    rows = known_tracks()
    path = write_tracks_csv(tmp_path / "t.csv", rows)
    assert path.read_text().splitlines()[0] == CSV_HEADER
    back = np.loadtxt(path, delimiter=",", skiprows=1)
    assert back.shape == rows.shape and np.allclose(back, rows, rtol=1e-5, atol=1e-6)
