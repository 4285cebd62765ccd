"""The pair ring buffer: slots, overruns and the live path's zero-copy view."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.ring import PairRing


def _img(v: int) -> np.ndarray:
    return np.full((4, 5), v, dtype=np.uint16)


def test_frames_land_in_the_slot_of_their_pair() -> None:
    ring = PairRing({"a": (4, 5), "b": (4, 5)}, slots=4)
    assert ring.put("a", 6, 1, _img(7), frame_id=13, timestamp_ns=99)
    s = ring.slot_of(6)
    assert s == 6 % 4
    assert (ring.data["a"][s, 1] == 7).all()
    assert ring.frame_id["a"][s].tolist() == [-1, 13]
    assert ring.timestamp_ns["a"][s, 1] == 99


def test_a_full_ring_counts_overruns_instead_of_overwriting() -> None:
    ring = PairRing({"a": (4, 5)}, slots=2)
    assert ring.put("a", 0, 0, _img(1), 0, 0)
    assert ring.put("a", 1, 0, _img(2), 2, 0)
    # Pair 2 needs pair 0's slot, which the recorder has not released yet.
    assert not ring.put("a", 2, 0, _img(3), 4, 0)
    assert ring.overruns == 1
    assert (ring.data["a"][0, 0] == 1).all()
    ring.release(0)
    assert ring.put("a", 2, 0, _img(3), 4, 0)
    assert (ring.data["a"][0, 0] == 3).all()


def test_latest_is_a_zero_copy_view_invalidated_by_reuse() -> None:
    ring = PairRing({"a": (4, 5)}, slots=2)
    assert ring.latest() is None
    for k in range(2):
        ring.put("a", 0, k, _img(10 + k), k, 100 + k)
    ring.publish(0)
    view = ring.latest()
    assert view is not None and view.pair == 0
    assert np.shares_memory(view.frames["a"], ring.data["a"])
    assert view.frames["a"][1, 0, 0] == 11 and view.frame_id["a"].tolist() == [0, 1]
    ring.release(0)
    assert ring.still_valid(view)  # released but not yet reused: the data is intact
    ring.put("a", 2, 0, _img(5), 4, 0)  # the recorder side reuses the slot
    assert not ring.still_valid(view)


def test_ring_needs_two_slots() -> None:
    with pytest.raises(ValueError, match="at least 2 slots"):
        PairRing({"a": (4, 5)}, slots=1)
