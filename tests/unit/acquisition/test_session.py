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
    """A Camera whose frames carry the given ids; ``later`` ids come once ``gate`` is set.

    ``stamps`` maps ids to device-clock time stamps (other frames get host fetch times). With
    ``discarded``, the camera counts discarded incomplete images in ``incomplete_frames`` as
    harvesters does: ``discarded[id]`` of them just before frame ``id`` is returned, and
    ``discarded[None]`` once every frame was fetched.
    """

    def __init__(self, rig, ids, later=(), first: int = 0, stamps: dict[int, int] | None = None,
                 discarded: dict[int | None, int] | None = None) -> None:
        cam = rig.camera[0]
        self.name = cam.name
        self.sensor_px = tuple(cam.sensor_px)
        self.first_frame_id = first
        self.gate = threading.Event()
        self._now, self._later = collections.deque(ids), collections.deque(later)
        self._stamps = stamps or {}
        self._discarded = dict(discarded) if discarded is not None else None
        if discarded is not None:
            self.incomplete_frames = 0

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
            if self._discarded is not None:
                self.incomplete_frames += self._discarded.pop(fid, 0)
            stamp = self._stamps.get(fid)
            return Frame(np.full((rows, cols), fid + 1, np.uint16), self.name, fid,
                         time.time_ns() if stamp is None else stamp, device_clock=stamp is not None)
        if self._discarded is not None:
            self.incomplete_frames += self._discarded.pop(None, 0)
        time.sleep(min(timeout_s, 0.005))
        return None


def _session(tmp_path: Path, rig, cam: ScriptedCamera, pairs: int, timing: dict | None = None,
             **kw) -> tuple[RecordingSession, RunStore]:
    store = RunStore.create(tmp_path / "r.zarr", rig, pairs, timing=timing or {}, software_version="test")
    return RecordingSession([cam], store, pairs, ring_slots=8, fetch_timeout_s=0.01, **kw), store


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


def _first_error(tmp_path: Path, rig, cam: ScriptedCamera, pairs: int, **kw) -> BaseException:
    """The error that ends a recording of ``cam``."""
    s, _ = _session(tmp_path, rig, cam, pairs, **kw)
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


# --- missed triggers, found from device time stamps ------------------------------------------
PERIOD_NS = 100_000_000  # 10 Hz triggers
FRAME_B_NS = 2_000_000  # frame B's time stamp comes 2 ms after frame A's
T0_NS = 5_000_000_000_000


def _stamps(triggers: list[int]) -> dict[int, int]:
    """Device time stamps of frames 0, 1, 2, ... made by the given triggers, two frames each."""
    return {2 * i + f: T0_NS + t * PERIOD_NS + f * FRAME_B_NS for i, t in enumerate(triggers) for f in range(2)}


def _record(tmp_path: Path, rig, cam: ScriptedCamera, pairs: int, **kw) -> tuple[RecordingSession, RunStore]:
    s, store = _session(tmp_path, rig, cam, pairs, **kw)
    s.start()
    try:
        assert s.wait(10.0), s.error
    finally:
        s.close()
    assert s.error is None
    return s, RunStore.open(tmp_path / "r.zarr")


def test_a_missed_trigger_is_a_dropped_pair_and_later_frames_keep_their_trigger(tiny_rig, tmp_path: Path) -> None:
    # triggers 0..5 fire, the camera misses trigger 2: frames 0..9 come from triggers 0, 1, 3, 4, 5
    triggers = [0, 1, 3, 4, 5]
    cam = ScriptedCamera(tiny_rig, range(10), stamps=_stamps(triggers))
    s, store = _record(tmp_path, tiny_rig, cam, 6, timing={"rate_hz": 10.0})  # the period from the store
    st = s.stats()
    assert (st.frames_recorded, st.frames_dropped, st.missed_triggers) == (10, 2, 1)
    drops = store.drops()
    assert [(d["pair"], d["frame"], d["frame_id"]) for d in drops] == [(2, 0, -1), (2, 1, -1)]
    assert all(d["reason"].startswith("missed trigger") for d in drops)
    ids = store.frame_ids(cam.name)
    assert ids.tolist() == [[0, 1], [2, 3], [-1, -1], [4, 5], [6, 7], [8, 9]]
    frames = store.frames(cam.name)
    for p, t in enumerate(triggers):  # each recorded pair holds the frames of its own trigger
        pair = t
        assert frames[pair, 0][0, 0] == 2 * p + 1 and frames[pair, 1][0, 0] == 2 * p + 2
    stamps = store.timestamps_ns(cam.name)
    assert np.all(stamps[[0, 1, 3, 4, 5], 0] == T0_NS + np.array([0, 1, 3, 4, 5]) * PERIOD_NS)


def test_missed_trigger_among_lost_frames_found_by_frame_b(tiny_rig, tmp_path: Path) -> None:
    # triggers 0, 1, 3, 4 (2 missed) make frames 0..7; frame 3 (B of trigger 1) and frame 4 (A of
    # trigger 3) are lost, so frame B of trigger 3 is the first to show the missed trigger
    stamps = _stamps([0, 1, 3, 4])
    cam = ScriptedCamera(tiny_rig, [0, 1, 2, 5, 6, 7], stamps=stamps)
    s, store = _record(tmp_path, tiny_rig, cam, 5, trigger_period_s=PERIOD_NS / 1e9)
    assert s.stats().missed_triggers == 1
    got = sorted((d["pair"], d["frame"], d["frame_id"], d["reason"].split(":")[0]) for d in store.drops())
    assert got == [(1, 1, 3, "frame_id gap"), (2, 0, -1, "missed trigger"), (2, 1, -1, "missed trigger"),
                   (3, 0, 4, "frame_id gap")]
    assert store.frame_ids(cam.name).tolist() == [[0, 1], [2, -1], [-1, -1], [-1, 5], [6, 7]]


def test_without_device_time_stamps_or_a_period_nothing_is_shifted(tiny_rig, tmp_path: Path) -> None:
    # the same missed trigger cannot be seen: frames pair by id, the last pair is not delivered
    cam = ScriptedCamera(tiny_rig, range(10), stamps=_stamps([0, 1, 3, 4, 5]))
    s, store = _session(tmp_path, tiny_rig, cam, 6)  # no rate in the store, no period given
    s.start()
    try:
        assert wait_for(lambda: s.committed_pairs == 5, 10.0)
        assert s.drop_undelivered("not delivered") == 2
        assert s.wait(10.0)
    finally:
        s.close()
    assert s.stats().missed_triggers == 0
    assert RunStore.open(tmp_path / "r.zarr").frame_ids(cam.name)[:5].ravel().tolist() == list(range(10))


def test_frames_without_a_trigger_stop_the_recording(tiny_rig, tmp_path: Path) -> None:
    # frames 2, 3 are stamped at trigger 0's time too: more frames than triggers
    stamps = _stamps([0, 0, 1, 2])
    error = _first_error(tmp_path, tiny_rig, ScriptedCamera(tiny_rig, range(8), stamps=stamps), 4,
                         trigger_period_s=PERIOD_NS / 1e9)
    assert isinstance(error, DeviceError) and "\n" not in str(error)
    assert "frame 2" in str(error) and "0 trigger period(s) for 1 pair(s)" in str(error)
    assert "can no longer be paired" in str(error)


def test_a_missed_trigger_seen_only_by_frame_b_after_its_frame_a_is_an_error(tiny_rig, tmp_path: Path) -> None:
    # trigger 1 missed; frame A of trigger 2 (id 2) has no device time stamp, so it was placed
    # in pair 1 before frame B (id 3) showed the missed trigger: that pairing cannot be undone
    stamps = _stamps([0, 2, 3])
    del stamps[2]
    error = _first_error(tmp_path, tiny_rig, ScriptedCamera(tiny_rig, range(6), stamps=stamps), 4,
                         trigger_period_s=PERIOD_NS / 1e9)
    assert isinstance(error, DeviceError) and "frame 3 (B)" in str(error) and "paired wrongly" in str(error)


# --- incomplete images the driver discarded ----------------------------------------------------
def test_gaps_of_discarded_incomplete_frames_say_so(tiny_rig, tmp_path: Path) -> None:
    # ids 2, 3: both discarded incomplete; id 6: lost; ids 9, 10: one of them incomplete; the
    # last pair: id 12 discarded incomplete, id 13 never came
    ids = [0, 1, 4, 5, 7, 8, 11]
    cam = ScriptedCamera(tiny_rig, ids, discarded={4: 2, 11: 1, None: 1})
    s, store = _session(tmp_path, tiny_rig, cam, 7)
    s.start()
    try:
        assert wait_for(lambda: s.committed_pairs == 6 and cam.incomplete_frames == 4, 10.0)
        assert s.drop_undelivered("not delivered") == 2
        assert s.wait(10.0)
    finally:
        s.close()
    reasons = {2 * d["pair"] + d["frame"]: d["reason"] for d in store.drops()}
    assert sorted(reasons) == [2, 3, 6, 9, 10, 12, 13]
    assert reasons[2].startswith("incomplete frame") and reasons[3].startswith("incomplete frame")
    assert reasons[6] == "frame_id gap: lost in camera or transport"
    assert reasons[9] == reasons[10] and reasons[9].startswith("frame_id gap: 1 of these 2 frames came incomplete")
    assert reasons[12].startswith("incomplete frame") and reasons[13] == "not delivered"
    assert s.stats().frames_recorded + len(reasons) == 14
