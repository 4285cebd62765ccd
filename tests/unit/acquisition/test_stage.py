"""The Zaber stage driver against the emulator, through a real pseudo-terminal."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from acquisition.protocols import DeviceError, Stage
from acquisition.serial_link import LinkTimeout
from acquisition.stage import CorruptReply, ZaberStage, checksum, parse_reply
from sim.serial_emulators import StageEmulator


@pytest.fixture
def emu():
    with StageEmulator(latency_s=0, speed_mm_s=100.0, position_mm=12.5) as e:
        yield e


@pytest.fixture
def stage(emu):
    with ZaberStage(emu.port, timeout_s=0.2, move_timeout_s=3.0, poll_s=0.005, retry_pause_s=0.001) as s:
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
    assert parse_reply("@02 0 RJ IDLE -- BADCOMMAND:F4").data == "BADCOMMAND"
    assert parse_reply("@02 0 RJ IDLE -- BADCOMMAND:f4").data == "BADCOMMAND"  # hex in either case
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
    with pytest.raises(DeviceError, match=r"WL \(unexpected limit trigger\)"):
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


def _one_line(msg: str, port: str, cmd: str) -> bool:
    return "\n" not in msg and port in msg and f"'{cmd}'" in msg and "check" in msg


# --- checksums ---------------------------------------------------------------------------

def test_checksum_is_the_twos_complement_of_the_byte_sum():
    # Test vector from zproto (Rust Zaber library): "/1 2 tools echo command\:12".
    assert checksum("1 2 tools echo command\\") == "12"
    for body in ("01 1 OK IDLE -- 0", "01 1 OK BUSY WR 125000", "1 1 move abs 5"):
        assert (sum(body.encode()) + int(checksum(body), 16)) % 256 == 0


def test_a_reply_with_a_wrong_checksum_is_never_parsed_as_data():
    good = "@01 1 OK IDLE -- 70000"
    line = f"{good}:{checksum(good[1:])}"
    assert parse_reply(line).data == "70000"
    corrupted = line.replace("70000", "20000")  # one digit flipped on the line
    with pytest.raises(CorruptReply, match="checksum"):
        parse_reply(corrupted)
    with pytest.raises(CorruptReply):
        parse_reply(f"{good}:00")


def test_stage_with_checksummed_replies_works(emu, stage):
    emu.checksums = True
    stage.home()
    assert stage.move_to(3.5) == pytest.approx(3.5)
    assert stage.position_mm() == pytest.approx(3.5)


def test_a_corrupt_position_reply_is_sent_again_not_used(emu, homed):
    emu.checksums = True
    homed.move_to(7.0)
    n_before = len(emu.commands)
    emu.inject("bad_checksum")  # the reply's first digit flips: 70000 -> 20000
    assert homed.position_mm() == pytest.approx(7.0)
    assert emu.commands[n_before:] == ["/1 1 get pos", "/1 1 get pos"]


def test_a_corrupt_reply_is_caught_even_without_checksums_switched_on(emu, homed):
    # The fault appends the checksum of the original text, as the device would have sent it.
    emu.inject("bad_checksum")
    assert homed.position_mm() == pytest.approx(0.0)


def test_a_corrupt_reply_to_a_move_resends_the_same_absolute_move(emu, homed):
    emu.checksums = True
    n_before = len(emu.commands)
    emu.inject("bad_checksum", after=2)  # 'warnings clear', 'warnings', then the move's reply
    assert homed.move_to(6.0) == pytest.approx(6.0)
    moves = [c for c in emu.commands[n_before:] if "move abs" in c]
    assert moves == ["/1 1 move abs 60000", "/1 1 move abs 60000"]
    assert emu.position_mm == pytest.approx(6.0)


def test_persistent_corruption_fails_on_one_line(emu, homed):
    emu.checksums = True
    emu.inject("bad_checksum", count=10)
    with pytest.raises(DeviceError, match=r"4 replies in a row failed their checksum") as info:
        homed.position_mm()
    assert _one_line(str(info.value), emu.port, "get pos")
    assert "cable" in str(info.value)


def test_commands_can_carry_checksums(emu):
    with ZaberStage(emu.port, timeout_s=0.2, poll_s=0.005, send_checksums=True) as st:
        st.home()
        assert st.move_to(2.0) == pytest.approx(2.0)
    assert any("move abs 20000:" in c for c in emu.commands)
    assert all(c[-3] == ":" and checksum(c[1:-3]) == c[-2:] for c in emu.commands)


def test_the_emulator_drops_a_command_with_a_wrong_checksum(emu, stage):
    stage._link.write_line("/1 1 get pos:00")
    with pytest.raises(LinkTimeout):
        stage._link.read_line(0.2)


# --- AGAIN -------------------------------------------------------------------------------

def test_again_is_retried(emu, homed):
    n_before = len(emu.commands)
    emu.inject("again", count=2)
    assert homed.position_mm() == pytest.approx(0.0)
    assert emu.commands[n_before:] == ["/1 1 get pos"] * 3


def test_again_on_a_move_is_retried_and_the_move_happens_once(emu, homed):
    n_before = len(emu.commands)
    emu.inject("again", after=2)  # 'warnings clear', 'warnings', then the move
    assert homed.move_to(9.0) == pytest.approx(9.0)
    moves = [c for c in emu.commands[n_before:] if "move abs" in c]
    assert moves == ["/1 1 move abs 90000", "/1 1 move abs 90000"]
    assert "NI" not in emu.flags  # the refused first copy never started a move


def test_again_that_does_not_stop_fails_on_one_line(emu, homed):
    emu.inject("again", count=10)
    with pytest.raises(DeviceError, match=r"rejected with AGAIN .* 4 times in a row") as info:
        homed.position_mm()
    assert _one_line(str(info.value), emu.port, "get pos")


def test_no_retries_when_switched_off(emu):
    with ZaberStage(emu.port, timeout_s=0.2, retries=0) as st:
        emu.inject("again")
        with pytest.raises(DeviceError, match="AGAIN .* 1 times in a row"):
            st.position_mm()


# --- the full warning list ---------------------------------------------------------------

def test_emulator_lists_every_flag_highest_priority_first(emu, stage):
    emu.set_flags("NC", "WV", "FQ")
    reply = stage._command("warnings")
    assert reply.warning == "FQ"
    assert reply.data == "04 FQ WV WR NC"
    with pytest.raises(ValueError, match="unknown flags"):
        emu.set_flags("XX")


def test_a_fatal_flag_below_a_harmless_one_fails_the_move(emu, homed):
    emu.inject("flags", flags=("WT", "WM"))  # temperature high (shown), displaced (hidden)
    with pytest.raises(DeviceError, match=r"stopped at 8\.0000 mm with flag WM \(displaced when stationary\)") as info:
        homed.move_to(8.0)
    assert _one_line(str(info.value), emu.port, "move abs 80000")
    assert "WT" not in str(info.value)
    assert homed._command("get pos").warning == "WT"  # what a single-flag check would have seen


def test_harmless_warnings_and_notices_do_not_fail_a_move(emu, homed, caplog):
    emu.inject("flags", flags=("WV", "NC"))
    with caplog.at_level(logging.WARNING, logger="acquisition.stage"):
        assert homed.move_to(4.5) == pytest.approx(4.5)
    assert any("WV" in r.getMessage() for r in caplog.records)


def test_a_fault_among_several_flags_fails_homing(emu, stage):
    emu.inject("flags", flags=("WT", "WM"))
    with pytest.raises(DeviceError, match=r"'home': finished at 0\.0000 mm with flag WM") as info:
        stage.home()
    assert _one_line(str(info.value), emu.port, "home")


def test_homing_that_leaves_no_reference_position_fails(emu, stage):
    emu.inject("flags", flags=("WR",))
    with pytest.raises(DeviceError, match=r"flag WR \(no reference position\)"):
        stage.home()


def test_a_standing_fault_refuses_the_move_before_sending_it(emu, homed):
    emu.set_flags("FD")  # not cleared by 'warnings clear'
    with pytest.raises(DeviceError, match=r"refused to move: flag FD .* still active") as info:
        homed.move_to(5.0)
    assert _one_line(str(info.value), emu.port, "move abs 50000")
    assert not any("move abs" in c for c in emu.commands)
