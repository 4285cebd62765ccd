"""Outlier test and replacement, units, derived quantities, the run store's vectors/, truth flows."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.flows import FLOW_NAMES, flow_from_params, standard_flow
from lfcore.rig import VolumeConfig
from lfcore.runstore import RunStore, RunStoreError
from lfcore.vectors import (
    FLAG_OUTLIER,
    FLAG_REPLACED,
    MedianTest,
    centres_mm,
    displacement_to_velocity,
    divergence,
    flags_from_masks,
    median_filter,
    normalized_median_test,
    q_criterion,
    replace_outliers,
    smooth,
    velocity_gradient,
    vorticity,
)

X = np.arange(10) * 0.5  # mm
Y = np.arange(9) * 0.5
Z = np.arange(6) * 1.0


def linear_field(noise=0.0):
    """(z, y, x, 3) field with gradients along every axis, plus optional noise (voxels)."""
    z, y, x = np.meshgrid(np.arange(6), np.arange(9), np.arange(10), indexing="ij")
    f = np.stack([0.1 * y + 0.02 * x, -0.05 * x + 0.03 * z, 0.2 + 0.04 * y], axis=-1)
    return f + noise * np.random.default_rng(0).standard_normal(f.shape)


def test_planted_outliers_are_found_and_replaced():
    f = linear_field(noise=0.02)
    truth = f.copy()
    planted = np.zeros(f.shape[:3], bool)
    for idx in [(2, 4, 5), (0, 0, 0), (5, 8, 9), (3, 0, 4), (1, 7, 2)]:  # interior, corners, faces
        planted[idx] = True
    f[planted] += np.array([1.5, -2.0, 0.8])
    f[2, 2, 2] = np.nan  # a window without signal
    planted[2, 2, 2] = True
    out = normalized_median_test(f)
    assert np.array_equal(out, planted)
    g, replaced = replace_outliers(f, out)
    assert np.array_equal(replaced, planted)
    assert np.abs(g[planted] - truth[planted]).max() < 0.35  # a neighbour median, one-sided at the edges
    assert np.array_equal(g[~planted], f[~planted])


def test_median_test_settings():
    f = linear_field(noise=0.05)
    f[3, 4, 5, 0] += 0.6
    assert normalized_median_test(f, test=MedianTest(epsilon=0.1, threshold=2.0))[3, 4, 5]
    assert not normalized_median_test(f, test=MedianTest(epsilon=0.1, threshold=10.0))[3, 4, 5]
    assert not normalized_median_test(f, test=MedianTest(epsilon=1.0, threshold=2.0))[3, 4, 5]
    with pytest.raises(ValueError, match="threshold"):
        MedianTest(threshold=0)
    with pytest.raises(ValueError, match="epsilon"):
        MedianTest(epsilon=-1)


def test_smooth_fields_have_no_outliers_even_at_the_edges():
    assert not normalized_median_test(linear_field()).any()


def test_clusters_of_outliers_are_filled_from_outside():
    f = linear_field()
    bad = np.zeros(f.shape[:3], bool)
    bad[1:4, 2:6, 2:6] = True
    g, replaced = replace_outliers(np.where(bad[..., None], np.nan, f), bad)
    assert replaced.sum() == bad.sum() and np.all(np.isfinite(g))
    assert np.abs(g - f).max() < 0.5


def test_median_filter_removes_a_spike_and_keeps_a_linear_field():
    f = linear_field()
    spiked = f.copy()
    spiked[3, 4, 5] += 5.0
    m = median_filter(spiked)
    assert np.allclose(m[1:-1, 1:-1, 1:-1], f[1:-1, 1:-1, 1:-1])


def test_smoothing_keeps_linear_fields():
    f = linear_field()
    assert np.allclose(smooth(f, sigma=1.0), f, atol=1e-12)


def test_flags():
    o = np.array([True, True, False])
    r = np.array([True, False, False])
    assert flags_from_masks(o, r).tolist() == [FLAG_OUTLIER | FLAG_REPLACED, FLAG_OUTLIER, 0]


def test_units():
    v = displacement_to_velocity(np.array([[2.0, -1.0, 0.5]]), (0.011, 0.011, 0.055), 2e-3)
    assert np.allclose(v, [[0.011, -0.0055, 0.01375]])  # voxels * mm * 1e-3 / s = m/s
    x, y, z = centres_mm((np.array([7.5, 11.5]), np.array([0.0]), np.array([3.5])), (-1.0, 0.0, 2.0),
                         (0.01, 0.02, 0.1))
    assert np.allclose(x, [-0.925, -0.885]) and np.allclose(y, [0.0]) and np.allclose(z, [2.35])
    with pytest.raises(ValueError, match="dt"):
        displacement_to_velocity(np.zeros((1, 3)), (1, 1, 1), 0.0)


def _grid_points():
    z, y, x = np.meshgrid(Z, Y, X, indexing="ij")
    return x, y, z


def test_derivatives_of_analytic_fields():
    x, y, z = _grid_points()
    om = 3.0  # 1/s
    # solid-body rotation about z (mm -> m): divergence-free, vorticity 2 om, Q = om^2
    rot = np.stack([-om * y * 1e-3, om * x * 1e-3, np.zeros_like(x)], axis=-1)
    assert np.allclose(divergence(rot, X, Y, Z), 0.0, atol=1e-12)
    assert np.allclose(vorticity(rot, X, Y, Z), [0.0, 0.0, 2 * om])
    assert np.allclose(q_criterion(rot, X, Y, Z), om**2)
    # pure strain: divergence 1 + 2 - 3 = 0, Q < 0
    strain = np.stack([1.0 * x, 2.0 * y, -3.0 * z], axis=-1) * 1e-3
    assert np.allclose(divergence(strain, X, Y, Z), 0.0, atol=1e-12)
    assert np.all(q_criterion(strain, X, Y, Z) < 0)
    # a compressing field: du/dx = 5 1/s everywhere, second order at the edges too
    comp = np.stack([5.0 * x * 1e-3 + 0.1 * (x * 1e-3) ** 2 * 0, np.zeros_like(x), np.zeros_like(x)], axis=-1)
    assert np.allclose(divergence(comp, X, Y, Z), 5.0)
    g = velocity_gradient(comp, X, Y, Z)
    assert g.shape == (*x.shape, 3, 3) and np.allclose(g[..., 0, 0], 5.0)
    with pytest.raises(ValueError, match="coordinates of axis x"):
        divergence(comp, X[:-1], Y, Z)


def test_divergence_free_flow_sampled_on_a_grid_is_nearly_divergence_free():
    vol = VolumeConfig(centre_mm=(0.0, 0.0, 0.0), size_mm=(10.0, 10.0, 10.0), pvr=(2.0, 2.0, 10.0))
    ring = standard_flow("vortex-ring", vol)
    xs = ys = zs = np.linspace(-4, 4, 33)
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    v = ring.velocity(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)).reshape((*x.shape, 3))
    div = divergence(v, xs, ys, zs)[2:-2, 2:-2, 2:-2]
    vort = np.linalg.norm(vorticity(v, xs, ys, zs), axis=-1)[2:-2, 2:-2, 2:-2]
    # central differences of a divergence-free field: small, but not zero, where the core is steep
    assert np.sqrt(np.mean(div**2)) < 0.02 * np.sqrt(np.mean(vort**2)) and np.abs(div).max() < 0.02 * vort.max()


@pytest.mark.parametrize("name", FLOW_NAMES)
def test_truth_flows_rebuild_from_their_params(name):
    vol = VolumeConfig(centre_mm=(0.1, 0.0, -0.2), size_mm=(1.0, 0.8, 1.6), pvr=(2.0, 2.0, 10.0))
    f = standard_flow(name, vol, omega=0.5)
    assert flow_from_params(f.params()) == f


def test_unknown_truth_flow():
    with pytest.raises(ValueError, match="unknown flow 'tornado'"):
        flow_from_params({"name": "tornado"})
    with pytest.raises(ValueError, match="do not fit"):
        flow_from_params({"name": "uniform", "speed": 1.0})


def test_run_store_vectors_round_trip(tmp_path, tiny_rig):
    s = RunStore.create(tmp_path / "r.zarr", tiny_rig, 3, timing={"dt_s": 1e-3, "rate_hz": 10.0},
                        software_version="test")
    with pytest.raises(RunStoreError, match="no vectors; run 'lfpiv correlate"):
        s.vectors()
    x, y, z = np.linspace(0, 1, 5), np.linspace(0, 2, 4), np.linspace(-1, 1, 3)
    s.create_vectors(x, y, z, dt_s=1e-3, windows=[[32, 32, 16], [16, 16, 8]], overlap=[0.75, 0.75, 0.5],
                     settings={"deform_iterations": 2})
    vel = np.random.default_rng(1).standard_normal((3, 4, 5, 3))
    flags = np.zeros((3, 4, 5), np.uint8)
    flags[0, 1, 2] = 3
    s.write_vectors(1, vel, flags, np.full((3, 4, 5), 4.0))
    with pytest.raises(RunStoreError, match="vectors of this run are"):
        s.write_vectors(0, vel[:2], flags, flags)
    r = RunStore.open(tmp_path / "r.zarr")
    v = r.vectors()
    assert r.correlated_pairs() == [1] and r.has_vectors
    assert v["u"].shape == (3, 3, 4, 5) and np.isnan(v["u"][0]).all()
    assert np.allclose(np.stack([v[c][1] for c in "uvw"], -1), vel, atol=1e-6)
    assert v["flags"][1, 0, 1, 2] == 3 and np.array_equal(v["x_mm"], x)
    a = v["attrs"]
    assert a["dt_s"] == 1e-3 and a["windows"] == [[32, 32, 16], [16, 16, 8]] and a["overlap"] == [0.75, 0.75, 0.5]
    g = r.group["vectors"]
    for name in ("u", "v", "w", "flags", "peak_ratio", "x_mm", "y_mm", "z_mm"):
        assert {"units", "axes"} <= set(g[name].attrs), name
    assert g["u"].attrs["units"] == "m/s" and g["u"].attrs["axes"] == ["pair", "z", "y", "x"]
    assert g["flags"].attrs["flag_meanings"] == "outlier replaced"


def test_vectors_written_through_arrays_opened_once(tmp_path, tiny_rig):
    # a worker writes through arrays opened once while the coordinator records pairs
    s = RunStore.create(tmp_path / "r.zarr", tiny_rig, 3, timing={"dt_s": 1e-3, "rate_hz": 10.0},
                        software_version="test")
    with pytest.raises(RunStoreError, match="no vectors/ group; create it first"):
        s.vector_arrays()
    s.create_vectors(np.arange(5.0), np.arange(4.0), np.arange(3.0), dt_s=1e-3, windows=[[8, 8, 8]],
                     overlap=[0.5, 0.5, 0.5], settings={})
    worker = RunStore.open(tmp_path / "r.zarr", mode="r+")
    arrays = worker.vector_arrays()
    vel = np.full((3, 4, 5, 3), 2.5)
    for p in (0, 2):
        worker.write_vectors(p, vel * (p + 1), np.zeros((3, 4, 5)), np.ones((3, 4, 5)), record=False, arrays=arrays)
        s.record_vectors([p])
    r = RunStore.open(tmp_path / "r.zarr").vectors()
    assert r["attrs"]["correlated_pairs"] == [0, 2] and np.isnan(r["u"][1]).all()
    assert np.allclose(r["w"][2], 7.5) and np.allclose(r["peak_ratio"][0], 1.0)


def test_outlier_kernels_agree_on_every_device(device):
    f = linear_field(noise=0.05)
    f[2, 4, 5] += 3.0
    f[0, 0, 1] = np.nan
    out = normalized_median_test(f, device=device)
    assert np.array_equal(out, normalized_median_test(f, device="cpu"))
    g, r = replace_outliers(f, out, device=device)
    g_cpu, r_cpu = replace_outliers(f, out, device="cpu")
    assert np.array_equal(r, r_cpu) and np.allclose(g, g_cpu, atol=1e-6)
