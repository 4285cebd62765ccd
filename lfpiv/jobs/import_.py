"""A run store made from image files recorded elsewhere (``lfpiv import``).

A lab's camera software writes TIFF, PNG or BMP files, or DaVis sets; ``import`` puts them into
a run store of the same layout as a recorded run (state ``complete``), ready for
``reconstruct``, ``correlate``, ``evaluate`` (without truth) and ``export``. The readers are
:mod:`lfpiv.formats.images`' (layouts ``interleaved``, ``double-frame``, ``separate``).

What keeps the lab's data safe:

- every file is inspected (and every frame's size checked against the camera's ``sensor_px``,
  compressed and signed TIFF pages decoded) before the store is created, so a set that cannot be
  imported leaves nothing behind; every entry the pattern matches that cannot be a frame (a
  dangling or looping link, a pipe, a file whose name breaks the others') is named, never
  skipped, which would shift frames A and B of every later pair; signed images with negative
  counts and 1-bit images are refused (:mod:`lfpiv.formats.images`);
- a source file that changes after it was inspected (still being copied or written) is refused
  when it is read;
- every byte of every source is read once, for its pixels and its checksum alike (CRC32C, or
  SHA-256), and each source's path, size and checksum go into the run's ``import`` attribute; values beyond the
  camera's ``bit_depth`` are refused with the file named; sources are only ever read;
- a frame a camera lacks (fewer files than another camera's, a last frame A without its B)
  is a row of ``drops`` with its reason, never silent;
- an existing store is replaced only with ``overwrite``; an interrupted import (Ctrl-C, an
  unreadable file found late) keeps its committed pairs, says ``aborted``, and goes on with
  ``skip_done`` from the first pair it lacks; one that stops before its first pair is whole
  removes the store it began.

Frames are compressed and written by several threads while the next files are read (zarr's
codecs and file I/O release the interpreter lock).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.device import cpu_threads
from lfcore.rig import Rig
from lfcore.runstore import FrameWriter, RunStore, RunStoreError
from lfpiv import __version__
from lfpiv.errors import UsageError
from lfpiv.formats import FormatError
from lfpiv.formats.images import (
    CHECKSUMS,
    LAYOUTS,
    FrameSource,
    PairSource,
    image_files,
    pair_frames,
    read_sources,
)

__all__ = ["CHECKSUMS", "LAYOUTS", "ImportResult", "import_files"]

log = logging.getLogger(__name__)

#: Seconds between writes of the frame ids, time stamps, provenance and commit while importing.
FLUSH_S = 2.0


@dataclass(frozen=True)
class ImportResult:
    """What an import did.

    Attributes
    ----------
    store
        The run store.
    pairs
        Pairs in the run (the most any camera has).
    imported
        Pairs written by this call (the others were there already, with ``skip_done``).
    drops
        Frames listed as lost.
    bytes_read
        Bytes of source files read.
    seconds
        Time spent reading and writing.
    timing
        The run's ``timing`` attribute (``dt_s``, ``rate_hz``).
    """

    store: RunStore
    pairs: int
    imported: int
    drops: int
    bytes_read: int
    seconds: float
    timing: dict[str, Any]


@dataclass(frozen=True)
class _Camera:
    """One camera's frames: where each pair's frames lie, and which frames are lost."""

    name: str
    sensor_px: tuple[int, int]
    bit_depth: int
    pattern: str
    pairs: list[PairSource]
    unpaired: list[FrameSource]


def _sources_of(rig: Rig, frames: Mapping[str, str], frames_b: Mapping[str, str] | None,
                davis: Mapping[str, str] | None, layout: str) -> tuple[list[_Camera], dict[str, float | None]]:
    """Where every camera's frames lie (all files inspected), and the timing DaVis files carry."""
    if layout not in LAYOUTS:
        raise UsageError(f"--layout must be one of {', '.join(LAYOUTS)}, got '{layout}'")
    given = {**frames, **(davis or {})}
    names = [c.name for c in rig.camera]
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise UsageError(f"camera '{unknown[0]}' is not in the rig (it has {', '.join(names)}); name the files of "
                         "each camera as CAM=PATTERN")
    twice = sorted(set(frames) & set(davis or {}))
    if twice:
        raise UsageError(f"camera '{twice[0]}' has both --frames and --davis; give one source per camera")
    missing = [n for n in names if n not in given]
    if missing:
        raise UsageError(f"no files for camera '{missing[0]}'; give --frames {missing[0]}=PATTERN (or --davis) for "
                         "every camera of the rig")
    if (layout == "separate") != bool(frames_b):
        raise UsageError("--layout separate takes frames B from --frames-b CAM=PATTERN" if layout == "separate"
                         else "--frames-b is for --layout separate only")
    if frames_b:
        lacking = [n for n in frames if n not in frames_b]
        if lacking or set(frames_b) - set(frames):
            n = lacking[0] if lacking else sorted(set(frames_b) - set(frames))[0]
            raise UsageError(f"camera '{n}' needs both --frames and --frames-b with --layout separate")
    timing: dict[str, float | None] = {"dt_s": None, "rate_hz": None}
    cams = []
    for k, cam in enumerate(rig.camera):
        unpaired: list[FrameSource] = []
        try:
            if cam.name in (davis or {}):
                from lfpiv.formats.davis import davis_timing
                from lfpiv.formats.images import inspect_image

                files = image_files(davis[cam.name])  # type: ignore[index]
                # a DaVis set of several cameras holds each camera's pair as frames 2k, 2k + 1
                at = k if len(set((davis or {}).values())) == 1 and len(davis or {}) > 1 else 0
                pairs = pair_frames(files, layout="double-frame", camera=at, sensor_px=cam.sensor_px)
                found = davis_timing([inspect_image(f) for f in files[:2]], camera=at)
                for key, v in (("dt_s", found.dt_s), ("rate_hz", found.rate_hz)):
                    timing[key] = timing[key] or v
                pattern = davis[cam.name]  # type: ignore[index]
            else:
                pattern = frames[cam.name]
                files = image_files(pattern)
                files_b = image_files(frames_b[cam.name]) if frames_b else None
                pairs = pair_frames(files, layout=layout, files_b=files_b, sensor_px=cam.sensor_px,
                                    unpaired=unpaired if layout == "interleaved" else None)
        except FormatError as exc:
            raise UsageError(f"camera '{cam.name}': {exc}") from None
        cams.append(_Camera(cam.name, tuple(cam.sensor_px), cam.bit_depth, str(pattern), pairs, unpaired))
        log.info("camera %s: %d pair(s) in %d file(s) of %s (%s)", cam.name, len(pairs), len(files), pattern,
                 "double-frame" if cam.name in (davis or {}) else layout)
    return cams, timing


def _timing(dt_us: float | None, rate_hz: float | None, found: dict[str, float | None]) -> dict[str, Any]:
    dt_s = dt_us * 1e-6 if dt_us is not None else found["dt_s"]
    if dt_s is None:
        raise UsageError("the time between frames A and B is not known: give --dt-us (the files carry no times)")
    if not (np.isfinite(dt_s) and 1e-9 <= dt_s <= 100.0):  # the rig's timing.dt_us range: 1 ns to 100 s
        given = f"--dt-us {dt_us:g}" if dt_us is not None else f"the files' time between frames A and B ({dt_s:g} s)"
        raise UsageError(f"{given} is not a time between frames A and B: it must be from 0.001 us (a nanosecond) "
                         "to 1e8 us (100 s)" + ("" if dt_us is not None else "; give --dt-us"))
    rate = rate_hz if rate_hz is not None else found["rate_hz"]
    if rate is not None and not (np.isfinite(rate) and rate > 0):
        raise UsageError(f"--rate-hz must be positive, got {rate_hz}")
    return {"dt_s": float(dt_s), "rate_hz": None if rate is None else float(rate), "source": "import"}


def _pairs_in_run(cams: list[_Camera]) -> int:
    """Pairs of the run: the most any camera has (a last frame A without its B counts)."""
    return max(len(c.pairs) + bool(c.unpaired) for c in cams)


def _frames_of(c: _Camera, p: int) -> list[tuple[int, FrameSource]]:
    """The frames (0: A, 1: B) camera ``c`` has of pair ``p``, with where they lie."""
    if p < len(c.pairs):
        return [(0, c.pairs[p].a), (1, c.pairs[p].b)]
    if c.unpaired and p == len(c.pairs):
        return [(0, c.unpaired[0])]
    return []


def _lost(cams: list[_Camera], n_pairs: int) -> list[dict[str, Any]]:
    """The drops rows of frames the files do not hold."""
    rows = []
    for c in cams:
        for p in range(len(c.pairs), n_pairs):
            have = {f for f, _ in _frames_of(c, p)}
            for f in (0, 1):
                if f in have:
                    continue
                why = (f"unpaired frame: {c.unpaired[0]} has no frame B after it" if have else
                       f"not in the imported files: {c.pattern} holds {len(c.pairs)} pair(s)")
                rows.append({"camera": c.name, "pair": p, "frame": f, "frame_id": -1, "timestamp_ns": -1,
                             "reason": why})
    return rows


def _plan(cams: list[_Camera], layout: str) -> dict[str, Any]:
    """What the import is made of, to tell a resumed import from one of other files."""
    return {"layout": layout, "cameras": {c.name: {"pattern": c.pattern, "pairs": len(c.pairs),
                                                   "files": sorted({str(s.path.resolve()) for p in c.pairs
                                                                    for s in (p.a, p.b)}
                                                                   | {str(s.path.resolve()) for s in c.unpaired})}
                                          for c in cams}}


def _open_or_create(rig: Rig, out: Path, n_pairs: int, timing: dict[str, Any], plan: dict[str, Any], *,
                    overwrite: bool, skip_done: bool) -> tuple[RunStore, int]:
    """The store to import into and the pairs it holds already (with ``skip_done``)."""
    if skip_done and out.exists() and not overwrite:
        store = RunStore.open(out, mode="r+")
        made = store.attrs.get("import")
        if made is None:
            raise UsageError(f"{out} is not an imported run; give another --out, or --overwrite to replace it")
        if made.get("plan") != plan or store.n_pairs != n_pairs:
            raise UsageError(f"{out} was imported from other files or with another layout; give the same --frames "
                             "and --layout to go on, or --overwrite to import again")
        return store, store.committed_pairs
    RunStore.check_new(out, overwrite=overwrite)
    store = RunStore.create(out, rig, n_pairs, timing=timing, software_version=__version__, overwrite=overwrite)
    store.group.attrs.update({"hardware": "import", "import": {"plan": plan, "sources": []}})
    return store, 0


def import_files(rig: Rig, out: str | os.PathLike[str], *, frames: Mapping[str, str],
                 frames_b: Mapping[str, str] | None = None, davis: Mapping[str, str] | None = None,
                 layout: str = "interleaved", dt_us: float | None = None, rate_hz: float | None = None,
                 overwrite: bool = False, skip_done: bool = False, progress: bool = True,
                 checksum: str = "crc32c", threads: int | None = None) -> ImportResult:
    """Make a run store of the image files of every camera of ``rig``.

    Parameters
    ----------
    rig
        The rig the files were recorded with (cameras' ``sensor_px`` and ``bit_depth``).
    out
        The run store to create.
    frames
        Camera name -> glob pattern, folder or DaVis set of its files (natural order,
        ``img2`` before ``img10``); frames A for ``layout = "separate"``.
    frames_b
        Camera name -> the files of frames B, for ``layout = "separate"``.
    davis
        Camera name -> a DaVis set (``.set`` or its folder) of double-frame images, read with
        lvpyio; dt and rate come from its frame times where it has them. One set named for
        several cameras holds each camera's frames in turn.
    layout
        ``"interleaved"`` (files alternate A, B), ``"double-frame"`` (each file holds both
        frames: two pages, or one image twice the sensor's height) or ``"separate"``.
    dt_us
        Time between frames A and B, us (required unless DaVis files carry it).
    rate_hz
        Pairs per second (None: unknown, unless DaVis files carry it).
    overwrite
        Replace an existing run store at ``out``.
    skip_done
        Go on with an interrupted import of the same files into ``out``.
    progress
        Show a progress bar on stderr.
    checksum
        The checksum each source file's provenance carries: ``"crc32c"`` (the default: what zarr
        checks its chunks with, hardware-accelerated) or ``"sha256"`` (what ``sha256sum`` prints,
        about six times slower to compute).
    threads
        Frames read and written at once (None: the CPU cores this process may use).

    Returns
    -------
    ImportResult

    Raises
    ------
    UsageError
        A file that cannot be imported (corrupt, truncated, of another size than the sensor,
        of more bits than the camera, a set of mixed sizes), a camera without files, a missing
        dt, an existing store: one line naming the file or option and the fix. A file found
        unreadable only while importing leaves the committed pairs, with ``state = "aborted"``.
    """
    out = Path(out)
    if checksum not in CHECKSUMS:
        raise UsageError(f"--checksum must be one of {', '.join(CHECKSUMS)}, got '{checksum}'")
    cams, found = _sources_of(rig, frames, frames_b, davis, layout)
    stamps = _stamps(cams)  # as the files were checked: one that changes from now on is refused
    timing = _timing(dt_us, rate_hz, found)
    n_pairs = _pairs_in_run(cams)
    plan = {**_plan(cams, layout), "checksum": checksum}
    store, done = _open_or_create(rig, out, n_pairs, timing, plan, overwrite=overwrite, skip_done=skip_done)
    timing = store.timing
    if done == 0:
        lost = _lost(cams, n_pairs)
        if lost:
            store.add_drops(lost)
    started = time.perf_counter()
    try:
        read = _copy(store, cams, done, n_pairs, progress=progress, threads=threads or max(2, cpu_threads()),
                     checksum=checksum, stamps_at_start=stamps)
    except BaseException as exc:
        if done == 0 and store.committed_pairs == 0:
            # nothing imported yet: the store this call made is removed, not left half-written
            shutil.rmtree(store.path, ignore_errors=True)
            raise
        reason = str(exc) if isinstance(exc, UsageError) else f"interrupted ({type(exc).__name__})"
        store.group.attrs.update({"abort_reason": reason})
        store.set_state("aborted")
        if isinstance(exc, UsageError):
            raise UsageError(f"{exc}; the {store.committed_pairs} pair(s) imported before are kept in {out} (state "
                             "'aborted'): fix the file, then import again with --skip-done") from None
        raise
    store.set_state("complete")
    return ImportResult(store=store, pairs=n_pairs, imported=n_pairs - done, drops=len(store.drops()),
                        bytes_read=read, seconds=time.perf_counter() - started, timing=timing)


#: A file that holds more frames than this is read frame by frame (a long TIFF stack does not
#: fit in memory whole), its checksum in a pass of its own.
FRAMES_READ_WHOLE = 2


def _stamp(path: Path) -> tuple[int, int]:
    """(size, time of last change in ns) of a source file, to tell whether it changed."""
    st = os.stat(path)
    return st.st_size, st.st_mtime_ns


def _stamps(cams: list[_Camera]) -> dict[Path, tuple[int, int]]:
    """:func:`_stamp` of every source file of every camera, taken when the files were checked."""
    out = {}
    for c in cams:
        for src in [s for p in c.pairs for s in (p.a, p.b)] + list(c.unpaired):
            if src.path not in out:
                try:
                    out[src.path] = _stamp(src.path)
                except OSError as exc:
                    raise UsageError(f"{src.path} cannot be examined ({exc.strerror or exc}); check the file") from None
    return out


@contextlib.contextmanager
def _unchanged(path: Path, stamps: dict[Path, tuple[int, int]]) -> Iterator[None]:
    """Inside, ``path`` is read; a :class:`FormatError` if it is not as it was when the files were
    checked (``stamps``), before or after: a file still being written, or replaced, is never
    imported half old and half new."""
    def check() -> None:
        try:
            now = _stamp(path)
        except OSError as exc:
            raise FormatError(f"{path} cannot be examined any more ({exc.strerror or exc}): was it moved or deleted "
                              "during the import? import again once the recording is in place") from None
        if now != stamps.get(path, now):
            raise FormatError(f"{path} changed during the import ({stamps[path][0]} bytes when the files were "
                              f"checked, {now[0]} now, or written since); import again once nothing writes to the "
                              "recording")
    check()
    yield
    check()


def _copy(store: RunStore, cams: list[_Camera], first: int, n_pairs: int, *, progress: bool, threads: int,
          checksum: str, stamps_at_start: dict[Path, tuple[int, int]] | None = None) -> int:
    """Read pairs ``first .. n_pairs - 1`` of every camera and write them; returns bytes read.

    One task per source file of up to :data:`FRAMES_READ_WHOLE` frames (read once, for pixels and
    checksum); larger files a task per frame and one for the checksum. Several tasks run at once.
    A pair is committed once every camera's frames of it, and every pair before it, are written;
    ids, time stamps, provenance and the commit are written every :data:`FLUSH_S` and at the end.
    """
    from lfpiv.formats.images import read_frame, source_file

    stamps_at_start = _stamps(cams) if stamps_at_start is None else stamps_at_start
    writers = {c.name: FrameWriter(store.frames(c.name)) for c in cams}
    rate, dt = store.timing.get("rate_hz"), float(store.timing["dt_s"])
    made = dict(store.attrs["import"])
    sources: list[dict[str, Any]] = list(made.get("sources", []))
    seen = {s["path"] for s in sources}
    by_file: dict[Path, list[tuple[_Camera, int, int, FrameSource]]] = {}
    for c in cams:
        for p in range(first, n_pairs):
            for f, src in _frames_of(c, p):
                by_file.setdefault(src.path, []).append((c, p, f, src))
    left = {p: 0 for p in range(first, n_pairs)}  # frames still to write per pair
    for frames in by_file.values():
        for _, p, _, _ in frames:
            left[p] += 1
    ids = {c.name: np.full((n_pairs, 2), -1, np.int64) for c in cams}
    stamps = {c.name: np.full((n_pairs, 2), -1, np.int64) for c in cams}

    def write(frames: list[tuple[_Camera, int, int, FrameSource]], images: list[np.ndarray]) -> list:
        for (c, p, f, _), img in zip(frames, images, strict=True):
            writers[c.name].write(p, f, img)
        return [(c.name, p, f) for c, p, f, _ in frames]

    def whole(path: Path, frames: list) -> tuple[dict[str, Any] | None, list]:
        cam = frames[0][0]
        with _unchanged(path, stamps_at_start):
            images, prov = read_sources(path, [s for *_, s in frames], sensor_px=cam.sensor_px,
                                        bit_depth=cam.bit_depth, checksum=checksum)
        return prov.to_dict(), write(frames, images)

    def one_frame(frame: tuple[_Camera, int, int, FrameSource]) -> tuple[None, list]:
        c = frame[0]
        with _unchanged(frame[3].path, stamps_at_start):
            image = read_frame(frame[3], sensor_px=c.sensor_px, bit_depth=c.bit_depth)
        return None, write([frame], [image])

    def digest_of(path: Path) -> tuple[dict[str, Any], list]:
        with _unchanged(path, stamps_at_start):
            return source_file(path, checksum=checksum).to_dict(), []

    tasks: list[tuple[Any, ...]] = []
    for path in sorted(by_file, key=lambda q: min(p for _, p, _, _ in by_file[q])):
        frames = by_file[path]
        if len(frames) <= FRAMES_READ_WHOLE:
            tasks.append((whole, path, frames))
        else:
            tasks += [(one_frame, fr) for fr in frames] + [(digest_of, path)]
    committed, read, last_flush = first, 0, time.monotonic()

    def flush() -> None:
        nonlocal last_flush
        for c in cams:
            store.group[f"{c.name}/frame_id"][first:n_pairs] = ids[c.name][first:n_pairs]
            store.group[f"{c.name}/timestamp_ns"][first:n_pairs] = stamps[c.name][first:n_pairs]
        store.group.attrs["import"] = {**made, "sources": sources}
        store.commit(committed)
        last_flush = time.monotonic()

    def settle(fut: Future) -> None:
        nonlocal committed, read
        prov, written = fut.result()
        if prov is not None:
            log.debug("read %s (%d bytes, %s %s)", prov["path"], prov["size"], checksum, prov[checksum])
            read += prov["size"]
            if prov["path"] not in seen:
                sources.append(prov)
                seen.add(prov["path"])
        for name, p, f in written:
            ids[name][p, f] = 2 * p + f
            # ns from the first pair's frame A, as a synthetic run's (unknown rate: dt only)
            stamps[name][p, f] = round(((p / rate) if rate else 0.0) * 1e9 + f * dt * 1e9)
            left[p] -= 1
        while committed < n_pairs and left[committed] <= 0:
            committed += 1
            bar.update(1)

    with (ThreadPoolExecutor(max_workers=threads, thread_name_prefix="lfpiv-import") as pool,
          tqdm(total=n_pairs - first, unit="pair", disable=not progress, desc="importing", leave=False) as bar):
        pending: list[Future] = []
        try:
            for task in tasks:
                pending.append(pool.submit(*task))
                if len(pending) >= 2 * threads:  # read ahead, a bounded number of frames in memory
                    settle(pending.pop(0))
                if time.monotonic() - last_flush > FLUSH_S:
                    flush()
            while pending:
                settle(pending.pop(0))
        except FormatError as exc:
            raise UsageError(str(exc)) from None
        finally:
            for fut in pending:
                fut.cancel()
            for fut in pending:  # a write under way finishes (its chunk is whole) before the last flush
                if not fut.cancelled():
                    try:
                        fut.exception()
                    except BaseException:  # noqa: BLE001 - the error that stopped the import is reported
                        pass
            try:
                flush()
            except (OSError, RunStoreError):
                pass
    return read
