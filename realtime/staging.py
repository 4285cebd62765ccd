"""Staging pairs for the live pipeline: out of the ring, into host slots, onto the device.

It runs beside the recorder and never slows it. A feeder thread copies the newest complete
pair out of the session's :class:`~acquisition.ring.PairRing` into a host staging slot (pinned
memory on a GPU machine; the only time it touches the ring, a memcpy), checks the slot's
generation (the ring's seqlock) and discards the copy if the recorder's side reused the slot
meanwhile. Pairs that arrived since the last one taken are skipped and counted; a newer pair
replaces a ready one not yet picked up. The copy of the next pair thus overlaps the work on the
current one, and on a GPU so does its upload: the next pair's upload starts on a CUDA stream of
its own while the current pair's kernels run, and the device waits for it with an event, not
the host.

The pipeline's thread takes pairs with :meth:`Staging.next_pair`; the processing of a pair
(:mod:`realtime.processing`) tells the staging when the device has consumed its frames
(:meth:`Staging.consumed`), gives its host slot back (:meth:`Staging.release`) and starts the
next upload between its kernels (:meth:`Staging.prefetch`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from acquisition.ring import PairView

__all__ = ["HostSlot", "PairSource", "StagedPair", "Staging"]


class PairSource(Protocol):
    """Where pairs come from: :class:`acquisition.ring.PairRing` (or anything like it)."""

    cameras: list[str]

    def latest(self) -> PairView | None: ...

    def still_valid(self, view: PairView) -> bool: ...


@dataclass(eq=False)
class HostSlot:
    """Host staging for one pair: (2, n_pixels) uint16 frames, pinned on a GPU machine."""

    host: object  # warp.array on the CPU
    frames: np.ndarray  # its NumPy view
    view: PairView | None = None
    source: object = None
    copy_s: float = 0.0


@dataclass(eq=False)
class StagedPair:
    """A pair on its way to the device: the slot, the device frames, the upload's event."""

    slot: HostSlot
    raw: object  # (2, n_pixels) uint16 warp.array on the device
    buffer: int  # which device buffer (-1 on the CPU, where the slot itself is used)
    uploaded: object = None  # warp.Event on a GPU
    released: bool = False  # the host slot was given back


class Staging:
    """The feeder thread, the host slots, the hand-over of the newest pair and its upload.

    Parameters
    ----------
    cameras
        The cameras whose frames are staged, in the order of the flat frames.
    lock
        The pipeline's lock: it guards :attr:`source`, :attr:`last_taken`, :attr:`skipped` and
        :attr:`discarded`, which the pipeline's counters read under it.
    stop, paused
        The pipeline's events: the feeder ends on ``stop`` and takes nothing while ``paused``.
    poll_s
        How often to look for a new pair while waiting.

    Attributes
    ----------
    source
        The ring pairs are taken from (None: none).
    last_taken
        The newest pair taken from ``source``, or -1.
    skipped, discarded
        Pairs skipped (newer ones were there) and discarded (overwritten during the copy).
    """

    def __init__(self, cameras: Sequence[str], *, lock: threading.Lock, stop: threading.Event,
                 paused: threading.Event, poll_s: float) -> None:
        self.cameras = list(cameras)
        self.lock = lock
        self.poll_s = poll_s
        self._stop = stop
        self._paused = paused
        self.source: PairSource | None = None
        self.last_taken = -1
        self.skipped = self.discarded = 0
        self._layout: Any = None  # the reconstructor: where each camera's pixels lie, its device
        # Host slots the feeder thread fills with the newest pair, the one pair ready for the
        # pipeline, and the one already on its way to the device.
        self._slots_cv = threading.Condition()
        self._free: list[HostSlot] = []
        self._ready: HostSlot | None = None
        self._prefetched: StagedPair | None = None
        self._feeder: threading.Thread | None = None

    def attach(self, source: PairSource | None) -> None:
        """Take pairs from ``source`` from now on (a new recording's ring), or from nothing."""
        with self.lock:
            self.source = source
            self.last_taken = -1

    def build(self, layout: Any) -> None:
        """Allocate the host slots and, on a GPU, the copy stream, device buffers and events.

        ``layout`` is the live reconstructor: its ``camera_image`` (where each camera's pixels
        lie in the flat frames), ``projector.n_pixels``, ``wp`` and ``device``.
        """
        wp, n = layout.wp, layout.projector.n_pixels
        gpu = layout.device != "cpu"
        # Four host slots: one being filled, one ready, one prefetched, one being preprocessed.
        for _ in range(4):
            host = wp.empty((2, n), dtype=wp.uint16, device="cpu", pinned=gpu)
            self._free.append(HostSlot(host=host, frames=host.numpy()))
        if gpu:
            # Uploads run on a stream of their own so that the next pair's copy overlaps the
            # kernels of the current one; two device buffers alternate between them.
            self._copy_stream = wp.Stream(layout.device)
            self._dev_raw = [wp.empty((2, n), dtype=wp.uint16, device=layout.device) for _ in range(2)]
            self._uploaded = [wp.Event(layout.device) for _ in range(2)]
            self._consumed = [wp.Event(layout.device) for _ in range(2)]
            self._next_buffer = 0
        self._layout = layout

    # --- the feeder thread --------------------------------------------------------------------------
    def start(self) -> None:
        """Start the feeder thread (after :meth:`build`)."""
        self._feeder = threading.Thread(target=self._feed, name="lfpiv-live-feed", daemon=True)
        self._feeder.start()

    def stop(self, timeout_s: float) -> None:
        """Wake whoever waits for a slot and let the feeder end (the pipeline's ``stop`` is set)."""
        with self._slots_cv:
            self._slots_cv.notify_all()
        if self._feeder is not None:
            self._feeder.join(timeout_s)

    def _feed(self) -> None:
        """Copy the newest pair not yet taken into a free host slot and make it the ready one.

        Runs on a thread of its own with host work only (a memcpy out of the ring), so the copy
        of the next pair overlaps the processing of the current one. A newer pair replaces a
        ready one that the pipeline has not yet picked up (that one counts as skipped): the
        pipeline always starts on the newest complete pair.
        """
        while not self._stop.is_set():
            if self._paused.is_set():
                self._stop.wait(0.05)
                continue
            with self.lock:
                src, last = self.source, self.last_taken
            view = src.latest() if src is not None else None
            if view is None or view.pair <= last:
                self._stop.wait(self.poll_s)
                continue
            with self._slots_cv:
                slot = self._free.pop() if self._free else None
                if slot is None:
                    self._slots_cv.wait(self.poll_s)
                    continue
            t0 = time.perf_counter()
            rc = self._layout
            for k, c in enumerate(self.cameras):
                for f in (0, 1):
                    np.copyto(rc.camera_image(slot.frames, f, k), view.frames[c][f])
            ok = src.still_valid(view)  # type: ignore[union-attr]
            slot.view, slot.source, slot.copy_s = view, src, time.perf_counter() - t0
            with self.lock:
                current = self.source is src
                if current:
                    self.skipped += view.pair - last - 1
                    self.last_taken = view.pair
                    if not ok:
                        self.discarded += 1
            if not (current and ok):
                self._free_slot(slot)
                continue
            with self._slots_cv:
                replaced, self._ready = self._ready, slot
                if replaced is not None:
                    self._free.append(replaced)
                self._slots_cv.notify_all()
            if replaced is not None:
                with self.lock:
                    self.skipped += 1

    def _free_slot(self, slot: HostSlot) -> None:
        slot.view = slot.source = None
        with self._slots_cv:
            self._free.append(slot)
            self._slots_cv.notify_all()

    # --- the hand-over, on the pipeline's thread ----------------------------------------------------
    def wait_for_ready(self) -> None:
        """Wait up to ``poll_s`` for the feeder to make a pair ready (unless one is, or the
        pipeline stops)."""
        with self._slots_cv:
            if self._ready is None and not self._stop.is_set():
                self._slots_cv.wait(self.poll_s)

    def _upload(self, slot: HostSlot) -> StagedPair:
        """Start the slot's frames on their way to the device (on the GPU: the copy stream)."""
        rc = self._layout
        assert rc is not None
        if rc.device == "cpu":
            return StagedPair(slot=slot, raw=slot.host, buffer=-1)
        i = self._next_buffer
        self._next_buffer ^= 1
        s = self._copy_stream
        s.wait_event(self._consumed[i])  # the pair before last has been preprocessed out of buffer i
        rc.wp.copy(self._dev_raw[i], slot.host, stream=s)
        s.record_event(self._uploaded[i])
        return StagedPair(slot=slot, raw=self._dev_raw[i], buffer=i, uploaded=self._uploaded[i])

    def release(self, staged: StagedPair) -> None:
        """The pair's host slot is free once its upload is done (once only)."""
        if staged.released:
            return
        staged.released = True
        if staged.uploaded is not None:
            self._layout.wp.synchronize_event(staged.uploaded)
        self._free_slot(staged.slot)

    def _claim_ready(self) -> HostSlot | None:
        with self._slots_cv:
            slot, self._ready = self._ready, None
        if slot is not None and slot.source is not self.source:  # from a recording since detached
            self._free_slot(slot)
            return None
        return slot

    def next_pair(self) -> StagedPair | None:
        """The newest pair: the prefetched one unless a newer one is ready."""
        pre, self._prefetched = self._prefetched, None
        if pre is not None and pre.slot.source is not self.source:  # from a recording since detached
            self.release(pre)
            pre = None
        slot = self._claim_ready()
        if pre is None:
            return None if slot is None else self._upload(slot)
        if slot is None:
            return pre
        self.release(pre)  # a newer pair came in since the prefetch: take that one instead
        with self.lock:
            self.skipped += 1
        return self._upload(slot)

    def prefetch(self) -> None:
        """If a pair is ready and none is prefetched, start its upload now (overlapping the
        current pair's kernels on the GPU)."""
        if self._prefetched is None:
            slot = self._claim_ready()
            if slot is not None:
                self._prefetched = self._upload(slot)

    def drop_pending(self) -> None:
        """Give back the ready and the prefetched pair, counting them as skipped."""
        dropped = 0
        pre, self._prefetched = self._prefetched, None
        if pre is not None:
            self.release(pre)
            dropped += 1
        with self._slots_cv:
            slot, self._ready = self._ready, None
        if slot is not None:
            self._free_slot(slot)
            dropped += 1
        if dropped:
            with self.lock:
                self.skipped += dropped

    # --- the device's side of a pair ----------------------------------------------------------------
    def device_waits_for_upload(self, staged: StagedPair) -> None:
        """Kernels launched from now on wait for the pair's upload on the device, not the host."""
        if staged.uploaded is not None:
            rc = self._layout
            rc.wp.get_stream(rc.device).wait_event(staged.uploaded)

    def consumed(self, staged: StagedPair) -> None:
        """The kernels launched so far read the pair's device frames: once they ran, its device
        buffer may take the pair after next."""
        if staged.buffer >= 0:
            rc = self._layout
            rc.wp.get_stream(rc.device).record_event(self._consumed[staged.buffer])
