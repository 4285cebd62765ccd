"""Synchronised double-frame recording of several cameras into a run store.

One grabber thread per camera fetches frames (oldest first, with a timeout) and places each in
the ring slot of its pair; pair and frame come from the frame counter
(``pair, frame = divmod(frame_id - first_frame_id + shift, 2)``), so frames of both cameras pair
up by trigger count even when some are lost. A gap in a camera's ``frame_id`` becomes one drop
record per missing frame ("incomplete frame" where the camera's driver counted that many
discarded incomplete images over the gap, "frame_id gap" otherwise); an incomplete frame, a
ring overrun or a frame that never arrives are drops too.

The recorder thread writes pairs to the run store strictly in order as soon as each is
settled (every frame of every camera either in the ring or listed as dropped), writing frames
in parallel, then advances ``committed_pairs``. Nothing is lost silently: for every triggered
frame there is a recorded image or a row in ``drops``.

Missed triggers. A trigger the camera missed makes no frames, so ``frame_id`` stays
consecutive and every later frame would land one pair early. Where frames carry the camera's
own time stamps (``Frame.device_clock``) and the trigger period is known, each complete frame
is compared with the camera's last complete frame of the same kind (A with A, B with B): the
time between them in trigger periods, rounded, is the number of triggers between them. More
triggers than pairs of ``frame_id`` means missed triggers: their pairs are listed as dropped
("missed trigger") and ``shift`` grows by 2 for each, so the frame goes to the pair of the
trigger that made it (the ``frame_id`` recorded for later pairs is then offset by 2 per missed
trigger). Fewer triggers than pairs of ``frame_id`` (frames without a trigger, or a clock
that jumped) cannot be put right and stop the recording with a :class:`DeviceError`. Both
frames of a pair must come from one trigger (a double-exposure camera). Not detectable: a
trigger missed before a camera's first complete time-stamped frame, and any missed by a
camera with host time stamps; there the later frames stay one pair early and the last pair
shows as not delivered.

Crash safety: zarr writes every chunk and metadata document atomically (a temporary file moved
into place), and ``committed_pairs`` moves only after a pair's frames, ids and drops are on disk,
so after a hard kill every committed pair reads back intact and ``state`` still says
"recording".
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from acquisition.protocols import Camera, DeviceError, Frame
from acquisition.ring import PairRing
from lfcore.runstore import FrameWriter, RunStore

__all__ = ["RecordingSession", "SessionStats"]

_log = logging.getLogger(__name__)

_PENDING, _IN_RING, _DROPPED = 0, 1, 2


def _incomplete_count(cam: Camera) -> int | None:
    """Incomplete images the camera's driver discarded so far, where it counts them."""
    n = getattr(cam, "incomplete_frames", None)
    return n if isinstance(n, int) and not isinstance(n, bool) else None


def _gap_reason(gap: int, incomplete: int) -> str:
    """Drop reason of the frames of a ``frame_id`` gap of ``gap`` frames while the camera's
    discarded-incomplete counter rose by ``incomplete``."""
    if incomplete >= gap:
        return "incomplete frame: discarded by the camera driver (lost packets)"
    if incomplete > 0:
        return (f"frame_id gap: {incomplete} of these {gap} frames came incomplete and were discarded by the "
                "camera driver, the rest were lost in camera or transport")
    return "frame_id gap: lost in camera or transport"


@dataclass(frozen=True)
class SessionStats:
    """A snapshot of a recording, for progress lines and the monitor.

    Attributes
    ----------
    committed_pairs
        Pairs written and committed to the run store.
    frames_recorded, frames_dropped
        Frames written, and frames listed in ``drops`` (including pending drops of pairs not
        yet committed).
    overruns
        Frames lost because the recorder fell a whole ring behind.
    extra_frames
        Frames delivered beyond the requested pairs (ignored, not recorded).
    elapsed_s
        Seconds since :meth:`RecordingSession.start`.
    pair_rate_hz
        Committed pairs per second since the first commit.
    late_frames
        Frames that arrived after their place was settled (already listed as not delivered,
        or a repeat); ignored, not recorded: each one's place holds a recorded frame or a drop
        row already.
    missed_triggers
        Triggers a camera made no frames for, found from its time stamps (summed over the
        cameras); their frames are in ``frames_dropped``.
    """

    committed_pairs: int
    frames_recorded: int
    frames_dropped: int
    overruns: int
    extra_frames: int
    elapsed_s: float
    pair_rate_hz: float
    late_frames: int = 0
    missed_triggers: int = 0


class RecordingSession:
    """Record ``n_pairs`` double-frame pairs from ``cameras`` into ``store``.

    Parameters
    ----------
    cameras
        Opened and configured cameras; their names match the store's cameras.
    store
        A run store created for these cameras with at least ``n_pairs`` pairs.
    n_pairs
        Pairs to record.
    ring_slots
        Pairs the ring holds (how far the recorder may fall behind).
    fetch_timeout_s
        Timeout of each fetch; bounds how quickly the grabbers notice a stop.
    writer_threads
        Threads compressing and writing frames in parallel.
    on_commit
        Called with the new ``committed_pairs`` after each commit (recorder thread).
    trigger_period_s
        Time between two triggers (the pulse generator's T0 period), to find missed triggers
        from device time stamps. None: ``1 / rate_hz`` of the run store's ``timing`` where it
        has one, else missed triggers are not looked for.
    """

    #: Most pairs written by one zarr call per camera.
    MAX_BATCH = 8

    def __init__(self, cameras: Sequence[Camera], store: RunStore, n_pairs: int, *, ring_slots: int = 32,
                 fetch_timeout_s: float = 0.1, writer_threads: int = 4,
                 on_commit: Callable[[int], None] | None = None,
                 trigger_period_s: float | None = None) -> None:
        if n_pairs < 1:
            raise ValueError(f"n_pairs must be at least 1, got {n_pairs}")
        if n_pairs > store.n_pairs:
            raise ValueError(f"the run store holds {store.n_pairs} pairs, fewer than the {n_pairs} requested")
        names = [c.name for c in cameras]
        missing = sorted(set(names) - set(store.cameras))
        if missing:
            raise ValueError(f"camera '{missing[0]}' is not in the run store (it has {store.cameras})")
        self.cameras = list(cameras)
        self.store = store
        self.n_pairs = int(n_pairs)
        self.n_frames = 2 * self.n_pairs
        shapes = {c.name: store.frames(c.name).shape[2:] for c in cameras}
        self.ring = PairRing(shapes, slots=ring_slots)
        self.fetch_timeout_s = float(fetch_timeout_s)
        self._cam_index = {n: i for i, n in enumerate(names)}
        self._status = np.zeros((self.n_pairs, len(names), 2), dtype=np.int8)
        self._drops: dict[int, list[dict]] = {}
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._pool = ThreadPoolExecutor(max_workers=max(1, writer_threads), thread_name_prefix="lfpiv-writer")
        self._on_commit = on_commit
        # Array handles opened once: opening one reads its metadata from disk.
        self._frames = {c.name: FrameWriter(store.frames(c.name)) for c in cameras}
        self._ids = {c.name: store.group[f"{c.name}/frame_id"] for c in cameras}
        self._stamps = {c.name: store.group[f"{c.name}/timestamp_ns"] for c in cameras}
        self._next_settle = 0
        self._committed = 0
        self._recorded = 0
        self._dropped = 0
        self._extra = 0
        self._late = 0
        self._started = 0.0
        self._first_commit: float | None = None
        self._last_frame = {n: 0.0 for n in names}
        # Per camera, in places (2 x pair + frame): the next place expected, and the offset
        # added to frame_id - first_frame_id (2 per missed trigger).
        self._expected = {n: 0 for n in names}
        self._shift = {n: 0 for n in names}
        # Per camera and frame kind (A, B): (place, device time stamp, frame_id) of the last
        # complete frame with a device time stamp.
        self._last_stamp: dict[str, list[tuple[int, int, int] | None]] = {n: [None, None] for n in names}
        self._incomplete_seen: dict[str, int | None] = {n: None for n in names}
        self._missed = 0
        # Frames one trigger makes, per camera (2: double exposure; 1: software pairing of
        # consecutive triggers), as the camera's configure() left it.
        self._per_trigger = {c.name: 1 if getattr(c, "frames_per_trigger", 2) == 1 else 2 for c in cameras}
        if trigger_period_s is None:
            rate = store.timing.get("rate_hz")
            trigger_period_s = 1.0 / float(rate) if rate else None
        if trigger_period_s is not None and not (math.isfinite(trigger_period_s) and trigger_period_s > 0):
            raise ValueError(f"trigger_period_s must be positive, got {trigger_period_s}")
        self._period_ns = None if trigger_period_s is None else float(trigger_period_s) * 1e9
        self.error: BaseException | None = None
        self._closed = False

    # --- life cycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Start the cameras, the grabbers and the recorder. Call before arming the laser."""
        self._started = time.monotonic()
        for cam in self.cameras:
            self._incomplete_seen[cam.name] = _incomplete_count(cam)
            cam.start()
            self._last_frame[cam.name] = self._started
        for cam in self.cameras:
            t = threading.Thread(target=self._grab, args=(cam,), name=f"lfpiv-grab-{cam.name}", daemon=True)
            self._threads.append(t)
        rec = threading.Thread(target=self._record, name="lfpiv-recorder", daemon=True)
        self._threads.append(rec)
        for t in self._threads:
            t.start()

    @property
    def done(self) -> bool:
        """True once every requested pair is committed."""
        return self._committed >= self.n_pairs

    @property
    def committed_pairs(self) -> int:
        return self._committed

    def seconds_since_frame(self, camera: str) -> float:
        """Seconds since ``camera`` last delivered a frame (or since start)."""
        return time.monotonic() - self._last_frame[camera]

    def stats(self) -> SessionStats:
        with self._cond:
            elapsed = time.monotonic() - self._started if self._started else 0.0
            rate = 0.0
            if self._first_commit is not None and self._committed > 1:
                span = time.monotonic() - self._first_commit
                rate = (self._committed - 1) / span if span > 0 else 0.0
            return SessionStats(self._committed, self._recorded, self._dropped, self.ring.overruns, self._extra,
                                elapsed, rate, self._late, self._missed)

    def wait(self, timeout_s: float) -> bool:
        """Block until every pair is committed, an error happened, or ``timeout_s`` passed."""
        end = time.monotonic() + timeout_s
        with self._cond:
            while not self.done and self.error is None:
                left = end - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.1))
        return self.done

    def drop_undelivered(self, reason: str, up_to_pair: int | None = None) -> int:
        """List every frame still missing (of pairs ``< up_to_pair``) as dropped with ``reason``.

        Call after the last trigger plus a grace period: those frames will not come, and one that
        still does is ignored (counted in ``late_frames``). Returns the number of frames dropped.
        """
        limit = self.n_pairs if up_to_pair is None else min(self.n_pairs, up_to_pair)
        n = 0
        with self._cond:
            # argwhere lists places in order; the first of a camera's places after its last
            # frame are the ones its driver discarded as incomplete since then, if it counted any
            incomplete = {cam.name: self._incomplete_rise(cam) for cam in self.cameras}
            pending = np.argwhere(self._status[:limit] == _PENDING)
            for pair, ci, frame in pending:
                cam = self.cameras[ci].name
                why = reason
                if incomplete[cam] > 0 and 2 * pair + frame >= self._expected[cam]:
                    incomplete[cam] -= 1
                    why = _gap_reason(1, 1)
                self._add_drop(cam, int(pair), int(frame), -1, why)
                n += 1
            for name in self._expected:  # those places are settled now
                self._expected[name] = max(self._expected[name], 2 * limit)
            self._settle()
        return n

    def close(self, wait_s: float = 30.0) -> None:
        """Stop the cameras and the grabbers, let the recorder write what is settled, release all.

        Pairs not settled stay uncommitted. Safe to call more than once.
        """
        if self._closed:
            return
        self._closed = True
        for cam in self.cameras:
            try:
                cam.stop()
            except Exception:  # noqa: BLE001 - a camera that fails to stop must not stop the others
                pass
        # Grabbers first, so nothing new arrives; then the recorder drains what is settled.
        self._stop.set()
        for t in self._threads[:-1]:
            t.join(timeout=wait_s)
        with self._cond:
            self._cond.notify_all()
        if self._threads:
            self._threads[-1].join(timeout=wait_s)
        self._pool.shutdown(wait=True)

    # --- drops and settlement (caller holds self._cond) -----------------------------------
    def _add_drop(self, camera: str, pair: int, frame: int, frame_id: int, reason: str) -> None:
        self._status[pair, self._cam_index[camera], frame] = _DROPPED
        self._drops.setdefault(pair, []).append({
            "camera": camera, "pair": pair, "frame": frame, "frame_id": frame_id,
            "timestamp_ns": time.time_ns(), "reason": reason,
        })
        self._dropped += 1

    def _incomplete_rise(self, cam: Camera) -> int:
        # Incomplete images the camera's driver discarded since the last look (0 if it does not say).
        now, seen = _incomplete_count(cam), self._incomplete_seen[cam.name]
        self._incomplete_seen[cam.name] = now
        return max(0, now - seen) if now is not None and seen is not None else 0

    def _missed_triggers(self, name: str, place: int, frame: Frame) -> int:
        # Triggers missed between the camera's last frame of this kind and ``frame`` (at ``place``
        # by its frame_id), from the device clock: consecutive frames A (or B) lie one trigger
        # period apart, n periods when n - 1 triggers made no frames.
        if self._period_ns is None or not frame.device_clock or not frame.complete:
            return 0
        step = self._per_trigger[name]
        ref = self._last_stamp[name][place % 2 if step == 2 else 0]
        if ref is None:
            return 0
        ref_place, ref_ns, ref_id = ref
        by_id = (place - ref_place) // step
        by_time = round((frame.timestamp_ns - ref_ns) / self._period_ns)
        if by_time < by_id:
            raise DeviceError(
                f"camera '{name}' time-stamped frame {frame.frame_id} {(frame.timestamp_ns - ref_ns) / 1e6:.3f} ms "
                f"after frame {ref_id}, {by_time} trigger period(s) for {by_id} pair(s) of frame ids: it made frames "
                "without a trigger (or its clock jumped), so its frames can no longer be paired; check its trigger "
                "mode and trigger cable, and that laser.rate_hz is the rate it is triggered at")
        return by_time - by_id

    def _settle(self) -> None:
        # Advance over pairs whose every frame is in the ring or dropped; publish complete ones.
        while self._next_settle < self.n_pairs and not np.any(self._status[self._next_settle] == _PENDING):
            if np.all(self._status[self._next_settle] == _IN_RING):
                self.ring.publish(self._next_settle)
            self._next_settle += 1
        self._cond.notify_all()

    # --- threads --------------------------------------------------------------------------
    def _fail(self, exc: BaseException) -> None:
        with self._cond:
            if self.error is None:
                self.error = exc
            self._cond.notify_all()

    def _grab(self, cam: Camera) -> None:
        name = cam.name
        ci = self._cam_index[name]
        first = cam.first_frame_id
        rows, cols = self.ring.data[name].shape[2:]
        try:
            while not self._stop.is_set():
                frame = cam.fetch(self.fetch_timeout_s)
                if frame is None:
                    continue
                with self._cond:
                    rel = frame.frame_id - first + self._shift[name]  # the frame's place
                    expected = self._expected[name]
                    if frame.frame_id < 0:
                        raise DeviceError(f"camera '{name}' delivers frames without a frame id, and frames are "
                                          "paired by their ids; check its driver (GenTL producer) and firmware")
                    if rel < expected:
                        # a repeat, or a frame already listed as not delivered: its place is
                        # accounted for
                        self._late += 1
                        continue
                    if expected == 0 and rel >= 2 * self.ring.slots:
                        raise DeviceError(
                            f"camera '{name}' numbered its first frame {frame.frame_id}, {rel} after the "
                            f"{first} it should start at: its frame counter did not restart with the "
                            "acquisition, so its frames cannot be paired; power-cycle it or reset its counter")
                    self._last_frame[name] = time.monotonic()
                    step = self._per_trigger[name]
                    missed = self._missed_triggers(name, rel, frame)
                    # the frames of the missed triggers come just before this frame's trigger
                    missed_from = rel - rel % 2 if step == 2 else rel
                    shift = self._shift[name]
                    if missed:
                        if step == 2 and rel % 2 and expected == rel:
                            # frame A of this frame's trigger is already placed, missed pairs too early
                            raise DeviceError(
                                f"camera '{name}': frame {frame.frame_id} (B) is {missed} trigger(s) later than the "
                                f"frame A before it, so that frame A was paired wrongly and its frames can no longer "
                                "be paired; check the camera's time stamps and trigger cable")
                        self._missed += missed
                        self._shift[name] += step * missed
                        rel += step * missed
                        _log.warning("camera '%s' missed %d trigger(s) before frame %d (its time stamps say so); "
                                     "their %d frame(s) are listed as dropped and later frames moved on",
                                     name, missed, frame.frame_id, step * missed)
                    gap = rel - expected - step * missed  # frames whose ids never came
                    incomplete = self._incomplete_rise(cam)
                    gap_reason = _gap_reason(gap, incomplete) if gap else ""
                    for missing in range(expected, min(rel, self.n_frames)):
                        pair, k = divmod(missing, 2)
                        if self._status[pair, ci, k] != _PENDING:
                            continue
                        if missing < missed_from:  # ids before the missed triggers
                            self._add_drop(name, pair, k, first + missing - shift, gap_reason)
                        elif missing < missed_from + step * missed:  # no frame was made
                            self._add_drop(name, pair, k, -1, "missed trigger: the camera made no frames for this "
                                           "trigger (its time stamps say so)")
                        else:  # frame A of this frame B's trigger
                            self._add_drop(name, pair, k, first + missing - self._shift[name], gap_reason)
                    if frame.device_clock and frame.complete:
                        self._last_stamp[name][rel % 2 if step == 2 else 0] = (rel, frame.timestamp_ns, frame.frame_id)
                    self._expected[name] = rel + 1
                    if rel >= self.n_frames:
                        self._extra += 1
                        self._settle()
                        continue
                    pair, k = divmod(rel, 2)
                    reason = None
                    if not frame.complete:
                        reason = "incomplete frame: lost packets"
                    elif frame.data.shape != (rows, cols):
                        reason = f"wrong image size {frame.data.shape}, expected {(rows, cols)}"
                    if reason is not None:
                        self._add_drop(name, pair, k, frame.frame_id, reason)
                        self._settle()
                        continue
                ok = self.ring.put(name, pair, k, frame.data, frame.frame_id, frame.timestamp_ns)
                with self._cond:
                    if self._status[pair, ci, k] != _PENDING:
                        # listed as not delivered while it was copied: the listing stands; a slot
                        # this copy claimed again after the pair was committed is given back
                        self._late += 1
                        if ok and pair < self._committed:
                            self.ring.release(pair)
                    elif ok:
                        self._status[pair, ci, k] = _IN_RING
                    else:
                        self._add_drop(name, pair, k, frame.frame_id,
                                       f"ring overrun: the recorder fell {self.ring.slots} pairs behind")
                    self._settle()
        except Exception as exc:  # noqa: BLE001 - any camera failure ends the recording cleanly
            msg = str(exc) if isinstance(exc, DeviceError) else f"camera '{name}' failed: {type(exc).__name__}: {exc}"
            self._fail(DeviceError(msg))

    def _write_frames(self, first: int, statuses: np.ndarray) -> list[tuple[dict, dict, int]]:
        # Writes the frames of pairs first .. first + len(statuses) - 1, whose ring slots are
        # consecutive; returns per pair the frame ids and timestamps (-1 where dropped) and the
        # number of frames written. A camera whose frames are all present is written in one
        # call (through zarr, its chunks are encoded and stored concurrently), as per-call
        # overhead, not bandwidth, limits small frames.
        n = len(statuses)
        slots = [self.ring.slot_of(first + i) for i in range(n)]
        out = [({}, {}, 0) for _ in range(n)]
        for ci, cam in enumerate(self.cameras):
            name = cam.name
            whole = all(s is not None for s in slots) and bool(np.all(statuses[:, ci] == _IN_RING))
            if whole:
                s0 = slots[0]
                self._frames[name].write_pairs(first, self.ring.data[name][s0:s0 + n])
            for i, s in enumerate(slots):
                ids = np.full(2, -1, dtype=np.int64)
                stamps = np.full(2, -1, dtype=np.int64)
                written = 0
                if s is not None:
                    for k in range(2):
                        if statuses[i, ci, k] == _IN_RING:
                            if not whole:
                                self._frames[name].write(first + i, k, self.ring.data[name][s, k])
                            ids[k] = self.ring.frame_id[name][s, k]
                            stamps[k] = self.ring.timestamp_ns[name][s, k]
                            written += 1
                out[i][0][name], out[i][1][name] = ids, stamps
                out[i] = (out[i][0], out[i][1], out[i][2] + written)
        return out

    def _commit(self, batch: list[tuple[int, tuple]]) -> None:
        # Pairs first..last are on disk: their ids, timestamps and drops follow, then the commit.
        first, last = batch[0][0], batch[-1][0]
        for cam in self.cameras:
            self._ids[cam.name][first:last + 1] = np.stack([r[0][cam.name] for _, r in batch])
            self._stamps[cam.name][first:last + 1] = np.stack([r[1][cam.name] for _, r in batch])
        with self._cond:
            drops = [d for pair in range(first, last + 1) for d in self._drops.pop(pair, [])]
        self.store.add_drops(drops)
        self.store.commit(last + 1)
        with self._cond:
            self._committed = last + 1
            self._recorded += sum(r[2] for _, r in batch)
            if self._first_commit is None:
                self._first_commit = time.monotonic()
            self._cond.notify_all()
        # released after _committed moves, so a grabber that sees the pair committed knows its
        # slot is released or about to be
        for pair in range(first, last + 1):
            self.ring.release(pair)
        if self._on_commit is not None:
            self._on_commit(last + 1)

    def _record(self) -> None:
        inflight: deque[tuple[int, Future]] = deque()
        next_submit = 0
        max_inflight = max(1, self.ring.slots // 2)
        try:
            while True:
                with self._cond:
                    while not (next_submit < self._next_settle and len(inflight) < max_inflight) and not inflight:
                        if self._stop.is_set():
                            return  # nothing settled is left to write
                        self._cond.wait(0.05)
                    submit = []
                    while next_submit < self._next_settle and len(inflight) + len(submit) < max_inflight:
                        # A batch: settled pairs in consecutive ring slots (no wrap-around).
                        room = self.ring.slots - next_submit % self.ring.slots
                        n = min(self._next_settle - next_submit, self.MAX_BATCH, room)
                        submit.append((next_submit, self._status[next_submit:next_submit + n].copy()))
                        next_submit += n
                # Frames of several batches compress and write in parallel ...
                for first, statuses in submit:
                    inflight.append((first, self._pool.submit(self._write_frames, first, statuses)))
                # ... and pairs are committed strictly in order, in batches of those already on
                # disk, so the per-commit metadata writes do not limit the pair rate.
                first, fut = inflight.popleft()
                batch = list(enumerate(fut.result(), start=first))
                while inflight and inflight[0][1].done():
                    first, fut = inflight.popleft()
                    batch += list(enumerate(fut.result(), start=first))
                self._commit(batch)
        except Exception as exc:  # noqa: BLE001 - a failing disk ends the recording cleanly
            # the real cause and where (zarr's writes on a full disk name no file)
            why = (f"{exc.strerror}: {exc.filename or self.store.path}" if isinstance(exc, OSError) and exc.strerror
                   else f"{type(exc).__name__}: {exc}")
            self._fail(RuntimeError(f"writing the run store failed ({why}); check free space and permissions"))
