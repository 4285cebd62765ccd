"""Sustained recording rate of the acquisition session against the raw speed of the same disk.

Run from the repository root::

    .venv/bin/python benchmarks/record.py                  # 2 cameras of 2048 x 2048, 150 pairs
    .venv/bin/python benchmarks/record.py --pairs 60 --px 1024

What is measured, in one run, on the disk that holds ``--dir`` (default: a temporary folder
under the repository):

raw
    The plain disk: the same number of frames, uncompressed, each written to its own file by
    the same number of threads the recorder uses, then ``os.sync()``. MB/s of frame data.
recorder
    The real path: two simulated light-field cameras (frames rendered once with the renderer
    from the one-camera example optics, cropped to ``--px``), triggered as fast as the recorder
    accepts (the trigger waits while the ring is more than half full, so nothing overruns), the
    grabbers, the ring buffer, parallel compressed zarr writes, in-order commits, then
    ``os.sync()``. MB/s of (uncompressed) frame data and pairs/s.

Goals: recorder >= 70% of raw, and at least the data rate of two 4 MP cameras in
double-frame mode at 15 Hz (2 x 2 x 4.19 MP x 2 bytes x 15 = 503 MB/s). Record results in
benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquisition.session import RecordingSession  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402
from sim.camera import SimCamera  # noqa: E402
from sim.world import SimWorld  # noqa: E402

GOAL_MB_S = 2 * 2 * 2048 * 2048 * 2 * 15 / 1e6


class Ticker:
    """Stands in for the pulse generator: triggers as fast as the recorder keeps up."""

    def __init__(self, channels: dict[str, int]) -> None:
        self.listeners = []
        self.outputs = {ch: 0.0 for ch in channels.values()}

    def add_listener(self, cb) -> None:
        self.listeners.append(cb)

    def run(self, n: int, session: RecordingSession, ahead: int) -> None:
        for k in range(n):
            while k - session.committed_pairs >= ahead:
                time.sleep(0.0005)
            t = time.time_ns()
            for cb in self.listeners:
                cb(k, t, self.outputs)


def two_camera_rig(px: int) -> Rig:
    d = load_rig(ROOT / "examples" / "one_camera.toml").to_dict()
    d["camera"][0]["sensor_px"] = [px, px]
    d["camera"].append(dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
    d["volume"]["size_mm"] = [min(s, 0.9 * px * 0.0055 / 0.6) for s in d["volume"]["size_mm"]]
    return Rig.from_dict(d)


def raw_disk(folder: Path, frame: np.ndarray, n: int, threads: int) -> float:
    folder.mkdir(parents=True)
    data = frame.tobytes()

    def write(i: int) -> None:
        with open(folder / f"{i}.raw", "wb") as fh:
            fh.write(data)

    t = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(write, range(n)))
    os.sync()
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=150)
    ap.add_argument("--px", type=int, default=2048, help="sensor size in pixels (square)")
    ap.add_argument("--threads", type=int, default=4, help="frame writer threads")
    ap.add_argument("--ring", type=int, default=32)
    ap.add_argument("--dir", default=None, help="folder on the disk to measure (default: under the repository)")
    args = ap.parse_args()

    rig = two_camera_rig(args.px)
    world = SimWorld(rig, ppm=0.5)
    ticker = Ticker(rig.pulse_generator.channels)
    t = time.perf_counter()
    cams = [SimCamera(c.name, rig, world, ticker, pool_pairs=2, rays_per_particle=200, buffers=64)
            for c in rig.camera]
    for c in cams:
        c.open()
        c.configure(triggered=True, frames_per_trigger=2, exposure_us=20.0)
    print(f"rendered the frame pools in {time.perf_counter() - t:.1f} s; {args.pairs} pairs of 2 cameras "
          f"x 2 frames of {args.px} x {args.px} px ({cams[0]._lit[0][0].nbytes / 1e6:.1f} MB each)")

    base = Path(args.dir) if args.dir else ROOT
    work = Path(tempfile.mkdtemp(prefix="lfpiv-bench-record-", dir=base))
    try:
        n_frames = args.pairs * 2 * len(cams)
        frame_bytes = cams[0]._lit[0][0].nbytes
        total_mb = n_frames * frame_bytes / 1e6

        raw_s = raw_disk(work / "raw", cams[0]._lit[0][0], n_frames, args.threads)
        shutil.rmtree(work / "raw")
        raw_mb_s = total_mb / raw_s

        store = RunStore.create(work / "run.zarr", rig, args.pairs, timing={}, software_version="bench")
        session = RecordingSession(cams, store, args.pairs, ring_slots=args.ring, writer_threads=args.threads)
        session.start()
        t = time.perf_counter()
        trig = threading.Thread(target=ticker.run, args=(args.pairs, session, args.ring // 2))
        trig.start()
        trig.join()
        session.wait(600)
        session.close()
        os.sync()
        rec_s = time.perf_counter() - t
        st = session.stats()
        ok = st.committed_pairs == args.pairs and st.frames_recorded == n_frames
        size = sum(f.stat().st_size for f in (work / "run.zarr").rglob("*") if f.is_file())
        rec_mb_s = total_mb / rec_s
        print(f"raw disk     : {raw_mb_s:8.0f} MB/s   ({total_mb:.0f} MB in {raw_s:.2f} s, {args.threads} threads)")
        print(f"recorder     : {rec_mb_s:8.0f} MB/s   {args.pairs / rec_s:6.1f} pairs/s   "
              f"({'all' if ok else 'NOT all'} {n_frames} frames recorded, drops {st.frames_dropped}, "
              f"overruns {st.overruns}; on disk {size / 1e6:.0f} MB, ratio {total_mb * 1e6 / size:.2f})")
        print(f"ratio        : recorder / raw = {rec_mb_s / raw_mb_s:.2f}   (goal >= 0.70)")
        print(f"vs 2 x 4 MP double-frame at 15 Hz ({GOAL_MB_S:.0f} MB/s): {rec_mb_s / GOAL_MB_S:.2f}x   (goal >= 1)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
