"""The demo's ring: the end-to-end vector error of ``lfpiv demo``'s voxel route under several
reconstruction settings, in one process, without the rest of the demo.

Run from the repository root::

    python benchmarks/ring.py                              # records the demo's 2 pairs into a temporary folder
    python benchmarks/ring.py --run RUN.zarr --rows "fixed=--protocol fixed" "fast=" "cap100=--max-iterations 100"

The recording is the demo's (``lfpiv acquire --rig examples/demo.toml --pairs 2 --sim-pool 2 --quiet``:
the same seeds, so the same frames as ``lfpiv demo``'s). Each row reconstructs a copy of it with
``lfpiv reconstruct RUN <options>`` (the demo gives none: ``fast``), correlates it as the demo does
(``lfpiv correlate RUN --windows <the demo's> --overlap 0.5``) and compares it with the truth as the
demo's table does (:func:`lfpiv.jobs.demo.route_figures`: the RMS velocity error over every vector
as a share of the truth's peak speed, and per axis in voxels) and as ``lfpiv evaluate`` does (Q of
every frame). Printed per row: the frames' iterations and why they stopped, mean Q, the ring's
error, and the CPU seconds of the reconstruction and the correlation in this process
(``time.process_time``, every thread), which a shared machine changes less than the wall time.

A row's options are ``lfpiv reconstruct``'s, and ``camera-subsets``: ordered subsets of one camera
each (``--subsets`` the number of cameras; subset k is camera k's pixels instead of an interleaved
lattice of every camera's: an experiment, not an option of ``lfpiv``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import lfcore.reconstruct as recon  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.cli import main as lfpiv  # noqa: E402
from lfpiv.jobs.demo import copy_recording, demo_windows, route_figures  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_run  # noqa: E402

ROWS = ["fixed=--protocol fixed", "fast=", "cap100=--max-iterations 100", "cap150=--max-iterations 150",
        "uncapped=--max-iterations 400", "no-los=--los-iterations 0", "cam-subsets=camera-subsets",
        "fixed-again=--protocol fixed"]


def camera_subsets(pixel_offsets, cameras, n_subsets: int) -> np.ndarray:
    """Subset k = camera k's pixels (``n_subsets`` must be the number of cameras)."""
    if n_subsets != len(cameras):
        raise SystemExit(f"camera-subsets needs --subsets {len(cameras)}, got {n_subsets}")
    out = np.empty(int(pixel_offsets[-1]), dtype=np.int32)
    for k in range(len(cameras)):
        out[int(pixel_offsets[k]):int(pixel_offsets[k + 1])] = k
    return out


def run_lfpiv(argv: list[str]) -> str:
    """``lfpiv argv`` in this process; its stdout (an error stops the benchmark)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = lfpiv(argv)
    if code != 0:
        raise SystemExit(f"lfpiv {shlex.join(argv)} failed ({code})")
    return buf.getvalue()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None, help="the demo's recording (default: recorded here, as the demo does)")
    ap.add_argument("--pairs", type=int, default=2, help="pairs recorded when --run is not given (the demo's: 2)")
    ap.add_argument("--rows", nargs="+", default=ROWS, help="NAME=OPTIONS of lfpiv reconstruct per row")
    ap.add_argument("--keep", default=None, help="keep each row's run store under this folder")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="ring-"))
    try:
        rec = args.run
        if rec is None:
            rec = str(tmp / "recording.zarr")
            run_lfpiv(["acquire", "--rig", str(ROOT / "examples" / "demo.toml"), "--pairs", str(args.pairs),
                       "--out", rec, "--sim-pool", str(min(args.pairs, 4)), "--quiet"])
        windows = demo_windows(rec) if RunStore.open(rec).has_volumes else None
        pool = recon.pixel_subsets
        print("| row | options | iterations a frame (stopped) | Q (mean of frames) | ring: % of peak "
              "| RMS x, y, z (voxel) | reconstruct CPU s | correlate CPU s | wall s |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for row in args.rows:
            name, _, opts = row.partition("=")
            argv = shlex.split(opts)
            cams = "camera-subsets" in argv
            if cams:
                argv = [a for a in argv if a != "camera-subsets"]
                n_cams = len(RunStore.open(rec).rig.camera)
                argv += ["--subsets", str(n_cams)] if "--subsets" not in argv else []
            run = str((Path(args.keep) if args.keep else tmp) / f"{name}.zarr")
            if Path(run).exists():
                shutil.rmtree(run)
            copy_recording(rec, run)
            recon.pixel_subsets = camera_subsets if cams else pool
            w0, c0 = time.perf_counter(), time.process_time()
            run_lfpiv(["reconstruct", run, "--quiet", *argv])
            c1 = time.process_time()
            recon.pixel_subsets = pool
            if windows is None:
                windows = demo_windows(run)
            run_lfpiv(["correlate", run, "--windows", windows, "--overlap", "0.5", "--quiet"])
            c2, w2 = time.process_time(), time.perf_counter()
            store = RunStore.open(run)
            q = [e.q for e in evaluate_run(store)]
            fig = route_figures(run, name, w2 - w0, store.n_pairs)
            conv = store.volume_attrs().get("convergence", {})
            per = conv.get("per_frame", {})
            its = ", ".join(str(v[0]) for v in per.values())
            why = ", ".join(f"{k} {v}" for k, v in (conv.get("stopped") or {}).items())
            rms = ", ".join(f"{v:.3f}" for v in fig.rms_voxels) if fig.rms_voxels else "n/a"
            print(f"| {name} | `{opts}` | {its} ({why}) | {np.mean(q):.3f} ({', '.join(f'{v:.3f}' for v in q)}) | "
                  f"{100 * fig.of_peak:.1f}% ({100 * fig.of_peak:.2f}) | {rms} | {c1 - c0:.1f} | {c2 - c1:.1f} | "
                  f"{w2 - w0:.1f} |", flush=True)
            if not args.keep:
                shutil.rmtree(run)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
