"""Issue 50's writes, streams and defaults, each as a hostile lab found it: a plot or screenshot
never replaced by a stub, a log never written into a store, a full disk named with its path, a
broken pipe or a closed stderr that does not change the exit code, defaults that never refuse
what was asked, and replacements that cannot be put in place refused before anything is computed."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import LFPIV, chunk_file, damage_chunk, one_error

TINY = str(EXAMPLES / "tiny.toml")
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny synthetic run of 2 pairs with volumes and vectors (copied by each test that writes)."""
    from lfpiv.cli import main

    path = tmp_path_factory.mktemp("made") / "made.zarr"
    for argv in (["synth", "--rig", TINY, "--out", str(path), "--pairs", "2", "--ppm", "0.2", "--rays", "300",
                  "--quiet"],
                 ["reconstruct", str(path), "--iterations", "2", "--quiet"],
                 ["correlate", str(path), "--windows", "32x32x16", "--quiet"]):
        assert main(argv) == 0
    return path


def _copy(made: Path, tmp_path: Path) -> Path:
    run = tmp_path / "run.zarr"
    shutil.copytree(made, run)
    return run


def _files(run: Path) -> dict[str, bytes]:
    return {p.relative_to(run).as_posix(): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


# --- atomic writes -------------------------------------------------------------------------------

def test_a_plot_that_fails_half_written_leaves_the_earlier_plot_whole(made, tmp_path, capsys, monkeypatch):
    """evaluate --plot interrupted or on a full disk replaced a good plot by a stub (124 bytes,
    or 0) under the final name; the plot is now written beside it and renamed once complete."""
    import matplotlib.figure

    plot = tmp_path / "q.png"
    rc, _, err = _run(capsys, "evaluate", str(made), "--plot", str(plot))
    assert rc == 0, err
    good = plot.read_bytes()
    assert good.startswith(b"\x89PNG") and len(good) > 1000

    real = matplotlib.figure.Figure.savefig

    def full_disk(self, fname, *args, **kwargs):  # 124 bytes written, then the disk is full
        Path(fname).write_bytes(b"\x89PNG" + b"\0" * 120)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full_disk)
    rc, _, err = _run(capsys, "evaluate", str(made), "--plot", str(plot))
    assert rc == 2 and one_error(err) and f"cannot use {plot}: No space left on device" in err, err
    assert plot.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["q.png"]

    def interrupted(self, fname, *args, **kwargs):
        Path(fname).write_bytes(b"\x89PNG" + b"\0" * 120)
        raise KeyboardInterrupt

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", interrupted)
    rc, _, err = _run(capsys, "evaluate", str(made), "--plot", str(plot))
    assert rc == 130 and plot.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["q.png"]

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", real)
    rc, _, err = _run(capsys, "evaluate", str(made), "--plot", str(plot))
    assert rc == 0 and plot.read_bytes().startswith(b"\x89PNG"), err


# --- logs ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("inside", ["zarr.json", "cam0/frames/zarr.json", "run.log", "vectors/x.log"])
def test_a_log_file_inside_a_store_is_refused_and_the_store_is_untouched(made, tmp_path, capsys, inside):
    """--log-file pointed at a store's zarr.json appended to it and made the store unreadable."""
    run = _copy(made, tmp_path)
    before = _files(run)
    rc, _, err = _run(capsys, "--log-file", str(run / inside), "info", str(run))
    assert rc == 2 and one_error(err) and f"is inside the store {run}" in err and "outside it" in err, err
    assert _files(run) == before
    rc, _, err = _run(capsys, "info", str(run), "--log-file", str(run / inside))  # after the command too
    assert rc == 2 and one_error(err) and _files(run) == before
    assert RunStore.check(run) == []


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a device that is always full)")
def test_a_log_file_on_a_full_disk_is_refused_before_anything_changes(made, tmp_path):
    """A full disk under --log-file printed logging's 24-line traceback and exited 0."""
    run = _copy(made, tmp_path)
    before = _files(run)
    r = subprocess.run([*LFPIV, "--log-file", "/dev/full", "reconstruct", str(run), "--iterations", "1",
                        "--pair-range", "0", "--quiet"], capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 2 and one_error(r.stderr) and "Traceback" not in r.stderr, r.stderr
    assert "--log-file /dev/full cannot be written (No space left on device)" in r.stderr, r.stderr
    assert _files(run) == before


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a device that is always full)")
def test_a_log_file_that_fills_up_during_the_command_is_one_line_and_a_failure(made, tmp_path, capsys, monkeypatch):
    """The disk fills after the log's first line: the command ends, then says so in one line."""
    from lfpiv import cli

    monkeypatch.setattr(cli._LogFile, "finish_line", lambda self: None)  # as if the first line fit
    run = _copy(made, tmp_path)
    rc, _, err = _run(capsys, "--log-file", "/dev/full", "reconstruct", str(run), "--iterations", "1",
                      "--pair-range", "0", "--quiet")
    assert rc == 2 and one_error(err) and "--- Logging error ---" not in err, err
    assert "--log-file /dev/full could not be written (No space left on device); the command itself ended " \
           "without error" in err
    assert RunStore.open(run).reconstructed_pairs() == [0]


# --- streams ---------------------------------------------------------------------------------------

def test_a_broken_pipe_keeps_the_commands_exit_code(made, tmp_path):
    """`lfpiv check DAMAGED | head -c 1` exited 0: the broken-pipe handler returned success."""
    run = _copy(made, tmp_path)
    damage_chunk(chunk_file(run, "cam0/frames", 1), "random")
    proc = subprocess.Popen([*LFPIV, "check", str(run)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    assert len(proc.stdout.read(1)) == 1
    proc.stdout.close()  # the reader goes away: what follows is a broken pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 1 and "Traceback" not in err and "Exception ignored" not in err, err


def test_a_closed_stderr_or_stdout_changes_nothing(made, tmp_path):
    """Closing stderr made reconstruct fail ("Invalid argument: RUN/volumes"): the next file
    opened took descriptor 2. With stderr, stdout or both closed it does what it does otherwise."""
    for k, fds in enumerate(((2,), (1,), (0, 1, 2))):
        run = tmp_path / f"r{k}.zarr"
        shutil.copytree(made, run, ignore=shutil.ignore_patterns("volumes", "vectors"))

        def close(fds=fds) -> None:
            for fd in fds:
                os.close(fd)

        r = subprocess.run([*LFPIV, "reconstruct", str(run), "--iterations", "1", "--pair-range", "0"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           env=ENV, preexec_fn=close, timeout=600)
        assert r.returncode == 0, fds
        s = RunStore.open(run)
        assert s.reconstructed_pairs() == [0] and RunStore.check(run) == [], fds


# --- replacements ------------------------------------------------------------------------------------

def test_a_stale_vectors_replaced_is_cleared_before_the_next_replacement(made, tmp_path, capsys):
    """An old vectors/ that could not all be deleted left vectors.replaced/, which the next
    correlate with other settings tripped on after computing everything."""
    run = _copy(made, tmp_path)
    stale = run / "vectors.replaced"
    shutil.copytree(run / "vectors", stale)
    rc, _, err = _run(capsys, "correlate", str(run), "--windows", "16x16x8", "--quiet")
    assert rc == 0, err
    assert not stale.exists() and RunStore.open(run).group["vectors"].attrs["windows"][-1] == [16, 16, 8]


def test_a_read_only_old_vectors_is_refused_before_computing(made, tmp_path, capsys):
    probe = tmp_path / "probe"
    probe.mkdir(mode=0o555)
    if os.access(probe, os.W_OK):
        pytest.skip("this user writes into read-only folders (root)")
    run = _copy(made, tmp_path)
    for folder, _, _ in os.walk(run / "vectors"):
        os.chmod(folder, 0o555)
    try:
        before = _files(run)
        rc, _, err = _run(capsys, "correlate", str(run), "--windows", "16x16x8", "--quiet")
        assert rc == 2 and one_error(err) and f"{run / 'vectors'} cannot be replaced" in err, err
        assert "chmod -R u+w" in err and not (run / "vectors.pending").exists() and _files(run) == before
    finally:
        for folder, _, _ in os.walk(run / "vectors"):
            os.chmod(folder, 0o755)


# --- defaults and the way on --------------------------------------------------------------------------

def test_a_run_with_a_lost_frame_names_pair_range_as_the_way_on(made, tmp_path, capsys):
    """A recorded drop made a plain reconstruct fail without naming --pair-range."""
    run = tmp_path / "run.zarr"
    shutil.copytree(made, run, ignore=shutil.ignore_patterns("volumes", "vectors"))
    s = RunStore.open(run, mode="r+")
    s.add_drops([dict(camera="cam0", pair=1, frame=0, frame_id=-1, timestamp_ns=-1, reason="frame timeout")])
    del s
    chunk_file(run, "cam0/frames", 1).unlink()
    rc, _, err = _run(capsys, "reconstruct", str(run), "--iterations", "1", "--quiet")
    assert rc == 2 and one_error(err) and "pair(s) 1 lost a frame while recording" in err, err
    assert "--pair-range 0" in err and not (run / "volumes").exists()
    rc, _, err = _run(capsys, "reconstruct", str(run), "--iterations", "1", "--pair-range", "0", "--quiet")
    assert rc == 0 and RunStore.open(run).reconstructed_pairs() == [0], err


def test_monitor_pairs_fewer_than_the_default_after_takes_its_screenshot(tmp_path):
    """`monitor --pairs 2 --screenshot` was refused for the default --after 3; an offscreen monitor
    without --screenshot never ended."""
    pytest.importorskip("pyqtgraph")
    env = dict(ENV, QT_QPA_PLATFORM="offscreen")
    shot = tmp_path / "m.png"
    common = ["--rig", TINY, "--pairs", "2", "--device", "cpu", "--iterations", "1", "--sim-rays", "200", "--quiet"]
    r = subprocess.run([*LFPIV, "monitor", *common, "--screenshot", str(shot)], capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 0 and shot.read_bytes().startswith(b"\x89PNG"), r.stderr
    r = subprocess.run([*LFPIV, "monitor", *common], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0 and "2 shown" in r.stdout, r.stderr


def test_an_explicit_after_beyond_pairs_is_still_refused(tmp_path, capsys):
    pytest.importorskip("pyqtgraph")
    rc, _, err = _run(capsys, "monitor", "--rig", TINY, "--pairs", "2", "--after", "3", "--screenshot",
                      str(tmp_path / "m.png"))
    assert rc == 2 and one_error(err) and "--after 3 is more pairs than --pairs 2 shows" in err, err


def test_a_full_disk_as_correlate_begins_names_the_path(made, tmp_path, capsys, monkeypatch):
    """correlate on a full disk said "cannot use: No space left on device" without the path: the
    error came from creating the new vectors group, outside the pairs' own naming."""
    from lfcore.runstore._common import StoreGroup

    run = _copy(made, tmp_path)

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(StoreGroup, "create_group", full)
    rc, _, err = _run(capsys, "correlate", str(run), "--windows", "16x16x8", "--quiet")
    assert rc == 2 and one_error(err) and f"cannot use {run}/vectors: No space left on device" in err, err
