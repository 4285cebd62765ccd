"""Multi-grid 3D cross-correlation on volumes of Gaussian blobs with known displacements (voxels)."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.correlate import CorrelationConfig, CorrelationError, Correlator, correlate, window_grid
from lfcore.vectors import divergence, vorticity
from tests.blobs import blob_pair

SHAPE = (24, 48, 48)  # z, y, x
CENTRE = np.array([23.5, 23.5, 11.5])  # x, y, z
FAST = CorrelationConfig(windows=((24, 24, 12), (16, 16, 8)), overlap=0.75)
#: The same passes, those after the first correlated directly within +-3 voxels of the predictor.
DIRECT = CorrelationConfig(windows=FAST.windows, overlap=0.75, search_radius=3)


def uniform(d):
    return lambda p: np.broadcast_to(np.asarray(d, dtype=float), p.shape)


def rotation(omega):
    """Solid-body rotation about the volume's z axis by omega radians over dt (voxels)."""

    def f(p):
        r = p - CENTRE
        return np.stack([-omega * r[:, 1], omega * r[:, 0], np.zeros(len(p))], axis=1)

    return f


def shear(gamma):
    """Linear shear: x displacement growing along y (voxels)."""

    def f(p):
        r = p - CENTRE
        return np.stack([gamma * r[:, 1], np.zeros(len(p)), np.zeros(len(p))], axis=1)

    return f


def truth_at(field, fn):
    z, y, x = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    return fn(pts).reshape(field.displacement.shape)


def rms(e):
    return np.sqrt(np.mean(np.asarray(e) ** 2, axis=(0, 1, 2)))


@pytest.fixture(scope="module", params=["fft", "direct"])
def cpu_correlator(request):
    """The FFT in every pass, or the FFT in the first and direct correlation around the predictor after."""
    return Correlator(SHAPE, config=FAST if request.param == "fft" else DIRECT, device="cpu")


def test_window_grid_is_centred_with_the_overlap_step():
    g = window_grid((24, 48, 50), (16, 16, 8), (0.75, 0.5, 0.75))
    assert g.step == (4, 8, 2)
    assert g.counts == ((50 - 16) // 4 + 1, (48 - 16) // 8 + 1, (24 - 8) // 2 + 1)
    assert g.shape == (g.counts[2], g.counts[1], g.counts[0])
    cx, cy, cz = g.centres()
    assert cx[0] - 7.5 == (50 - 16 - (g.counts[0] - 1) * 4) // 2  # the leftover is split between both ends
    assert cy[0] == 7.5 and cy[-1] == 48 - 8.5 and cz[0] == 3.5
    starts = g.starts()
    assert starts.shape == (g.size, 3) and tuple(starts[1]) == (starts[0, 0] + 4, starts[0, 1], starts[0, 2])


@pytest.mark.parametrize("shift", [(0.3, -0.7, 0.45), (0.05, 0.5, -0.25), (2.6, -1.2, 0.8)])
def test_uniform_subvoxel_shift_is_recovered(cpu_correlator, shift):
    a, b = blob_pair(SHAPE, uniform(shift), density=0.02, seed=1)
    f = cpu_correlator(a, b)
    assert f.shape == (9, 9, 9)
    err = f.displacement - np.asarray(shift)
    assert np.all(rms(err) < 0.05), rms(err)  # the goal, per component
    assert np.abs(err).max() < 0.3  # the worst: a corner window, where particles leave the volume
    assert not f.outlier.any()
    assert np.median(f.peak_ratio) > 2.0 and np.median(f.peak_height) > 0.8


def test_trilinear_deformation_is_biased_but_close():
    shift = (0.3, -0.7, 0.45)
    a, b = blob_pair(SHAPE, uniform(shift), density=0.02, seed=1)
    f = correlate(a, b, config=CorrelationConfig(windows=FAST.windows, interpolation="linear"), device="cpu")
    assert np.all(rms(f.displacement - np.asarray(shift)) < 0.08)


def test_solid_body_rotation(cpu_correlator):
    fn = rotation(0.06)  # up to 1.4 voxel at the corners
    a, b = blob_pair(SHAPE, fn, seed=2)
    f = cpu_correlator(a, b)
    e = f.displacement - truth_at(f, fn)
    assert np.all(rms(e) < 0.03), rms(e)
    assert np.abs(e).max() < 0.15
    # the measured field rotates at the right rate and does not diverge (per dt, in 1/voxel units)
    x, y, z = f.x, f.y, f.z
    w = vorticity(f.displacement, x * 1e3, y * 1e3, z * 1e3)[1:-1, 1:-1, 1:-1]
    assert np.median(w[..., 2]) == pytest.approx(2 * 0.06, rel=0.05)
    div = divergence(f.displacement, x * 1e3, y * 1e3, z * 1e3)[1:-1, 1:-1, 1:-1]
    assert np.sqrt(np.mean(div**2)) < 0.05 * 2 * 0.06


def test_linear_shear(cpu_correlator):
    fn = shear(0.08)  # du/dy = 0.08: 1.3 voxel across a final window
    a, b = blob_pair(SHAPE, fn, seed=3)
    f = cpu_correlator(a, b)
    e = f.displacement - truth_at(f, fn)
    assert np.all(rms(e) < 0.03), rms(e)
    assert np.abs(e).max() < 0.15


def test_a_single_pass_matches_a_numpy_reference():
    """Without predictor, each window's peak is that of numpy's circular correlation, fitted alike."""
    a, b = blob_pair((16, 32, 32), uniform((0.4, -1.3, 0.7)), seed=4)
    cfg = CorrelationConfig(windows=((16, 16, 8),), overlap=0.5, deform_iterations=0)
    f = correlate(a, b, config=cfg, device="cpu")
    g = f.grid
    ref, height, ratio = [], [], []
    for x0, y0, z0 in g.starts():
        wa = a[z0:z0 + 8, y0:y0 + 16, x0:x0 + 16].astype(np.float64)
        wb = b[z0:z0 + 8, y0:y0 + 16, x0:x0 + 16].astype(np.float64)
        wa, wb = wa - wa.mean(), wb - wb.mean()
        r = np.fft.ifftn(np.conj(np.fft.fftn(wa)) * np.fft.fftn(wb)).real / np.sqrt(np.sum(wa**2) * np.sum(wb**2))
        k = np.unravel_index(np.argmax(r), r.shape)
        # the second peak: the highest value outside a cyclic box of +-2 voxels (peak_exclusion)
        near = np.ones(r.shape, bool)
        for ax, n in enumerate(r.shape):
            dist = np.abs(np.arange(n) - k[ax]) % n
            near &= (np.minimum(dist, n - dist) <= 2).reshape([-1 if i == ax else 1 for i in range(3)])
        height.append(r[k])
        ratio.append(r[k] / r[~near].max())
        d = []
        for ax in (2, 1, 0):
            lo, hi = list(k), list(k)
            lo[ax], hi[ax] = (k[ax] - 1) % r.shape[ax], (k[ax] + 1) % r.shape[ax]
            ll, lc, lh = np.log([r[tuple(lo)], r[k], r[tuple(hi)]])
            s = k[ax] if k[ax] < r.shape[ax] / 2 else k[ax] - r.shape[ax]
            d.append(s + (ll - lh) / (2 * (ll - 2 * lc + lh)))
        ref.append(d)
    assert np.allclose(f.displacement.reshape(-1, 3), ref, atol=1e-4)
    assert np.allclose(f.peak_height.ravel(), height, atol=1e-5)
    assert np.allclose(f.peak_ratio.ravel(), ratio, rtol=1e-4)


@pytest.mark.parametrize("layout", ["rows", "elements"])
def test_warp_fft_matches_scipy_fft(layout):
    """Warp's tile FFT path (the GPU's) gives the CPU path's result, zero padding included, with
    either thread layout; a 24-voxel x window leaves a partial block of FFT columns."""
    a, b = blob_pair((16, 32, 48), uniform((0.4, -0.6, 0.3)), seed=5)
    for pad, window in ((False, (16, 16, 8)), (True, (16, 16, 8)), (False, (24, 16, 8))):
        cfg = dict(windows=(window,), overlap=0.5, deform_iterations=1, zero_pad=pad)
        ref = Correlator(a.shape, config=CorrelationConfig(fft="scipy", **cfg), device="cpu", layout="rows")(a, b)
        got = Correlator(a.shape, config=CorrelationConfig(fft="warp", **cfg), device="cpu", layout=layout)(a, b)
        assert np.isfinite(ref.displacement).mean() > 0.9
        assert np.allclose(got.displacement, ref.displacement, atol=1e-4, equal_nan=True)
        assert np.allclose(got.peak_height, ref.peak_height, atol=1e-4)


def test_zero_padding_recovers_a_large_shift():
    # 5.4 voxels is beyond half of the 8-voxel z window: circular correlation aliases it to
    # -2.6, the padded correlation finds it (biased low by the shrinking overlap, which the
    # deformation passes then remove)
    a, b = blob_pair((32, 32, 32), uniform((0.3, 0.2, 5.4)), seed=6, density=0.03)
    cfg = dict(windows=((16, 16, 8),), overlap=0.5, deform_iterations=2)
    padded = correlate(a, b, config=CorrelationConfig(zero_pad=True, **cfg), device="cpu")
    assert np.median(padded.displacement[..., 2]) == pytest.approx(5.4, abs=0.1)
    circular = correlate(a, b, config=CorrelationConfig(**cfg), device="cpu")
    assert abs(np.median(circular.displacement[..., 2]) - 5.4) > 2


def test_spurious_vectors_are_flagged_and_replaced(cpu_correlator):
    shift = (0.6, -0.4, 0.3)
    a, b = blob_pair(SHAPE, uniform(shift), seed=7)
    other, _ = blob_pair(SHAPE, uniform(shift), seed=99)
    b[6:18, 14:34, 14:34] = other[6:18, 14:34, 14:34]  # B's particles there are unrelated to A's
    f = cpu_correlator(a, b)
    assert f.outlier.any() and np.array_equal(f.outlier, f.replaced)
    z, y, x = np.meshgrid(f.z, f.y, f.x, indexing="ij")
    inside = (z > 6) & (z < 17) & (y > 14) & (y < 33) & (x > 14) & (x < 33)
    assert not f.outlier[~inside].any()  # only where the volumes disagree
    err = np.abs(f.displacement - np.asarray(shift))
    # With a search box, noise peaks of the corrupt windows lie within +-3 voxels of the predictor,
    # so fewer of them fail the median test and replacements draw on more corrupt neighbours.
    tolerance = 0.15 if cpu_correlator.config.search_radius is None else 0.25
    assert np.all(np.isfinite(f.displacement)) and np.median(err[f.replaced]) < tolerance


def test_blank_volumes_have_no_peak():
    z = np.zeros(SHAPE, dtype=np.float32)
    f = correlate(z, z, config=FAST, device="cpu")
    assert f.outlier.all() and not f.replaced.any() and np.isnan(f.displacement).all()


@pytest.mark.parametrize(("layout", "search"), [("auto", None), ("elements", None), ("auto", 3)])
def test_identical_results_on_every_device(device, layout, search):
    """The default FFT of each device (pocketfft on the CPU, Warp's tile FFT on CUDA) and every
    kernel, in the device's own thread layout and in the GPU's, and the direct correlation."""
    fn = rotation(0.04)
    a, b = blob_pair(SHAPE, fn, seed=8)
    cfg = CorrelationConfig(windows=((32, 32, 16), (16, 16, 8)), overlap=0.75,  # power-of-two FFTs everywhere
                            search_radius=search)
    ref = Correlator(SHAPE, config=cfg, device="cpu")(a, b)
    got = Correlator(SHAPE, config=cfg, device=device, layout=layout)(a, b)
    assert np.allclose(got.displacement, ref.displacement, atol=2e-3)
    assert np.array_equal(got.outlier, ref.outlier)
    assert np.allclose(got.peak_ratio, ref.peak_ratio, rtol=1e-3)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(windows=((64, 16, 8),)), "larger than the volume along x (64 > 48 voxels"),
        (dict(windows=((16, 16, 32),)), "larger than the volume along z (32 > 24 voxels"),
        (dict(overlap=1.0), "overlap must be at least 0 and below 1"),
        (dict(overlap=(0.5, 0.5)), "overlap must be at least 0 and below 1"),
        (dict(windows=((16, 16, 2),)), "too small"),
        (dict(windows=()), "at least one window"),
        (dict(fft="fftw"), "fft must be"),
        (dict(interpolation="sinc"), "interpolation must be"),
        (dict(search_radius=1), "search_radius must be 2 to 8"),
        (dict(search_radius=(3, 3)), "search_radius must be 2 to 8"),
        (dict(first_overlap=1.5), "first_overlap must be at least 0"),
        (dict(windows=((24, 24, 12), (15, 15, 8)), search_radius=3), "share no block of voxels"),
    ],
)
def test_bad_settings(kwargs, message):
    with pytest.raises(CorrelationError, match=message.replace("(", r"\(")):
        Correlator(SHAPE, config=CorrelationConfig(**{"windows": ((16, 16, 8),), **kwargs}), device="cpu")


def test_non_finite_volumes_are_refused(device):
    a = np.zeros(SHAPE, np.float32)
    a[3, 4, 5] = np.nan
    c = Correlator(SHAPE, config=CorrelationConfig(windows=((16, 16, 8),)), device=device)
    with pytest.raises(CorrelationError, match="must be finite"):
        c(a, np.zeros_like(a))


@pytest.mark.parametrize("bspline", [0, 1])
def test_deforming_by_a_predictor_far_out_of_the_volume_samples_zeros(device, bspline):
    """A predictor that is not finite or points far outside (beyond any int index) samples
    nothing, on each device: its index conversion was undefined, and read out of bounds."""
    import warp as wp

    from lfcore._kernels import correlate as kc

    vol = wp.array(np.ones((8, 9, 10), np.float32), device=device)
    out_a, out_b = wp.zeros((8, 9, 10), dtype=wp.float32, device=device), wp.zeros((8, 9, 10), dtype=wp.float32,
                                                                                     device=device)
    for bad in (np.nan, 3e10, -3e10, 1e6):
        pred = wp.array(np.full((2, 2, 2, 3), bad, np.float32), dtype=wp.vec3, device=device)
        wp.launch(kc.deform_volumes, dim=(8, 9, 10), inputs=[vol, vol, pred, wp.vec3(0.0, 0.0, 0.0),
                                                              wp.vec3(8.0, 8.0, 8.0), bspline, 0, out_a, out_b],
                  device=device)
        assert not out_a.numpy().any() and not out_b.numpy().any(), bad
    pred = wp.array(np.zeros((2, 2, 2, 3), np.float32), dtype=wp.vec3, device=device)  # and no shift: the volume
    wp.launch(kc.deform_volumes, dim=(8, 9, 10), inputs=[vol, vol, pred, wp.vec3(0.0, 0.0, 0.0), wp.vec3(8.0, 8.0, 8.0),
                                                          0, 0, out_a, out_b], device=device)
    assert np.allclose(out_a.numpy(), 1.0)


def test_wrong_volume_shape(cpu_correlator):
    with pytest.raises(CorrelationError, match="takes volumes of shape"):
        cpu_correlator(np.zeros((8, 8, 8), np.float32), np.zeros((8, 8, 8), np.float32))


@pytest.mark.parametrize("kind", ["fft", "dft"])
def test_column_transforms_match_numpy(device, kind):
    """The y/z transforms of the Warp FFT path, forward and inverse, against NumPy: 5 groups of 16
    rows, 40 columns (a partial block of 16), on each device with its block size."""
    import warp as wp

    from lfcore._kernels import correlate as kc

    rng = np.random.default_rng(3)
    groups, n, width = 5, 16, 40
    x = (rng.standard_normal((groups, n, width)) + 1j * rng.standard_normal((groups, n, width))).astype(np.complex64)
    buf = wp.array(x.reshape(groups * n, width).view(np.float32).reshape(groups * n, width, 2), dtype=wp.vec2f,
                   device=device)
    gpu = device != "cpu"
    tw = np.exp(-2j * np.pi * np.arange(n) / n)
    twiddle = wp.array(np.stack([tw.real, tw.imag], axis=1).astype(np.float32), dtype=wp.vec2f, device=device)

    def run(inverse):
        if kind == "fft":
            wp.launch_tiled(kc.fft_columns(n, 16), dim=(groups, 3), inputs=[buf, inverse],
                            block_dim=n // 2 if gpu else 1, device=device)
        else:
            wp.launch_tiled(kc.dft_columns(n, 16), dim=(groups, 3), inputs=[buf, twiddle, inverse],
                            block_dim=128 if gpu else 1, device=device)
        y = buf.numpy().reshape(groups, n, width, 2)
        return y[..., 0] + 1j * y[..., 1]

    ref = np.fft.fft(x, axis=1)
    got = run(0)
    assert np.abs(got - ref).max() < 1e-5 * np.abs(ref).max()
    back = run(1) / n
    assert np.abs(back - x).max() < 1e-5


def direct_lag_sums(a, b, start, window, radius):
    """NumPy reference of one window's lag sums: (sum a b, sum b, sum a) at every lag d (x fastest),
    A's window moved back by floor(d / 2) and B's forward by the rest, zero outside the volumes."""
    rx, ry, rz = radius
    pad = max(radius)
    ap, bp = (np.pad(v.astype(np.float64), pad) for v in (a, b))
    x0, y0, z0 = (s + pad for s in start)
    wx, wy, wz = window
    out = []
    for dz in range(-rz, rz + 1):
        for dy in range(-ry, ry + 1):
            for dx in range(-rx, rx + 1):
                oa = [-(d // 2) for d in (dx, dy, dz)]
                ob = [d + o for d, o in zip((dx, dy, dz), oa, strict=True)]
                wa = ap[z0 + oa[2]:z0 + oa[2] + wz, y0 + oa[1]:y0 + oa[1] + wy, x0 + oa[0]:x0 + oa[0] + wx]
                wb = bp[z0 + ob[2]:z0 + ob[2] + wz, y0 + ob[1]:y0 + ob[1] + wy, x0 + ob[0]:x0 + ob[0] + wx]
                out.append(((wa * wb).sum(), wb.sum(), wa.sum()))
    return np.array(out)


@pytest.mark.parametrize("radius", [(3, 2, 2), (2, 3, 3)])
def test_direct_lag_sums_match_numpy(device, radius):
    """Blocks of voxels summed into windows give every window's lag sums (random volumes, so that
    every voxel counts), including windows at the volume's faces where B's lags leave it."""
    import warp as wp

    rng = np.random.default_rng(4)
    shape = (12, 20, 24)
    a, b = (rng.random(shape).astype(np.float32) for _ in range(2))
    cfg = CorrelationConfig(windows=((24, 20, 12), (8, 8, 4)), overlap=0.5, search_radius=radius,
                            deform_iterations=0)
    c = Correlator(shape, config=cfg, device=device)
    g = c.grids[1]
    c._def_in[0].assign(a)
    c._def_in[1].assign(b)
    c._run_local(c._def_a, c._def_b, 1)
    wp.synchronize_device(c.device)
    lag = c._lags[1]
    n = g.size
    cols = lag.columns
    rows = c._lag_sums[1].numpy()[: n * cols].reshape(n, cols, 3)  # the last slab's window sums
    first_row = (g.counts[2] - ((g.counts[2] - 1) % lag.slab + 1)) * g.counts[1] * g.counts[0]
    starts = g.starts()
    for w in (first_row, n - 1, first_row + g.counts[0] // 2):
        ref = direct_lag_sums(a, b, starts[w], g.window, radius)
        got = rows[w - first_row]
        assert np.allclose(got[:-1], ref, rtol=1e-4, atol=1e-3), w
        wa = a[starts[w][2]:starts[w][2] + 4, starts[w][1]:starts[w][1] + 8, starts[w][0]:starts[w][0] + 8]
        assert got[-1, 0] == pytest.approx((wa.astype(np.float64) ** 2).sum(), rel=1e-4)


def test_direct_search_beats_the_fft_on_a_uniform_shift():
    """The direct correlation is unbiased where the circular FFT is pulled towards zero."""
    shift = (0.3, -0.7, 0.45)
    a, b = blob_pair((32, 64, 64), uniform(shift), density=0.02, seed=2)
    cfg = dict(windows=((32, 32, 16), (16, 16, 8)), overlap=0.75)
    fft = correlate(a, b, config=CorrelationConfig(**cfg), device="cpu")
    direct = correlate(a, b, config=CorrelationConfig(search_radius=3, **cfg), device="cpu")
    e_fft, e_direct = (rms(f.displacement - np.asarray(shift)) for f in (fft, direct))
    assert np.all(e_direct < 0.012), e_direct
    assert np.sqrt(np.mean(e_direct**2)) < 0.6 * np.sqrt(np.mean(e_fft**2))


def test_predictor_interpolation_is_exact_for_a_linear_field():
    """The separable trilinear interpolation between pass grids reproduces a linear field at every
    new centre, including beyond the outermost old centres (linear extrapolation)."""
    from lfcore.correlate import _interp

    coarse = window_grid((128, 256, 256), (128, 128, 32), (0.5, 0.5, 0.5))
    fine = window_grid((128, 256, 256), (64, 64, 16), (0.75, 0.75, 0.75))

    def lin(x, y, z):
        return np.stack([0.01 * x - 0.02 * y + 0.5, 0.03 * z + 0.001 * x, -0.004 * y + 0.2 * np.ones_like(x)], axis=-1)

    cx, cy, cz = coarse.centres()
    z, y, x = np.meshgrid(cz, cy, cx, indexing="ij")
    fx, fy, fz = fine.centres()
    zf, yf, xf = np.meshgrid(fz, fy, fx, indexing="ij")
    assert fx[0] < cx[0] and fz[-1] > cz[-1]  # some new centres lie beyond the old ones
    got = _interp(lin(x, y, z), coarse, fine)
    assert np.allclose(got, lin(xf, yf, zf).reshape(-1, 3), atol=1e-12)
