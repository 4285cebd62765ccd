"""The run store's I/O in a background thread: order, errors, and what is finished on the way out."""

from __future__ import annotations

import threading

import pytest

from lfpiv.overlap import WriteBehind, prefetched


def test_writes_run_in_order_in_the_background_one_at_a_time():
    written, threads = [], set()
    release = threading.Event()

    def write(i):
        threads.add(threading.get_ident())
        if i == 0:
            assert release.wait(5)  # the caller goes on while this write is under way
        written.append(i)

    with WriteBehind() as w:
        w.submit(write, 0)
        assert written == []
        release.set()
        w.submit(write, 1)  # waits for write 0 first
        assert written[0] == 0
        w.submit(write, 2)
    assert written == [0, 1, 2]
    assert threading.get_ident() not in threads


def test_a_write_error_is_raised_by_the_next_call():
    def fail(_):
        raise OSError("disk full")

    later = []
    with pytest.raises(OSError, match="disk full"), WriteBehind() as w:
        w.submit(fail, 0)
        w.submit(later.append, 1)
    assert later == []  # not started after the failure
    with pytest.raises(OSError, match="disk full"), WriteBehind() as w:
        w.submit(fail, 1)  # raised on leaving


def test_leaving_on_an_error_finishes_the_write_under_way_and_keeps_the_first_error():
    done = []
    with pytest.raises(KeyboardInterrupt), WriteBehind() as w:
        w.submit(done.append, "volume 0")
        raise KeyboardInterrupt
    assert done == ["volume 0"]

    def fail(_):
        raise OSError("disk full")

    with pytest.raises(ValueError, match="bad pair"), WriteBehind() as w:
        w.submit(fail, 0)
        raise ValueError("bad pair")


def test_prefetched_loads_the_next_key_ahead_and_in_order():
    loaded = []
    out = []
    for key, value in prefetched([3, 1, 2], lambda k: loaded.append(k) or k * 10):
        out.append((key, value))
        # the current key and at most one ahead are loaded
        assert len(loaded) <= len(out) + 1
    assert out == [(3, 30), (1, 10), (2, 20)]
    assert loaded == [3, 1, 2]
    assert list(prefetched([], lambda k: k)) == []


def test_prefetched_raises_the_load_error_of_its_key():
    def load(k):
        if k == 2:
            raise OSError(f"chunk of pair {k} unreadable")
        return k

    got = []
    with pytest.raises(OSError, match="pair 2"):
        for key, _ in prefetched([0, 1, 2, 3], load):
            got.append(key)
    assert got == [0, 1]
