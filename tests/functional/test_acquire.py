"""Recording on the simulated lab: the real serial driver talks to the emulated pulse generator on
a pseudo-terminal, which triggers two simulated light-field cameras; the session and recorder
write the run store. Every failure path must leave the laser disarmed and what was recorded
readable."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition.protocols import DeviceError
from lfcore.rig import Rig
from lfcore.runstore import RunStore, RunStoreError
from lfpiv.cli import main
from lfpiv.errors import UsageError
from lfpiv.jobs.acquire import record
from lfpiv.jobs.devices import list_devices
from lfpiv.rigfile import load_rig
from lfpiv.rigging import open_rig
from tests.helpers import (
    LFPIV,
    VIKY,
    fast_rig_text,
    signal_when_committed,
    sim_lab,
    terminal_signals,
    wait_committed,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def fast_rig_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "fast.toml"
    path.write_text(fast_rig_text())
    return path


@pytest.fixture(scope="module")
def fast_rig(fast_rig_file: Path):
    return load_rig(fast_rig_file)


def _check_every_frame_accounted(store: RunStore, pairs: int) -> dict[str, list[dict]]:
    """Each of the 2 x pairs frames of each camera is recorded (with the right id) or dropped,
    never both, never neither."""
    drops = store.drops()
    per_cam = {}
    for cam in store.cameras:
        ids = store.frame_ids(cam)[:pairs]
        dropped = {(d["pair"], d["frame"]) for d in drops if d["camera"] == cam}
        mine = [d for d in drops if d["camera"] == cam]
        assert len(dropped) == len(mine), "a frame was dropped twice"
        recorded = {(p, f) for p in range(pairs) for f in range(2) if ids[p, f] >= 0}
        assert not (recorded & dropped)
        assert len(recorded) + len(dropped) == 2 * pairs
        p, f = np.nonzero(ids >= 0)
        assert np.array_equal(ids[p, f], 2 * p + f)  # frame ids pair up by trigger count
        per_cam[cam] = mine
    return per_cam


def test_soak_2000_pairs_two_cameras_with_faults(fast_rig, tmp_path: Path) -> None:
    pairs = 2000
    faults = {"cam0": {"lose_frames": {5, 777, 1500}, "incomplete_frames": {42, 43}, "lose_rate": 0.002},
              "cam1": {"incomplete_frames": {1001}, "lose_rate": 0.002}}
    with sim_lab(fast_rig, **faults) as lab:
        res = record(fast_rig, tmp_path / "soak.zarr", pairs, sim_options={"lab": lab}, ring_slots=128)
        gen = lab.pulse_generator
        triggered = gen.ticks_fired
        assert not gen.firing and not gen.outputs_enabled()
        lit = {c.name: c._lit for c in lab.cameras}
    assert res.state == "complete"
    assert triggered == pairs
    store = RunStore.open(tmp_path / "soak.zarr")
    assert store.state == "complete" and store.committed_pairs == pairs
    per_cam = _check_every_frame_accounted(store, pairs)
    # recorded + dropped == triggered, frame by frame, for both cameras
    assert res.stats.frames_recorded + len(store.drops()) == triggered * 2 * 2
    reasons = {(d["pair"] * 2 + d["frame"]): d["reason"] for d in per_cam["cam0"]}
    for fid in (5, 777, 1500):
        assert "gap" in reasons[fid]
    assert "incomplete" in reasons[42] and "incomplete" in reasons[43]
    assert "incomplete" in {d["pair"] * 2 + d["frame"]: d["reason"] for d in per_cam["cam1"]}[1001]
    assert {d["reason"].split(":")[0] for d in per_cam["cam1"]} == {"frame_id gap", "incomplete frame"}
    assert 3 <= len(per_cam["cam1"]) < 40  # about 0.2% of 4000 at random, plus one
    assert res.stats.overruns == 0
    # Recorded images are the ones the cameras produced for that trigger (pool entry k % 3).
    frames = store.frames("cam1")
    for p in (0, 1, 998, 1999):
        for f in range(2):
            if store.frame_ids("cam1")[p, f] >= 0:
                assert np.array_equal(frames[p, f], lit["cam1"][p % 3][f])
    truth = store.truth()
    assert truth is not None and truth["particles"].shape[:2] == (pairs, 2)
    # the truth flow of each pair is taken at the time of the pool pair it showed
    assert np.allclose(truth["t0_s"][:pairs], (np.arange(pairs) % 3) / store.timing["rate_hz"])


def test_missed_triggers_are_dropped_and_later_frames_keep_their_pair(fast_rig, tmp_path: Path) -> None:
    # cam0 misses triggers 4 and 9: it makes no frames for them and its frame ids stay
    # consecutive, so only its time stamps tell that every later frame belongs one or two pairs on
    pairs = 15
    with sim_lab(fast_rig, cam0={"miss_triggers": {4, 9}}) as lab:
        res = record(fast_rig, tmp_path / "missed.zarr", pairs, sim_options={"lab": lab})
        triggered = lab.pulse_generator.ticks_fired
        lit = {c.name: c._lit for c in lab.cameras}
    assert triggered == pairs and res.stats.missed_triggers == 2
    store = RunStore.open(tmp_path / "missed.zarr")
    drops = [d for d in store.drops() if d["camera"] == "cam0"]
    assert sorted((d["pair"], d["frame"]) for d in drops) == [(4, 0), (4, 1), (9, 0), (9, 1)]
    assert all(d["reason"].startswith("missed trigger") for d in drops)
    assert not [d for d in store.drops() if d["camera"] == "cam1"]
    frames = store.frames("cam0")
    for p in set(range(pairs)) - {4, 9}:  # each recorded pair holds its own trigger's images
        for f in range(2):
            assert np.array_equal(frames[p, f], lit["cam0"][p % 3][f]), (p, f)
    assert res.stats.frames_recorded + len(store.drops()) == triggered * 2 * 2


def test_camera_fault_stops_recording_disarms_and_keeps_the_data(fast_rig, tmp_path: Path) -> None:
    with sim_lab(fast_rig, cam1={"fail_after_frames": 60}) as lab:
        with pytest.raises(DeviceError, match="cam1.*laser was disarmed"):
            record(fast_rig, tmp_path / "fault.zarr", 500, sim_options={"lab": lab}, stall_s=1.0)
        assert not lab.pulse_generator.firing and not lab.pulse_generator.outputs_enabled()
        assert lab.pulse_generator.ticks_fired < 500
    store = RunStore.open(tmp_path / "fault.zarr")
    assert store.state == "aborted" and "cam1" in store.attrs["abort_reason"]
    assert 10 <= store.committed_pairs <= 30
    _check_every_frame_accounted(store, store.committed_pairs)


def test_ctrl_c_disarms_and_marks_the_run_aborted(fast_rig, tmp_path: Path) -> None:
    def interrupt(stats) -> None:
        if stats.committed_pairs >= 5:
            raise KeyboardInterrupt

    with sim_lab(fast_rig) as lab:
        with pytest.raises(KeyboardInterrupt):
            record(fast_rig, tmp_path / "int.zarr", 1000, sim_options={"lab": lab}, progress=interrupt)
        assert not lab.pulse_generator.firing and not lab.pulse_generator.outputs_enabled()
    store = RunStore.open(tmp_path / "int.zarr")
    assert store.state == "aborted" and store.committed_pairs >= 5
    _check_every_frame_accounted(store, store.committed_pairs)


def test_a_second_ctrl_c_while_the_run_is_closed_waits_for_it(fast_rig, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture) -> None:
    """Two Ctrl-Cs in quick succession: the second arrives while the run is being closed, and is
    held until the laser is disarmed and the run marked aborted with its truth."""
    def interrupt(stats) -> None:
        if stats.committed_pairs >= 5:
            raise KeyboardInterrupt

    def second_ctrl_c_on_close(session) -> None:
        close = session.close

        def close_after_ctrl_c(*args, **kwargs):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs here
            return close(*args, **kwargs)

        session.close = close_after_ctrl_c

    with sim_lab(fast_rig) as lab:
        with pytest.raises(KeyboardInterrupt):
            record(fast_rig, tmp_path / "int.zarr", 1000, sim_options={"lab": lab}, progress=interrupt,
                   on_session=second_ctrl_c_on_close)
        assert not lab.pulse_generator.outputs_enabled()
    assert "closing the run, one moment" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    store = RunStore.open(tmp_path / "int.zarr")
    assert store.state == "aborted" and store.committed_pairs >= 5 and store.truth() is not None


def test_a_ctrl_c_before_recording_begins_marks_the_run_aborted(fast_rig, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import lfpiv.jobs.acquire as acquire

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(acquire, "RecordingSession", interrupted)
    with sim_lab(fast_rig) as lab, pytest.raises(KeyboardInterrupt):
        record(fast_rig, tmp_path / "early.zarr", 10, sim_options={"lab": lab})
    store = RunStore.open(tmp_path / "early.zarr")
    assert store.state == "aborted" and store.committed_pairs == 0
    assert store.attrs["abort_reason"] == "stopped before recording began (KeyboardInterrupt)"


def test_a_full_disk_at_the_end_keeps_the_fault_and_the_laser_report(fast_rig, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch,
                                                                    capsys: pytest.CaptureFixture) -> None:
    def full(self, state):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(RunStore, "set_state", full)
    with sim_lab(fast_rig, cam1={"fail_after_frames": 40}) as lab:
        with pytest.raises(DeviceError, match="cam1.*the laser was disarmed"):
            record(fast_rig, tmp_path / "fault.zarr", 500, sim_options={"lab": lab}, stall_s=1.0)
        assert not lab.pulse_generator.outputs_enabled()
    assert ("warning: the run could not be marked 'aborted' (No space left on device), so it still says "
            "'recording'") in capsys.readouterr().err
    store = RunStore.open(tmp_path / "fault.zarr")
    assert store.state == "recording" and store.committed_pairs >= 5
    _check_every_frame_accounted(store, store.committed_pairs)
    # the error says the same as the warning: the run still says 'recording', not 'aborted'
    with sim_lab(fast_rig, cam1={"fail_after_frames": 40}) as lab, \
            pytest.raises(DeviceError, match="could not be marked 'aborted', so it still says 'recording'"):
        record(fast_rig, tmp_path / "fault2.zarr", 500, sim_options={"lab": lab}, stall_s=1.0)
    # a recording that completes but cannot be marked so is an error too, and says what it kept
    with sim_lab(fast_rig) as lab, pytest.raises(RunStoreError, match=r"recorded 10 pair\(s\) into .*done.zarr, "
                                                 "but the run could not be marked 'complete'"):
        record(fast_rig, tmp_path / "done.zarr", 10, sim_options={"lab": lab})
    assert RunStore.open(tmp_path / "done.zarr").committed_pairs == 10


def test_a_generator_that_stops_answering_stops_the_recording(fast_rig, tmp_path: Path) -> None:
    def pull_the_cable(stats) -> None:
        if stats.committed_pairs >= 5:
            lab.pulse_generator.inject("no_reply")

    with sim_lab(fast_rig) as lab:
        with pytest.raises(DeviceError, match="pulse generator") as err:
            record(fast_rig, tmp_path / "gen.zarr", 400, sim_options={"lab": lab}, progress=pull_the_cable)
        # The driver could not confirm the disarm, and the error says so (not that it was
        # disarmed); burst mode still stops the laser after the planned pulses.
        assert "laser could NOT be confirmed disarmed" in str(err.value)
        assert "the laser was disarmed" not in str(err.value)
        assert lab.pulse_generator.wait_stopped(10.0)
    store = RunStore.open(tmp_path / "gen.zarr")
    assert store.state == "aborted"
    _check_every_frame_accounted(store, store.committed_pairs)


def test_a_complete_recording_whose_disarm_is_unconfirmed_is_an_error(fast_rig, tmp_path: Path) -> None:
    # the generator stops answering after the last trigger was programmed, before the first
    # liveness ping (1 s after arming): every pair is recorded, the disarm cannot be confirmed
    def pull_the_cable(stats) -> None:
        if stats.committed_pairs >= 1:
            lab.pulse_generator.inject("no_reply")

    with sim_lab(fast_rig) as lab:
        with pytest.raises(DeviceError, match=r"recorded 20 pair\(s\): the run is kept in .*state 'complete'.*"
                                              "laser could NOT be confirmed disarmed"):
            record(fast_rig, tmp_path / "done.zarr", 20, sim_options={"lab": lab}, progress=pull_the_cable)
    store = RunStore.open(tmp_path / "done.zarr")
    assert store.state == "complete" and store.committed_pairs == 20


def test_impossible_timing_is_refused_before_any_device_opens(fast_rig_file: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture) -> None:
    rig_file = tmp_path / "bad.toml"
    rig_file.write_text(fast_rig_file.read_text().replace("dt_us = 1000.0", "dt_us = 0.1"))
    assert main(["acquire", "--rig", str(rig_file), "--pairs", "3", "--out", str(tmp_path / "x.zarr")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lfpiv: error:") and "dt" in err and "\n" not in err
    assert not (tmp_path / "x.zarr").exists()


def test_devices_lists_the_simulatedsim_lab(fast_rig_file: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["devices", "--rig", str(fast_rig_file)]) == 0
    out = capsys.readouterr().out
    assert "cam0" in out and "cam1" in out and "QC," in out and "Zaber" in out


def test_devices_addresses_the_stage_the_rig_names(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # a stage at address 2, axis 3, with a finer microstep: the emulator is set up from the same keys,
    # so the driver finds it only at that address and reads its travel in millimetres
    rig_file = tmp_path / "stage.toml"
    rig_file.write_text(fast_rig_text(cameras=1) + "\n[stage]\ndevice = 2\naxis = 3\nmicrostep_um = 0.047625\n")
    assert main(["devices", "--rig", str(rig_file)]) == 0
    out = capsys.readouterr().out
    assert "Zaber stage at" in out and "travel 0..50 mm" in out


@pytest.mark.skipif(VIKY is None, reason="GenTL simulator viky.cti not found (pip install 'lfpiv[genicam]')")
@pytest.mark.parametrize("cameras", [1, 2])
def test_devices_of_cameras_without_a_serial(cameras: int, tmp_path: Path) -> None:
    from acquisition.genicam import reset_system

    text = fast_rig_text(cameras=cameras).replace('hardware = "sim"',
                                                  f'hardware = "real"\ngentl_producers = ["{VIKY}"]', 1)
    rig_file = tmp_path / "real.toml"
    rig_file.write_text(text)
    try:
        lines = list_devices(load_rig(rig_file))
    finally:
        reset_system()
    cams = [(line, found) for line, found in lines if line.startswith("camera")]
    assert len(cams) == cameras and not any("None" in line for line, _ in cams)
    if cameras == 1:  # the first device found is used, and the line says how to pin it
        assert cams[0][1] and 'serial = "0" in the rig file to pin it' in cams[0][0]
    else:  # both would open the same device: each needs its serial
        assert all(not found and "set serial to one of ['0', '1', '2']" in line for line, found in cams)
        d = load_rig(rig_file).to_dict()
        d["pulse_generator"]["port"] = str(tmp_path / "no-such-port")
        with pytest.raises(UsageError, match="camera 'cam0' has no serial in the rig file; with 2 cameras"):
            with open_rig(Rig.from_dict(d)):
                pass
    assert ("pulse generator: no port in the rig file", False) in lines


def _start(fast_rig_file: Path, out: Path, pairs: int) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [*LFPIV, "acquire", "--rig", str(fast_rig_file), "--pairs", str(pairs), "--out", str(out), "--quiet",
           "--sim-rays", "300", "--sim-ppm", "0.2", "--sim-pool", "2"]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=terminal_signals)


def test_sigkill_leaves_every_committed_pair_intact(fast_rig_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "killed.zarr"
    proc = _start(fast_rig_file, out, 5000)
    try:
        wait_committed(out, 30, proc)
    finally:
        proc.kill()
        proc.wait(10)
    store = RunStore.open(out)
    assert store.state == "recording"  # nobody could say otherwise
    n = store.committed_pairs
    assert n >= 30
    _check_every_frame_accounted(store, n)
    for cam in store.cameras:
        frames = store.frames(cam)[:n]  # every committed chunk decodes
        ids = store.frame_ids(cam)[:n]
        assert np.all(frames[ids >= 0].reshape(int((ids >= 0).sum()), -1).mean(axis=1) > 50)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_signals_abort_cleanly(fast_rig_file: Path, tmp_path: Path, sig: signal.Signals) -> None:
    out = tmp_path / "stopped.zarr"
    proc = _start(fast_rig_file, out, 5000)
    _, err = signal_when_committed(proc, out, 10, sig, exit_timeout_s=30)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    store = RunStore.open(out)
    assert store.state == "aborted"
    _check_every_frame_accounted(store, store.committed_pairs)


def test_the_run_records_the_timing_as_the_generator_holds_it_and_devices_names_the_stage(fast_rig, tmp_path,
                                                                                           capsys):
    """The timing a run records is read back from the generator (rounded to its resolution), and
    ``lfpiv devices`` names the stage by its device id; ``--pairing timestamps`` is for real
    cameras only."""
    with sim_lab(fast_rig) as lab:
        res = record(fast_rig, tmp_path / "t.zarr", 3, sim_options={"lab": lab})
    t = RunStore.open(res.store.path).timing
    assert t["dt_s"] == pytest.approx(fast_rig.timing.dt_us * 1e-6, abs=1e-12)
    assert t["planned"]["dt_s"] == pytest.approx(fast_rig.timing.dt_us * 1e-6)
    assert all(round(c["delay_s"] / 250e-12) * 250e-12 == pytest.approx(c["delay_s"], abs=1e-15)
               for c in t["channels"])  # on the instrument's 250 ps grid
    rig_file = tmp_path / "fast.toml"
    rig_file.write_text(fast_rig_text())
    lines = list_devices(load_rig(rig_file))
    stage = next(text for text, _ in lines if text.startswith("stage"))
    assert "deviceid" in stage and "serial" in stage, stage
    rc = main(["acquire", "--rig", str(rig_file), "--pairs", "2", "--out", str(tmp_path / "p.zarr"), "--pairing",
               "timestamps"])
    assert rc == 2 and "--pairing timestamps is for real GenICam cameras" in capsys.readouterr().err


def test_ctrl_c_three_times_says_the_laser_is_disarmed_and_exits_130(fast_rig_file: Path, tmp_path: Path) -> None:
    """One Ctrl-C says at once that the laser is disarmed and what is kept; Ctrl-Cs that follow it
    0.2 s apart, while the run is closed and the interpreter shuts down, change nothing: exit 130,
    no traceback (they used to kill the process by SIGINT, exit -2)."""
    out = tmp_path / "ctrl-c.zarr"
    proc = _start(fast_rig_file, out, 5000)
    try:
        wait_committed(out, 10, proc)
        for _ in range(3):
            proc.send_signal(signal.SIGINT)
            time.sleep(0.2)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "lfpiv: the laser is disarmed; " in err and "(state 'aborted')" in err, err
    store = RunStore.open(out)
    assert store.state == "aborted" and store.committed_pairs >= 10
