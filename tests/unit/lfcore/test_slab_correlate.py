"""Correlation in depth slabs (lfcore.slab_correlate) against the in-memory correlation of the same
blob pairs with a known flow: the same vectors on the same grid."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.correlate import CorrelationConfig, CorrelationError, Correlator, WindowGrid, pass_grids
from lfcore.slab_correlate import (
    BSPLINE_ERROR_GAIN,
    BSPLINE_POLE,
    SlabCorrelator,
    correlator_bytes,
    plan_correlation_slabs,
    prefilter_planes,
)
from tests.blobs import blob_pair

SHAPE = (160, 32, 32)  # z, y, x: deep enough that 3 slabs and their halos each read less than the box
WINDOWS = ((16, 16, 16), (16, 16, 8))
CONFIGS = {
    "fft": CorrelationConfig(windows=WINDOWS, overlap=0.75),
    "direct": CorrelationConfig(windows=WINDOWS, overlap=0.75, search_radius=2),
    "linear-median": CorrelationConfig(windows=WINDOWS, overlap=0.75, interpolation="linear", median_filter=True),
}
#: Largest difference from the in-memory vectors, voxels: measured 5e-7 (FFT passes, cubic), 1.2e-6
#: (direct correlation) and 5.4e-7 (trilinear, median filter); float32 round-off of the sample
#: positions (x - d/2 in the slab's coordinates) and the prefilter's bounded 1e-6 difference.
TOLERANCE = 1e-5


def flow(p):
    """A linear flow with every gradient along z (voxels over dt), up to 1.5 voxel along z."""
    r = p - np.array([16.0, 16.0, 80.0])
    return np.stack([0.5 + 0.03 * r[:, 1], -0.3 + 0.02 * r[:, 2], 0.6 - 0.03 * r[:, 0]], axis=1)


@pytest.fixture(scope="module")
def pair():
    return blob_pair(SHAPE, flow, seed=4, density=0.03)


def reader(a, b, log):
    def read(lo, hi):
        log.append((lo, hi))
        return a[lo:hi], b[lo:hi]

    return read


def assert_same_field(got, ref):
    assert got.shape == ref.shape
    for axis in "xyz":
        assert np.array_equal(getattr(got, axis), getattr(ref, axis))
    assert got.grid == ref.grid
    assert np.array_equal(got.outlier, ref.outlier) and np.array_equal(got.replaced, ref.replaced)
    assert np.array_equal(np.isnan(got.displacement), np.isnan(ref.displacement))
    assert np.nanmax(np.abs(got.displacement - ref.displacement)) < TOLERANCE
    np.testing.assert_allclose(got.peak_ratio, ref.peak_ratio, rtol=1e-4)
    np.testing.assert_allclose(got.peak_height, ref.peak_height, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_three_slabs_give_the_in_memory_vectors(pair, name, device):
    a, b = pair
    cfg = CONFIGS[name]
    ref = Correlator(SHAPE, config=cfg, device=device)(a, b)
    truth = flow(np.stack(np.meshgrid(ref.x, ref.y, ref.z, indexing="ij"), -1).reshape(-1, 3))
    assert np.abs(ref.displacement.transpose(2, 1, 0, 3).reshape(-1, 3) - truth).max() < 0.3  # a real flow
    log = []
    sc = SlabCorrelator(SHAPE, cfg, 3, device=device)
    got = sc(reader(a, b, log))
    assert_same_field(got, ref)
    assert len(sc.slabs) == 3 and sc.retries == 0
    # the end slabs read less than the box (the middle one's halos, 44-63 planes a side here, may
    # reach the box's ends), with a halo wherever a slab was cut
    assert log[0][0] == 0 and log[0][1] < SHAPE[0] and log[-1][0] > 0 and log[-1][1] == SHAPE[0], log
    for s in sc.slabs:
        assert (s.z0 == 0 or s.halo[0] > 0) and (s.z1 == SHAPE[0] or s.halo[1] > 0)
    assert sc.peak_bytes > 2 * 4 * max(hi - lo for lo, hi in log) * SHAPE[1] * SHAPE[2]


def test_an_outlier_cluster_beyond_the_assumed_reach_is_correlated_again(pair):
    """A patch of B without its particles makes a cluster of outliers that needs more replacement
    sweeps (and shifts more) than the slabs were planned for: those slabs are planned again."""
    a, b = pair
    b = b.copy()
    _, other = blob_pair(SHAPE, flow, seed=9, density=0.03)
    b[44:64, :20, :20] = other[44:64, :20, :20]
    cfg = CONFIGS["fft"]
    ref = Correlator(SHAPE, config=cfg, device="cpu")(a, b)
    assert ref.outlier.sum() > 5
    sc = SlabCorrelator(SHAPE, cfg, 3, device="cpu", reach=0, max_shift=0.5)
    got = sc(reader(a, b, []))
    assert sc.retries >= 1
    assert_same_field(got, ref)


def test_the_slabs_keep_every_final_row_once_on_the_whole_volumes_windows():
    cfg = CorrelationConfig(windows=((24, 24, 12), (16, 16, 8)), overlap=(0.75, 0.75, 0.5), first_overlap=0.5)
    shape = (101, 40, 40)
    whole = pass_grids(shape, cfg)
    slabs = plan_correlation_slabs(shape, cfg, 4)
    assert [s.k0 for s in slabs] == [0] + [s.k1 for s in slabs[:-1]] and slabs[-1].k1 == whole[-1].counts[2]
    assert slabs[0].lo == 0 and slabs[-1].hi == shape[0]
    zc = whole[-1].centres()[2]
    for s in slabs:
        assert np.all((zc[s.k0:s.k1] >= s.z0) & ((zc[s.k0:s.k1] < s.z1) | (s.z1 == shape[0])))
        for g, sub in zip(whole, s.grids, strict=True):
            # the slab's windows are the whole volume's windows that lie in its planes
            assert sub.window == g.window and sub.step == g.step and sub.counts[:2] == g.counts[:2]
            starts = g.first[2] + g.step[2] * np.arange(g.counts[2])
            inside = starts[(starts >= s.lo) & (starts + g.window[2] <= s.hi)]
            assert np.array_equal(sub.first[2] + sub.step[2] * np.arange(sub.counts[2]) + s.lo, inside)
            assert np.allclose(sub.centres()[0], g.centres()[0]) and np.allclose(sub.centres()[1], g.centres()[1])
    # slabs that hold no final centre are left out
    assert len(plan_correlation_slabs(shape, cfg, shape[0])) == whole[-1].counts[2]
    with pytest.raises(ValueError, match="slabs must be from 1 to 101"):
        plan_correlation_slabs(shape, cfg, 0)


def test_the_prefilter_difference_at_a_cut_stays_within_its_bound(device):
    """The cubic B-spline coefficients of a cut volume against the whole volume's, plane by plane
    from the cut (lower and upper): below gain * |pole|^n of the largest intensity."""
    rng = np.random.default_rng(3)
    vol = rng.uniform(0.0, 1.0, (60, 8, 8)).astype(np.float32)
    cfg = CorrelationConfig(windows=((8, 8, 8),), overlap=0.5, deform_iterations=1)

    def coef(v):
        c = Correlator(v.shape, config=cfg, device=device)
        c._prefilter(c._upload(v, c._vol_a), c._upload(v, c._vol_b))
        return c._coef_a.numpy()

    whole = coef(vol)
    lo, hi = 20, 45
    cut = coef(vol[lo:hi])
    err = np.abs(cut - whole[lo:hi]).max(axis=(1, 2))
    n = np.minimum(np.arange(hi - lo), np.arange(hi - lo)[::-1])  # planes from the nearer cut
    bound = BSPLINE_ERROR_GAIN * BSPLINE_POLE**n * vol.max() + 1e-6  # and float32 round-off
    assert np.all(err <= bound), (err, bound)
    assert err[0] > 1e-3  # the cut does change the edge's coefficients
    assert prefilter_planes(tolerance=1e-6) == 14 and BSPLINE_ERROR_GAIN * BSPLINE_POLE**14 < 1e-6


def test_window_grids_must_fit_the_passes_and_the_volume():
    cfg = CONFIGS["fft"]
    grids = pass_grids((40, 32, 32), cfg)
    c = Correlator((40, 32, 32), config=cfg, device="cpu", grids=grids)
    assert c.grids == grids and correlator_bytes(c) > 0
    with pytest.raises(CorrelationError, match="4 passes need as many window grids, got 2"):
        Correlator((40, 32, 32), config=cfg, device="cpu", grids=grids[:2])
    off = WindowGrid(window=grids[0].window, step=grids[0].step, first=(0, 0, 30), counts=grids[0].counts)
    with pytest.raises(CorrelationError, match="does not lie inside the volume"):
        Correlator((40, 32, 32), config=cfg, device="cpu", grids=[off, *grids[1:]])
    with pytest.raises(CorrelationError, match="a window grid of 16x16x8 voxels for a pass of 16x16x16"):
        Correlator((40, 32, 32), config=cfg, device="cpu", grids=[grids[1], *grids[1:]])
