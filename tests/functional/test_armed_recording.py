"""The armed-recording context manager on the simulated lab: every way out of the block (done, cut
short, an error, Ctrl-C, a kill, a device fault, a failure before arming) leaves the laser
disarmed, the devices closed and the run marked, and says so."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from acquisition.protocols import DeviceError
from lfcore.runstore import RunStore
from lfpiv.jobs.acquire import ArmedRecording, Terminated, armed, check_plan
from lfpiv.rigfile import load_rig
from tests.helpers import fast_rig_text, sim_lab


@pytest.fixture(scope="module")
def fast_rig(tmp_path_factory: pytest.TempPathFactory):
    path = tmp_path_factory.mktemp("rig") / "fast.toml"
    path.write_text(fast_rig_text())
    return load_rig(path)


def _until(rec: ArmedRecording, committed: int, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while rec.session.committed_pairs < committed and time.monotonic() < end:
        rec.session.wait(0.05)
    assert rec.session.committed_pairs >= committed


def _safe(lab, rec: ArmedRecording) -> None:
    """The laser is off and every device was let go."""
    gen = lab.pulse_generator
    assert not gen.firing and not gen.outputs_enabled()
    assert not rec.generator.armed
    assert all(not cam._open for cam in lab.cameras)  # closed by the context manager's owner, open_rig


def _open(fast_rig, lab, out: Path, pairs: int, said: list[str], **kw):
    return armed(fast_rig, out, pairs, plan=check_plan(fast_rig, pairs), sim_options={"lab": lab}, say=said.append,
                 **kw)


def test_a_block_that_ends_with_every_pair_in_marks_the_run_complete(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    with sim_lab(fast_rig) as lab:
        with _open(fast_rig, lab, tmp_path / "done.zarr", 5, said) as rec:
            assert rec.generator.armed and rec.armed_at <= time.monotonic()
            while not rec.session.done:
                rec.session.wait(0.1)
        _safe(lab, rec)
        assert lab.pulse_generator.ticks_fired == 5
    assert rec.state == "complete" and rec.message == "recorded 5 pair(s)"
    assert rec.stats is not None and rec.stats.committed_pairs == 5 and rec.drops == 0
    store = RunStore.open(tmp_path / "done.zarr")
    assert store.state == "complete" and store.committed_pairs == 5 and store.truth() is not None
    assert said == []


def test_a_block_left_early_marks_the_run_aborted_with_what_was_written(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    with sim_lab(fast_rig) as lab:
        with _open(fast_rig, lab, tmp_path / "short.zarr", 500, said) as rec:
            _until(rec, 3)
        _safe(lab, rec)
    store = RunStore.open(tmp_path / "short.zarr")
    n = store.committed_pairs
    assert rec.state == "aborted" and store.state == "aborted" and 3 <= n < 500
    assert store.attrs["abort_reason"] == rec.message == f"only {n} of 500 pairs could be written"


def test_an_error_in_the_block_goes_on_after_the_laser_is_disarmed(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    with sim_lab(fast_rig) as lab:
        with pytest.raises(ValueError, match="a bug"), _open(fast_rig, lab, tmp_path / "bug.zarr", 500, said) as rec:
            _until(rec, 2)
            raise ValueError("a bug")
        _safe(lab, rec)
    store = RunStore.open(tmp_path / "bug.zarr")
    assert store.state == "aborted" and store.committed_pairs >= 2


def test_ctrl_c_disarms_marks_aborted_and_says_what_is_kept(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    out = tmp_path / "int.zarr"
    with sim_lab(fast_rig) as lab:
        with pytest.raises(KeyboardInterrupt), _open(fast_rig, lab, out, 500, said) as rec:
            _until(rec, 3)
            raise KeyboardInterrupt
        _safe(lab, rec)
    store = RunStore.open(out)
    n = store.committed_pairs
    assert store.state == "aborted" and store.attrs["abort_reason"] == f"interrupted after {n} committed pair(s)"
    assert said == [f"lfpiv: the laser is disarmed; {n} pair(s) are kept in {out} (state 'aborted')"]


def test_a_kill_ends_the_block_as_ctrl_c_does(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    out = tmp_path / "term.zarr"
    with sim_lab(fast_rig) as lab:
        with pytest.raises(KeyboardInterrupt), _open(fast_rig, lab, out, 500, said) as rec:
            _until(rec, 2)
            raise Terminated()  # what the SIGTERM / SIGHUP hook raises in the main thread
        _safe(lab, rec)
    store = RunStore.open(out)
    n = store.committed_pairs
    assert store.state == "aborted"
    assert store.attrs["abort_reason"] == f"terminated by a signal after {n} committed pair(s)"
    assert said and said[-1].startswith("lfpiv: the laser is disarmed; ")


def test_a_device_fault_says_the_laser_was_disarmed_and_what_is_kept(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []
    out = tmp_path / "fault.zarr"
    with sim_lab(fast_rig) as lab:
        with pytest.raises(DeviceError) as err, _open(fast_rig, lab, out, 500, said) as rec:
            _until(rec, 2)
            raise DeviceError("camera 'cam1' stopped answering")
        _safe(lab, rec)
    store = RunStore.open(out)
    n = store.committed_pairs
    assert str(err.value) == (f"camera 'cam1' stopped answering; the laser was disarmed; the {n} pair(s) recorded so "
                              f"far are kept in {out} (state 'aborted')")
    assert store.state == "aborted" and store.attrs["abort_reason"] == "camera 'cam1' stopped answering"
    assert said == []


def test_a_failure_before_arming_never_fires_the_laser(fast_rig, tmp_path: Path) -> None:
    said: list[str] = []

    def refuse(session) -> None:
        raise RuntimeError("the live view could not attach")

    with sim_lab(fast_rig) as lab:
        with pytest.raises(DeviceError, match="could not attach; the laser was disarmed; the 0 pair"):
            with _open(fast_rig, lab, tmp_path / "early.zarr", 50, said, on_session=refuse):
                pytest.fail("the block runs only once the laser is armed")
        assert lab.pulse_generator.ticks_fired == 0 and not lab.pulse_generator.outputs_enabled()
        assert all(not cam._open for cam in lab.cameras)
    store = RunStore.open(tmp_path / "early.zarr")
    assert store.state == "aborted" and store.committed_pairs == 0
