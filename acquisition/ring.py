"""The pair ring buffer shared by the recorder and the live pipeline (docs/development.md, "Data flow").

A fixed number of slots, each holding one double-frame pair of every camera, allocated once
before the first trigger. The camera grabbers copy each frame straight into the slot of its
pair; the recorder writes settled pairs to the run store in order and then releases their slots;
the live pipeline reads the newest complete pair in place (zero copy) and never holds a slot:
it checks the slot's generation after use and drops its result if the recorder's side reused
the slot meanwhile (a seqlock). So the live path can never slow the recorder, and a recorder
that falls ``slots`` pairs behind makes the grabbers count overruns instead of blocking them.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

__all__ = ["PairRing", "PairView"]


@dataclass(frozen=True)
class PairView:
    """A read-only, zero-copy view of one complete pair in the ring.

    Attributes
    ----------
    pair
        Pair index in the run.
    frames
        Per camera, the uint16 (2, rows, columns) frames A and B (views into the ring).
    frame_id, timestamp_ns
        Per camera, the (2,) frame ids and timestamps.
    slot, generation
        Where the pair lives, and the slot's generation when the view was taken; see
        :meth:`PairRing.still_valid`.
    """

    pair: int
    frames: dict[str, np.ndarray]
    frame_id: dict[str, np.ndarray]
    timestamp_ns: dict[str, np.ndarray]
    slot: int
    generation: int


class PairRing:
    """Preallocated slots for double-frame pairs of several cameras.

    Parameters
    ----------
    shapes
        Image shape of each camera.
    slots
        Number of pairs the ring holds; how far the recorder may fall behind the cameras.
    """

    def __init__(self, shapes: dict[str, tuple[int, int]], slots: int = 32) -> None:
        if slots < 2:
            raise ValueError(f"a ring needs at least 2 slots, got {slots}")
        self.cameras = list(shapes)
        self.slots = int(slots)
        self.data = {c: np.zeros((slots, 2, *shape), dtype=np.uint16) for c, shape in shapes.items()}
        self.frame_id = {c: np.full((slots, 2), -1, dtype=np.int64) for c in shapes}
        self.timestamp_ns = {c: np.full((slots, 2), -1, dtype=np.int64) for c in shapes}
        self._holder = np.full(slots, -1, dtype=np.int64)  # pair held by each slot, -1 free
        self._generation = np.zeros(slots, dtype=np.int64)
        self._lock = threading.Lock()
        self._latest: int = -1
        self.overruns = 0

    @property
    def nbytes(self) -> int:
        """Bytes of image memory the ring holds."""
        return sum(a.nbytes for a in self.data.values())

    def _claim(self, pair: int) -> int | None:
        # Caller holds the lock. A slot is reusable once the recorder released it.
        s = pair % self.slots
        held = self._holder[s]
        if held == pair:
            return s
        if held == -1:
            self._holder[s] = pair
            self._generation[s] += 1
            for c in self.cameras:
                self.frame_id[c][s] = -1
                self.timestamp_ns[c][s] = -1
            return s
        return None

    def put(self, camera: str, pair: int, frame: int, image: np.ndarray, frame_id: int, timestamp_ns: int) -> bool:
        """Copy one frame into the slot of its pair.

        Returns
        -------
        bool
            False on overrun: the slot still holds an older pair the recorder has not written
            (the caller records the frame as dropped). The overrun is counted.
        """
        with self._lock:
            s = self._claim(pair)
            if s is None:
                self.overruns += 1
                return False
        # The slot belongs to this pair until the recorder releases it, and each (camera, frame)
        # is written by one grabber only, so the copy needs no lock.
        self.data[camera][s, frame] = image
        with self._lock:
            self.frame_id[camera][s, frame] = frame_id
            self.timestamp_ns[camera][s, frame] = timestamp_ns
        return True

    def slot_of(self, pair: int) -> int | None:
        """The slot holding ``pair``, or None."""
        s = pair % self.slots
        with self._lock:
            return s if self._holder[s] == pair else None

    def release(self, pair: int) -> None:
        """The recorder is done with ``pair``: its slot may be reused (data stays until then)."""
        s = pair % self.slots
        with self._lock:
            if self._holder[s] == pair:
                self._holder[s] = -1

    def publish(self, pair: int) -> None:
        """Mark ``pair`` complete (every frame of every camera present) for :meth:`latest`."""
        with self._lock:
            if pair > self._latest:
                self._latest = pair

    def latest(self) -> PairView | None:
        """The newest complete pair still in the ring, or None.

        The view is zero-copy; after using it call :meth:`still_valid` and discard the result
        if it returns False.
        """
        with self._lock:
            pair = self._latest
            if pair < 0:
                return None
            s = pair % self.slots
            if self._holder[s] not in (pair, -1):
                return None
            gen = int(self._generation[s])
            return PairView(
                pair=pair,
                frames={c: self.data[c][s] for c in self.cameras},
                frame_id={c: self.frame_id[c][s].copy() for c in self.cameras},
                timestamp_ns={c: self.timestamp_ns[c][s].copy() for c in self.cameras},
                slot=s,
                generation=gen,
            )

    def still_valid(self, view: PairView) -> bool:
        """True if nothing overwrote the pair of ``view`` since it was taken."""
        with self._lock:
            return int(self._generation[view.slot]) == view.generation
