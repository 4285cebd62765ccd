"""Shake-the-Box's prediction (``lfpiv particles --along-pairs``) against each frame on its own, on a
time-resolved synthetic run, against the truth.

Run from the repository root on two copies of one time-resolved run, one whose particles were made
frame by frame and one made along the pairs (the particles are the costly part; made once)::

    lfpiv synth --rig examples/demo.toml --out ring5.zarr --pairs 5 --time-resolved --flow vortex-ring
    cp -r ring5.zarr ring5_stb.zarr
    lfpiv particles ring5.zarr --candidate-iterations 20 --rounds 2                      # before
    lfpiv particles ring5_stb.zarr --candidate-iterations 20 --rounds 2 --along-pairs \\
        --search-voxels 4,4,4                                                           # after
    python benchmarks/stb_particles.py ring5.zarr ring5_stb.zarr --search-voxels 4,4,4 --bin 16x16x16 \\
        --field divfree --best "--bridge-frames 3 --link-voxels 1.5,1.5,1.5 --pool-pairs 4"

For each run: every frame's recall and ghosts (``lfpiv evaluate``'s particle figures: matched one to
one within a voxel per axis); the particles by their true speed (voxels a frame, from each pair's
frame A to B; those that re-enter the box at its opposite face left out), how many of each band are
found in both frames of their pair (a particle within 0.5 voxel of the true one) and, after ``lfpiv
track --along-pairs`` (``--track`` options; on a copy), how many have a pair track whose two ends are
within 0.5 voxel of the true ones; and the field's RMS velocity error as a share of the peak speed,
each pair and over all, by ``lfpiv track --along-pairs`` with the ``--track`` options alone and with
``--best`` as well (CPU seconds of each track command).
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from series_tracks import _cli  # noqa: E402  (the lfpiv command in this process, its output)

from lfcore.runstore import RunStore  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_particles, evaluate_vector_fields  # noqa: E402

BANDS = ((0.0, 1.0), (1.0, 2.0), (2.0, 3.0), (3.0, 5.0))
NEAR_VOXELS = 0.5


def _within(points: np.ndarray, truth: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """Whether each true point has a point within :data:`NEAR_VOXELS` (Euclidean, voxels)."""
    if not len(points):
        return np.zeros(len(truth), bool)
    d, _ = cKDTree(points / voxel).query(truth / voxel, k=1)
    return d <= NEAR_VOXELS


def _bands(run: Path, tracked: bool) -> list[tuple[int, int, int]]:
    """Per speed band: true particles, found in both frames, tracked (0 without ``tracked``), all pairs."""
    s = RunStore.open(run)
    voxel = np.asarray(VolumeGrid.from_rig(s.rig).voxel_mm)
    truth = s.truth()["particles"]
    out = np.zeros((len(BANDS), 3), int)
    for p in s.particle_pairs():
        a, b = truth[p, 0], truth[p, 1]
        speed = np.linalg.norm((b - a) / voxel, axis=1)
        both = _within(s.read_particles(p, 0)[:, :3], a, voxel) & _within(s.read_particles(p, 1)[:, :3], b, voxel)
        on_track = np.zeros(len(a), bool)
        if tracked:
            rows = s.read_tracks(p)
            rows = rows[rows[:, 6] == 0]
            if len(rows):
                da, ia = cKDTree(rows[:, :3] / voxel).query(a / voxel, k=1)
                db, ib = cKDTree(rows[:, 3:6] / voxel).query(b / voxel, k=1)
                on_track = (da <= NEAR_VOXELS) & (db <= NEAR_VOXELS) & (ia == ib)
        for k, (lo, hi) in enumerate(BANDS):
            sel = (speed >= lo) & (speed < hi)
            out[k] += (int(sel.sum()), int((sel & both).sum()), int((sel & on_track).sum()))
    return [tuple(r) for r in out]


def _field(run: Path) -> tuple[list[float], float, np.ndarray]:
    """The field's RMS velocity error, % of the peak speed, each pair and over all; and its RMS per axis, voxels."""
    store = RunStore.open(run)
    each = [100 * evaluate_vector_fields(store, slice(p, p + 1)).errors.of_peak  # type: ignore[union-attr]
            for p in store.correlated_pairs()]
    ev = evaluate_vector_fields(store)
    return each, 100 * ev.errors.of_peak, ev.rms_voxels  # type: ignore[union-attr,return-value]


def main() -> None:
    """Print each run's particle figures and, after ``lfpiv track --along-pairs`` on a copy, its field's."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="time-resolved synthetic runs with particles/")
    ap.add_argument("--track", default="", help="lfpiv track options besides --along-pairs (one string)")
    ap.add_argument("--search-voxels", default=None, help="lfpiv track --search-voxels")
    ap.add_argument("--bin", default=None, help="lfpiv track --bin")
    ap.add_argument("--field", default="fit", help="lfpiv track --field (default: fit, the field along the pairs "
                    "before the fourteenth session)")
    ap.add_argument("--best", default="", help="further lfpiv track options of the second row (one string)")
    args = ap.parse_args()
    base = shlex.split(args.track)
    for opt, v in (("--search-voxels", args.search_voxels), ("--bin", args.bin), ("--field", args.field)):
        if v:
            base += [opt, v]
    for run in args.runs:
        s = RunStore.open(run)
        print(f"## {run}: {RunStore.open(run).particle_attrs()['settings'].get('along_pairs', 'frame by frame')}")
        evals = evaluate_particles(s)
        print("frame | recall | ghosts (% of found) | found")
        for e in evals:
            m = e.match
            print(f"{e.pair}{'AB'[e.frame]} | {m.recall:.3f} | {100 * m.ghosts / max(m.n_detected, 1):.1f} | "
                  f"{m.n_detected}")
        found = sum(e.match.n_detected for e in evals)
        print(f"all | {np.mean([e.match.recall for e in evals]):.3f} | "
              f"{100 * sum(e.match.ghosts for e in evals) / max(found, 1):.1f} | {found}")
        for name, extra in (("track", []), ("best", shlex.split(args.best))):
            if name == "best" and not extra:
                continue
            with tempfile.TemporaryDirectory(prefix="stb_") as tmp:
                copy = Path(tmp) / "r.zarr"
                shutil.copytree(run, copy)
                t0 = time.process_time()
                # the defaults along the pairs before the fourteenth session, unless the options say otherwise
                _cli("track", copy, "--along-pairs", "--no-relink", "--pool-pairs", "0", *base, *extra, "--quiet")
                cpu = time.process_time() - t0
                each, over, rms = _field(copy)
                bands = _bands(copy, tracked=True)
            print(f"{name} ({' '.join(base + extra)}): each pair {', '.join(f'{v:.1f}' for v in each)}; all "
                  f"**{over:.1f}%** of the peak speed; RMS {', '.join(f'{v:.3f}' for v in rms)} voxel; {cpu:.0f} CPU s")
            print("  speed band (voxel/frame) | particles | found in both frames | tracked: "
                  + "; ".join(f"{lo:g}-{hi:g}: {n}, {f}, {t}"
                              for (lo, hi), (n, f, t) in zip(BANDS, bands, strict=True)))


if __name__ == "__main__":
    main()
