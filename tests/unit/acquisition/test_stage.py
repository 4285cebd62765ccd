"""The Zaber stage driver against the emulator, through a real pseudo-terminal."""

from __future__ import annotations

import threading
import time

import pytest

from acquisition.protocols import DeviceError, Stage
from acquisition.stage import ZaberStage, parse_reply
from sim.serial_emulators import StageEmulator


@pytest.fixture
def emu():
    with StageEmulator(latency_s=0, speed_mm_s=100.0, position_mm=12.5) as e:
        yield e


@pytest.fixture
def stage(emu):
    with ZaberStage(emu.port, timeout_s=0.2, move_timeout_s=3.0, poll_s=0.005) as s:
        yield s


@pytest.fixture
def homed(stage):
    stage.home()
    return stage


def test_driver_satisfies_the_protocol(stage):
    assert isinstance(stage, Stage)


def test_reply_parsing():
    r = parse_reply("@01 1 OK BUSY WR 1234")
    assert (r.device, r.axis, r.flag, r.status, r.warning, r.data) == (1, 1, "OK", "BUSY", "WR", "1234")
    assert parse_reply("@02 0 RJ IDLE -- BADCOMMAND:4F").data == "BADCOMMAND"
    assert parse_reply("#01 1 info") is None and parse_reply("garbage") is None


def test_open_reads_the_travel(stage):
    assert stage.travel_mm == (0.0, 50.0)


def test_unhomed_stage_refuses_to_move(emu, stage):
    assert not emu.homed
    with pytest.raises(DeviceError, match=r"not homed.*home\(\) first"):
        stage.move_to(3.0)
    assert not any(c.endswith("move abs 30000") for c in emu.commands)
    assert emu.position_mm == pytest.approx(12.5)


def test_the_device_itself_rejects_an_unhomed_move(emu, stage):
    # Even if the driver's own check were skipped, the device's WR rejection is recognised.
    with pytest.raises(DeviceError, match="not homed"):
        stage._command("move abs 30000")
    assert emu.position_mm == pytest.approx(12.5)


def test_home_zeroes_the_position(emu, stage):
    stage.home()
    assert emu.homed and not emu.busy
    assert emu.position_mm == pytest.approx(0.0)
    assert stage.position_mm() == pytest.approx(0.0)


def test_move_polls_until_idle_and_returns_the_readback(emu, homed):
    n_before = len(emu.commands)
    reached = homed.move_to(7.25)
    assert reached == pytest.approx(7.25)
    assert emu.position_mm == pytest.approx(7.25)
    assert homed.position_mm() == pytest.approx(7.25)
    polls = [c for c in emu.commands[n_before:] if c.endswith("get pos")]
    assert len(polls) >= 2  # BUSY was seen at least once before IDLE


def test_target_outside_the_travel_is_refused_before_sending(emu, homed):
    with pytest.raises(DeviceError, match=r"outside the travel \[0, 50\] mm"):
        homed.move_to(60.0)
    assert not any("move abs 600000" in c for c in emu.commands)


def test_limit_sensor_stops_the_move(emu, homed):
    emu.inject("limit")
    with pytest.raises(DeviceError, match=r"WL \(unexpected limit sensor\)"):
        homed.move_to(20.0)
    assert 0.0 < emu.position_mm < 20.0
    assert homed.move_to(4.0) == pytest.approx(4.0)  # latched WL is cleared before the next move


def test_stall_times_out_and_stops_the_stage(emu, homed):
    homed.move_timeout_s = 0.3
    emu.inject("stall")
    with pytest.raises(DeviceError, match=r"did not reach 5.0000 mm within 0.3 s.*stalled"):
        homed.move_to(5.0)
    assert not emu.busy
    assert any(c.endswith(" stop") for c in emu.commands)


def test_slip_beyond_tolerance_is_reported(emu, homed):
    emu.inject("slip")
    with pytest.raises(DeviceError, match=r"um from the target 5.0000 mm \(tolerance 1 um\)"):
        homed.move_to(5.0)


def test_stop_interrupts_a_move_from_another_thread(emu, homed):
    emu.speed_mm_s = 20.0
    errors: list[Exception] = []

    def move():
        try:
            homed.move_to(40.0)
        except DeviceError as e:
            errors.append(e)

    mover = threading.Thread(target=move)
    mover.start()
    deadline = time.monotonic() + 5
    while not emu.busy and time.monotonic() < deadline:
        time.sleep(0.002)
    homed.stop()
    mover.join(timeout=5)
    assert not emu.busy
    assert 0.0 < emu.position_mm < 40.0
    assert errors and "from the target" in str(errors[0])


def test_rejected_command_names_the_reason(stage):
    with pytest.raises(DeviceError, match=r"'get foo': rejected with BADCOMMAND"):
        stage._command("get foo")


@pytest.mark.parametrize("fault, words", [
    ("no_reply", "no reply within 0.2 s"),
    ("garbled", "garbled reply"),
    ("disconnect", "device disconnected"),
])
def test_link_faults_raise_one_line_naming_port_and_command(emu, homed, fault, words):
    emu.inject(fault)
    with pytest.raises(DeviceError) as info:
        homed.position_mm()
    msg = str(info.value)
    assert "\n" not in msg and emu.port in msg and "'get pos'" in msg and words in msg and "check" in msg


def test_a_stage_at_another_address_does_not_answer(emu):
    with pytest.raises(DeviceError, match=r"no reply.*device number \(2\)"):
        ZaberStage(emu.port, device=2, timeout_s=0.2).open()


def test_context_manager_stops_a_moving_stage_when_the_body_raises(emu):
    with pytest.raises(RuntimeError, match="boom"), ZaberStage(emu.port, timeout_s=0.2) as st:
        st.home()
        emu.speed_mm_s = 5.0
        st._command("move abs 400000")
        assert emu.busy
        raise RuntimeError("boom")
    assert not emu.busy
