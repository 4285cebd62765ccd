"""The recording session's frame accounting with a scripted camera: every triggered frame is
recorded or dropped exactly once, whatever order the frames come in."""

from __future__ import annotations

import collections
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition.protocols import DeviceError, Frame
from acquisition.session import RecordingSession
from lfcore.runstore import RunStore
from tests.conftest import wait_for


class ScriptedCamera:
    """A Camera whose frames carry the given ids; ``later`` ids come once ``gate`` is set."""

    def __init__(self, rig, ids, later=(), first: int = 0) -> None:
        cam = rig.camera[0]
        self.name = cam.name
        self.sensor_px = tuple(cam.sensor_px)
        self.first_frame_id = first
        self.gate = threading.Event()
        self._now, self._later = collections.deque(ids), collections.deque(later)

    def open(self) -> None: ...
    def configure(self, **kw) -> None: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...

    def fetch(self, timeout_s: float) -> Frame | None:
        q = self._now or (self._later if self.gate.is_set() else None)
        if q:
            cols, rows = self.sensor_px
            fid = q.popleft()
            return Frame(np.full((rows, cols), fid + 1, np.uint16), self.name, fid, time.time_ns())
        time.sleep(min(timeout_s, 0.005))
        return None


def _session(tmp_path: Path, rig, cam: ScriptedCamera, pairs: int) -> tuple[RecordingSession, RunStore]:
    store = RunStore.create(tmp_path / "r.zarr", rig, pairs, timing={}, software_version="test")
    return RecordingSession([cam], store, pairs, ring_slots=8, fetch_timeout_s=0.01), store


def test_frames_after_the_grace_period_are_counted_once(tiny_rig, tmp_path: Path) -> None:
    # pairs 0-3 arrive; pairs 4-5 are declared not delivered; then frames 9-11 come after all
    cam = ScriptedCamera(tiny_rig, range(8), later=(9, 10, 11))
    s, store = _session(tmp_path, tiny_rig, cam, 6)
    s.start()
    try:
        assert wait_for(lambda: s.committed_pairs == 4, 10.0)
        assert s.drop_undelivered("not delivered within the grace period") == 4
        cam.gate.set()
        assert s.wait(10.0)
        assert wait_for(lambda: s.stats().late_frames == 3, 10.0)
    finally:
        s.close()
    st = s.stats()
    assert s.error is None and st.frames_recorded == 8 and st.frames_dropped == 4
    drops = store.drops()
    places = [(d["pair"], d["frame"]) for d in drops]
    assert sorted(places) == [(4, 0), (4, 1), (5, 0), (5, 1)]  # each once
    ids = RunStore.open(tmp_path / "r.zarr").frame_ids(cam.name)
    assert np.array_equal(ids[:4].ravel(), np.arange(8)) and np.all(ids[4:] == -1)


def _first_error(tmp_path: Path, rig, cam: ScriptedCamera, pairs: int) -> BaseException:
    """The error that ends a recording of ``cam``."""
    s, _ = _session(tmp_path, rig, cam, pairs)
    s.start()
    try:
        assert wait_for(lambda: s.error is not None, 10.0)
    finally:
        s.close()
    return s.error


def test_a_frame_counter_that_did_not_restart_is_an_error(tiny_rig, tmp_path: Path) -> None:
    error = _first_error(tmp_path, tiny_rig, ScriptedCamera(tiny_rig, range(1001, 1013), first=1), 6)
    assert isinstance(error, DeviceError)
    assert "numbered its first frame 1001, 1000 after the 1 it should start at" in str(error)
    assert "reset its counter" in str(error)


def test_frames_without_an_id_are_an_error(tiny_rig, tmp_path: Path) -> None:
    error = _first_error(tmp_path, tiny_rig, ScriptedCamera(tiny_rig, [-1] * 4), 2)
    with pytest.raises(DeviceError, match="without a frame id"):
        raise error


def test_a_gap_and_a_repeat_are_one_drop_each_place(tiny_rig, tmp_path: Path) -> None:
    # frame 3 is lost, frame 2 comes twice
    cam = ScriptedCamera(tiny_rig, [0, 1, 2, 2, 4, 5, 6, 7])
    s, store = _session(tmp_path, tiny_rig, cam, 4)
    s.start()
    try:
        assert s.wait(10.0)
    finally:
        s.close()
    st = s.stats()
    assert st.frames_recorded == 7 and st.frames_dropped == 1 and st.late_frames == 1
    (d,) = store.drops()
    assert (d["pair"], d["frame"], d["frame_id"]) == (1, 1, 3) and d["reason"].startswith("frame_id gap")
