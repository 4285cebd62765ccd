"""``lfpiv track`` with no options against chosen options, on time-resolved synthetic runs with
particles: the field's RMS velocity error as a share of the peak speed, each pair and over all, and
the command's CPU seconds (issue 48: what ``track``'s defaults along the pairs should be).

Run from the repository root; each row tracks a fresh copy of each run (the run is not written)::

    python benchmarks/track_defaults.py ring.zarr a1.zarr --row= --row="--relink --pool-pairs 4"

A row is one string of ``lfpiv track`` options ("" for none: on a time-resolved run, along the
pairs by default); the command's line saying along the pairs or pair by pair is printed with it.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from series_tracks import _cli  # noqa: E402  (the lfpiv command in this process, its output)
from stb_particles import _field  # noqa: E402


def main() -> None:
    """Print each run's field error for each row of options."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="time-resolved synthetic runs with particles/")
    ap.add_argument("--row", action="append", default=[], help="lfpiv track options (one string; repeat)")
    ap.add_argument("--pairs", default=None, help="lfpiv track --pair-range for every row")
    args = ap.parse_args()
    for run in args.runs:
        print(f"## {run}", flush=True)
        for row in args.row or [""]:
            extra = shlex.split(row) + (["--pair-range", args.pairs] if args.pairs else [])
            with tempfile.TemporaryDirectory(prefix="trkdef_", dir="/tmp/tres") as tmp:
                copy = Path(tmp) / "r.zarr"
                shutil.copytree(run, copy)
                t0 = time.process_time()
                out = _cli("track", copy, *extra, "--quiet")
                cpu = time.process_time() - t0
                each, over, rms = _field(copy)
            line = next((ln for ln in out.splitlines() if ln.startswith(("along the pairs:", "pair by pair:"))), "")
            print(f"`{row or '(none)'}` | {', '.join(f'{v:.1f}' for v in each)} | **{over:.1f}** | "
                  f"{', '.join(f'{v:.3f}' for v in rms)} | {cpu:.0f} | {line.split(':')[0]}", flush=True)


if __name__ == "__main__":
    main()
