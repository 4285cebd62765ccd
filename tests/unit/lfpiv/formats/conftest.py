"""A known flow for the writers: solid-body rotation about z, whose vorticity is 2 Omega everywhere."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.formats.fields import Fields, fields_of

#: Rotation rate of pair p: OMEGA * (1 + p / 4), 1/s.
OMEGA = 40.0
START = "2026-01-02T03:04:05+00:00"
RATE_HZ = 10.0


def omega(pair: int) -> float:
    return OMEGA * (1 + pair / 4)


def rotation_vectors(pairs: int = 3, nx: int = 6, ny: int = 5, nz: int = 4) -> dict:
    """``RunStore.vectors()`` of a flow rotating about z, with an axial drift, on a grid in mm."""
    x = -5.0 + 2.0 * np.arange(nx)
    y = -4.0 + 2.0 * np.arange(ny)
    z = -3.0 + 1.5 * np.arange(nz)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    u = np.stack([-omega(p) * yy * 1e-3 for p in range(pairs)])  # m/s: positions in mm -> m
    v = np.stack([omega(p) * xx * 1e-3 for p in range(pairs)])
    w = np.stack([np.full(xx.shape, 0.1 + 0.01 * p) for p in range(pairs)])
    flags = np.zeros(u.shape, np.uint8)
    flags[0, 1, 2, 3] = FLAG_OUTLIER
    flags[2, 2, 3, 4] = FLAG_OUTLIER | FLAG_REPLACED
    peak = 1.5 + 0.01 * np.arange(u.size, dtype=np.float32).reshape(u.shape)
    return {"u": u, "v": v, "w": w, "flags": flags, "peak_ratio": peak, "x_mm": x, "y_mm": y, "z_mm": z,
            "attrs": {"dt_s": 1e-4, "windows": [[16, 16, 8]], "overlap": [0.5, 0.5, 0.5]}}


def assert_grid_in_metres(img, fields: Fields) -> None:
    """A vtkImageData that VTK read is the fields' grid: its dimensions, origin and spacing in metres."""
    x, y, z = fields.coords_m()
    assert img.IsA("vtkImageData")
    assert img.GetDimensions() == (len(x), len(y), len(z))
    assert img.GetOrigin() == pytest.approx((x[0], y[0], z[0]))
    assert img.GetSpacing() == pytest.approx((x[1] - x[0], y[1] - y[0], z[1] - z[0]))


def paraview_gradient(algorithm, vectors: str = "velocity"):
    """The point data after ParaView's Gradient filter (vorticity on) of the array ``vectors`` of a VTK pipeline."""
    import vtk

    grad = vtk.vtkGradientFilter()
    grad.SetInputConnection(algorithm.GetOutputPort())
    grad.SetInputArrayToProcess(0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, vectors)
    grad.SetComputeVorticity(True)
    grad.Update()
    return grad.GetOutput().GetPointData()


@pytest.fixture
def rotation() -> Fields:
    """Pairs 0 and 2 of the rotation (pair 1 left out, as an uncorrelated pair is)."""
    return fields_of(rotation_vectors(), [0, 2], RATE_HZ, start=START)
