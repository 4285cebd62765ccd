"""Tracks along a time-resolved series (``lfpiv track --along-pairs``) against each pair tracked on
its own (``lfpiv track``), against the truth, on runs that already hold their particles.

Run from the repository root, on time-resolved runs with particles::

    lfpiv synth --rig examples/one_camera_off_focus.toml --out a1.zarr --pairs 5 --flow A1 --omega 4.449 \\
        --displacement-px 10 --ppm 0.5 --seed 14 --time-resolved
    lfpiv particles a1.zarr
    python benchmarks/series_tracks.py a1.zarr [ring.zarr ...] [--search-voxels 6,2,2] [--fit-frames 4,6,8] \\
        [--field fit,divfree]

For each run (a copy of it, so the run itself is left as it was): ``lfpiv track`` pair by pair and
``lfpiv track --along-pairs`` with each ``--fit-frames`` (the same ``--search-voxels``, no predictor,
each ``--field``, the default ``fit``, on 16 x 16 x 8 bins), then ``lfpiv evaluate``'s RMS velocity error over all
pairs, per axis in voxels and as a share of the peak speed. And the position noise of the tracks
through the series before and after their polynomial fit: each point of a fitted track (its particle,
and the track's fitted position there) against the nearest true particle of its frame within a voxel
per axis, RMS per axis in voxels; and how long the tracks are.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lfcore.runstore import RunStore
from lfcore.volume import VolumeGrid
from lfpiv.cli import main

_RMS = re.compile(r"velocity error: RMS .* m/s \(([\d.]+), ([\d.]+), ([\d.]+) voxel\); ([\d.]+)% of the peak")


def _cli(*argv: object) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main([str(a) for a in argv])
    if rc:
        sys.exit(f"lfpiv {' '.join(map(str, argv))} failed ({rc})")
    return out.getvalue()


def _evaluate(run: Path) -> tuple[float, float, float, float]:
    m = _RMS.search(_cli("evaluate", run))
    assert m, "no velocity error in evaluate's output"
    return tuple(float(m.group(k)) for k in range(1, 5))  # type: ignore[return-value]


def _noise(run: Path) -> tuple[np.ndarray, np.ndarray, int, float, float]:
    """RMS (x, y, z voxels) of the fitted tracks' particles and of their fitted positions against the
    truth; the fitted tracks, their mean length and the share of points matched."""
    s = RunStore.open(run)
    voxel = np.asarray(VolumeGrid.from_rig(s.rig).voxel_mm)
    truth = s.truth()["particles"]
    truth = truth.reshape(-1, *truth.shape[2:])
    pts = s.read_series_tracks()
    fitted = pts[np.isfinite(pts[:, 5])]
    before, after = [], []
    for f in np.unique(fitted[:, 1]).astype(int):
        rows = fitted[fitted[:, 1] == f]
        d, i = cKDTree(truth[f] / voxel).query(rows[:, 2:5] / voxel, p=np.inf)
        ok = d <= 1.0
        before.append((rows[ok, 2:5] - truth[f][i[ok]]) / voxel)
        after.append((rows[ok, 5:8] - truth[f][i[ok]]) / voxel)
    b, a = np.concatenate(before), np.concatenate(after)
    lengths = np.bincount(fitted[:, 0].astype(int))
    lengths = lengths[lengths > 0]
    return (np.sqrt(np.mean(b ** 2, axis=0)), np.sqrt(np.mean(a ** 2, axis=0)), len(lengths),
            float(lengths.mean()), len(b) / len(fitted))


def main_(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="time-resolved runs with particles/")
    ap.add_argument("--search-voxels", default="6,2,2", help="the first pass's search (default: 6,2,2)")
    ap.add_argument("--fit-frames", default="6", help="--along-pairs' --fit-frames, comma-separated (default: 6)")
    ap.add_argument("--link-voxels", default="1,1,1", help="--along-pairs' --link-voxels (default: 1,1,1)")
    ap.add_argument("--bin", default="16x16x8", help="the field's bins (default: 16x16x8)")
    ap.add_argument("--field", default="fit", help="the fields (--field), comma-separated (default: fit)")
    args = ap.parse_args(argv)
    print("| run | tracking | RMS x, y, z (voxel) | % of peak speed |")
    print("| --- | --- | --- | --- |")
    noise = []
    with tempfile.TemporaryDirectory() as tmp:
        for run in args.runs:
            copy = Path(tmp) / run.name
            for field in args.field.split(","):
                common = ("--search-voxels", args.search_voxels, "--bin", args.bin, "--field", field, "--quiet")
                shutil.copytree(run, copy)
                _cli("track", copy, *common, "--pair-by-pair")
                x, y, z, pct = _evaluate(copy)
                print(f"| {run.name} | each pair on its own, {field} | {x:.3f}, {y:.3f}, {z:.3f} | {pct:.1f} |")
                for ff in args.fit_frames.split(","):
                    shutil.rmtree(copy)
                    shutil.copytree(run, copy)
                    _cli("track", copy, *common, "--along-pairs", "--fit-frames", ff, "--link-voxels",
                         args.link_voxels, "--no-relink", "--pool-pairs", "0")  # the defaults before the 14th session
                    x, y, z, pct = _evaluate(copy)
                    print(f"| {run.name} | along the pairs, {ff} frames a fit, {field} | {x:.3f}, {y:.3f}, {z:.3f} | "
                          f"{pct:.1f} |", flush=True)
                    if field == args.field.split(",")[0]:
                        noise.append((run.name, ff, *_noise(copy)))
                shutil.rmtree(copy)
    print()
    print("| run | frames a fit | tracks (mean length) | particles' RMS x, y, z (voxel) | fitted | matched |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, ff, b, a, n, length, matched in noise:
        print(f"| {name} | {ff} | {n} ({length:.1f} frames) | {b[0]:.3f}, {b[1]:.3f}, {b[2]:.3f} | "
              f"{a[0]:.3f}, {a[1]:.3f}, {a[2]:.3f} | {100 * matched:.0f}% |")


if __name__ == "__main__":
    main_()
