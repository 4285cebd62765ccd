"""The simulated camera's injected faults, driven by hand-fired triggers (no emulator thread):
a missed trigger makes no frames and leaves no frame_id gap, and the recording session puts
every later frame in the pair of the trigger that made it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acquisition.session import RecordingSession
from lfcore.runstore import RunStore
from sim.camera import SimCamera
from sim.world import SimWorld
from tests.helpers import PERIOD_NS, T0_NS, HandTrigger


@pytest.fixture(scope="module")
def world(tiny_rig) -> SimWorld:
    return SimWorld(tiny_rig, ppm=0.05)


def _camera(rig, world, **faults) -> tuple[SimCamera, HandTrigger]:
    trigger = HandTrigger(rig)
    cam = SimCamera(rig.camera[0].name, rig, world, trigger, pool_pairs=3, rays_per_particle=50, **faults)
    cam.open()
    cam.configure(triggered=True, frames_per_trigger=2, exposure_us=rig.timing.camera_exposure_us,
                  dt_us=rig.timing.dt_us)
    return cam, trigger


def _drain(cam: SimCamera) -> list:
    frames = []
    while (f := cam.fetch(0.0)) is not None:
        frames.append(f)
    return frames


def test_a_missed_trigger_makes_no_frames_and_no_id_gap(tiny_rig, world) -> None:
    cam, trigger = _camera(tiny_rig, world, miss_triggers={2})
    cam.start()
    for k in range(5):
        trigger.fire(k)
    frames = _drain(cam)
    assert [f.frame_id for f in frames] == list(range(8))  # 4 triggers answered, ids consecutive
    assert cam.triggers_missed == 1 and cam.frames_lost == 0
    assert all(f.device_clock and f.complete for f in frames)
    b_delay = round((tiny_rig.timing.camera_exposure_us + tiny_rig.timing.camera_interframe_us) * 1e3)
    want = [T0_NS + t * PERIOD_NS + 100_000 + f * b_delay for t in (0, 1, 3, 4) for f in range(2)]
    assert [f.timestamp_ns for f in frames] == want  # only the time stamps show the missed trigger
    cam.start()  # trigger counting restarts with the acquisition
    trigger.fire(0)
    trigger.fire(1)
    trigger.fire(2)
    assert [f.frame_id for f in _drain(cam)] == [0, 1, 2, 3] and cam.triggers_missed == 1
    cam.close()


def test_session_records_each_pair_from_its_own_trigger(tiny_rig, world, tmp_path: Path) -> None:
    pairs = 6
    cam, trigger = _camera(tiny_rig, world, miss_triggers={2}, incomplete_frames={7})
    store = RunStore.create(tmp_path / "r.zarr", tiny_rig, pairs, timing={"rate_hz": 1e9 / PERIOD_NS},
                            software_version="test")
    session = RecordingSession([cam], store, pairs, ring_slots=8, fetch_timeout_s=0.01)
    session.start()
    try:
        for k in range(pairs):
            trigger.fire(k)
        assert session.wait(20.0), session.error
    finally:
        session.close()
        cam.close()
    assert session.error is None and session.stats().missed_triggers == 1
    store = RunStore.open(tmp_path / "r.zarr")
    reasons = {(d["pair"], d["frame"]): d["reason"].split(":")[0] for d in store.drops()}
    # pair 2: the missed trigger; frame id 7 (B of trigger 4, so of pair 4) came incomplete
    assert reasons == {(2, 0): "missed trigger", (2, 1): "missed trigger", (4, 1): "incomplete frame"}
    ids = store.frame_ids(cam.name)
    assert ids.tolist() == [[0, 1], [2, 3], [-1, -1], [4, 5], [6, -1], [8, 9]]
    frames = store.frames(cam.name)
    for p in (0, 1, 3, 4, 5):  # trigger p showed pool entry p % 3 (the simulated truth)
        for f in range(2):
            if ids[p, f] >= 0:
                assert np.array_equal(frames[p, f], cam._lit[cam.pool_index(p)][f])


def test_the_lab_renders_a_shown_scene_before_any_trigger(tiny_rig) -> None:
    # a scene takes seconds to render on a large sensor: SimLab.show renders it at once, so a
    # capture's wait for frames never includes it
    from sim.lab import SimLab

    calls: list[int] = []

    def scene(ci: int) -> np.ndarray:
        calls.append(ci)
        return np.full(tuple(reversed(tiny_rig.camera[ci].sensor_px)), 500, np.uint16)

    with SimLab(tiny_rig, pool_pairs=1, rays_per_particle=16, reply_latency_s=0.0) as lab:
        lab.show(scene, "grey")
        assert calls == [0]
        assert lab.cameras[0]._scene_image()[0, 0] == 500 and calls == [0]  # served from the cache
        lab.show(None)
        assert lab.world.scene is None and calls == [0]
