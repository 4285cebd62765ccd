"""The simulated cameras' GenICam node map: the driver's SFNC trigger set-up runs on it, the
vendor's double-exposure hook switches a vendor node, and a camera left with one frame per
trigger is paired in software by its time stamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acquisition import genicam as gc
from acquisition.protocols import DeviceError
from acquisition.session import RecordingSession
from lfcore.runstore import RunStore
from sim.camera import SIM_VENDOR, SimCamera
from sim.world import SimWorld
from tests.helpers import PERIOD_NS, T0_NS, HandTrigger


@pytest.fixture(scope="module")
def world(tiny_rig) -> SimWorld:
    return SimWorld(tiny_rig, ppm=0.05)


def _camera(rig, world, **kw) -> tuple[SimCamera, HandTrigger]:
    trigger = HandTrigger(rig)
    cam = SimCamera(rig.camera[0].name, rig, world, trigger, pool_pairs=2, rays_per_particle=50, **kw)
    cam.open()
    return cam, trigger


def _configure(cam, rig) -> None:
    cam.configure(triggered=True, frames_per_trigger=2, exposure_us=rig.timing.camera_exposure_us,
                  dt_us=rig.timing.dt_us)


def test_the_driver_setup_runs_on_the_node_map_and_the_vendor_hook_sets_piv_mode(tiny_rig, world):
    cam, trigger = _camera(tiny_rig, world, pixel_format="Mono12")
    _configure(cam, tiny_rig)
    nm = cam.node_map
    assert nm.TriggerSelector.value == "FrameStart" and nm.TriggerMode.value == "On"
    assert nm.TriggerSource.value == "Line0" and nm.TriggerActivation.value == "RisingEdge"
    assert nm.ExposureTime.value == pytest.approx(tiny_rig.timing.camera_exposure_us)
    assert nm.ExposureAuto.value == "Off" and nm.ExposureMode.value == "Timed"
    assert nm.AcquisitionMode.value == "Continuous" and nm.PixelFormat.value == "Mono12"
    assert nm.PIVDoubleExposure.value == "On" and f"double exposure ({SIM_VENDOR})" in cam.mode
    assert cam.frames_per_trigger == 2
    cam.start()
    trigger.fire(0)
    a, b = cam.fetch(0.1), cam.fetch(0.1)
    assert (a.frame_id, b.frame_id) == (0, 1) and a.data.max() <= 4095
    assert b.timestamp_ns - a.timestamp_ns == round(
        (tiny_rig.timing.camera_exposure_us + tiny_rig.timing.camera_interframe_us) * 1e3)


def test_without_a_hook_the_camera_is_refused_or_paired_in_software(tiny_rig, world):
    gc.unregister_double_exposure(SIM_VENDOR)
    try:
        cam, _ = _camera(tiny_rig, world)
        with pytest.raises(DeviceError, match="no double-exposure mode known to lfpiv|FrameBurstStart starts frame B"):
            _configure(cam, tiny_rig)
        cam, trigger = _camera(tiny_rig, world, allow_software_pairing=True)
        _configure(cam, tiny_rig)
        assert cam.frames_per_trigger == 1 and "paired in software" in cam.mode
        assert cam.node_map.PIVDoubleExposure.value == "Off"
        cam.start()
        trigger.fire(0)
        trigger.fire(1)
        a, b = cam.fetch(0.1), cam.fetch(0.1)
        assert (a.frame_id, b.frame_id) == (0, 1) and b.timestamp_ns - a.timestamp_ns == PERIOD_NS
    finally:
        from sim import camera as sim_camera

        gc.register_double_exposure(SIM_VENDOR, sim_camera._piv_double_exposure)


def test_a_falling_edge_trigger_starts_the_exposure_at_the_end_of_the_pulse(tiny_rig, world):
    cam, trigger = _camera(tiny_rig, world)
    _configure(cam, tiny_rig)
    cam.node_map.TriggerActivation.value = "FallingEdge"  # changed through the node map after set-up
    cam.start()
    trigger.fire(0)
    a = cam.fetch(0.1)
    assert a.timestamp_ns == T0_NS + 100_000 + round(tiny_rig.timing.camera_exposure_us * 1e3)


def test_software_pairing_by_time_stamps_pairs_consecutive_triggers(tiny_rig, world, tmp_path: Path):
    gc.unregister_double_exposure(SIM_VENDOR)
    try:
        cam, trigger = _camera(tiny_rig, world, allow_software_pairing=True, miss_triggers={3})
        _configure(cam, tiny_rig)
    finally:
        from sim import camera as sim_camera

        gc.register_double_exposure(SIM_VENDOR, sim_camera._piv_double_exposure)
    pairs = 3
    store = RunStore.create(tmp_path / "r.zarr", tiny_rig, pairs, timing={}, software_version="test")
    session = RecordingSession([cam], store, pairs, ring_slots=8, fetch_timeout_s=0.01,
                               trigger_period_s=PERIOD_NS / 1e9)
    session.start()
    try:
        for k in range(2 * pairs):
            trigger.fire(k)
        assert session.wait(10.0), session.error
    finally:
        session.close()
    assert session.error is None
    ids = store.group[f"{cam.name}/frame_id"][:]
    # triggers 0..5 make frames 0, 1, 2, (3 missed), 4 -> ids 0 1 2 3 4; trigger 3's place dropped
    np.testing.assert_array_equal(ids, [[0, 1], [2, -1], [3, 4]])
    stamps = store.group[f"{cam.name}/timestamp_ns"][:]
    assert stamps[2, 1] - stamps[0, 0] == 5 * PERIOD_NS
    drops = store.drops()
    assert [(d["pair"], d["frame"]) for d in drops] == [(1, 1)] and "missed trigger" in drops[0]["reason"]
    assert session.stats().missed_triggers == 1
