"""The Quantum Composers 9520 driver against the emulator, through a real pseudo-terminal."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from acquisition.protocols import DeviceError, PulseGenerator, TimingPlan
from acquisition.pulse_generator import QuantumComposers9520
from acquisition.timing import plan_timing
from sim.serial_emulators import PulseGeneratorEmulator
from tests.conftest import wait_for

REPO = Path(__file__).resolve().parents[3]
PERIOD_S = 0.004  # faster than any laser, to keep the tests short


@pytest.fixture
def emu():
    with PulseGeneratorEmulator(latency_s=0) as e:
        yield e


@pytest.fixture
def gen(emu):
    g = QuantumComposers9520(emu.port, timeout_s=0.2)
    g.open()
    yield g
    g.close()


@pytest.fixture
def plan(tiny_rig) -> TimingPlan:
    return dataclasses.replace(plan_timing(tiny_rig), period_s=PERIOD_S)


def burst(plan: TimingPlan, n: int) -> TimingPlan:
    return dataclasses.replace(plan, pulses=n)


def assert_safe(emu: PulseGeneratorEmulator) -> None:
    """T0 stopped and every output disabled (waits for commands sent without waiting for replies)."""
    assert wait_for(lambda: not emu.running and not emu.outputs_enabled(), 3.0), (
        f"running={emu.running} enabled={emu.enabled_channels()}")


def test_driver_satisfies_the_protocol(gen):
    assert isinstance(gen, PulseGenerator)


def test_open_identifies_counts_channels_and_starts_safe(emu, gen):
    assert gen.identify().startswith("QC,9528,")
    assert gen.n_channels == 8
    assert not gen.armed
    assert emu.commands[0] == "*IDN?"
    assert ":PULSE0:STATE OFF" in emu.commands
    assert_safe(emu)


@pytest.mark.parametrize("pulses", [0, 25])
def test_program_loads_every_setting_with_outputs_off(emu, gen, plan, pulses):
    gen.program(burst(plan, pulses))
    assert emu.period_s == pytest.approx(PERIOD_S)
    assert emu.trigger_mode == "DIS"
    assert emu.mode == ("BURS" if pulses else "NORM")
    if pulses:
        assert emu.burst_count == pulses
    for c in plan.channels:
        st = emu.channel_state(c.channel)
        assert st.delay_s == pytest.approx(c.delay_s, abs=1e-11)
        assert st.width_s == pytest.approx(c.width_s, abs=1e-11)
        assert (st.sync, st.polarity, st.mode, st.enabled) == ("T0", "NORM", "NORM", False)
    assert not emu.running and not gen.armed


def test_program_undoes_front_panel_routing_and_gating(emu, gen, plan):
    # left from the front panel: output 2 driven by timer 1 as well, and an external gate
    for cmd in (":PULSE2:MUX 3", ":PULSE0:GATE:MODE PULS"):
        assert emu._execute(cmd) == "ok"
    assert emu.channel_state(2).mux == 3 and emu.gate_mode == "PULS"
    gen.program(plan)
    assert emu.gate_mode == "DIS"
    assert {c.channel: emu.channel_state(c.channel).mux for c in plan.channels} == {
        c.channel: 1 << (c.channel - 1) for c in plan.channels}


def test_arm_fires_and_disarm_stops(emu, gen, plan):
    ticks: list[tuple[int, int, dict[int, float]]] = []
    emu.add_listener(lambda tick, t0_ns, outputs: ticks.append((tick, t0_ns, outputs)))
    gen.program(plan)
    gen.arm()
    assert gen.armed and emu.running and emu.firing
    assert set(emu.enabled_channels()) == {c.channel for c in plan.channels}
    assert wait_for(lambda: len(ticks) >= 3)
    assert [t[0] for t in ticks[:3]] == [0, 1, 2]
    assert ticks[1][1] > ticks[0][1]
    assert ticks[0][2] == pytest.approx({c.channel: c.delay_s for c in plan.channels})
    gen.disarm()
    assert not gen.armed
    assert_safe(emu)
    fired = emu.ticks_fired
    time.sleep(3 * PERIOD_S)
    assert emu.ticks_fired == fired


def test_burst_mode_stops_by_itself_after_n_periods(emu, gen, plan):
    ticks = []
    emu.add_listener(lambda tick, t0_ns, outputs: ticks.append(tick))
    gen.program(burst(plan, 5))
    gen.arm()
    assert emu.wait_stopped(5.0)
    assert emu.ticks_fired == 5 and ticks == [0, 1, 2, 3, 4]
    assert not gen.is_running()
    gen.disarm()
    assert_safe(emu)


def test_programming_an_armed_generator_disarms_it_first(emu, gen, plan):
    gen.program(plan)
    gen.arm()
    gen.program(burst(plan, 3))
    assert not gen.armed
    assert_safe(emu)


def test_arm_before_program_is_refused(gen):
    with pytest.raises(DeviceError, match="program"):
        gen.arm()


def test_plan_on_a_missing_channel_is_refused(plan):
    with PulseGeneratorEmulator(channels=4, latency_s=0) as emu, QuantumComposers9520(emu.port) as gen:
        assert gen.n_channels == 4
        with pytest.raises(DeviceError, match=r"channel 5 .*pulse_generator.channels"):
            gen.program(plan)
        assert_safe(emu)


@pytest.mark.parametrize("fault, words", [
    ("no_reply", ["no reply within 0.2 s", "laser state UNKNOWN", "interlock"]),
    ("garbled", ["garbled reply", "laser state UNKNOWN", "interlock"]),
])
def test_silent_or_garbled_generator_is_still_switched_off(emu, gen, plan, fault, words):
    gen.program(plan)
    gen.arm()
    emu.inject(fault)
    with pytest.raises(DeviceError) as info:
        gen.identify()
    msg = str(info.value)
    assert "\n" not in msg and emu.port in msg and "'*IDN?'" in msg
    for w in words:
        assert w in msg
    assert not gen.armed
    assert_safe(emu)  # the driver sent the shutdown anyway, and the instrument obeyed


def test_error_code_is_explained_and_outputs_switched_off(emu, gen, plan):
    gen.program(plan)
    gen.arm()
    emu.inject("error", code=5)
    with pytest.raises(DeviceError) as info:
        gen.identify()
    msg = str(info.value)
    assert "?5 (invalid parameter)" in msg and "timing plan" in msg and "outputs switched off" in msg
    assert not gen.armed
    assert_safe(emu)


@pytest.mark.parametrize("after", [0, 2, 4])
def test_error_in_the_middle_of_arming_leaves_everything_off(emu, gen, plan, after):
    gen.program(plan)
    emu.inject("error", code=8, after=after)
    with pytest.raises(DeviceError, match=r"\?8 \(command unavailable"):
        gen.arm()
    assert not gen.armed
    assert_safe(emu)


def test_error_in_the_middle_of_programming_leaves_everything_off(emu, gen, plan):
    emu.inject("error", code=5, after=12)
    with pytest.raises(DeviceError, match=r"\?5"):
        gen.program(plan)
    assert gen.plan is None
    assert_safe(emu)


def test_disconnect_reports_unknown_state_and_the_generator_keeps_firing(emu, gen, plan):
    # An unplugged cable: the host can no longer stop the generator. The driver must say so
    # (and count itself disarmed); the instrument, like the real one, keeps firing.
    gen.program(plan)
    gen.arm()
    emu.inject("disconnect")
    with pytest.raises(DeviceError) as info:
        gen.disarm()
    msg = str(info.value)
    assert "device disconnected" in msg and "laser state UNKNOWN" in msg and "interlock" in msg
    assert not gen.armed
    assert not emu.connected and emu.running and emu.firing
    fired = emu.ticks_fired
    assert wait_for(lambda: emu.ticks_fired > fired)
    gen.close()  # no longer armed: releasing the port does not raise


def test_context_manager_disarms_when_the_body_raises(emu, plan):
    with pytest.raises(RuntimeError, match="boom"), QuantumComposers9520(emu.port) as gen:
        gen.program(plan)
        gen.arm()
        assert emu.firing
        raise RuntimeError("boom")
    assert not gen.armed
    assert_safe(emu)


@pytest.mark.parametrize("fault, words", [("no_reply", "no reply"), ("garbled", "garbled")])
def test_open_refuses_a_port_that_does_not_identify(emu, fault, words):
    emu.inject(fault)
    with pytest.raises(DeviceError, match=rf"'\*IDN\?'.*{words}"):
        QuantumComposers9520(emu.port, timeout_s=0.2).open()


def test_open_refuses_a_foreign_identification(emu):
    emu.idn = "HELLO"
    with pytest.raises(DeviceError, match="not a Quantum Composers"):
        QuantumComposers9520(emu.port).open()


def test_open_refuses_a_missing_port(tmp_path):
    with pytest.raises(DeviceError, match="cannot open the port"):
        QuantumComposers9520(str(tmp_path / "ttyNONE")).open()


CHILD = textwrap.dedent("""
    import dataclasses, signal, sys, time
    from acquisition.protocols import ChannelSetting, TimingPlan
    from acquisition.pulse_generator import QuantumComposers9520

    mode = sys.argv[2]
    if mode == "chain":
        def previous(signum, frame):
            print("previous handler ran", flush=True)
            sys.exit(3)
        signal.signal(signal.SIGTERM, previous)
    plan = TimingPlan(period_s=0.004, dt_s=1e-4, channels=(
        ChannelSetting(1, "flashlamp1", 0.0, 1e-5), ChannelSetting(2, "qswitch1", 1.8e-4, 1e-5)))
    gen = QuantumComposers9520(sys.argv[1])
    gen.open()
    gen.program(plan)
    if mode == "thread":
        # as the live monitor does: the main thread installs the handlers, a thread arms
        import threading
        from acquisition.pulse_generator import install_signal_handlers
        install_signal_handlers()
        t = threading.Thread(target=gen.arm)
        t.start()
        t.join()
    else:
        gen.arm()
    print("armed", flush=True)
    if mode == "exit":
        sys.exit(0)  # forgets to disarm: atexit must do it
    time.sleep(30)
""")


@pytest.mark.parametrize("mode, returncode", [
    ("default", -signal.SIGTERM), ("chain", 3), ("exit", 0), ("thread", -signal.SIGTERM),
])
def test_a_process_that_dies_disarms_its_generator(emu, mode, returncode):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen([sys.executable, "-c", CHILD, emu.port, mode], cwd=REPO, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(child.stdout), daemon=True)
        reader.start()
        assert wait_for(lambda: "armed\n" in lines or child.poll() is not None, 20.0)
        if mode != "exit":
            assert "armed\n" in lines, child.stderr.read()
            assert emu.firing
            child.send_signal(signal.SIGTERM)
        assert child.wait(timeout=20) == returncode, child.stderr.read()
        reader.join(timeout=5)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert "armed\n" in lines
    if mode == "chain":
        assert "previous handler ran\n" in lines
    assert_safe(emu)


def test_an_ignored_sighup_stays_ignored():
    # under nohup a closed terminal must not stop the recording (nor the laser it needs)
    from acquisition.pulse_generator import install_signal_handlers

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        install_signal_handlers()
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_signals_held_disarm_and_wait_then_give_way(emu, gen, plan):
    """While a run is closed, Ctrl-C and SIGTERM disarm and are held during the grace time; one
    after it ends the cleanup."""
    from acquisition.pulse_generator import signals_held

    gen.program(plan)
    notes = []
    with signals_held(lambda: notes.append("one moment"), grace_s=60.0) as held:
        gen.arm()
        assert wait_for(lambda: emu.firing)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # handlers run between bytecodes of the main thread
        assert held == [signal.SIGTERM] and notes == ["one moment"]
        assert_safe(emu)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert held == [signal.SIGTERM, signal.SIGINT] and len(notes) == 1
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with signals_held(grace_s=0.0) as held, pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
    assert held == [signal.SIGINT, signal.SIGINT]


def test_a_signal_during_a_signals_disarm_does_not_break_into_it(emu, gen, plan, monkeypatch):
    """Two SIGTERMs milliseconds apart: the second arrives while the first handler talks to the
    generator, and must neither interleave its own commands nor raise into that exchange (which
    reported the laser state as unknown)."""
    import acquisition.pulse_generator as pg

    gen.program(plan)
    gen.arm()
    assert wait_for(lambda: emu.firing)
    calls = []
    shutdown = gen._shutdown

    def second_signal_mid_shutdown():
        calls.append("shutdown")
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the nested handler runs here
        return shutdown()

    monkeypatch.setattr(gen, "_shutdown", second_signal_mid_shutdown)
    hooks = []

    def hook():
        hooks.append("hook")
        raise KeyboardInterrupt

    with pg.signals_call(hook), pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)
    assert calls == ["shutdown"] and hooks == ["hook"]  # the nested signal did nothing
    assert_safe(emu)
