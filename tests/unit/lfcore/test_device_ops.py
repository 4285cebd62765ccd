"""Device image and volume operations against their host versions (every device Warp finds)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from lfcore.correlate import CorrelationConfig, CorrelationError, Correlator
from lfcore.device import warp
from lfcore.device_ops import ImagePreprocessor, VolumeOps, gaussian_taps
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import preprocess
from lfcore.volume import VolumeGrid
from tests.blobs import blob_pair


def test_gaussian_taps_are_scipys() -> None:
    for sigma in (0.6, 1.0, 2.5):
        taps = gaussian_taps(sigma)
        impulse = np.zeros(41)
        impulse[20] = 1.0
        ref = ndimage.gaussian_filter1d(impulse, sigma, mode="constant", truncate=3.0)
        r = (taps.size - 1) // 2
        assert np.allclose(ref[20 - r:21 + r], taps, atol=1e-7)
        assert np.allclose(np.delete(ref, range(20 - r, 21 + r)), 0)


@pytest.mark.parametrize("grow", [0, 2])
def test_preprocessing_equals_the_host_rule(tiny_rig, device, grow) -> None:
    wp = warp()
    cams = [tiny_rig.camera[0], tiny_rig.camera[0]]  # two cameras: offsets and borders per camera
    rows, cols = cams[0].sensor_px[1], cams[0].sensor_px[0]
    rng = np.random.default_rng(3)
    imgs = [rng.normal(100.0, 4.0, (rows, cols)).clip(0).astype(np.uint16) for _ in cams]
    imgs[1][0, 0] = imgs[1][-1, -1] = 2000  # lit corners: the dilation must not wrap into the other camera
    levels, sigmas, thr = [100.0, 98.5], [4.0, 4.2], 2.0
    pre = ImagePreprocessor(cams, device=device)
    raw = wp.array(np.concatenate([i.ravel() for i in imgs]), dtype=wp.uint16, device=pre.device)
    signal = wp.zeros(pre.n_pixels, dtype=float, device=pre.device)
    lit = wp.zeros(pre.n_pixels, dtype=wp.uint8, device=pre.device)
    pre(raw, levels, [thr * s for s in sigmas], signal, lit, grow=grow)
    got_s, got_l = signal.numpy(), lit.numpy()
    for k, img in enumerate(imgs):
        ref_s, ref_l = preprocess(img, levels[k], sigmas[k], thr, grow=grow)
        sl = slice(pre.offsets[k], pre.offsets[k + 1])
        assert np.array_equal(got_s[sl].reshape(rows, cols), ref_s)
        assert np.array_equal(got_l[sl].reshape(rows, cols).astype(bool), ref_l)
    assert 0.005 < got_l.mean() < 0.9


def test_smoothing_projections_and_slices_equal_numpy(device) -> None:
    wp = warp()
    rng = np.random.default_rng(1)
    vol = rng.random((9, 12, 15)).astype(np.float32) ** 8
    ops = VolumeOps(vol.shape, device=device)
    d = wp.array(vol, dtype=float, device=ops.device)
    for axis in (0, 1, 2):
        assert np.array_equal(ops.projection(d, axis), vol.max(axis=axis))
        assert np.array_equal(ops.plane(d, axis, 3), np.take(vol, 3, axis=axis))
    with pytest.raises(IndexError, match="outside the volume"):
        ops.plane(d, 0, 9)
    ops.smooth(d, 0.6)
    ref = ndimage.gaussian_filter(vol, 0.6, mode="constant", truncate=3.0)
    assert np.allclose(d.numpy(), ref, rtol=1e-5, atol=1e-7)
    ops.smooth(d, 0.0)  # no smoothing: unchanged
    assert np.allclose(d.numpy(), ref, rtol=1e-5, atol=1e-7)


def test_the_smoothing_kernels_equal_scipy(device) -> None:
    """The three kernel passes (a GPU's smoothing; the CPU's is SciPy's filter itself) checked on every
    device, to float32 rounding."""
    wp = warp()
    vol = np.random.default_rng(2).random((9, 12, 15)).astype(np.float32) ** 8
    ops = VolumeOps(vol.shape, device=device)
    for sigma in (0.6, 1.5):
        d = wp.array(vol, dtype=float, device=ops.device)
        ops._smooth_passes(d, sigma)
        ref = ndimage.gaussian_filter(vol, sigma, mode="constant", truncate=3.0)
        assert np.allclose(d.numpy(), ref, rtol=1e-5, atol=1e-7)
        assert not np.allclose(d.numpy(), vol, rtol=1e-2)  # it did smooth


def test_scatter_keeps_the_volume_on_the_device(tiny_rig, device) -> None:
    grid = VolumeGrid.from_rig(tiny_rig)
    p = LightFieldProjector(tiny_rig.camera, grid, device=device)
    w = p.weights(p.all_voxels()[:50])
    e = p.wp.array(np.arange(1, 51, dtype=np.float32), dtype=float, device=p.device)
    out = p.wp.full(grid.shape, 7.0, dtype=float, device=p.device)
    vol = w.scatter(e, out=out)
    assert vol is out and vol.shape == grid.shape
    host = w.to_volume(e)
    assert np.array_equal(vol.numpy(), host)
    assert np.array_equal(host.ravel()[:50], np.arange(1, 51)) and host.ravel()[50:].sum() == 0
    with pytest.raises(ValueError, match="must be"):
        w.scatter(e, out=p.wp.zeros((2, 2, 2), dtype=float, device=p.device))


def test_correlator_takes_device_volumes_in_place(device) -> None:
    wp = warp()
    a, b = blob_pair((32, 48, 48), lambda p: np.tile([0.6, -1.2, 0.4], (len(p), 1)), seed=5)
    cfg = CorrelationConfig(windows=((16, 16, 8),), overlap=0.5)
    corr = Correlator(a.shape, config=cfg, device=device)
    host = corr(a, b)
    da = wp.array(a, dtype=float, device=corr.device)
    db = wp.array(b, dtype=float, device=corr.device)
    dev = corr(da, db)
    assert np.allclose(np.nan_to_num(dev.displacement), np.nan_to_num(host.displacement), atol=1e-5)
    with pytest.raises(CorrelationError, match="float32 volumes of shape"):
        corr(wp.zeros((4, 4, 4), dtype=float, device=corr.device), db)
