"""The pulse-generator driver reads back what it programs, reports the timing as programmed,
and every fault of a real link ends with the laser disarmed and one line naming the cause."""

from __future__ import annotations

import dataclasses
import threading

import pytest

from acquisition.protocols import DeviceError, TimingPlan
from acquisition.pulse_generator import PULSE_GENERATOR_MODELS, QuantumComposers9520
from acquisition.timing import plan_timing
from sim.serial_emulators import PulseGeneratorEmulator
from tests.conftest import wait_for

PERIOD_S = 0.004


@pytest.fixture
def emu():
    with PulseGeneratorEmulator(latency_s=0) as e:
        yield e


@pytest.fixture
def plan(tiny_rig) -> TimingPlan:
    return dataclasses.replace(plan_timing(tiny_rig), period_s=PERIOD_S)


def _gen(emu, **kw) -> QuantumComposers9520:
    # a reply may wait for a busy CPU (the emulator is a thread of this process): 1 s, not the default 0.5 s
    g = QuantumComposers9520(emu.port, timeout_s=1.0, reconnect_s=kw.pop("reconnect_s", 1.0), **kw)
    g.open()
    return g


def assert_safe(emu) -> None:
    assert wait_for(lambda: not emu.running and not emu.outputs_enabled(), 3.0), (
        f"running={emu.running} enabled={emu.enabled_channels()}")


def _odd(plan: TimingPlan, extra_s: float) -> TimingPlan:
    """The plan with ``extra_s`` added to the first channel's delay."""
    first = dataclasses.replace(plan.channels[0], delay_s=plan.channels[0].delay_s + extra_s)
    return dataclasses.replace(plan, channels=(first, *plan.channels[1:]))


@pytest.mark.parametrize("model, rounded", [("9528", 0.25e-9), ("575-8", 0.25e-9), ("9518", 0.0)])
def test_the_programmed_timing_is_the_rounded_read_back(plan, model, rounded):
    with PulseGeneratorEmulator(latency_s=0, model=model) as e:
        gen = _gen(e)
        try:
            assert gen.model == PULSE_GENERATOR_MODELS[model]
            gen.program(_odd(plan, 0.37e-9))
            got = gen.programmed.channels[0].delay_s
            assert got == pytest.approx(plan.channels[0].delay_s + rounded, abs=1e-15)
            assert gen.plan.channels[0].delay_s == pytest.approx(plan.channels[0].delay_s + 0.37e-9, abs=1e-15)
            assert gen.programmed.period_s == pytest.approx(PERIOD_S)
            assert any(c.endswith("DELAY?") for c in e.commands) and any(c.endswith("WIDT?") for c in e.commands)
            gen.arm()
            assert e.firing
        finally:
            gen.close()
        assert_safe(e)


def test_a_read_back_further_off_than_the_resolution_refuses_to_arm(emu, plan):
    gen = _gen(emu)
    emu.model = PULSE_GENERATOR_MODELS["9518"]  # the instrument rounds to 1 ns, the driver expects 250 ps
    with pytest.raises(DeviceError) as info:
        gen.program(_odd(plan, 0.6e-9))
    msg = str(info.value)
    assert "\n" not in msg and "reads back" in msg and "250 ps resolution" in msg and "outputs switched off" in msg
    assert gen.plan is None and gen.programmed is None
    with pytest.raises(DeviceError, match="program"):
        gen.arm()
    assert_safe(emu)
    gen.close()


def test_a_setting_changed_behind_the_drivers_back_refuses_to_arm(emu, plan, monkeypatch):
    gen = _gen(emu)
    real = emu._execute

    def front_panel(line):  # someone turns on the gate while the plan is loaded
        if line.startswith(":PULSE0:GATE:MODE?"):
            return "PULS"
        return real(line)

    monkeypatch.setattr(emu, "_execute", front_panel)
    with pytest.raises(DeviceError, match=r"':PULSE0:GATE:MODE\?': reads back 'PULS', programmed 'DIS'"):
        gen.program(plan)
    assert gen.programmed is None
    gen.close()


def test_verify_catches_a_power_cycle_in_the_middle_of_a_run(emu, plan):
    gen = _gen(emu)
    gen.program(plan)
    gen.arm()
    gen.verify()  # all as programmed
    emu.power_cycle()
    with pytest.raises(DeviceError) as info:
        gen.verify()
    msg = str(info.value)
    assert "\n" not in msg and emu.port in msg and "power cycle" in msg and "outputs switched off" in msg
    assert not gen.armed
    assert_safe(emu)
    gen.close()


def test_a_reset_command_lost_with_the_power_is_caught_on_the_next_command(emu, plan):
    gen = _gen(emu)
    gen.program(plan)
    gen.arm()
    emu.inject("reset")
    with pytest.raises(DeviceError, match=r"no reply.*outputs switched off"):
        gen.identify()
    assert not gen.armed
    assert_safe(emu)
    gen.close()


def test_a_split_reply_is_read_whole(emu, plan):
    emu.inject("split", gap_s=0.02)
    gen = _gen(emu)
    gen.program(plan)
    gen.arm()
    assert emu.firing
    gen.close()
    assert_safe(emu)


def test_a_stray_byte_while_armed_disarms_and_says_so(emu, plan):
    gen = _gen(emu)
    gen.program(plan)
    gen.arm()
    emu.inject("stray")
    with pytest.raises(DeviceError) as info:
        gen.is_running()
    msg = str(info.value)
    assert "\n" not in msg and "garbled reply" in msg and "outputs switched off" in msg
    assert not gen.armed
    assert_safe(emu)
    gen.close()


def test_echo_switched_on_at_the_front_panel(emu, plan):
    emu._execute(":SYST:COMM:SER:ECHO ON")
    gen = _gen(emu)  # open notices the echo and switches it off
    assert not emu.echo
    gen.program(plan)
    gen.arm()
    emu._execute(":SYST:COMM:SER:ECHO ON")  # on again while the laser fires
    with pytest.raises(DeviceError) as info:
        gen.is_running()
    msg = str(info.value)
    assert "\n" not in msg and "echoing every command" in msg and "outputs switched off" in msg
    assert not gen.armed
    assert_safe(emu)
    gen.close()


def test_an_adapter_unplugged_and_back_in_is_used_to_disarm(emu, plan):
    gen = _gen(emu)
    gen.program(plan)
    gen.arm()
    emu.inject("reconnect", down_s=0.2)
    with pytest.raises(DeviceError) as info:
        gen.is_running()
    msg = str(info.value)
    assert "\n" not in msg and "device disconnected" in msg and "the port came back" in msg
    assert "outputs switched off" in msg and "UNKNOWN" not in msg
    assert not gen.armed
    assert_safe(emu)
    gen.close()


def test_an_adapter_unplugged_for_good_says_the_laser_state_is_unknown(emu, plan):
    gen = _gen(emu, reconnect_s=0.3)
    gen.program(plan)
    gen.arm()
    emu.disconnect()
    with pytest.raises(DeviceError, match=r"device disconnected.*laser state UNKNOWN"):
        gen.is_running()
    assert emu.firing  # nothing can reach it
    threading.Thread(target=emu.reconnect).start()
    gen.close()
