"""Tracks pooled from neighbouring pairs of a time-resolved series (``lfpiv track --along-pairs
--pool-pairs K``) against each pair's own tracks, per pair, against the truth.

Run from the repository root, on time-resolved runs that hold their particles (computed once; the
tracks are cheap, the particles are not)::

    lfpiv synth --rig examples/demo.toml --out ring5.zarr --pairs 5 --time-resolved --flow vortex-ring
    lfpiv particles ring5.zarr --candidate-iterations 20 --rounds 2
    python benchmarks/pool_tracks.py ring5.zarr --search-voxels 4,4,4 --bin 16x16x16 --pool 0,1,2 \\
        --field fit,divfree [--truth 0,0.1 [--truth-only]]

For each run, field and K of ``--pool`` (a copy of the run each time, so the run is left as it was):
``lfpiv track --along-pairs --pool-pairs K`` and ``lfpiv evaluate``'s figures, the RMS velocity error
per pair and over all pairs as a share of the peak speed (and per axis in voxels over all), with
what ``track`` printed about the pooling; CPU seconds of the track command. With ``--truth NOISES``
also the floor: the truth's own tracks of every particle at each pair's frames A and B (those that
re-enter the box at its opposite face left out), with Gaussian noise of each of NOISES voxels per
axis, made into each pair's field directly (:func:`lfcore.track.field_of_tracks` and
:func:`lfcore.track.pooled_field_of_tracks`), with the pattern's estimated translation per pair.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from series_tracks import _cli  # noqa: E402  (the lfpiv command in this process, its output)

from lfcore import metrics  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfcore.track import TrackSettings, field_of_tracks, pooled_field_of_tracks  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_vector_fields  # noqa: E402

_POOLED = re.compile(r"pooled the tracks .* into (\d+) of the (\d+) pairs' .* per pair \(x, y, z\) ([-\d., ]+) voxel")


def _per_pair(run: Path) -> tuple[list[float], float, np.ndarray]:
    store = RunStore.open(run)
    pairs = store.correlated_pairs()
    each = [100 * evaluate_vector_fields(store, slice(p, p + 1)).errors.of_peak for p in pairs]  # type: ignore[union-attr]
    ev = evaluate_vector_fields(store)
    return each, 100 * ev.errors.of_peak, ev.rms_voxels  # type: ignore[union-attr,return-value]


def _truth_rows(run: Path, noise: float, pools: list[int], fields: list[str], bins: tuple[int, int, int]) -> None:
    store = RunStore.open(run)
    grid = VolumeGrid.from_rig(store.rig)
    voxel = np.asarray(grid.voxel_mm)
    truth, flow, dt = store.truth(), store.truth_flow(), float(store.timing["dt_s"])
    pts = truth["particles"]
    rng = np.random.default_rng(1)
    tracks = {}
    for p in range(pts.shape[0]):
        a, b = pts[p, 0], pts[p, 1]
        ok = np.all(np.abs(b - a) < 10 * voxel, axis=1)  # not the particles that re-enter at the opposite face
        tracks[p] = tuple(v[ok] + rng.normal(scale=noise, size=v[ok].shape) * voxel for v in (a, b))
    for fld in fields:
        s = TrackSettings(bin_voxels=bins, field=fld)
        for k in pools:
            t0 = time.process_time()
            fields_, each, taken, shifts = [], [], 0, []
            ref = []
            for p in range(pts.shape[0]):
                near = [(j, *tracks[p + j]) for j in range(-k, k + 1) if j and p + j in tracks]
                res, ch = (pooled_field_of_tracks(*tracks[p], near, grid, settings=s) if k else
                           (field_of_tracks(*tracks[p], grid, settings=s), None))
                r = metrics.grid_velocity(flow, res.x_mm, res.y_mm, res.z_mm, truth["t0_s"][p] + 0.5 * dt)
                v = res.field_mm * 1e-3 / dt
                each.append(100 * metrics.velocity_errors(v[None], r[None]).of_peak)
                fields_.append(v)
                ref.append(r)
                if ch is not None:
                    taken += int(ch.pooled)
                    shifts.append(np.asarray(ch.shift_mm) / voxel)
            e = metrics.velocity_errors(np.stack(fields_), np.stack(ref))
            vox = e.rms_m_s * dt * 1e3 / voxel
            pooled = f"{taken}/{len(shifts)}, shift {np.round(np.median(shifts, axis=0), 2)}" if shifts else ""
            print(f"| {run.name} | true tracks, {noise:g} voxel noise | {fld} | {k} | "
                  f"{', '.join(f'{v:.1f}' for v in each)} | **{100 * e.of_peak:.1f}** | "
                  f"{vox[0]:.3f}, {vox[1]:.3f}, {vox[2]:.3f} | {pooled} | {time.process_time() - t0:.0f} |", flush=True)


def main_(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="time-resolved runs with particles/")
    ap.add_argument("--search-voxels", default="4,4,4", help="the first pass's search (default: 4,4,4)")
    ap.add_argument("--bin", default="16x16x16", help="the field's bins (default: 16x16x16)")
    ap.add_argument("--field", default="fit,divfree", help="the fields, comma-separated (default: fit,divfree)")
    ap.add_argument("--pool", default="0,1,2", help="--pool-pairs values, comma-separated (default: 0,1,2)")
    ap.add_argument("--truth", default="", metavar="NOISES",
                    help="also the truth's tracks with these noises (voxels), comma-separated (default: none)")
    ap.add_argument("--truth-only", action="store_true", help="only the truth's tracks (runs without particles)")
    args = ap.parse_args(argv)
    pools = [int(v) for v in args.pool.split(",")]
    fields = args.field.split(",")
    bins = tuple(int(v) for v in args.bin.split("x"))
    print("| run | tracks | field | K | % of peak speed, each pair | all pairs | RMS x, y, z (voxel) | pooled, "
          "translation per pair (voxel, median) | CPU s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for run in args.runs:
            for noise in [float(v) for v in args.truth.split(",") if v]:
                _truth_rows(run, noise, pools, fields, bins)  # type: ignore[arg-type]
            copy = Path(tmp) / run.name
            for fld in ([] if args.truth_only else fields):
                for k in pools:
                    shutil.copytree(run, copy)
                    t0 = time.process_time()
                    text = _cli("track", copy, "--search-voxels", args.search_voxels, "--bin", args.bin, "--field",
                                fld, "--along-pairs", "--quiet", "--no-relink", "--pool-pairs", k)
                    cpu = time.process_time() - t0
                    each, allp, vox = _per_pair(copy)
                    m = _POOLED.search(text)
                    pooled = f"{m.group(1)}/{m.group(2)}, shift ({m.group(3)})" if m else ""
                    print(f"| {run.name} | along the pairs | {fld} | {k} | {', '.join(f'{v:.1f}' for v in each)} | "
                          f"**{allp:.1f}** | {vox[0]:.3f}, {vox[1]:.3f}, {vox[2]:.3f} | {pooled} | {cpu:.0f} |",
                          flush=True)
                    shutil.rmtree(copy)


if __name__ == "__main__":
    main_()
