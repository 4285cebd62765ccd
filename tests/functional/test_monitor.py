"""``lfpiv monitor`` offscreen on the simulated lab: the screenshot holds every panel, the status
numbers agree with the run store, and disarming works from every state."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from lfcore.runstore import RunStore  # noqa: E402
from lfpiv import cli  # noqa: E402
from lfpiv.jobs.monitor import LiveRecorder  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402
from realtime.pipeline import LivePipeline, LiveSettings  # noqa: E402
from tests.helpers import (  # noqa: E402
    LFPIV,
    fast_rig_text,
    signal_when_committed,
    sim_lab,
    store_held,
    terminal_signals,
)

pytest.importorskip("pyqtgraph")


@pytest.fixture
def main():
    return cli.main


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "fast2.toml"
    path.write_text(fast_rig_text(rate_hz=20.0, cameras=2))
    return path


def _png(path: Path) -> np.ndarray:
    import matplotlib.image

    return (matplotlib.image.imread(str(path))[..., :3] * 255).astype(np.uint8)


def test_monitor_screenshot_and_status_match_the_run_store(main, rig_file: Path, tmp_path: Path, capsys,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    import realtime.monitor as monitor

    seen = {}
    make = monitor.MonitorWindow

    def capturing(*args, **kwargs):
        win = make(*args, **kwargs)
        shoot = win.screenshot

        def screenshot(path):
            seen["rects"] = win.panel_rects()
            seen["size"] = (win.width(), win.height())
            return shoot(path)

        win.screenshot = screenshot
        seen["win"] = win
        return win

    monkeypatch.setattr(monitor, "MonitorWindow", capturing)
    out, shot = tmp_path / "run.zarr", tmp_path / "shot.png"
    pairs = 30
    rc = main(["monitor", "--rig", str(rig_file), "--pairs", str(pairs), "--out", str(out), "--screenshot", str(shot),
               "--after", "2", "--device", "cpu", "--iterations", "3", "--method", "mlos-mart", "--sim-rays", "300",
               "--sim-pool", "3", "--pvr", "4,4,20", "--quiet"])
    stdout, stderr = capsys.readouterr()
    assert rc == 0, stderr
    # status numbers against the run store
    m = re.search(r"recording: (\S+): (\d+) pair\(s\) x 2 camera\(s\), (\d+) frames recorded, (\d+) dropped, "
                  r"(\d+) overruns, state (\w+)", stdout)
    assert m, stdout
    store = RunStore.open(out)
    committed, recorded, dropped, overruns = (int(g) for g in m.groups()[1:5])
    assert m.group(1) == str(out) and m.group(6) == "complete" == store.state
    assert committed == store.committed_pairs == pairs
    assert recorded == sum(int(np.count_nonzero(store.frame_ids(c) >= 0)) for c in store.cameras)
    assert dropped == len(store.drops())
    assert recorded + dropped == pairs * 2 * 2 and overruns == 0  # recorded + dropped == triggered
    live = re.search(r"live: (\d+) pair\(s\) processed, (\d+) skipped, (\d+) discarded, (\d+) shown", stdout)
    processed, skipped, discarded, shown = (int(g) for g in live.groups())
    assert 1 <= shown <= processed and processed + skipped + discarded <= committed
    # the live volume at the monitoring PVR (the tiny rig's 82 x 68 x 29 voxels at 2,2,10)
    assert "mlos-mart, 3 iteration(s) on cpu, 41x34x15 voxels at PVR 4,4,20" in stdout
    assert f"screenshot: {shot}" in stdout
    # the screenshot: every panel drew something
    img = _png(shot)
    assert img.shape[:2] == seen["size"][::-1]
    rects = seen["rects"]
    assert set(rects) == {"raw:cam0", "raw:cam1", "mip:z", "mip:y", "slice", "vectors"}
    for name, (x, y, w, h) in rects.items():
        assert w > 100 and h > 100, name
        region = img[y + 2:y + h - 2, x + 2:x + w - 2].reshape(-1, 3)
        colours = np.unique(region, axis=0)
        assert len(colours) >= 3 and region.max() >= 100, f"panel {name} is empty"
    # the status line was drawn with the numbers of the run
    win = seen["win"]
    assert win.displayed == shown
    assert f"frames {recorded}, drops {dropped}" in win.status.text()


def test_monitor_without_the_gui_extra_says_how_to_install_it(main, rig_file: Path, capsys,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyqtgraph", None)
    assert main(["monitor", "--rig", str(rig_file), "--screenshot", "x.png"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'lfpiv[gui]'" in err


def test_monitor_with_a_bad_pvr_is_one_line(main, rig_file: Path, capsys) -> None:
    assert main(["monitor", "--rig", str(rig_file), "--pvr", "0,2,10", "--screenshot", "x.png"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--pvr must be three positive numbers, got 0,2,10" in err


def test_monitor_screenshot_after_more_pairs_than_shown_is_one_line(main, rig_file: Path, capsys) -> None:
    assert main(["monitor", "--rig", str(rig_file), "--pairs", "3", "--after", "1000000", "--screenshot", "x.png"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--after 1000000 is more pairs than --pairs 3 shows" in err
    assert main(["monitor", "--rig", str(rig_file), "--iterations", "20000", "--screenshot", "x.png"]) == 2
    assert "--iterations: must be at most 10000" in capsys.readouterr().err


def test_monitor_over_a_run_another_process_writes_is_refused_at_once(main, rig_file: Path, tmp_path: Path,
                                                                      capsys) -> None:
    """The adversarial sweep's find: ``monitor --out RUN --overwrite`` while another process wrote
    RUN opened the devices and the window, the recording thread met the lock, and the window
    waited on (a hang) instead of the one line naming the writer that the other writers give."""
    run = tmp_path / "busy.zarr"
    RunStore.create(run, load_rig(rig_file), 2, timing={"dt_s": 0.001, "rate_hz": 20.0}, software_version="x").close()
    with store_held(run) as holder:
        rc = main(["monitor", "--rig", str(rig_file), "--pairs", "3", "--out", str(run), "--overwrite",
                   "--screenshot", str(tmp_path / "m.png")])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1 and f"being written by pid {holder.pid}" in err, err
    assert not (tmp_path / "m.png").exists()


def test_monitor_with_an_unwritable_screenshot_is_one_line(main, rig_file: Path, tmp_path: Path, capsys) -> None:
    (tmp_path / "afile").write_text("")
    assert main(["monitor", "--rig", str(rig_file), "--screenshot", str(tmp_path / "afile" / "m.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot write the screenshot into" in err and "writable" in err


def test_monitor_without_a_display_is_one_line(main, rig_file: Path, capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM"):
        monkeypatch.delenv(var, raising=False)
    assert main(["monitor", "--rig", str(rig_file)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no display" in err and "--screenshot" in err


def test_disarm_from_every_state(rig_file: Path, tmp_path: Path) -> None:
    rig = load_rig(rig_file)
    pipe = LivePipeline(rig, settings=LiveSettings(iterations=1), device="cpu")
    with sim_lab(rig) as lab, pipe:
        gen = lab.pulse_generator
        rec = LiveRecorder(rig, pipe, pairs=2000, out=tmp_path / "run.zarr", sim_options={"lab": lab})
        rec.disarm()  # never armed: nothing happens
        assert not rec.armed and rec.recordings == []
        rec.arm()
        rec.arm()  # already armed: one recording only
        end = time.monotonic() + 30
        while rec.status()["committed_pairs"] < 5 and time.monotonic() < end:
            time.sleep(0.02)
        rec.disarm()
        rec.disarm()
        assert rec.wait(30.0)
        assert not gen.firing and not gen.outputs_enabled()
        first = rec.recordings[-1]
        assert first.state == "aborted" and first.path == tmp_path / "run.zarr"
        store = RunStore.open(first.path)
        assert store.state == "aborted" and 5 <= store.committed_pairs == first.committed_pairs < 2000
        n = store.committed_pairs
        assert first.frames_recorded + first.frames_dropped == n * 2 * 2
        # record off: a scratch run, deleted afterwards; disarmed before the laser was armed
        rec.set_record(False)
        rec.arm()
        rec.disarm()
        assert rec.wait(30.0)
        second = rec.recordings[-1]
        assert second.path is None and second.state == "aborted"
        assert not gen.firing and not gen.outputs_enabled()
        # record on again: the next run gets its own name
        rec.set_record(True)
        rec.pairs = 10
        rec.arm()
        assert rec.wait(30.0)
        third = rec.recordings[-1]
        assert third.state == "complete" and third.path == tmp_path / "run-3.zarr" and third.committed_pairs == 10
        assert third.frames_recorded + third.frames_dropped == 10 * 2 * 2
    assert pipe.stats().state == "stopped"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_killed_monitor_disarms_and_closes_its_recording(rig_file: Path, tmp_path: Path, sig: int) -> None:
    # The monitor arms from its recording thread, where no signal handler can be set: a kill or
    # a closed terminal must still disarm, and the recording end as after "disarm".
    out = tmp_path / "run.zarr"
    cmd = [*LFPIV, "monitor", "--rig", str(rig_file), "--pairs", "5000", "--out", str(out), "--screenshot",
           str(tmp_path / "shot.png"), "--after", "5000", "--device", "cpu", "--iterations", "1", "--method",
           "mlos-mart", "--sim-rays", "300", "--sim-pool", "2", "--pvr", "4,4,20", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=terminal_signals)
    stdout, stderr = signal_when_committed(proc, out, 5, sig, timeout_s=120.0)
    assert proc.returncode == 130 and "Traceback" not in stderr and "interrupted" in stderr, stderr
    store = RunStore.open(out)
    assert store.state == "aborted" and 5 <= store.committed_pairs < 5000
    assert f"{store.committed_pairs} pair(s) x 2 camera(s)" in stdout and "state aborted" in stdout
    recorded = sum(int(np.count_nonzero(store.frame_ids(c) >= 0)) for c in store.cameras)
    assert recorded + len(store.drops()) == store.committed_pairs * 2 * 2


def test_monitor_on_pinhole_cameras_runs_mlos_smart(main, tmp_path: Path, capsys) -> None:
    """A Tomo-PIV rig live: MLOS-SMART by default, every camera's raw panel, a complete recording."""
    from tests.conftest import EXAMPLES

    text = (EXAMPLES / "tomo_4_cameras.toml").read_text()
    rig = tmp_path / "tomo4.toml"
    rig.write_text(text.replace("size_mm = [10.0, 10.0, 4.0]", "size_mm = [3.0, 3.0, 2.0]"))
    out, shot = tmp_path / "run.zarr", tmp_path / "shot.png"
    rc = main(["monitor", "--rig", str(rig), "--pairs", "4", "--out", str(out), "--screenshot", str(shot),
               "--after", "1", "--device", "cpu", "--iterations", "3", "--sim-pool", "2", "--quiet"])
    stdout, stderr = capsys.readouterr()
    assert rc == 0, stderr
    assert "state complete" in stdout and RunStore.open(out).committed_pairs == 4
    assert re.search(r"mlos-smart, 3 iteration\(s\) on cpu, 40x40x27 voxels at PVR 1,1,1", stdout), stdout
    assert shot.exists()
    rc = main(["monitor", "--rig", str(rig), "--pairs", "2", "--method", "drt-mart", "--device", "cpu", "--quiet",
               "--sim-pool", "1"])
    _, stderr = capsys.readouterr()
    assert rc == 2 and stderr.count("\n") == 1 and "is a pinhole camera" in stderr


def test_monitor_checks_panel_shows_each_cameras_checks(rig_file: Path, tmp_path: Path) -> None:
    # The checks before recording, beside the live panels: verdicts, histogram and refocused plane.
    import pyqtgraph as pg

    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer
    from realtime.monitor import MonitorWindow

    rig = load_rig(rig_file)
    cfg = rig.render.model_copy(update={"rays_per_particle": 2000})
    pts = seed_particles(rig.volume, particle_count(rig, ppm=0.5), np.random.default_rng(1))
    raw = {c.name: LightFieldRenderer(c, cfg, wavelength_nm=532.0, device="cpu").frame(pts, 50_000.0, seed=k)
           for k, c in enumerate(rig.camera)}
    raw["cam1"] = np.full_like(raw["cam1"], 2**rig.render.bit_depth - 1)  # a camera blinded by the laser
    pg.mkQApp()
    win = MonitorWindow(LivePipeline(rig, device="cpu"))
    try:
        win.show()
        win.run_checks(raw, wait=True)
        text0, text1 = win.check_labels["cam0"].text(), win.check_labels["cam1"].text()
        assert "PPM (recommended 0.5" in text0 and "FIX" not in text0
        assert "FIX</span> saturated 100.000%" in text1
        assert win.last_checks["cam0"].ppm == pytest.approx(0.5, rel=0.3)
        shot = win.screenshot(tmp_path / "checks.png")
        img = _png(shot)
        rects = win.check_rects()
        assert set(rects) == {"hist:cam0", "plane:cam0", "hist:cam1", "plane:cam1"}
        x, y, w, h = rects["plane:cam0"]
        assert w > 50 and h > 50
        region = img[y + 2:y + h - 2, x + 2:x + w - 2].reshape(-1, 3)
        assert len(np.unique(region, axis=0)) >= 3
        assert set(win.panel_rects()) == {"raw:cam0", "raw:cam1", "mip:z", "mip:y", "slice", "vectors"}
    finally:
        win.close()


def test_monitor_on_the_particle_route_shows_particles_and_tracks(main, rig_file: Path, tmp_path: Path,
                                                                   capsys) -> None:
    out, shot = tmp_path / "run.zarr", tmp_path / "shot.png"
    pairs = 6
    rc = main(["monitor", "--rig", str(rig_file), "--route", "particles", "--pairs", str(pairs), "--out", str(out),
               "--screenshot", str(shot), "--after", "1", "--device", "cpu", "--sim-rays", "300", "--sim-pool", "2",
               "--pvr", "4,4,20", "--quiet"])
    stdout, stderr = capsys.readouterr()
    assert rc == 0, stderr
    # the recording is the voxel route's: complete, every triggered frame recorded or dropped
    store = RunStore.open(out)
    assert store.state == "complete" and store.committed_pairs == pairs
    recorded = sum(int(np.count_nonzero(store.frame_ids(c) >= 0)) for c in store.cameras)
    assert recorded + len(store.drops()) == pairs * 2 * 2
    m = re.search(r"particles \(IPR with drt-mart's weights\) and tracks, last pair (\d+)/(\d+) particles \(A/B\) "
                  r"and (\d+) tracks on cpu, 41x34x15 voxels at PVR 4,4,20", stdout)
    assert m, stdout
    assert int(m.group(1)) > 0 and int(m.group(3)) > 0
    assert "projector" not in stdout.split("live:")[1]
    assert f"screenshot: {shot}" in stdout and _png(shot).max() > 0


def test_monitor_with_an_unknown_route_is_one_line(main, rig_file: Path, capsys) -> None:
    assert main(["monitor", "--rig", str(rig_file), "--route", "volume"]) == 2
    err = capsys.readouterr().err
    assert "argument --route: invalid choice: 'volume'" in err and "'particles'" in err and len(err.splitlines()) == 1


_LIVE_LINE = "{method}, 2 iteration(s) on cpu, 41x34x15 voxels at PVR 4,4,20, projector stored; plan {plan}"


@pytest.mark.parametrize(("options", "line"), [
    ([], _LIVE_LINE.format(method="mlos-mart", plan="fast (mlos-mart, frame B warm)")),
    (["--protocol", "drt"], _LIVE_LINE.format(method="drt-mart", plan="drt (drt-mart, uniform starts)")),
    (["--protocol", "drt", "--method", "mlos-mart", "--warm-start"],
     _LIVE_LINE.format(method="mlos-mart", plan="drt (mlos-mart, frame B warm)")),
])
def test_monitor_says_which_plan_ran(main, rig_file: Path, tmp_path: Path, capsys, options: list[str],
                                     line: str) -> None:
    """``--protocol`` (default fast) and the options that change it, as the monitor's last line names them."""
    rc = main(["monitor", "--rig", str(rig_file), "--pairs", "3", "--screenshot", str(tmp_path / "m.png"), "--after",
               "1", "--device", "cpu", "--iterations", "2", "--sim-rays", "300", "--sim-pool", "2", "--pvr", "4,4,20",
               "--projector", "auto", "--quiet", *options])
    stdout, stderr = capsys.readouterr()
    assert rc == 0, stderr
    assert line in stdout, stdout


def test_monitor_protocol_on_the_particle_route_is_one_line(main, rig_file: Path, capsys) -> None:
    """The plan is the voxel route's: asked for with the particle route, one line before anything is armed."""
    assert main(["monitor", "--rig", str(rig_file), "--route", "particles", "--protocol", "drt", "--screenshot",
                 "x.png"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--protocol drt is the voxel route's plan; leave it out with --route " \
        "particles" in err, err


def test_monitor_protocol_choices_are_the_live_plans() -> None:
    from lfpiv.cli import _build_parser
    from realtime.settings import LIVE_PROTOCOLS

    sub = next(a for a in _build_parser()._actions if a.dest == "command")
    option = next(a for a in sub.choices["monitor"]._actions if a.dest == "protocol")
    assert tuple(option.choices) == tuple(LIVE_PROTOCOLS)
