"""Whole-run benchmark: the run store's I/O overlapped with reconstruction and correlation.

Run from the repository root::

    python benchmarks/batch.py --case S --pairs 3 --device cpu      # seconds (Mc: minutes)
    python benchmarks/batch.py --case M --pairs 4 --device cuda     # where the overlap matters

A run of ``--pairs`` pairs is made from one rendered image per camera of the case (the cases of
``benchmarks/recon.py``; every frame the same image, which changes no timing). Then, on the
same device and run store:

1. the baseline: every frame reconstructed and then written, one after the other, in this
   process (what ``lfpiv reconstruct`` did before the write-behind), with the time of each
   part; then ``reconstruct_run``, which writes each volume while the next is reconstructed;
2. the same for correlation: each pair's volumes read and then correlated, against
   ``correlate_run``, which reads the next pair while this one is correlated.

It prints each wall time, the ratio of the baseline's to the overlapped and the time saved
against the time the I/O took (differences beyond the I/O are run-to-run noise). On the GPU the
I/O is a large part of a frame's time (writing one M volume of 482 MiB took about 2 s on the
development VM's CPU); on a CPU the reconstruction itself takes the cores the I/O would use, so
expect little there.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recon import scene  # noqa: E402

from lfcore.correlate import CorrelationConfig, Correlator  # noqa: E402
from lfcore.device import resolve_device  # noqa: E402
from lfcore.reconstruct import ReconSettings  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.commands.correlate import parse_windows  # noqa: E402
from lfpiv.jobs.correlate import _correlate_pair, _read_pair, _Target, correlate_run  # noqa: E402
from lfpiv.jobs.reconstruct import _operator, _reconstruct_frame, reconstruct_run  # noqa: E402


def make_run(path: Path, case: str, pairs: int, device: str) -> RunStore:
    """A run of ``pairs`` pairs, every frame the case's rendered image, for the case's cameras."""
    rig, _, cams, _, _, images = scene(case, device, 0.5)
    rig = rig.model_copy(update={"camera": tuple(cams)})
    store = RunStore.create(path, rig, pairs, timing={"dt_s": rig.timing.dt_us * 1e-6, "rate_hz": rig.laser.rate_hz},
                            software_version="benchmark")
    for cam, img in zip(cams, images, strict=True):
        frame = np.clip(np.rint(np.asarray(img)), 0, 65535).astype(np.uint16)
        for p in range(pairs):
            for f in (0, 1):
                store.write_frame(cam.name, p, f, frame, frame_id=2 * p + f, timestamp_ns=0)
    store.commit(pairs)
    return store


def reconstruction(store: RunStore, settings: ReconSettings, device: str) -> None:
    rig = store.rig
    grid = VolumeGrid.from_rig(rig)
    names = [c.name for c in rig.camera]
    pairs = range(store.n_pairs)
    # warm-up: kernels loaded and compiled before either is timed
    reconstruct_run(store, settings, pairs=slice(0, 1), device=device, progress=False)

    t0 = time.perf_counter()
    _, frames = _operator(rig.camera, grid, settings, device)
    t_build = time.perf_counter() - t0
    t_rec = t_write = 0.0
    for p in pairs:
        for f in (0, 1):
            t = time.perf_counter()
            res = _reconstruct_frame(frames, store, names, p, f)
            t_rec += time.perf_counter() - t
            t = time.perf_counter()
            store.write_volume(p, f, res.volume)
            t_write += time.perf_counter() - t
    serial = time.perf_counter() - t0
    del frames

    t0 = time.perf_counter()
    reconstruct_run(store, settings, device=device, progress=False)
    overlapped = time.perf_counter() - t0
    n = 2 * len(pairs)
    print(f"  reconstruction ({settings.method}, {settings.iterations} iterations), {n} frames:")
    print(f"    one after the other: {serial:.2f} s (operator {t_build:.2f} s, reconstructing {t_rec / n:.3f} s and "
          f"writing {t_write / n:.3f} s a frame)")
    print(f"    written behind:      {overlapped:.2f} s: {serial / overlapped:.2f}x the speed, "
          f"{serial - overlapped:.2f} s saved of the {t_write:.2f} s of writing")


def correlation(store: RunStore, cfg: CorrelationConfig, device: str) -> None:
    grid = store.volume_grid()
    pairs = list(range(store.n_pairs))
    correlate_run(store, cfg, pairs[:1], device=device, progress=False)  # warm-up

    t0 = time.perf_counter()
    correlator = Correlator(grid.shape, config=cfg, device=device)
    t_build = time.perf_counter() - t0
    t_read = t_corr = 0.0
    target = _Target.of(store)
    for p in pairs:
        t = time.perf_counter()
        vols = _read_pair(store, p)
        t_read += time.perf_counter() - t
        t = time.perf_counter()
        _correlate_pair(correlator, target, p, vols)
        t_corr += time.perf_counter() - t
    serial = time.perf_counter() - t0
    del correlator

    t0 = time.perf_counter()
    correlate_run(store, cfg, pairs, device=device, progress=False)
    overlapped = time.perf_counter() - t0
    n = len(pairs)
    print(f"  correlation ({' then '.join('x'.join(map(str, w)) for w in cfg.windows)}), {n} pairs:")
    print(f"    one after the other: {serial:.2f} s (correlator {t_build:.2f} s, reading {t_read / n:.3f} s and "
          f"correlating {t_corr / n:.3f} s a pair)")
    print(f"    read ahead:          {overlapped:.2f} s: {serial / overlapped:.2f}x the speed, "
          f"{serial - overlapped:.2f} s saved of the {t_read:.2f} s of reading")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", choices=("S", "S2", "Mc", "Mc2", "M"), default="Mc")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--device", default=None)
    ap.add_argument("--method", default="mlos-mart", choices=("drt-mart", "mlos-mart"))
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--windows", type=parse_windows, default=None,
                    help="correlation windows (default 32x32x16,16x16x8 for S and S2, 320x320x64,160x160x32 for M "
                    "as lfpiv correlate, else 64x64x32,32x32x16)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    default = {"S": "32x32x16,16x16x8", "S2": "32x32x16,16x16x8", "M": "320x320x64,160x160x32"}
    windows = args.windows or parse_windows(default.get(args.case, "64x64x32,32x32x16"))
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as tmp:
        t = time.perf_counter()
        store = make_run(Path(tmp) / "run.zarr", args.case, args.pairs, device)
        grid = store.rig.volume
        print(f"case {args.case}, {args.pairs} pairs on {device}, run store in {tmp} "
              f"(made in {time.perf_counter() - t:.1f} s; volume {grid.size_mm} mm at PVR {grid.pvr})")
        reconstruction(store, ReconSettings(method=args.method, iterations=args.iterations), device)
        correlation(store, CorrelationConfig(windows=windows), device)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
