"""What the monitor shows of a processed pair (:func:`realtime.view.derive`), from a known volume and
a known vector field: no pipeline, no threads."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.ring import PairView
from lfcore.correlate import VectorField, WindowGrid
from lfcore.device import warp
from lfcore.device_ops import VolumeOps
from lfcore.volume import VolumeGrid
from realtime.processing import ProcessedPair
from realtime.settings import LiveSettings
from realtime.view import derive

GRID = VolumeGrid(shape=(12, 10, 16), voxel_mm=(0.5, 0.5, 1.0), origin_mm=(-3.75, -2.25, -5.5))
DT_S = 1e-3
OMEGA = 40.0  # 1/s: solid-body rotation about z, vorticity 2 * OMEGA along z


def _volume() -> np.ndarray:
    """A (z, y, x) volume whose every voxel is distinct, so that projections and planes are checkable."""
    rng = np.random.default_rng(7)
    return rng.random(GRID.shape, dtype=np.float32)


def _rotation() -> VectorField:
    """Window centres every 4 voxels and the displacement of u = -OMEGA y, v = OMEGA x, w = 0."""
    xs, ys, zs = np.arange(2.0, 16, 4), np.arange(1.0, 10, 3), np.array([1.0, 5.0, 9.0])
    x_mm = GRID.origin_mm[0] + GRID.voxel_mm[0] * xs
    y_mm = GRID.origin_mm[1] + GRID.voxel_mm[1] * ys
    yy, xx = np.meshgrid(y_mm, x_mm, indexing="ij")
    vel = np.zeros((len(zs), len(ys), len(xs), 3))
    vel[..., 0] = -OMEGA * yy * 1e-3  # m/s
    vel[..., 1] = OMEGA * xx * 1e-3
    disp = vel * DT_S / (np.asarray(GRID.voxel_mm) * 1e-3)  # voxels
    shape = disp.shape[:3]
    outlier = np.zeros(shape, bool)
    outlier[0, 0, :2] = True
    return VectorField(x=xs, y=ys, z=zs, displacement=disp, peak_ratio=np.full(shape, 2.0),
                       peak_height=np.ones(shape), outlier=outlier, replaced=outlier.copy(),
                       grid=WindowGrid(window=(4, 4, 4), step=(4, 3, 4), first=(0, 0, 0), counts=(4, 3, 3)))


def _pair(vol: np.ndarray) -> ProcessedPair:
    ops = VolumeOps(GRID.shape, device="cpu")
    dev = warp().array(vol, dtype=float, device="cpu")
    view = PairView(pair=3, frames={}, frame_id={}, timestamp_ns={}, slot=0, generation=0)
    return ProcessedPair(view=view, raw={}, volume=dev, ops=ops, field=_rotation(), grid=GRID, dt_s=DT_S,
                         active_fraction=0.5, projector="stored", timings={})


def test_projections_slice_and_extents_of_a_known_volume() -> None:
    vol = _volume()
    d = derive(_pair(vol), LiveSettings(slice_axis="y", slice_index=4))
    nz, ny, nx = GRID.shape
    assert np.array_equal(d.mip["z"], vol.max(axis=0)) and d.mip["z"].shape == (ny, nx)
    assert np.array_equal(d.mip["y"], vol.max(axis=1)) and d.mip["y"].shape == (nz, nx)
    assert np.array_equal(d.mip["x"], vol.max(axis=2)) and d.mip["x"].shape == (nz, ny)
    assert d.slice_axis == "y" and d.slice_index == 4 and np.array_equal(d.slice_image, vol[:, 4, :])
    for a in "xyz":
        assert d.extent_mm[a] == (float(GRID.axis_mm(a)[0]), float(GRID.axis_mm(a)[-1]))
    assert d.extent_mm["x"] == (-3.75, -3.75 + 0.5 * (nx - 1))


@pytest.mark.parametrize(("axis", "index", "expected"), [("z", None, 6), ("x", 1000, 15), ("x", -3, 0),
                                                         ("y", 2, 2)])
def test_the_slice_index_is_the_middle_or_clipped(axis: str, index: int | None, expected: int) -> None:
    vol = _volume()
    d = derive(_pair(vol), LiveSettings(slice_axis=axis, slice_index=index))
    assert d.slice_index == expected
    assert np.array_equal(d.slice_image, np.take(vol, expected, axis="zyx".index(axis)))


def test_velocity_vorticity_and_the_vector_plane_nearest_the_slice() -> None:
    d = derive(_pair(_volume()), LiveSettings(slice_axis="z", slice_index=7))
    vf = _rotation()
    x_mm, y_mm, z_mm = d.grid_mm
    assert np.allclose(x_mm, GRID.origin_mm[0] + GRID.voxel_mm[0] * vf.x)
    assert np.allclose(z_mm, GRID.origin_mm[2] + GRID.voxel_mm[2] * vf.z)
    yy, xx = np.meshgrid(y_mm, x_mm, indexing="ij")
    assert np.allclose(d.velocity[..., 0], -OMEGA * yy * 1e-3) and np.allclose(d.velocity[..., 1], OMEGA * xx * 1e-3)
    assert np.allclose(d.vorticity[..., 2], 2 * OMEGA) and np.allclose(d.vorticity[..., :2], 0.0, atol=1e-9)
    vs = d.vectors
    # vector planes at z = 1, 5, 9 voxels: 5 is nearest slice 7
    assert vs.axis == "z" and vs.index == 1 and vs.position_mm == pytest.approx(float(z_mm[1]))
    assert np.array_equal(vs.h_mm, x_mm) and np.array_equal(vs.v_mm, y_mm)
    assert vs.uv.shape == (len(y_mm), len(x_mm), 2)
    assert np.allclose(vs.uv[..., 0], d.velocity[1, ..., 0]) and np.allclose(vs.uv[..., 1], d.velocity[1, ..., 1])
    assert np.allclose(vs.normal_vorticity, 2 * OMEGA)
    assert d.outlier_fraction == pytest.approx(2 / vf.outlier.size)


def test_a_plane_across_the_flow_shows_its_own_components() -> None:
    # normal x: the plane's axes are y (horizontal) and z (vertical), the vorticity is w_x (zero here)
    d = derive(_pair(_volume()), LiveSettings(slice_axis="x", slice_index=9))
    vs = d.vectors
    assert vs.axis == "x" and vs.index == 2  # centres 2, 6, 10, 14: 10 is nearest 9
    assert np.array_equal(vs.h_mm, d.grid_mm[1]) and np.array_equal(vs.v_mm, d.grid_mm[2])
    assert np.allclose(vs.uv[..., 0], d.velocity[:, :, 2, 1]) and np.allclose(vs.uv[..., 1], 0.0)
    assert np.allclose(vs.normal_vorticity, 0.0, atol=1e-9)


def test_derive_is_pure() -> None:
    vol = _volume()
    pair = _pair(vol)
    s = LiveSettings(slice_axis="z", slice_index=3)
    a, b = derive(pair, s), derive(pair, s)
    assert np.array_equal(pair.volume.numpy(), vol)  # the volume is read, not changed
    for name in ("slice_image", "velocity", "vorticity"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert all(np.array_equal(a.mip[k], b.mip[k]) for k in "xyz")
