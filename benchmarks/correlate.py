"""3D cross-correlation: our Warp correlator against OpenPIV, and GPU throughput.

Run from the repository root, in an environment that has lfpiv and (for the CPU case) OpenPIV::

    python -m venv /tmp/bench && /tmp/bench/bin/pip install -e . openpiv
    /tmp/bench/bin/python benchmarks/correlate.py --case cpu          # CPU: ratios against OpenPIV
    /tmp/bench/bin/python benchmarks/correlate.py --case gpu --profile  # GPU: 1024 x 1024 x 128 pair

OpenPIV is never a dependency of lfpiv; without it the CPU case measures against the plain
SciPy baseline only (it always measures that one too).

Cases
-----
cpu
    One volume pair of Gaussian-blob particles (sigma 1 voxel, 0.02 per voxel) of 128 x 128 x 64
    voxels (x, y, z) moved by a uniform sub-voxel displacement. Single pass with 32 x 32 x 16
    windows at 75% overlap: OpenPIV's ``pyprocess3D.extended_search_area_piv3D`` (a Python loop
    over windows, each zero-padded to the next power of two of twice its size, Gaussian peak
    fit), a plain SciPy baseline (a Python loop of unpadded ``scipy.fft.rfftn`` correlations,
    Gaussian fit), and ours (one batched launch). Ours is also timed with its full multi-grid
    (64 x 64 x 32 then 32 x 32 x 16, two deformation passes). Times exclude kernel compilation
    (a warm-up run first); RMS errors are against the known displacement over every vector.
gpu
    A 1024 x 1024 x 128 pair (a 256 x 256 x 128 block of particles tiled in x and y), windows
    128 x 128 x 32 then 64 x 64 x 16 at 75% overlap with two deformation passes: the whole
    multi-grid run, timed after a warm-up, as vectors per second. The goal on one H100 is at most
    0.5 s. Three variants (``--variant``): the FFT in every pass; the passes after the first
    correlated directly within ``--search-radius`` voxels of the predictor; and that with the
    first pass at 50% overlap. Each is timed from NumPy volumes (the host-to-device copy
    included) and from volumes already on the device (as the live pipeline has them).
    ``--gpu-scale 0.25`` runs a smaller volume (e.g. to try the script on a CPU).

Record results in benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore.correlate import CorrelationConfig, Correlator  # noqa: E402
from lfcore.device import available_devices, resolve_device  # noqa: E402
from tests.blobs import blob_pair  # noqa: E402

SHIFT = np.array([0.3, -0.7, 0.45])  # x, y, z voxels


def _gauss(lo: float, c: float, hi: float) -> float:
    if lo > 0 and c > 0 and hi > 0:
        ll, lc, lh = np.log(lo), np.log(c), np.log(hi)
        den = 2 * (ll - 2 * lc + lh)
        if den < 0:
            return (ll - lh) / den
    return 0.0


def scipy_baseline(a: np.ndarray, b: np.ndarray, window: tuple[int, int, int],
                   step: tuple[int, int, int]) -> np.ndarray:
    """Plain SciPy: a Python loop of unpadded rfftn correlations with a Gaussian peak fit; (n, 3) x, y, z."""
    from scipy.fft import irfftn, rfftn

    wx, wy, wz = window
    nz, ny, nx = a.shape
    out = []
    for z0 in range(0, nz - wz + 1, step[2]):
        for y0 in range(0, ny - wy + 1, step[1]):
            for x0 in range(0, nx - wx + 1, step[0]):
                wa = a[z0:z0 + wz, y0:y0 + wy, x0:x0 + wx]
                wb = b[z0:z0 + wz, y0:y0 + wy, x0:x0 + wx]
                r = irfftn(np.conj(rfftn(wa - wa.mean())) * rfftn(wb - wb.mean()), s=wa.shape)
                k = np.unravel_index(np.argmax(r), r.shape)
                d = []
                for ax in (2, 1, 0):
                    lo, hi = list(k), list(k)
                    lo[ax], hi[ax] = (k[ax] - 1) % r.shape[ax], (k[ax] + 1) % r.shape[ax]
                    s = k[ax] if k[ax] < r.shape[ax] / 2 else k[ax] - r.shape[ax]
                    d.append(s + _gauss(r[tuple(lo)], r[k], r[tuple(hi)]))
                out.append(d)
    return np.asarray(out)


def openpiv_single_pass(a: np.ndarray, b: np.ndarray, window: tuple[int, int, int],
                        overlap: tuple[int, int, int]) -> np.ndarray | None:
    """OpenPIV's single-pass 3D correlation as (n, 3) displacements x, y, z, or None without OpenPIV.

    Its arrays are read as (axis 0, 1, 2) = our (z, y, x); measured with a known shift, its
    (u, v, w) are (-dy, dz, dx) in our terms (it correlates B against A flipped).
    """
    try:
        from openpiv.pyprocess3D import extended_search_area_piv3D
    except ImportError:
        return None
    ws = (window[2], window[1], window[0])
    ov = (overlap[2], overlap[1], overlap[0])
    import contextlib
    import io

    with contextlib.redirect_stderr(io.StringIO()):  # its tqdm bar
        u, v, w = extended_search_area_piv3D(a.astype(np.float64), b.astype(np.float64), window_size=ws, overlap=ov,
                                             search_area_size=ws, subpixel_method="gaussian")
    return np.stack([w.ravel(), -u.ravel(), v.ravel()], axis=1)


def rms(d: np.ndarray, truth: np.ndarray) -> float:
    e = np.asarray(d).reshape(-1, 3) - truth
    e = e[np.all(np.isfinite(e), axis=1)]
    return float(np.sqrt(np.mean(e**2)))


def timed(fn, repeat: int = 1):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def cpu_case(args) -> None:
    shape = (64, 128, 128)  # z, y, x
    a, b = blob_pair(shape, lambda p: np.broadcast_to(SHIFT, p.shape), density=0.02, seed=1)
    window, overlap = (32, 32, 16), 0.75
    step = tuple(int(round(w * (1 - overlap))) for w in window)
    rows = []
    single = CorrelationConfig(windows=(window,), overlap=overlap, deform_iterations=0)
    c = Correlator(shape, config=single, device="cpu")
    c(a, b)  # compile
    ours, t_ours = timed(lambda: c(a, b), repeat=3)
    rows.append(("ours, single pass (Warp CPU kernels + pocketfft)", ours.displacement.reshape(-1, 3), t_ours))
    multi = CorrelationConfig(windows=((64, 64, 32), window), overlap=overlap, deform_iterations=2)
    cm = Correlator(shape, config=multi, device="cpu")
    cm(a, b)
    ours_m, t_m = timed(lambda: cm(a, b), repeat=2)
    rows.append(("ours, multi-grid 64x64x32 -> 32x32x16 + 2 deformation passes", ours_m.displacement, t_m))
    base, t_base = timed(lambda: scipy_baseline(a, b, window, step))
    rows.append(("plain SciPy loop (rfftn per window), single pass", base, t_base))
    ov_vox = tuple(w - s for w, s in zip(window, step, strict=True))
    op, t_op = timed(lambda: openpiv_single_pass(a, b, window, ov_vox))
    if op is not None:
        rows.append(("OpenPIV pyprocess3D, single pass", op, t_op))
    ref_name, ref_d, ref_t = rows[-1]
    n = len(ours.displacement.reshape(-1, 3))
    print(f"CPU case: {shape[2]} x {shape[1]} x {shape[0]} voxels (x, y, z), windows {'x'.join(map(str, window))} at "
          f"{overlap:.0%} overlap, {n} vectors; displacement ({', '.join(f'{s:g}' for s in SHIFT)}) voxels (x, y, z)")
    print(f"{'method':66s} {'time s':>8s} {'vectors/s':>10s} {'RMS err vox':>12s} {'time ratio':>11s} "
          f"{'RMS ratio':>10s}")
    ref_rms = rms(ref_d, SHIFT)
    for name, d, t in rows:
        nv = len(np.asarray(d).reshape(-1, 3))
        e = rms(d, SHIFT)
        print(f"{name:66s} {t:8.3f} {nv / t:10.3g} {e:12.4f} {ref_t / t:10.1f}x {e / ref_rms:10.2f}")
    print(f"(ratios against: {ref_name}; time ratio > 1 means faster than it, RMS ratio < 1 more accurate)")
    if op is None:
        print("OpenPIV is not installed in this environment: measured against the SciPy baseline only")


def gpu_case(args) -> None:
    device = resolve_device(args.device)
    if device == "cpu" and args.gpu_scale >= 1:
        print("GPU case: no CUDA device here (give --gpu-scale 0.125 to try it on the CPU); skipped")
        return
    s = args.gpu_scale
    nz, ny, nx = int(128 * min(1, 4 * s)), int(1024 * s), int(1024 * s)
    block = (nz, min(256, ny), min(256, nx))
    a0, b0 = blob_pair(block, lambda p: np.broadcast_to(SHIFT, p.shape), density=0.02, seed=2)
    reps = (1, ny // block[1], nx // block[2])
    a, b = np.tile(a0, reps), np.tile(b0, reps)
    wins = ((128, 128, 32), (64, 64, 16)) if s >= 0.5 else ((64, 64, 16), (32, 32, 8))
    variants = {
        "fft": CorrelationConfig(windows=wins, overlap=0.75, deform_iterations=2),
        "direct": CorrelationConfig(windows=wins, overlap=0.75, deform_iterations=2,
                                    search_radius=args.search_radius),
        "direct-first50": CorrelationConfig(windows=wins, overlap=0.75, deform_iterations=2,
                                            search_radius=args.search_radius, first_overlap=0.5),
    }
    import warp as wp

    a_dev, b_dev = (wp.array(v, dtype=wp.float32, device=device) for v in (a, b))
    print(f"GPU case on {device}: {nx} x {ny} x {nz} voxels (x, y, z), windows "
          f"{' -> '.join('x'.join(map(str, w)) for w in wins)} at 75% overlap + 2 deformation passes")
    for name in args.variant:
        cfg = variants[name]
        c = Correlator(a.shape, config=cfg, device=device)
        c(a, b)  # compile and warm up
        wp.synchronize_device(device)
        f, t = timed(lambda c=c: c(a, b), repeat=args.repeat)
        _, t_dev = timed(lambda c=c: c(a_dev, b_dev), repeat=args.repeat)
        n = f.displacement.size // 3
        first = "" if cfg.first_overlap is None else f", first pass at {cfg.first_overlap[0]:.0%} overlap"
        search = "FFT in every pass" if cfg.search_radius is None else \
            f"passes after the first direct within +-{cfg.search_radius[0]} voxels"
        print(f"  {name} ({search}{first}; fft={c.fft}): {n} vectors in {t:.3f} s (best of {args.repeat}, "
              f"host-to-device copy of both volumes included), {t_dev:.3f} s from volumes on the device; "
              f"{n / t:.3g} vectors/s; RMS error {rms(f.displacement, SHIFT):.4f} voxel; "
              f"outliers {f.outlier.mean():.2%}; goal 0.5 s {'met' if t <= 0.5 else 'not met'}")
        if args.profile:
            profile(c, a, b, device)
        del c


def profile(c: Correlator, a: np.ndarray, b: np.ndarray, device: str) -> None:
    """Time of every kernel (synchronised around each launch, so the total exceeds the run's)."""
    from _kernel_clock import kernel_clock, print_clock

    with kernel_clock(device) as spent:
        t = time.perf_counter()
        c(a, b)
        total = time.perf_counter() - t
    print(f"  profile (synchronised launches, {total:.3f} s in all):")
    print_clock(spent, total, "host (FFT on the CPU, median test, copies)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--case", choices=("cpu", "gpu", "all"), default="all")
    p.add_argument("--device", default=None, help="device of the GPU case (default: the first GPU)")
    p.add_argument("--gpu-scale", type=float, default=1.0, help="scale of the GPU case's x and y (default 1)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--profile", action="store_true", help="GPU case: also time every kernel")
    p.add_argument("--variant", nargs="+", default=["fft", "direct", "direct-first50"],
                   choices=("fft", "direct", "direct-first50"),
                   help="GPU case: FFT in every pass; passes after the first correlated directly around the "
                   "predictor; and that with the first pass at 50%% overlap (default: all three)")
    p.add_argument("--search-radius", type=int, default=3, help="GPU case: radius of the direct passes (voxels)")
    args = p.parse_args()
    print(f"devices: {', '.join(available_devices())}")
    if args.case in ("cpu", "all"):
        cpu_case(args)
    if args.case in ("gpu", "all"):
        gpu_case(args)


if __name__ == "__main__":
    main()
