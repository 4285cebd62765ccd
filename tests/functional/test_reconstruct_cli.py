"""`lfpiv reconstruct` and `lfpiv evaluate` end to end, and their one-line errors."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import time

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.cli import main
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import LFPIV, stop_when, terminal_signals

TINY = str(EXAMPLES / "tiny.toml")



@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("recon") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "2", "--ppm", "0.2", "--flow", "uniform",
                 "--quiet"]) == 0
    return path


def test_reconstruct_then_evaluate(capsys, synthetic_run, tmp_path):
    rc, out, err = _run(capsys, "reconstruct", str(synthetic_run), "--iterations", "20", "--pairs", "1", "--quiet")
    assert rc == 0, err
    assert "reconstructed 2 volume(s) of 82 x 68 x 29 voxels (x, y, z) with drt-mart" in out
    s = RunStore.open(synthetic_run)
    assert s.reconstructed_pairs() == [1]
    vol = s.volumes()
    assert vol.shape == (2, 2, 29, 68, 82) and vol[1].max() > 0 and not vol[0].any()
    assert s.group["volumes"].attrs["settings"]["iterations"] == 20
    rc, out, err = _run(capsys, "evaluate", str(synthetic_run), "--plot", str(tmp_path / "q.png"))
    assert rc == 0, err
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("pair"))
    assert "Q" in lines[header] and "recall" in lines[header] and "ghosts" in lines[header]
    q = [float(line.split()[2]) for line in lines[header + 1:header + 3]]
    assert all(0.4 < v <= 1.0 for v in q), out  # frames A and B of pair 1
    assert "vectors: none yet" in out
    assert (tmp_path / "q.png").read_bytes()[:4] == b"\x89PNG"
    # adding pair 0 with the same settings keeps pair 1
    assert _run(capsys, "reconstruct", str(synthetic_run), "--iterations", "20", "--pairs", "0", "--quiet")[0] == 0
    assert RunStore.open(synthetic_run).reconstructed_pairs() == [0, 1]


def test_mart_baseline_from_the_command(capsys, synthetic_run, tmp_path):
    rc, out, err = _run(capsys, "reconstruct", str(synthetic_run), "--method", "mart", "--iterations", "3",
                        "--pairs", "0", "--quiet")
    assert rc == 0, err
    assert "100.00% of voxels active" in out
    assert RunStore.open(synthetic_run).group["volumes"].attrs["method"] == "mart"


def test_mlos_mart_from_the_command(capsys, synthetic_run, tmp_path):
    rc, out, err = _run(capsys, "reconstruct", str(synthetic_run), "--method", "mlos-mart", "--iterations", "3",
                        "--pairs", "0", "--quiet")
    assert rc == 0, err
    active = float(out.split("% of voxels active")[0].rsplit(" ", 1)[1])
    assert 0 < active < 20  # eliminated like DRT-MART
    assert RunStore.open(synthetic_run).group["volumes"].attrs["method"] == "mlos-mart"


def test_weights_made_on_the_fly_from_the_command(capsys, synthetic_run):
    argv = ["reconstruct", str(synthetic_run), "--protocol", "fixed", "--method", "mlos-mart", "--iterations", "5",
            "--pairs", "1", "--quiet"]  # fixed: fast's subsets split stored weights only
    rc, out, err = _run(capsys, *argv, "--weight-storage", "stored")
    assert rc == 0, err
    assert "made again in each iteration" not in out
    stored = RunStore.open(synthetic_run).volumes()[1]
    rc, out, err = _run(capsys, *argv, "--weight-storage", "on-the-fly")
    assert rc == 0, err
    assert "active voxels per volume were made again in each iteration instead of stored: the same" in out
    fly = RunStore.open(synthetic_run).volumes()[1]
    assert stored.max() > 0
    np.testing.assert_allclose(fly, stored, rtol=1e-4, atol=1e-5 * float(stored.max()))


def test_crossed_cameras_on_deep_voxels_are_warned(capsys, tmp_path):
    # the tiny rig with a second camera 90 degrees away, on its one-camera PVR (2, 2, 10)
    text = (EXAMPLES / "tiny.toml").read_text().replace("size_mm = [0.9, 0.75, 1.6]", "size_mm = [0.8, 0.7, 0.8]")
    cam0 = text[text.index("[[camera]]"):text.index("[laser]")]
    rig = tmp_path / "dual.toml"
    rig.write_text(text + "\n" + cam0.replace('"cam0"', '"cam1"').replace("[0.0, 0.0, 0.0]  #", "[0.0, 90.0, 0.0]  #"))
    run = str(tmp_path / "dual.zarr")
    assert main(["synth", "--rig", str(rig), "--out", run, "--pairs", "1", "--ppm", "0.1", "--quiet"]) == 0
    argv = ["reconstruct", run, "--iterations", "1", "--quiet"]
    rc, out, err = _run(capsys, *argv)
    assert rc == 0 and "reconstructed 2 volume(s)" in out
    (line,) = err.splitlines()
    assert line.startswith("lfpiv: warning: cameras 'cam0' and 'cam1' view the volume 90 degrees apart")
    assert line.endswith("use equal PVRs, e.g. --pvr 2,2,2 (the chapter's dual-camera cases use 3,3,3)")
    for more in (["--pvr", "4,4,4"], ["--cameras", "cam0"]):  # equal voxels, or one camera: no warning
        rc, out, err = _run(capsys, *argv, *more)
        assert rc == 0 and "warning" not in err  # (a note says the earlier volumes were replaced)


def _empty_run(tmp_path):
    path = tmp_path / "empty.zarr"
    RunStore.create(path, load_rig(TINY), 2, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="x")
    return str(path)


BAD = [
    (lambda t, r: ["reconstruct", str(t / "none.zarr")], "does not exist"),
    (lambda t, r: ["reconstruct", _empty_run(t)], "no recorded pairs (committed_pairs = 0)"),
    (lambda t, r: ["reconstruct", r, "--pvr", "0,2,10"], "--pvr must be three positive numbers"),
    (lambda t, r: ["reconstruct", r, "--pvr", "2,2"], "is not three numbers like 2,2,10"),
    (lambda t, r: ["reconstruct", r, "--pvr", "0.001,0.001,0.001"], "more than it has free; use a coarser"),
    (lambda t, r: ["reconstruct", r, "--pairs", "7"], "selects no pair of this run"),
    (lambda t, r: ["reconstruct", r, "--pairs", "1:0"], "selects no pair of this run (it has pairs 0 to 1)"),
    (lambda t, r: ["reconstruct", r, "--pairs", "-1"], "--pairs: '-1' is not a pair or a range START:STOP"),
    (lambda t, r: ["evaluate", r, "--pairs", "one"], "--pairs: 'one' is not a pair or a range START:STOP"),
    (lambda t, r: ["reconstruct", r, "--pairs", "2 0"], "--pairs: '2 0' is not a pair or a range START:STOP"),
    (lambda t, r: ["reconstruct", r, "--relaxation", "3"], "diverge; use at most 2, or the sequential form"),
    (lambda t, r: ["reconstruct", r, "--cameras", "camX"], "no camera 'camX' in this run"),
    (lambda t, r: ["reconstruct", r, "--weight-storage", "on-the-fly"],
     "made on the fly by the matrix-free projector alone"),
]


@pytest.mark.parametrize(("argv", "expected"), BAD)
def test_bad_input_is_one_line(capsys, tmp_path, synthetic_run, argv, expected):
    rc, out, err = _run(capsys, *argv(tmp_path, str(synthetic_run)))
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("lfpiv: error: ") and expected in err, err


def test_evaluate_needs_something_to_evaluate(capsys, tmp_path):
    path = tmp_path / "fresh.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--quiet"]) == 0
    capsys.readouterr()
    rc, out, err = _run(capsys, "evaluate", str(path))
    assert rc == 2 and out == "" and "has neither volumes nor vectors yet; run 'lfpiv reconstruct" in err


def test_evaluate_needs_a_synthetic_run(capsys, tmp_path):
    path = _empty_run(tmp_path)
    RunStore.open(path, mode="r+").write_frame("cam0", 0, 0, np.zeros((160, 192), np.uint16), 0, 0)
    rc, _, err = _run(capsys, "evaluate", path)  # a recording: frames, no truth
    assert rc == 2 and "recorded run with no truth" in err


def test_running_out_of_device_memory_is_one_line_and_keeps_volumes(capsys, tmp_path, monkeypatch):
    """A weight build whose allocation fails (as Warp reports it) midway through a run."""
    from lfcore.weight_build import WeightBuilder

    path = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--ppm", "0.2", "--quiet"]) == 0
    capsys.readouterr()
    build = WeightBuilder._weights
    calls = []

    def failing(self, *args):
        calls.append(1)
        if len(calls) == 2:  # frame B
            raise RuntimeError("Failed to allocate 3221225472 bytes on device 'cuda:0'")
        return build(self, *args)

    monkeypatch.setattr(WeightBuilder, "_weights", failing)
    # (--projector auto would go on with the matrix-free templates where the weights do not fit)
    rc, out, err = _run(capsys, "reconstruct", str(path), "--iterations", "2", "--quiet", "--projector", "stored")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "pair 0 frame B: the weights of" in err and "ran out of memory on " in err and "(3.0 GiB more)" in err
    assert "use a coarser --pvr" in err and "the 1 volume(s) written before are kept" in err
    vol = RunStore.open(path).volumes()
    assert vol[0, 0].max() > 0  # frame A is in the store


def test_replacing_volumes_says_so_and_marks_their_vectors_outdated(capsys, tmp_path, monkeypatch):
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "2", "--ppm", "0.2", "--flow", "uniform",
                 "--quiet"]) == 0
    fixed = ("--protocol", "fixed")  # the volumes' line in lfpiv info as a fixed count, no warm start, gives it
    assert _run(capsys, "reconstruct", str(run), *fixed, "--iterations", "2", "--quiet")[0] == 0
    rc, _, err = _run(capsys, "correlate", str(run), "--windows", "32x32x16,16x16x8", "--quiet")
    assert rc == 0 and not RunStore.open(run).vectors_outdated, err
    import lfpiv.replacement as replacement

    usage = shutil.disk_usage
    monkeypatch.setattr(replacement.shutil, "disk_usage", lambda path: usage(path)._replace(free=1000))
    rc, _, err = _run(capsys, "reconstruct", str(run), *fixed, "--iterations", "3", "--pairs", "0", "--quiet")
    assert rc == 0
    assert "note: the volumes of 2 pair(s) made with other settings (iterations differ) are replaced" in err
    assert "warning: the new volumes are made beside the old ones, which take 0.00 GiB, and only 0.00 GiB" in err
    assert RunStore.open(run).vectors_outdated
    for argv in (["evaluate", run], ["export", run, "--format", "netcdf", "--out", tmp_path / "f"]):
        rc, _, err = _run(capsys, *argv)
        assert rc == 0 and "were correlated from volumes that have since been replaced" in err, err
    rc, out, _ = _run(capsys, "info", run)
    assert "volumes  1 pair(s) (0) reconstructed by drt-mart, 3 iterations, 82 x 68 x 29 voxels" in out
    assert "vectors  2 pair(s) (0 to 1) correlated, windows 32x32x16 then 16x16x8; from volumes since replaced" in out


def test_reconstruct_by_default_takes_the_pairs_a_cut_short_recording_committed(capsys, tmp_path):
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "3", "--ppm", "0.2", "--quiet"]) == 0
    s = RunStore.open(run, mode="r+")
    s.commit(2)
    s.set_state("aborted")
    rc, _, err = _run(capsys, "reconstruct", str(run), "--iterations", "1", "--quiet")
    assert rc == 0, err
    assert RunStore.open(run).reconstructed_pairs() == [0, 1]


def test_an_interrupted_replacement_leaves_the_old_volumes_whole_and_goes_on(capsys, tmp_path, monkeypatch):
    """Ctrl-C while volumes of other settings are made: the old volumes/ (and the vectors
    correlated from them) stay as they were; the same command with --skip-done finishes the new
    ones, which then replace them."""
    import lfpiv.jobs.reconstruct as recon

    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "2", "--ppm", "0.2", "--quiet"]) == 0
    assert _run(capsys, "reconstruct", str(run), "--iterations", "2", "--quiet")[0] == 0
    assert _run(capsys, "correlate", str(run), "--windows", "32x32x16", "--quiet")[0] == 0
    before = RunStore.open(run).volumes()[...]
    frames = []
    real = recon._reconstruct_frame

    def interrupted_at_pair_1(recon_frames, store, names, pair, frame, *args, **kwargs):
        if pair == 1:
            raise KeyboardInterrupt
        frames.append((pair, frame))
        return real(recon_frames, store, names, pair, frame, *args, **kwargs)

    monkeypatch.setattr(recon, "_reconstruct_frame", interrupted_at_pair_1)
    rc, _, err = _run(capsys, "reconstruct", str(run), "--iterations", "3", "--quiet")
    assert rc == 130
    assert "interrupted; the 1 pair(s) of new volumes are kept aside and the volumes made before with other " \
           "settings are unchanged" in err
    s = RunStore.open(run)
    assert np.array_equal(s.volumes()[...], before) and s.reconstructed_pairs() == [0, 1]
    assert s.group["volumes"].attrs["settings"]["iterations"] == 2 and not s.vectors_outdated
    assert s.pending("volumes").attrs["reconstructed_pairs"] == [0]
    rc, out, _ = _run(capsys, "info", str(run))
    assert "volumes          2 pair(s) (0 to 1) reconstructed by drt-mart, 2 iterations" in out
    assert "volumes.pending  a replacement (drt-mart, 3 iterations) interrupted after 1 pair(s) (0); it takes" in out

    frames.clear()
    monkeypatch.setattr(recon, "_reconstruct_frame", lambda *a, **k: (frames.append(a[3:5]), real(*a, **k))[1])
    # going on for a part of the pairs: the replacement waits for the rest, the old volumes stay
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "3", "--pairs", "0", "--skip-done", "--quiet")
    assert rc == 0 and frames == [], err
    assert "going on with the interrupted replacement of volumes/ made with these settings (1 pair(s) done" in err
    assert "the replacement of volumes/ still lacks 1 pair(s) (1) asked of it before" in err
    assert np.array_equal(RunStore.open(run).volumes()[...], before)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "3", "--skip-done", "--quiet")
    assert rc == 0, err
    assert frames == [(1, 0), (1, 1)]  # pair 0 of the interrupted replacement was kept
    assert "volumes/ now holds the new volumes (2 pair(s))" in err
    s = RunStore.open(run)
    assert s.pending("volumes") is None and s.reconstructed_pairs() == [0, 1]
    assert s.group["volumes"].attrs["settings"]["iterations"] == 3 and s.vectors_outdated
    assert not np.array_equal(s.volumes()[...], before)
    assert sorted(p.name for p in run.iterdir() if p.name.startswith("volumes")) == ["volumes"]


def test_other_settings_after_an_interrupted_replacement_start_it_again(capsys, tmp_path, monkeypatch):
    import lfpiv.jobs.reconstruct as recon

    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "2", "--ppm", "0.2", "--quiet"]) == 0
    assert _run(capsys, "reconstruct", str(run), "--iterations", "1", "--quiet")[0] == 0
    real = recon._reconstruct_frame

    def interrupted_at_pair_1(*args, **kwargs):
        if args[3] == 1:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(recon, "_reconstruct_frame", interrupted_at_pair_1)
    assert _run(capsys, "reconstruct", str(run), "--iterations", "2", "--quiet")[0] == 130
    monkeypatch.setattr(recon, "_reconstruct_frame", real)
    # back to the first settings: the volumes already hold them, the stale replacement is dropped
    rc, _, err = _run(capsys, "reconstruct", str(run), "--iterations", "1", "--skip-done", "--quiet")
    assert rc == 0 and "replaced" not in err, err
    s = RunStore.open(run)
    assert s.group["volumes"].attrs["settings"]["iterations"] == 1 and s.pending("volumes") is not None
    # third settings: a new replacement, made whole
    assert _run(capsys, "reconstruct", str(run), "--iterations", "3", "--quiet")[0] == 0
    s = RunStore.open(run)
    assert s.group["volumes"].attrs["settings"]["iterations"] == 3 and s.pending("volumes") is None
    assert s.reconstructed_pairs() == [0, 1]


def test_a_full_disk_while_reconstructing_names_the_store(capsys, tmp_path, monkeypatch):
    """ENOSPC under zarr's writes carries no file name: the message names where it was writing."""
    import lfcore.runstore as runstore

    path = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--ppm", "0.2", "--quiet"]) == 0
    capsys.readouterr()

    def full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(runstore.RunStore, "write_volume", full)
    rc, out, err = _run(capsys, "reconstruct", str(path), "--iterations", "1", "--quiet")
    assert rc == 2 and err.count("\n") == 1, err
    assert f"cannot use {path}/volumes: No space left on device" in err


def test_three_ctrl_cs_while_reconstructing_exit_130_without_a_traceback(capsys, tmp_path):
    """The adversarial sweep's find: Ctrl-Cs 0.2 s apart met the first one's stop half way (a
    KeyboardInterrupt "ignored" in a Warp array's __del__, with its traceback); now the first
    stops the command and those that follow it within a few seconds are ignored."""
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "12", "--ppm", "0.2", "--rays", "500",
                 "--quiet"]) == 0
    proc = subprocess.Popen([*LFPIV, "reconstruct", str(run), "--iterations", "3", "--quiet"],
                            stderr=subprocess.PIPE, text=True, preexec_fn=terminal_signals)
    try:
        stop_when(proc, run, lambda s: len(s.group["volumes"].attrs.get("reconstructed_pairs", [])), 2,
                  timeout_s=120, what="reconstructed pairs")
        proc.send_signal(signal.SIGINT)  # taken as it goes on, before it can reach the 12th pair
        proc.send_signal(signal.SIGCONT)
        for _ in range(2):
            time.sleep(0.2)
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130 and "Traceback" not in err and "Exception ignored" not in err, err
    assert err.strip().splitlines()[-1] == "lfpiv: interrupted; what was recorded so far is kept"
    n = len(RunStore.open(run).reconstructed_pairs())
    assert 2 <= n < 12 and RunStore.check(run) == []


def test_prune_from_the_command(capsys, synthetic_run, tmp_path):
    """--prune: the dark voxels leave after --prune-every iterations, which the summary says and the
    settings record; --prune 0 is the chapter's protocol; a fraction of 1 or more is one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    fixed = ("--protocol", "fixed")  # the pruning alone, without fast's subsets and line-of-sight first
    rc, out, err = _run(capsys, "reconstruct", str(run), *fixed, "--iterations", "30", "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    left = re.search(r"of voxels active \((\d+)% of them left after pruning\)", out)
    assert left and 0 < int(left.group(1)) < 100, out
    settings = RunStore.open(run).group["volumes"].attrs["settings"]
    assert settings["prune"] == 0.01 and settings["prune_every"] == 10
    rc, out, err = _run(capsys, "reconstruct", str(run), *fixed, "--iterations", "30", "--pair-range", "0:1",
                        "--prune", "0", "--quiet")
    assert rc == 0 and "left after pruning" not in out and "replaced" in err, err  # other settings: replaced
    rc, out, err = _run(capsys, "reconstruct", str(run), "--prune", "1.5", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "prune must be from 0" in err, err


def test_coarse_from_the_command(capsys, synthetic_run, tmp_path):
    """--coarse and --coarse-iterations are recorded with the settings (the tiny rig's box is under the
    size rule, so it is eliminated whole); depth slabs run the fast protocol's subsets and coarse grid as
    in memory; a factor past the most is one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "10", "--coarse", "2",
                        "--coarse-iterations", "5", "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    settings = RunStore.open(run).group["volumes"].attrs["settings"]
    assert settings["coarse"] == 2 and settings["coarse_iterations"] == 5
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--max-iterations", "30", "--slabs",
                        "2", "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    settings = RunStore.open(run).group["volumes"].attrs["settings"]
    assert settings["subsets"] == 6 and settings["coarse"] == 3 and not settings["warm_start"]
    rc, out, err = _run(capsys, "reconstruct", str(run), "--coarse", "9", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--coarse" in err, err


def test_warm_start_from_the_command(capsys, tmp_path):
    """--warm-start --warm-predictor last: each frame B after the first pair's starts from its frame A
    carried along the last pair's field, in a fifth of the iterations, to the uniform start's quality
    (against the truth); --warm-start alone (its own pair's predictor): every pair's B, the first
    included; the settings record which; volumes made before it match a plain run; in depth slabs it is
    one line."""
    from lfcore import metrics

    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(run), "--pairs", "3", "--ppm", "0.4", "--quiet"]) == 0
    cold = tmp_path / "cold.zarr"
    shutil.copytree(run, cold)
    fixed = ("--protocol", "fixed")  # 50 iterations, and no warm start unless asked for
    own = tmp_path / "own.zarr"
    shutil.copytree(run, own)
    rc, out, err = _run(capsys, "reconstruct", str(run), *fixed, "--warm-start", "--warm-predictor", "last", "--quiet")
    assert rc == 0, err
    assert "2 frame(s) B started from their frame A carried along the last pair's displacement: 10 iterations " \
           "each instead of 50" in out, out
    assert _run(capsys, "reconstruct", str(cold), *fixed, "--quiet")[0] == 0
    s, c = RunStore.open(run), RunStore.open(cold)
    settings = s.group["volumes"].attrs["settings"]
    assert settings["warm_start"] is True and settings["warm_iterations"] is None
    assert settings["warm_predictor"] == "last"
    rc, out, err = _run(capsys, "info", str(run))
    assert rc == 0 and "50 iterations (frames B warm-started by the last pair: 10)" in out, out + err
    rc, out, err = _run(capsys, "reconstruct", str(own), *fixed, "--warm-start", "--quiet")
    assert rc == 0 and "3 frame(s) B started from their frame A carried along their own pair's displacement: 10 " \
        "iterations each instead of 50" in out, out + err
    assert RunStore.open(own).group["volumes"].attrs["settings"]["warm_predictor"] == "own"
    rc, out, err = _run(capsys, "info", str(own))
    assert rc == 0 and "50 iterations (frames B warm-started by their own pair: 10)" in out, out + err
    grid, truth = s.volume_grid(), s.truth()
    q = {name: [metrics.q_recon(st.read_volume(p, 1), metrics.truth_volume(grid, truth["particles"][p, 1]))
                for p in (1, 2)] for name, st in (("warm", s), ("cold", c), ("own", RunStore.open(own)))}
    assert np.mean(q["warm"]) >= np.mean(q["cold"]) - 0.015, q
    assert np.mean(q["own"]) >= np.mean(q["cold"]) - 0.015, q
    # the first pair is the same either way (its B had no predictor yet)
    np.testing.assert_allclose(s.read_volume(0, 1), c.read_volume(0, 1), rtol=1e-5, atol=1e-6)
    # volumes of a plain run are taken as made without warm starts: nothing to do again
    rc, out, err = _run(capsys, "reconstruct", str(cold), *fixed, "--skip-done", "--quiet")
    assert rc == 0 and "nothing to do" in out, out + err
    rc, out, err = _run(capsys, "reconstruct", str(cold), *fixed, "--warm-start", "--slabs", "2", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "--warm-start" in err and "slabs" in err, err
    rc, out, err = _run(capsys, "reconstruct", str(cold), *fixed, "--warm-start", "--form", "sequential",
                        "--relaxation", "2.5", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "simultaneous" in err, err


def test_line_of_sight_first_from_the_command(capsys, synthetic_run, tmp_path):
    """--los-iterations: the first iterations on line-of-sight weights, recorded with the volumes; as
    many as --iterations is one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "30", "--los-iterations", "10",
                        "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    assert RunStore.open(run).group["volumes"].attrs["settings"]["los_iterations"] == 10
    assert RunStore.open(run).read_volume(0, 1).max() > 0
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "30", "--los-iterations", "30", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "fewer than the iterations" in err, err


def test_ordered_subsets_from_the_command(capsys, synthetic_run, tmp_path):
    """--subsets: OS-SMART, recorded with the volumes, in memory and in depth slabs; volumes made before it
    are taken as the plain form's; a bad count or the sequential form is one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "10", "--subsets", "4", "--subset-halving",
                        "5", "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    recorded = RunStore.open(run).group["volumes"].attrs["settings"]
    assert recorded["subsets"] == 4 and recorded["subset_halving"] == 5
    assert RunStore.open(run).read_volume(0, 1).max() > 0
    rc, out, err = _run(capsys, "reconstruct", str(run), "--subsets", "0", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--subsets" in err, err
    rc, out, err = _run(capsys, "reconstruct", str(run), "--subsets", "4", "--form", "sequential", "--relaxation",
                        "2.5", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "simultaneous" in err, err
    # depth slabs run the subsets as in memory (tests/functional/test_slabs_cli.py compares the volumes)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--subsets", "4", "--slabs", "2", "--pair-range", "0:1",
                        "--quiet")
    assert rc == 0 and RunStore.open(run).group["volumes"].attrs["settings"]["subsets"] == 4, err
    # the store's recorded settings without the key (volumes made before it) read as one subset
    from lfpiv.jobs.reconstruct import _recorded

    assert _recorded({"method": "drt-mart"})["subsets"] == 1
    rc, out, err = _run(capsys, "reconstruct", str(run), "--subsets", "4", "--subset-halving", "-1", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--subset-halving" in err, err


def test_protocols_and_the_stopping_rule_from_the_command(capsys, synthetic_run, tmp_path):
    """--protocol fast stops each frame by the rule (at most --max-iterations), and the summary line,
    the settings, the volumes' convergence record and lfpiv info say which protocol ran, how many
    iterations and voxels the frames took and why they stopped; --iterations keeps its meaning (a fixed
    count, exactly that many); contradicting options are one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--max-iterations", "60",
                        "--pair-range", "0:1", "--quiet")
    assert rc == 0, err
    assert re.search(r"protocol fast: [\d-]+ iterations a frame \(.*at most 60 by the stopping rule", out), out
    # what each frame ran: the tiny box is too small for the coarse grid, and says so
    stages = ("each frame ran: elimination on the whole grid (no coarse grid for a box of fewer than 1,000,000 "
              "voxels); 20 iterations on line-of-sight weights, then DRT weights for the voxels still bright; 6 "
              "ordered subsets a pass; frames B warm-started from frame A carried along their own pair's "
              "displacement, at most 12 iterations; at most 60 iterations by the stopping rule")
    assert stages in out, out
    attrs = RunStore.open(run).group["volumes"].attrs
    assert attrs["settings"]["protocol"] == "fast" and attrs["settings"]["stop_tolerance"] > 0
    assert attrs["settings"]["iterations"] == 60 and attrs["settings"]["los_iterations"] == 20
    went = attrs["convergence"]
    assert went["frames"] == 2 and sum(went["stopped"].values()) == 2
    assert set(went["stopped"]) <= {"converged", "max iterations"} and 20 < went["iterations"][1] <= 60
    rc, out, err = _run(capsys, "info", str(run))
    assert rc == 0 and "at most 60 iterations (stopping rule)" in out and "protocol fast: " in out, out + err
    assert re.search(r"^stages +" + re.escape(stages.removeprefix("each frame ran: ")) + "$", out, re.M), out
    # --iterations is a fixed count, whatever the protocol
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--iterations", "25",
                        "--pair-range", "0:1", "--quiet")
    assert rc == 0 and "25 iterations a frame (fixed count; stopped: fixed count 2)" in out, out + err
    went = RunStore.open(run).group["volumes"].attrs["convergence"]
    assert went["iterations"] == [25, 25, 50] and went["stopped"] == {"fixed count": 2}
    # volumes recorded before the protocols were (no protocol in their settings) match the same settings
    f = run / "volumes" / "zarr.json"
    meta = json.loads(f.read_text())
    del meta["attributes"]["settings"]["protocol"]
    f.write_text(json.dumps(meta))
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--iterations", "25",
                        "--pair-range", "0:1", "--skip-done", "--quiet")
    assert rc == 0 and "nothing to do" in out, out + err
    for argv, expected in ((["--iterations", "20", "--max-iterations", "40"], "give one"),
                           (["--iterations", "20", "--stop-tolerance", "0.01"], "drop --stop-tolerance"),
                           (["--protocol", "slow"], "invalid choice: 'slow'")):
        rc, out, err = _run(capsys, "reconstruct", str(run), *argv, "--quiet")
        assert rc == 2 and out == "" and err.count("\n") == 1 and expected in err, err


def test_a_pair_made_again_replaces_its_frames_in_the_convergence_record(capsys, synthetic_run, tmp_path):
    """The volumes' convergence record keeps a row per frame: a pair reconstructed again into the same
    volumes replaces its rows instead of counting its frames twice; a record of an older lfpiv (totals
    without rows) is added to as before."""
    from lfpiv.jobs.reconstruct import convergence_figures

    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    for _ in range(2):
        rc, out, err = _run(capsys, "reconstruct", str(run), "--iterations", "12", "--pair-range", "0:1", "--quiet")
        assert rc == 0, err
    went = RunStore.open(run).group["volumes"].attrs["convergence"]
    assert went["frames"] == 2 and went["iterations"] == [12, 12, 24] and went["stopped"] == {"fixed count": 2}
    assert sorted(went["per_frame"]) == ["0,0", "0,1"] and went["per_frame"]["0,1"][0] == 12
    rc, out, err = _run(capsys, "info", str(run))
    assert rc == 0 and "12 iterations a frame" in out, out + err

    class Done:  # what convergence_figures reads of a ReconResult
        iterations, final_voxels, stopped = 30, 100, "converged"

    old = {"frames": 2, "iterations": [12, 12, 24], "voxels": [5, 9, 14], "stopped": {"fixed count": 2}}
    added = convergence_figures([Done()], old, frames=[(1, 0)])
    assert added["frames"] == 3 and added["iterations"] == [12, 30, 54] and "per_frame" not in added
    again = convergence_figures([Done()], {k: v for k, v in went.items()}, frames=[(0, 1)])
    assert again["frames"] == 2 and again["iterations"] == [12, 30, 42]
    assert again["voxels"][2] == went["per_frame"]["0,0"][1] + 100
    assert again["stopped"] == {"converged": 1, "fixed count": 1}


def test_a_warm_start_asked_for_in_slabs_is_refused_even_with_the_fast_protocol(capsys, synthetic_run, tmp_path):
    """The fast protocol's own warm start is left out in depth slabs; one the user typed is refused in one line."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    before = sorted((run / "volumes").rglob("*")) if (run / "volumes").exists() else []
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--warm-start", "--slabs", "2",
                        "--max-iterations", "30", "--pair-range", "0:1", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--warm-start" in err and "slabs" in err, err
    after = sorted((run / "volumes").rglob("*")) if (run / "volumes").exists() else []
    assert after == before  # nothing written


def test_the_default_is_fast_and_its_volumes_do_not_depend_on_how_the_run_is_processed(capsys, synthetic_run,
                                                                                       tmp_path):
    """lfpiv reconstruct without options runs the fast protocol (the stopping rule, converged frames, frames
    B warm-started by their own pair); pairs made one range at a time and resumed with --skip-done give the
    volumes of one run in order (a frame B depends on its own pair alone, not on the pairs a process
    happened to make before it)."""
    whole, parts = tmp_path / "whole.zarr", tmp_path / "parts.zarr"
    shutil.copytree(synthetic_run, whole)
    shutil.copytree(synthetic_run, parts)
    rc, out, err = _run(capsys, "reconstruct", str(whole), "--quiet")
    assert rc == 0 and re.search(r"protocol fast: [\d-]+ iterations a frame \(.*stopping rule", out), out + err
    settings = RunStore.open(whole).group["volumes"].attrs["settings"]
    assert settings["protocol"] == "fast" and settings["stop_tolerance"] > 0 and settings["warm_start"] is True
    assert settings["warm_predictor"] == "own" and "2 frame(s) B started from their frame A" in out, out
    assert _run(capsys, "reconstruct", str(parts), "--pair-range", "1:2", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "reconstruct", str(parts), "--skip-done", "--quiet")
    assert rc == 0 and "reconstructed 2 volume(s)" in out, out + err  # pair 0 only
    a, b = RunStore.open(whole), RunStore.open(parts)
    for pair in (0, 1):
        for frame in (0, 1):
            want = a.read_volume(pair, frame)
            np.testing.assert_allclose(b.read_volume(pair, frame), want, rtol=1e-5, atol=1e-6 * float(want.max()))


def test_skip_done_finishes_a_run_by_the_protocol_it_was_begun_with(capsys, synthetic_run, tmp_path):
    """--skip-done without --protocol goes on with the protocol the volumes record (a run begun under the
    previous default, fixed, is finished by it, with a note), rather than remaking them by the default;
    --protocol given remakes them; volumes recorded before protocols were count as fixed."""
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    assert _run(capsys, "reconstruct", str(run), "--protocol", "fixed", "--iterations", "50", "--pair-range", "0:1",
                "--quiet")[0] == 0
    rc, out, err = _run(capsys, "reconstruct", str(run), "--skip-done", "--quiet")
    assert rc == 0 and "reconstructed 2 volume(s)" in out and "protocol fixed: 50 iterations a frame" in out, out
    assert err.count("\n") == 1 and "note: going on with --protocol fixed, which the volumes of" in err, err
    assert "replaced" not in err and RunStore.open(run).reconstructed_pairs() == [0, 1]
    # volumes recorded without a protocol (before protocols were): the default of then, fixed
    f = run / "volumes" / "zarr.json"
    meta = json.loads(f.read_text())
    del meta["attributes"]["settings"]["protocol"]
    f.write_text(json.dumps(meta))
    rc, out, err = _run(capsys, "reconstruct", str(run), "--skip-done", "--quiet")
    assert rc == 0 and "nothing to do" in out and "going on with --protocol fixed" in err, out + err
    # the protocol given wins: the volumes are made again by it
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fast", "--skip-done", "--pair-range", "0:1",
                        "--quiet")
    assert rc == 0 and "protocol fast: " in out and "going on" not in err and "replaced" in err, out + err


def test_a_frame_b_planned_warm_that_starts_uniform_grows_the_progress_bar(capsys, synthetic_run, tmp_path,
                                                                            monkeypatch):
    """A frame B whose own pair gives no predictor (a box too thin to correlate) runs the cold count:
    the progress bar's total grows with it instead of the count running past it."""
    import lfpiv.jobs.reconstruct as job
    from lfcore.reconstruct import FrameReconstructor

    def no_predictor(self, voxels, coarse, noise, warm):
        return None, self.los_operator(voxels) if self.settings.method == "drt-mart" else self.operator(voxels), 0.0

    bars = []

    class Recorded(job.tqdm):
        def __init__(self, *a, **k):
            super().__init__(*a, **{**k, "disable": False})
            bars.append(self)

    monkeypatch.setattr(FrameReconstructor, "_own_predictor", no_predictor)
    monkeypatch.setattr(job, "tqdm", Recorded)
    run = tmp_path / "run.zarr"
    shutil.copytree(synthetic_run, run)
    rc, out, err = _run(capsys, "reconstruct", str(run), "--protocol", "fixed", "--warm-start", "--iterations", "6",
                        "--warm-iterations", "2")
    assert rc == 0, err
    (bar,) = [b for b in bars if b.desc.startswith("reconstructing")]
    assert bar.n == 4 * 6 and bar.total == bar.n, (bar.n, bar.total)  # planned 2 x 6 + 2 x 2, ran 4 x 6
