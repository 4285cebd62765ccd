"""Import throughput: ``lfpiv import`` of a lab's TIFF files against a plain read of the same files.

Run from the repository root::

    .venv/bin/python benchmarks/import.py                  # 200 double-frame pairs, two 2048 x 2048 cameras
    .venv/bin/python benchmarks/import.py --pairs 20 --px 1024

What is measured, in one run, on the disk that holds ``--dir`` (default: a temporary folder under
the repository), each pass starting from files the page cache does not hold
(``posix_fadvise(DONTNEED)``, as a lab's recording on disk would be):

plain read
    Every file decoded with ``tifffile.imread`` (both pages), one file at a time, and nothing
    more: MB/s of file data.
import
    ``lfpiv.jobs.import_.import_files`` of the same files into a new run store: every file read
    once for its pixels and its CRC32C, both frames checked against the sensor and bit depth,
    compressed (Blosc LZ4, bit shuffle) and written by its threads, frame ids and commits, then
    ``os.sync()``: MB/s of file data.

The files are double-frame two-page 16-bit TIFFs (frame A, frame B), 12-bit light-field-like
content (a background with read noise and sparse bright micro-images). Goal: import at least 70%
of the plain read rate. Record results in benchmarks/RESULTS.md.

What bounds an import on the machine it runs on, measured in the same run, so that a missed goal
says whether the code or the machine missed it:

codec
    The run store's frame codec (:data:`lfcore.runstore.FRAME_CODEC`) encoding the same frames on
    one core, times the cores the import's threads have: MB/s of file data.
disk write
    The store's own bytes written again as one file and ``fsync``-ed: the disk's write rate, scaled
    by the file bytes per store byte (the compression), since the import must write its store
    before ``os.sync()`` returns.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore.device import cpu_threads  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfpiv.jobs.import_ import import_files  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402

GOAL = 0.70


def _rig(px: int) -> Rig:
    """The one-camera example's optics on a ``px`` square sensor, twice (cam0, cam1), 12 bits."""
    base = load_rig(ROOT / "examples" / "one_camera.toml").to_dict()
    cam = dict(base["camera"][0], sensor_px=[px, px], bit_depth=12)
    base["camera"] = [dict(cam, name="cam0"), dict(cam, name="cam1", rotation_deg=[0.0, 90.0, 0.0])]
    base["volume"]["size_mm"] = [min(s, 2.0) for s in base["volume"]["size_mm"]]
    return Rig.from_dict(base)


def _frames(px: int, seed: int) -> np.ndarray:
    """(2, px, px) uint16 light-field-like frames: background, read noise, sparse bright discs."""
    rng = np.random.default_rng(seed)
    img = rng.normal(100.0, 3.0, (2, px, px))
    n = px * px // 400
    r, c = rng.integers(2, px - 2, n), rng.integers(2, px - 2, n)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            img[:, r + dr, c + dc] += rng.uniform(500, 3000, n)
    return np.clip(img, 0, 4095).astype(np.uint16)


def _evict(files: list[Path]) -> None:
    """Drop the files from the page cache (what a recording on disk looks like to a reader)."""
    os.sync()
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _codec_rate(frames: list[np.ndarray], cores: int) -> float:
    """MB/s of frame data the run store's frame codec encodes on ``cores`` cores (one measured)."""
    import numcodecs

    from lfcore.runstore import FRAME_CODEC

    shuffle = {"noshuffle": numcodecs.Blosc.NOSHUFFLE, "shuffle": numcodecs.Blosc.SHUFFLE,
               "bitshuffle": numcodecs.Blosc.BITSHUFFLE}[FRAME_CODEC.shuffle.value]
    blosc = numcodecs.Blosc(cname=FRAME_CODEC.cname.value, clevel=FRAME_CODEC.clevel, shuffle=shuffle)
    blosc.encode(frames[0][0])
    numcodecs.blosc.use_threads = False  # one core: the import's threads each encode on their own
    try:
        t = time.perf_counter()
        for f in frames:
            for img in f:
                blosc.encode(img)
        per_core = sum(f.nbytes for f in frames) / (time.perf_counter() - t) / 1e6
    finally:
        numcodecs.blosc.use_threads = None
    return per_core * cores


def _write_rate(base: Path, nbytes: int) -> float:
    """MB/s at which the disk under ``base`` takes ``nbytes`` of incompressible data, fsync-ed."""
    block = np.random.default_rng(0).integers(0, 256, 1 << 24, dtype=np.uint8).tobytes()
    path = base / "write-rate.bin"
    t = time.perf_counter()
    with open(path, "wb") as fh:
        for _ in range(max(1, nbytes // len(block))):
            fh.write(block)
        fh.flush()
        os.fsync(fh.fileno())
    rate = max(1, nbytes // len(block)) * len(block) / (time.perf_counter() - t) / 1e6
    path.unlink()
    return rate


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--px", type=int, default=2048)
    ap.add_argument("--dir", default=None, help="folder for the files and the run store (default: a temporary one)")
    args = ap.parse_args()
    import tifffile

    base = Path(tempfile.mkdtemp(prefix="lfpiv-import-bench-", dir=args.dir or ROOT))
    try:
        rig = _rig(args.px)
        files: dict[str, list[Path]] = {}
        t = time.perf_counter()
        pool = [_frames(args.px, s) for s in range(4)]  # a few distinct frames, written over and over
        for cam in ("cam0", "cam1"):
            (base / cam).mkdir()
            files[cam] = []
            for p in range(args.pairs):
                f = base / cam / f"{cam}_{p + 1:05d}.tif"
                tifffile.imwrite(f, pool[(p + (cam == "cam1")) % len(pool)])
                files[cam].append(f)
        every = [f for fs in files.values() for f in fs]
        size = sum(f.stat().st_size for f in every)
        print(f"wrote {len(every)} double-frame TIFF files, {size / 1e9:.2f} GB, in {time.perf_counter() - t:.1f} s "
              f"({args.pairs} pairs x 2 cameras of {args.px} x {args.px} px)")

        _evict(every)
        t = time.perf_counter()
        for f in every:
            tifffile.imread(f)
        plain = size / (time.perf_counter() - t) / 1e6

        _evict(every)
        t = time.perf_counter()
        res = import_files(rig, base / "run.zarr", frames={c: str(base / c / "*.tif") for c in files},
                           layout="double-frame", dt_us=500.0, rate_hz=10.0, progress=False)
        returned = size / (time.perf_counter() - t) / 1e6
        os.sync()
        imported = size / (time.perf_counter() - t) / 1e6
        assert res.pairs == args.pairs and res.store.committed_pairs == args.pairs
        stored = sum(f.stat().st_size for f in (base / "run.zarr").rglob("*") if f.is_file())
        codec, disk = _codec_rate(pool, cpu_threads()), _write_rate(base, stored)
        bound = min(plain, codec, disk * size / stored)
        ratio = imported / plain
        print(f"plain read {plain:8.0f} MB/s")
        print(f"import     {imported:8.0f} MB/s   {ratio:.0%} of the plain read (goal {GOAL:.0%}: "
              f"{'met' if ratio >= GOAL else 'missed'}); {returned:.0f} MB/s until import_files returned, "
              "before os.sync()")
        print(f"bounds     codec {codec:.0f} MB/s on {cpu_threads()} core(s); disk write {disk:.0f} MB/s of store "
              f"bytes = {disk * size / stored:.0f} MB/s of file data at the store's {size / stored:.2f}x "
              f"compression; so at most {bound:.0f} MB/s = {bound / plain:.0%} of the plain read on this "
              f"machine, and the import reached {imported / bound:.0%} of that")
    finally:
        shutil.rmtree(base, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
