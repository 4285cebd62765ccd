"""The Zaber driver as the application builds it (message ids, the device's own resolution),
the faults of a real link, and the official zaber-motion library against the same emulator."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from acquisition.protocols import DeviceError
from acquisition.stage import ZABER_PRODUCTS, ZaberStage, stage_for
from lfcore.rig import StageConfig
from sim.serial_emulators import StageEmulator, ZaberAxis, ZaberDevice
from tests.conftest import wait_for


@pytest.fixture
def emu():
    with StageEmulator(latency_s=0, speed_mm_s=100.0, position_mm=12.5) as e:
        yield e


def _stage(emu, **kw) -> ZaberStage:
    opts = dict(timeout_s=0.2, move_timeout_s=3.0, poll_s=0.005, retry_pause_s=0.001, message_ids=True,
                reconnect_s=0.5)
    opts.update(kw)
    return ZaberStage(emu.port, **opts)


def test_stage_for_uses_message_ids_and_the_devices_resolution(emu):
    st = stage_for(emu.port, StageConfig())
    with st:
        assert st.identity.deviceid == 59901 and st.identity.resolution == 64
        assert st.identity.microstep_um == pytest.approx(0.1)
        st.home()
        assert st.move_to(4.25) == pytest.approx(4.25)
    ids = [c.split()[2] for c in emu.commands if c.startswith("/1 1 ") and c.split()[2].isdigit()]
    assert len(ids) > 5 and ids[:3] == [str(i) for i in range(int(ids[0]), int(ids[0]) + 3)]


def test_the_stage_is_named_by_its_deviceid(emu):
    with _stage(emu) as st:
        line = st.describe()
    assert "deviceid 59901" in line and "serial 1234" in line and "firmware 7.38" in line
    assert "microstep 0.1 um (resolution 64)" in line and "travel 0..50 mm" in line


def test_a_late_reply_with_another_id_is_not_taken(emu):
    with _stage(emu) as st:
        st.home()
        st._link.write_line("/1 1 77 get limit.max")  # answered, but nobody reads it in time
        time.sleep(0.05)
        assert st.position_mm() == pytest.approx(0.0)


def test_microstep_follows_a_changed_resolution(emu):
    with _stage(emu) as st:
        st._command("set resolution 128")
    with _stage(emu) as st:
        assert st.identity.resolution == 128 and st.microstep_um == pytest.approx(0.05)
        assert st.travel_mm == (0.0, 50.0)
        st.home()
        assert st.move_to(3.0) == pytest.approx(3.0)
        assert emu.position_mm == pytest.approx(3.0)


def test_a_rig_microstep_that_disagrees_is_reported_and_not_used(emu, caplog):
    with caplog.at_level(logging.WARNING, logger="acquisition.stage"), _stage(emu, microstep_um=0.047625) as st:
        assert st.microstep_um == pytest.approx(0.1)
    assert any("microstep_um = 0.047625 um" in r.getMessage() and "using 0.1 um" in r.getMessage()
               for r in caplog.records)


def test_an_unknown_product_needs_the_rig_microstep(emu, monkeypatch):
    monkeypatch.delitem(ZABER_PRODUCTS, 59901)
    with pytest.raises(DeviceError, match=r"deviceid 59901 is not in lfpiv's Zaber product table.*microstep_um"):
        _stage(emu).open()
    with _stage(emu, microstep_um=0.1) as st:
        assert st.travel_mm == (0.0, 50.0)


def test_a_peripheral_on_a_controller_is_found_by_its_peripheral_id():
    ctrl = ZaberDevice(address=3, deviceid=59950, axes=[ZaberAxis(ZABER_PRODUCTS[69901], peripheral_id=69901)
                                                       for _ in range(2)])
    with StageEmulator(chain=[ctrl], device=3, axis=2, latency_s=0, homed=True, position_mm=1.0) as e:
        with _stage(e, device=3, axis=2) as st:
            assert st.identity.peripheral_id == 69901 and st.travel_mm == (0.0, 100.0)
            assert st.move_to(60.0) == pytest.approx(60.0)
            assert e.position_mm == pytest.approx(60.0)
        with pytest.raises(DeviceError, match=r"has 2 axis\(es\), not axis 3"):
            _stage(e, device=3, axis=3).open()


def test_alerts_are_collected(emu):
    with _stage(emu) as st:
        st._command("set comm.alert 1", axis=0)
        st.home()
        st.move_to(2.0)
        assert wait_for(lambda: (st.position_mm(), len(st.alerts))[1] >= 1, 2.0)
    assert all(a.startswith("!01 1 ") for a in st.alerts)


def test_warnings_are_reported_with_their_meaning(emu):
    emu.set_flags("WT")
    with _stage(emu) as st:
        assert st.warnings() == [("WT", "temperature high"), ("WR", "no reference position")]


def test_a_long_warning_list_split_into_packets_is_joined(emu):
    emu.set_flags("FD", "FQ", "FS", "FT", "FB", "FP", "FE", "WH", "WL", "WP", "WV", "WT", "WM", "NC", "NI")
    with _stage(emu) as st:
        st._command("set comm.packet.size.max 30", axis=0)
        flags = [f for f, _ in st.warnings()]
    assert len(flags) == 16 and flags[0] == "FD" and flags[-1] == "NI"


def test_stop_waits_until_the_stage_has_braked(emu):
    with _stage(emu) as st:
        st.home()
        st._command("set accel 200")
        emu.speed_mm_s = 40.0
        st._command("move abs 450000")
        time.sleep(0.3)
        st.stop()
        assert not emu.busy and "NI" in emu.flags


# --- faults of a real link ---------------------------------------------------------------
def test_a_reply_split_across_reads_is_read_whole(emu):
    emu.inject("split", gap_s=0.03)
    with _stage(emu) as st:
        st.home()
        assert st.move_to(1.5) == pytest.approx(1.5)


def test_a_stray_byte_is_a_corrupt_reply_and_the_command_is_sent_again(emu):
    with _stage(emu) as st:
        st.home()
        st.move_to(7.0)
        emu.inject("stray")
        assert st.position_mm() == pytest.approx(7.0)


def test_persistent_noise_fails_on_one_line(emu):
    with _stage(emu) as st:
        emu.inject("stray", count=100)
        with pytest.raises(DeviceError) as info:
            st.position_mm()
    msg = str(info.value)
    assert "\n" not in msg and emu.port in msg and "garbled reply" in msg and "4 replies in a row" in msg


def test_an_echoing_port_is_read_past(emu, caplog):
    emu.inject("echo")
    with caplog.at_level(logging.WARNING, logger="acquisition.stage"), _stage(emu) as st:
        st.home()
        assert st.move_to(2.5) == pytest.approx(2.5)
    assert any("echoes every command" in r.getMessage() for r in caplog.records)


def test_a_power_cycle_during_a_move_is_reported_as_a_lost_reference(emu):
    with _stage(emu) as st:
        st.home()
        emu.speed_mm_s = 20.0
        threading.Timer(0.2, emu.power_cycle).start()
        with pytest.raises(DeviceError) as info:
            st.move_to(30.0)
    msg = str(info.value)
    assert "\n" not in msg and "lost its reference position" in msg and "power-cycled" in msg and "home again" in msg
    assert "WR" in emu.flags and "NI" in emu.flags and not emu.busy


def test_an_adapter_unplugged_and_back_stops_the_stage(emu):
    with _stage(emu) as st:
        st.home()
        emu.speed_mm_s = 10.0
        st._command("move abs 400000")
        emu.inject("reconnect", down_s=0.1)
        with pytest.raises(DeviceError) as info:
            st.position_mm()
        msg = str(info.value)
        assert "\n" not in msg and "device disconnected" in msg and "came back" in msg and "told to stop" in msg
        assert wait_for(lambda: not emu.busy, 2.0)
        assert st.position_mm() == pytest.approx(emu.position_mm, abs=1e-3)  # the port works again


def test_a_second_device_on_the_chain_is_addressed_alone():
    a = ZaberDevice(address=1, deviceid=59901, axes=[ZaberAxis(ZABER_PRODUCTS[59901])])
    b = ZaberDevice(address=2, deviceid=59902, axes=[ZaberAxis(ZABER_PRODUCTS[59902])])
    with StageEmulator(chain=[a, b], device=2, latency_s=0, homed=True, position_mm=3.0) as e, \
            _stage(e, device=2) as st:
        assert st.identity.deviceid == 59902 and st.microstep_um == pytest.approx(0.047625)
        assert st.move_to(10.0) == pytest.approx(10.0, abs=1e-4)
        assert b.axes[0].true_um == pytest.approx(10000.0, abs=0.1) and a.axes[0].true_um == pytest.approx(3000.0)


# --- the official Zaber library ------------------------------------------------------------
def test_zaber_motion_drives_the_emulated_stage(emu):
    zm = pytest.importorskip("zaber_motion")
    from zaber_motion.ascii import Connection

    # Offline, the library cannot identify devices: identification downloads the product's
    # description from Zaber's device database (or reads the devices-public.sqlite file). So
    # devices are detected without it and driven in native units, converted with the full step
    # of the product and the resolution the library reads from the device.
    with Connection.open_serial_port(emu.port, direct=True) as conn:
        (device,) = conn.detect_devices(identify_devices=False)
        assert device.device_address == 1
        assert int(device.settings.get("deviceid")) == 59901
        axis = device.get_axis(1)
        um = ZABER_PRODUCTS[59901].full_step_um / axis.settings.get("resolution")
        assert "WR" in axis.warnings.get_flags()
        axis.home()
        assert axis.get_position() == 0 and emu.homed
        axis.move_absolute(round(7.5 * 1000 / um))
        assert axis.get_position() * um / 1000 == pytest.approx(7.5)
        assert emu.position_mm == pytest.approx(7.5)
        axis.move_relative(round(-2.5 * 1000 / um))
        assert emu.position_mm == pytest.approx(5.0)
        axis.move_velocity(round(5.0 * 1000 / um * 1.6384))  # 5 mm/s
        time.sleep(0.1)
        axis.stop()
        assert not axis.is_busy() and not emu.busy and emu.position_mm > 5.0
        emu.set_flags("WT")
        assert "WT" in axis.warnings.get_flags()
    assert zm is not None
