"""The GenICam camera driver, against the GenTL simulator (viky.cti) that ships with genicam.

The pure parts (producer search, pixel conversion, the SFNC trigger set-up on a stand-in node
map) run without harvesters; the device tests skip when harvesters or viky.cti is missing.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from acquisition import genicam as gc
from acquisition.protocols import Camera, DeviceError
from tests.helpers import VIKY

needs_viky = pytest.mark.skipif(
    VIKY is None, reason="GenTL simulator viky.cti not found (pip install 'lfpiv[genicam]')"
)


@pytest.fixture(autouse=True)
def _fresh_system():
    yield
    gc.reset_system()


def _camera(name: str = "cam0", serial: str | None = "0", **kw) -> gc.GenICamCamera:
    return gc.GenICamCamera(name, serial=serial, producers=[str(VIKY)], **kw)


def _fast(cam: gc.GenICamCamera, fps: float = 100.0) -> None:
    """Make viky run faster than its default 20 frames/s (keeps the tests short)."""
    cam.node_map.AcquisitionFrameRate.value = fps


# --- producers -----------------------------------------------------------------------------
def test_producer_paths_explicit_dedup_and_rig(tmp_path: Path) -> None:
    a, b = tmp_path / "a.cti", tmp_path / "b.cti"
    a.touch()
    b.touch()
    assert gc.producer_paths([a, str(b), a]) == [str(a.resolve()), str(b.resolve())]
    rig = SimpleNamespace(gentl_producers=(str(b),))
    assert gc.producer_paths(rig) == [str(b.resolve())]
    with pytest.raises(DeviceError, match="missing.cti"):
        gc.producer_paths([tmp_path / "missing.cti"])


def test_producer_paths_from_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    d1, d2 = tmp_path / "vendor", tmp_path / "other"
    d1.mkdir()
    d2.mkdir()
    (d1 / "b.cti").touch()
    (d1 / "a.cti").touch()
    (d1 / "readme.txt").touch()
    monkeypatch.setenv(gc.ENV_VAR, f"{d1}:{d2}:{tmp_path / 'nowhere'}")
    assert [Path(p).name for p in gc.producer_paths(None)] == ["a.cti", "b.cti"]
    monkeypatch.setenv(gc.ENV_VAR, str(d2))
    with pytest.raises(DeviceError, match=gc.ENV_VAR):
        gc.producer_paths(SimpleNamespace(gentl_producers=()))


def test_missing_harvesters_is_one_line_with_install_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    gc.reset_system()
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    with pytest.raises(DeviceError, match=r"pip install 'lfpiv\[genicam\]'") as info:
        gc._System.get([])
    assert "\n" not in str(info.value)


# --- pixel formats -------------------------------------------------------------------------
def test_image_to_uint16_mono_rgb_and_padding() -> None:
    mono = np.arange(12, dtype=np.uint8)
    out = gc.image_to_uint16(mono, "Mono8", 4, 3)
    assert out.dtype == np.uint16 and out.shape == (3, 4)
    np.testing.assert_array_equal(out, mono.reshape(3, 4))
    deep = np.array([0, 4095, 65535, 7], dtype=np.uint16)
    np.testing.assert_array_equal(gc.image_to_uint16(deep, "Mono16", 2, 2), deep.reshape(2, 2))
    padded = np.array([1, 2, 0, 3, 4, 0], dtype=np.uint8)  # one padding value per line
    np.testing.assert_array_equal(gc.image_to_uint16(padded, "Mono8", 2, 2), [[1, 2], [3, 4]])
    rgba = np.array([255, 255, 255, 9, 255, 0, 0, 9, 0, 255, 0, 9, 0, 0, 255, 9], dtype=np.uint8)
    np.testing.assert_array_equal(gc.image_to_uint16(rgba, "RGBa8", 2, 2), [[255, 77], [149, 29]])
    bgr = np.array([255, 0, 0, 0, 0, 255], dtype=np.uint8)
    np.testing.assert_array_equal(gc.image_to_uint16(bgr, "BGR8", 2, 1), [[29, 77]])
    with pytest.raises(DeviceError, match="YUV422_8"):
        gc.image_to_uint16(mono, "YUV422_8", 2, 3)
    with pytest.raises(ValueError):
        gc.image_to_uint16(mono, "Mono8", 8, 3)


# --- SFNC set-up on a stand-in node map ----------------------------------------------------
class _Node:
    def __init__(self, value, symbolics=None, lo=None, hi=None):
        self._value, self.symbolics, self.min, self.max = value, symbolics, lo, hi

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if self.min is not None and not self.min <= v <= self.max:
            raise ValueError("out of range")
        self._value = v


class _SelectedNodeMap:
    """A node map whose TriggerMode/TriggerSource depend on TriggerSelector, as in SFNC."""

    def __init__(self, selectors=("FrameStart", "AcquisitionStart"), burst=False, fps=None):
        self.TriggerSelector = _Node(selectors[0], tuple(selectors))
        self._modes = {s: _Node("On", ("Off", "On")) for s in selectors}
        self._sources = {s: _Node("Software", ("Software", "Line0", "Line1")) for s in selectors}
        self.TriggerActivation = _Node("FallingEdge", ("RisingEdge", "FallingEdge"))
        self.ExposureMode = _Node("TriggerWidth", ("Timed", "TriggerWidth"))
        self.ExposureTime = _Node(1000.0, lo=10.0, hi=1e6)
        if burst:
            self.AcquisitionBurstFrameCount = _Node(1, lo=1, hi=255)
        if fps is not None:
            self.ResultingFrameRate = _Node(fps)

    @property
    def TriggerMode(self):  # noqa: N802 - GenICam feature name
        return self._modes[self.TriggerSelector.value]

    @property
    def TriggerSource(self):  # noqa: N802
        return self._sources[self.TriggerSelector.value]


def _configure(nm, **kw):
    args = dict(
        where="camera 'c'",
        vendor="Acme Imaging",
        triggered=True,
        frames_per_trigger=1,
        exposure_us=50.0,
        trigger_line="Line1",
        allow_software_pairing=False,
    )
    args.update(kw)
    return gc._configure_node_map(nm, **args)


def test_sfnc_trigger_setup_frame_start() -> None:
    nm = _SelectedNodeMap()
    mode = _configure(nm)
    assert mode == "FrameStart trigger on Line1"
    assert nm.TriggerSelector.value == "FrameStart"
    assert (nm._modes["FrameStart"].value, nm._modes["AcquisitionStart"].value) == ("On", "Off")
    assert nm._sources["FrameStart"].value == "Line1"
    assert nm.TriggerActivation.value == "RisingEdge" and nm.ExposureMode.value == "Timed"
    assert nm.ExposureTime.value == 50.0
    free = _SelectedNodeMap()
    assert _configure(free, triggered=False).startswith("free run")
    assert all(m.value == "Off" for m in free._modes.values())


def _burst_map(fps=None) -> _SelectedNodeMap:
    return _SelectedNodeMap(selectors=("FrameStart", "FrameBurstStart"), burst=True, fps=fps)


def test_sfnc_double_frame_burst_hook_and_errors() -> None:
    # exposure 50 us, dt 2000 us: pulse 1 is 0.5 us before frame A closes, pulse 2 dt later, so
    # a burst's frame B (same exposure, one frame period T after A) holds it for 2000 <= T <= 2049 us
    nm = _burst_map(fps=1e6 / 2020.0)
    assert "bursts of 2" in _configure(nm, frames_per_trigger=2, dt_us=2000.0)
    assert nm.TriggerSelector.value == "FrameBurstStart" and nm.AcquisitionBurstFrameCount.value == 2
    assert nm._modes["FrameStart"].value == "Off" and nm._modes["FrameBurstStart"].value == "On"

    with pytest.raises(DeviceError, match="register_double_exposure"):
        _configure(_SelectedNodeMap(), frames_per_trigger=2)
    assert "paired in software" in _configure(_SelectedNodeMap(), frames_per_trigger=2, allow_software_pairing=True)

    seen = []
    gc.register_double_exposure("acme", lambda node_map: seen.append(node_map.TriggerSelector.value))
    try:
        assert "double exposure" in _configure(_SelectedNodeMap(), frames_per_trigger=2)
        assert seen == ["FrameStart"]
    finally:
        gc.unregister_double_exposure("ACME")

    no_source = _SelectedNodeMap()
    no_source._sources = {}
    with pytest.raises(DeviceError, match="no TriggerSource feature") as info:
        _configure(no_source)
    assert "camera 'c'" in str(info.value)
    with pytest.raises(DeviceError, match=r"ExposureTime.*allowed 10.0 to 1000000.0"):
        _configure(_SelectedNodeMap(), exposure_us=2.0)
    with pytest.raises(DeviceError, match="it accepts Software, Line0, Line1"):
        _configure(_SelectedNodeMap(), trigger_line="Line7")


@pytest.mark.parametrize(("fps", "dt_us", "says"), [
    (60.0, 2000.0, r"frame period \(16666.7 us\).*opens after laser pulse 2.*2000.0-2049.0 us"),  # 4 MP at 60 fps
    (1000.0, 2000.0, r"frame period \(1000.0 us\).*closes before laser pulse 2"),
    (1e6 / 2020.0, None, "not given dt_us"),
    (None, 2000.0, "states no frame rate"),
])
def test_a_burst_whose_frame_b_misses_pulse_2_is_refused(fps, dt_us, says) -> None:
    nm = _burst_map(fps)
    with pytest.raises(DeviceError, match=says) as info:
        _configure(nm, frames_per_trigger=2, dt_us=dt_us)
    msg = str(info.value)
    assert msg.startswith("camera 'c': FrameBurstStart") and "\n" not in msg
    assert "register_double_exposure" in msg and "allow_software_pairing=True" in msg


def test_an_unusable_burst_falls_back_to_software_pairing_when_allowed() -> None:
    nm = _burst_map(fps=60.0)
    mode = _configure(nm, frames_per_trigger=2, dt_us=2000.0, allow_software_pairing=True)
    assert mode == "FrameStart trigger on Line1, one frame per trigger (paired in software; no usable burst)"
    assert nm._modes["FrameStart"].value == "On" and nm._modes["FrameBurstStart"].value == "Off"
    assert nm._sources["FrameStart"].value == "Line1" and nm.AcquisitionBurstFrameCount.value == 1
    # a vendor hook wins over the burst, whatever its frame rate
    gc.register_double_exposure("acme", lambda node_map: None)
    try:
        assert "double exposure" in _configure(_burst_map(fps=60.0), frames_per_trigger=2, dt_us=2000.0)
    finally:
        gc.unregister_double_exposure("acme")


def test_frame_period_from_resulting_or_acquisition_frame_rate() -> None:
    assert gc._frame_period_us(SimpleNamespace(ResultingFrameRate=_Node(500.0))) == 2000.0
    assert gc._frame_period_us(SimpleNamespace(ResultingFrameRateAbs=_Node(250.0))) == 4000.0
    # a frame rate that is switched off does not limit the camera: it runs at the highest
    off = SimpleNamespace(AcquisitionFrameRate=_Node(100.0, lo=1.0, hi=500.0), AcquisitionFrameRateEnable=_Node(False))
    assert gc._frame_period_us(off) == 2000.0
    on = SimpleNamespace(AcquisitionFrameRate=_Node(100.0, lo=1.0, hi=500.0), AcquisitionFrameRateEnable=_Node(True))
    assert gc._frame_period_us(on) == 10000.0
    assert gc._frame_period_us(SimpleNamespace(AcquisitionFrameRate=_Node(20.0))) == 50000.0
    assert gc._frame_period_us(SimpleNamespace()) is None


def test_configure_refuses_a_non_positive_dt() -> None:
    with pytest.raises(ValueError, match="dt_us must be positive"):
        gc.GenICamCamera("c").configure(triggered=True, frames_per_trigger=2, exposure_us=20.0, dt_us=0.0)


class _Raw:
    """A GenTL buffer's info: frame id, completeness and, if given, a device time stamp."""

    def __init__(self, frame_id: int, stamp_ns: int | None) -> None:
        self.frame_id, self._stamp = frame_id, stamp_ns

    def is_complete(self) -> bool:
        return True

    @property
    def timestamp_ns(self) -> int:
        if self._stamp is None:
            raise RuntimeError("NotAvailable")  # what producers without time stamps raise
        return self._stamp

    @property
    def timestamp(self) -> int:
        raise RuntimeError("NotAvailable")


def _buffer(frame_id: int, stamp_ns: int | None) -> SimpleNamespace:
    comp = SimpleNamespace(data=np.arange(6, dtype=np.uint8), data_format="Mono8", width=3, height=2)
    return SimpleNamespace(module=_Raw(frame_id, stamp_ns), payload=SimpleNamespace(components=[comp]))


def test_frames_say_whether_their_time_stamp_is_the_camera_clock() -> None:
    cam = gc.GenICamCamera("c")
    device = cam._to_frame(_buffer(7, 123_456_789), host_ns=999)
    assert (device.frame_id, device.timestamp_ns, device.device_clock) == (7, 123_456_789, True)
    host = cam._to_frame(_buffer(8, None), host_ns=999)
    assert (host.frame_id, host.timestamp_ns, host.device_clock) == (8, 999, False)
    np.testing.assert_array_equal(host.data, [[0, 1, 2], [3, 4, 5]])


# --- viky ----------------------------------------------------------------------------------
@needs_viky
def test_list_devices_sees_three_simulated_cameras() -> None:
    devices = gc.list_devices([VIKY])
    assert [d.serial_number for d in devices] == ["0", "1", "2"]
    assert {d.vendor for d in devices} == {"Machine Vision Games Ltd."}
    assert all(d.model == "Viky" and d.tl_type == "Custom" and d.access == "available" for d in devices)
    assert [d.id for d in devices] == ["VikyTL_DEV_red", "VikyTL_DEV_green", "VikyTL_DEV_blue"]
    assert devices[0].producer == str(VIKY.resolve())


@needs_viky
def test_open_by_serial_index_and_wrong_serial() -> None:
    cam = _camera(serial="1")
    assert isinstance(cam, Camera)
    assert cam.sensor_px == (0, 0)  # until open
    before = signal.getsignal(signal.SIGINT)
    cam.open()
    assert signal.getsignal(signal.SIGINT) is before  # harvesters' SIGINT handler is undone
    assert cam.device_info.id == "VikyTL_DEV_green"
    assert cam.sensor_px == (400, 400) and cam.first_frame_id == 1
    assert [d.access for d in gc.list_devices([VIKY])] == ["available", "open", "available"]
    by_index = _camera("cam1", serial=None, index=2)
    by_index.open()
    assert by_index.device_info.serial_number == "2"
    with pytest.raises(DeviceError, match=r"serial '42'.*seen: '0', '1', '2'") as info:
        _camera("cam2", serial="42").open()
    assert "cam2" in str(info.value) and "\n" not in str(info.value)
    cam.close()
    by_index.close()


@needs_viky
def test_triggered_configure_names_the_missing_feature() -> None:
    cam = _camera()
    cam.open()
    with pytest.raises(DeviceError, match=r"camera 'cam0' \(.*Viky, serial 0\) has no TriggerMode feature"):
        cam.configure(triggered=True, frames_per_trigger=2, exposure_us=100.0)
    cam.configure(triggered=False, frames_per_trigger=2, exposure_us=100.0)
    assert cam.mode.startswith("free run")
    cam.close()


@needs_viky
@pytest.mark.parametrize("pixel_format", ["Mono8", None])  # None: viky's default RGBa8
def test_free_run_acquisition(pixel_format: str | None) -> None:
    cam = _camera(pixel_format=pixel_format)
    cam.open()
    cam.configure(triggered=False, frames_per_trigger=1, exposure_us=100.0)
    _fast(cam)
    cam.start()
    frames = [cam.fetch(timeout_s=2.0) for _ in range(20)]
    cam.stop()
    assert all(f is not None for f in frames)
    assert [f.frame_id for f in frames] == list(range(cam.first_frame_id, cam.first_frame_id + 20))
    assert all(f.data.shape == (400, 400) and f.data.dtype == np.uint16 for f in frames)
    assert all(f.camera == "cam0" and f.complete and not f.device_clock for f in frames)
    assert all(0 < f.data.max() <= 255 for f in frames)
    stamps = [f.timestamp_ns for f in frames]
    assert stamps == sorted(stamps) and abs(stamps[0] - time.time_ns()) < 60e9  # host clock on viky
    cam.close()


@needs_viky
def test_frames_delivered_before_stop_are_kept_then_none() -> None:
    cam = _camera(num_buffers=4)
    cam.open()
    cam.configure(triggered=False, frames_per_trigger=1, exposure_us=100.0)
    _fast(cam)
    cam.start()
    time.sleep(0.25)  # ~25 frames produced, 4 buffers: OldestFirst keeps 1..4, drops the rest
    first = [cam.fetch(1.0).frame_id for _ in range(4)]
    later = cam.fetch(1.0).frame_id
    assert first == [1, 2, 3, 4] and later > 5  # the overflow shows as a frame_id gap
    time.sleep(0.05)
    cam.stop()
    drained = []
    while (f := cam.fetch(0.5)) is not None:
        drained.append(f.frame_id)
    assert drained and drained[0] > later and drained == sorted(drained)
    t0 = time.monotonic()
    assert cam.fetch(timeout_s=0.3) is None
    assert time.monotonic() - t0 < 0.3
    cam.start()  # numbering starts again
    assert cam.fetch(2.0).frame_id == cam.first_frame_id
    cam.close()


@needs_viky
def test_two_cameras_share_one_harvester_and_fetch_in_threads() -> None:
    cams = [_camera("left", "0"), _camera("right", "2", pixel_format="Mono8")]
    for c in cams:
        c.open()
        c.configure(triggered=False, frames_per_trigger=2, exposure_us=100.0)
        _fast(c)
    assert len(gc._System.harvester.image_acquirers) == 2
    ids: dict[str, list[int]] = {}

    def grab(cam: gc.GenICamCamera) -> None:
        ids[cam.name] = [cam.fetch(2.0).frame_id for _ in range(10)]

    for c in cams:
        c.start()
    threads = [threading.Thread(target=grab, args=(c,)) for c in cams]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert ids == {"left": list(range(1, 11)), "right": list(range(1, 11))}
    for c in cams:
        c.close()
    assert gc._System.harvester.image_acquirers == []


@needs_viky
def test_close_is_idempotent_and_safe_in_any_state() -> None:
    never_opened = _camera()
    never_opened.close()
    cam = _camera()
    cam.open()
    cam.configure(triggered=False, frames_per_trigger=1, exposure_us=100.0)
    cam.start()
    assert cam.fetch(2.0) is not None
    cam.close()
    cam.close()
    with pytest.raises(DeviceError, match="not open"):
        cam.fetch(0.1)
    with _camera() as again:  # the device was released: it opens again
        assert again.is_open
    assert not again.is_open
    survivor = _camera("cam9", "1")
    survivor.open()
    gc.reset_system()
    survivor.close()


@needs_viky
def test_viky_recording_session_pairs_frames_of_two_cameras(tiny_rig, tmp_path: Path) -> None:
    """The real GenICam path through the session and recorder: two simulated GenTL devices in
    free run (software pairing of consecutive frames) recorded into a run store."""
    from acquisition.session import RecordingSession
    from lfcore.rig import Rig
    from lfcore.runstore import RunStore

    d = tiny_rig.to_dict()
    d["camera"][0]["sensor_px"] = [400, 400]
    d["camera"].append(dict(d["camera"][0], name="cam1"))
    rig = Rig.from_dict(d)
    cams = [_camera("cam0", "0", pixel_format="Mono8"), _camera("cam1", "1", pixel_format="Mono8")]
    try:
        for cam in cams:
            cam.open()
            _fast(cam)
            cam.configure(triggered=False, frames_per_trigger=2, exposure_us=100.0)
        pairs = 10
        store = RunStore.create(tmp_path / "viky.zarr", rig, pairs, timing={}, software_version="test")
        session = RecordingSession(cams, store, pairs)
        session.start()
        assert session.wait(20.0), session.error
        session.close()
    finally:
        for cam in cams:
            cam.close()
    assert session.error is None
    store = RunStore.open(tmp_path / "viky.zarr")
    assert store.committed_pairs == pairs
    for cam in ("cam0", "cam1"):
        ids = store.frame_ids(cam)
        recorded = ids >= 0
        dropped = {(r["pair"], r["frame"]) for r in store.drops() if r["camera"] == cam}
        assert recorded.sum() + len(dropped) == 2 * pairs
        p, f = np.nonzero(recorded)
        assert np.array_equal(ids[p, f], 1 + 2 * p + f)  # viky numbers frames from 1
        assert store.frames(cam)[p[0], f[0]].max() > 0  # the simulator's test pattern
        assert np.all(np.diff(store.timestamps_ns(cam)[recorded]) >= 0)


def test_16_bit_gige_frame_ids_are_unwrapped() -> None:
    # GigE Vision 1.x block ids wrap from 65535 to 1 (0 is never used); the count goes on
    cam = gc.GenICamCamera("cam0")
    got = [cam._unwrap(i) for i in (65533, 65534, 65535, 1, 2, 4)]
    assert got == [65533, 65534, 65535, 65536, 65537, 65539]
    assert [cam._unwrap(i) for i in (65535, 1)] == [131070, 131071]  # and again
    # 64-bit ids (USB3 Vision, extended ids) are never taken for a wrap; no id stays -1
    cam = gc.GenICamCamera("cam1")
    assert [cam._unwrap(i) for i in (70000, 100, 70001, -1)] == [70000, 100, 70001, -1]
