"""The `lfpiv` command end to end: synth, info, demo, and every bad input's one-line error."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from lfcore.render import LightFieldRenderer
from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import no_space, one_error, signal_when_committed

TINY = str(EXAMPLES / "tiny.toml")



def _synth(capsys, out, *extra):
    rc, stdout, err = _run(capsys, "synth", "--rig", TINY, "--out", str(out), "--quiet", *extra)
    assert rc == 0, err
    return stdout


def test_synth_then_info(capsys, tmp_path):
    run = tmp_path / "run.zarr"
    out = _synth(capsys, run, "--ppm", "0.5", "--flow", "vortex-ring", "--pairs", "2", "--dt-ms", "2", "--seed", "1")
    assert "2 pair(s) x 1 camera(s)" in out
    s = RunStore.open(run)
    assert (s.state, s.committed_pairs, s.n_pairs) == ("complete", 2, 2)
    frames = s.frames("cam0")[...]
    assert frames.shape == (2, 2, 160, 192) and frames.dtype == np.uint16
    assert frames.max() > 1000 and np.median(frames) < 200  # particles over a dark background
    assert s.frame_ids("cam0").tolist() == [[0, 1], [2, 3]]
    assert s.timestamps_ns("cam0").tolist() == [[0, 2_000_000], [100_000_000, 102_000_000]]
    t = s.truth()
    assert t["particles"].shape == (2, 2, 186, 3) and t["attrs"]["flow"]["name"] == "vortex-ring"
    # the default peak displacement is 10 object-side pixels, in every pair: the ring is
    # phase-locked to the laser (one ring would be 1 mm on, out of the volume, by pair 1)
    disp = np.linalg.norm(t["particles"][:, 1] - t["particles"][:, 0], axis=-1).max(axis=1)
    assert disp / s.rig.camera[0].object_pixel_mm == pytest.approx([10.0, 10.0], rel=0.15)
    assert t["attrs"]["flow"]["period_s"] == pytest.approx(0.1) and np.allclose(t["t0_s"], [0.0, 0.1])

    rc, out, err = _run(capsys, "info", str(run))
    assert rc == 0 and err == ""
    for text in ("complete (2 of 2 pairs committed)", "cam0: 192 x 160 px", "hex MLA 55 um",
                 "vortex-ring", "186 particles per frame (0.5 PPM)", "dt 2 ms", "drops    none"):
        assert text in out, text


def test_synth_is_reproducible_by_seed(capsys, tmp_path):
    _synth(capsys, tmp_path / "a.zarr", "--pairs", "1", "--seed", "5", "--flow", "B2", "--omega", "0.5")
    _synth(capsys, tmp_path / "b.zarr", "--pairs", "1", "--seed", "5", "--flow", "B2", "--omega", "0.5")
    _synth(capsys, tmp_path / "c.zarr", "--pairs", "1", "--seed", "6", "--flow", "B2", "--omega", "0.5")
    a, b, c = (RunStore.open(tmp_path / f"{n}.zarr").frames("cam0")[...] for n in "abc")
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    t = RunStore.open(tmp_path / "a.zarr").truth()
    assert t["attrs"]["flow"] == {**t["attrs"]["flow"], "name": "B2", "omega": 0.5}
    d = t["particles"][0, 1] - t["particles"][0, 0]
    assert np.abs(d[:, :2]).max() < 1e-12  # B cases move along z only
    assert np.abs(d[:, 2]).max() / 5.5e-3 == pytest.approx(25.0, rel=0.05)  # the chapter's 25 px


def test_synth_from_points_csv(capsys, tmp_path):
    csv = tmp_path / "points.csv"
    csv.write_text("x_mm,y_mm,z_mm\n0.0,0.0,0.0\n0.1,-0.05,0.4\n-0.2,0.1,-0.6\n")
    run = tmp_path / "pts.zarr"
    _synth(capsys, run, "--particles", str(csv))
    s = RunStore.open(run)
    assert s.n_pairs == 1
    p = s.truth()["particles"]
    assert np.array_equal(p[0, 0], p[0, 1]) and p[0, 0].tolist()[1] == [0.1, -0.05, 0.4]
    a, b = s.frames("cam0")[0].astype(np.float64)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9  # the same points, different noise


def test_synth_warns_of_csv_particles_outside_the_volume(capsys, tmp_path):
    csv = tmp_path / "points.csv"
    # the second point was written in 100 um units: 10 mm is far outside the tiny volume
    csv.write_text("x_mm,y_mm,z_mm\n0.0,0.0,0.0\n10,-5,4\n")
    rc, _, err = _run(capsys, "synth", "--rig", TINY, "--out", str(tmp_path / "x.zarr"), "--particles", str(csv),
                      "--quiet")
    assert rc == 0 and err.count("lie outside") == 1 and "1 of 2 particles" in err


def test_demo_runs_the_whole_instrument_on_the_simulated_lab(capsys, tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / ".lfpiv-demo").write_text("")  # a previous demo's folder is replaced
    (out / "old.png").write_bytes(b"x")
    rc, stdout, err = _run(capsys, "demo", "--rig", TINY, "--out", str(out), "--pairs", "1", "--rays", "500",
                           "--monitor", "no")
    assert rc == 0, err
    assert not (out / "old.png").exists()
    for name in ("raw_images.png", "vectors.png", "quality.png", "calibration.png"):
        png = out / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000, name
    run = RunStore.open(out / "run.zarr")
    assert run.state == "complete" and run.has_volumes and run.has_vectors
    assert run.truth() is not None  # recorded on the simulated lab, which knows what it showed
    assert (out / "field" / "vectors.nc").stat().st_size > 1000
    assert (out / "calib.zarr").is_dir()
    assert "$ lfpiv acquire" in err and "Q" in stdout and "done in" in stdout
    # the particle route on a copy of the same recording, and both routes side by side
    assert "$ lfpiv particles" in err and "$ lfpiv track" in err
    particles = RunStore.open(out / "particles.zarr")
    assert particles.has_particles and particles.has_vectors and not particles.has_volumes
    assert particles.committed_pairs == run.committed_pairs and particles.truth() is not None
    table = stdout[stdout.index("The two routes on the same recording"):]
    rows = {line.split("  ")[0]: line for line in table.splitlines()[2:4]}
    assert set(rows) == {"DRT-MART + correlation", "particles (IPR) + tracking"}, table
    for line in rows.values():
        assert re.search(r"  1  +\d+\.\d  +\d+\.\d  +\d+\.\d%  +[\d.]+, [\d.]+, [\d.]+  +\d+/\d+$", line), line
    png = out / "routes.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_demo_never_replaces_a_users_run(capsys, tmp_path):
    out = tmp_path / "lab"
    out.mkdir()
    _synth(capsys, out / "run.zarr", "--pairs", "1")
    before = RunStore.open(out / "run.zarr").frames("cam0")[...]
    rc, _, err = _run(capsys, "demo", "--rig", TINY, "--out", str(out), "--pairs", "1")
    assert rc == 2 and "is not empty and was not written by 'lfpiv demo'; choose another --out" in err
    assert np.array_equal(RunStore.open(out / "run.zarr").frames("cam0")[...], before)


def test_interrupted_synth_keeps_committed_pairs(capsys, tmp_path, monkeypatch):
    real = LightFieldRenderer.frame
    calls = {"n": 0}

    def flaky(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # pair 1, frame A
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(LightFieldRenderer, "frame", flaky)
    run = tmp_path / "cut.zarr"
    rc, _, err = _run(capsys, "synth", "--rig", TINY, "--out", str(run), "--pairs", "3", "--quiet")
    assert rc == 130 and "interrupted" in err
    s = RunStore.open(run)
    assert (s.state, s.committed_pairs) == ("aborted", 1)
    assert s.frames("cam0")[0].max() > 1000 and s.truth()["particles"].shape[0] == 3


def test_a_killed_synth_ends_as_after_ctrl_c(tmp_path):
    run = tmp_path / "killed.zarr"
    proc = subprocess.Popen([sys.executable, "-m", "lfpiv", "synth", "--rig", TINY, "--out", str(run), "--pairs",
                             "300", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, err = signal_when_committed(proc, run, 2, signal.SIGTERM, timeout_s=120.0)
    assert proc.returncode == 130 and "Traceback" not in err and "interrupted" in err, err
    s = RunStore.open(run)
    assert s.state == "aborted" and 2 <= s.committed_pairs < 300


def _bad_rig(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text((EXAMPLES / "tiny.toml").read_text().replace("f_number = 2.0", "f_number = 2.0\nfocal = 3"))
    return str(p)


def _user_folder(t):
    """A folder of the user's that is not a run store."""
    (t / "mydata").mkdir(exist_ok=True)
    (t / "mydata" / "notes.txt").write_text("keep me")
    return str(t / "mydata")


def _under_a_file(t):
    (t / "afile").write_text("")
    return str(t / "afile" / "x.zarr")


BAD_INPUTS = [
    (lambda t: ["synth", "--rig", TINY, "--out", _user_folder(t), "--overwrite"],
     "not an lfpiv run store (no zarr v3 group there: GroupNotFoundError), and --overwrite replaces only run stores"),
    (lambda t: ["synth", "--rig", TINY, "--out", _under_a_file(t)], "cannot use"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--iterations", "0"], "--iterations: must be at least 1"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--iterations", "1000000000"], "--iterations: must be at most 10000"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "no" / "such" / "x.zarr")], "no/such does not exist (to hold "
     "x.zarr); create it first"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--background", "-5"], "--background: must be 0 or more"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--pvr", "-2,2,10"], "--pvr must be three positive numbers"),
    (lambda t: ["evaluate", str(t / "r.zarr"), "--threshold", "2"], "--threshold: must be a fraction above 0"),
    (lambda t: ["calibrate", "volume", "--rig", TINY, "--out", str(t / "c.zarr"), "--settle-s", "-1"],
     "--settle-s: must be 0 or more"),
    (lambda t: ["synth", "--rig", str(t / "none.toml"), "--out", str(t / "x.zarr")], "none.toml not found"),
    (lambda t: ["synth", "--rig", _bad_rig(t), "--out", str(t / "x.zarr")], "camera[0].focal: unknown key"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--ppm", "0"], "--ppm: must be a positive"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "0"], "--pairs: must be at least 1"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--flow", "tornado"], "invalid choice"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--dt-ms", "-1"], "--dt-ms: must be a positive"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--device", "cuda:7"],
     "device 'cuda:7' is not available"),
    (lambda t: ["synth", "--rig", TINY], "the following arguments are required: --out"),
    (lambda t: ["info", str(t / "nothing.zarr")], "does not exist"),
    (lambda t: ["info", str(t)], "not an lfpiv run store"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--seed", "-1"], "--seed: must be at least 0"),
    (lambda t: ["synth", "--rig", _not_utf8(t), "--out", str(t / "x.zarr")], "latin1.toml is not UTF-8 text (byte 23)"),
    (lambda t: ["acquire", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "1", "--ring", "1"],
     "--ring: must be at least 2"),
    (lambda t: ["acquire", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "100000000000"],
     "--pairs 100000000000 is more than one burst of the pulse generator fires (1,000,000)"),
    (lambda t: ["evaluate", str(t / "r.zarr"), "--plot", "q.txt"], "'q.txt' does not end in .png"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--smooth", "inf"], "--smooth: must be finite, got inf"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--ppm", "1e6"],
     "--ppm: must be at most 10 particles per microlens"),
    (lambda t: ["acquire", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "1", "--sim-ppm", "-1"],
     "--sim-ppm: must be a positive number"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--rays", "100000000"],
     "--rays: must be at most 1000000"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--sub-apertures", "1000"], "--sub-apertures: must be at most 64"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--cameras", "cam0,cam0"], "--cameras: 'cam0' is named twice"),
    (lambda t: ["reconstruct", str(t / "r.zarr"), "--cameras", "cam0,"], "--cameras: 'cam0,' has an empty name"),
    (lambda t: ["calibrate", "volume", "--rig", TINY, "--out", str(t / "x.zarr"), "--spacing-mm", "0.0001"],
     "dots 0.0001 mm apart are closer than 2 lenslets of the cameras (0.11 mm in the volume)"),
    (lambda t: ["calibrate", "volume", "--rig", TINY, "--out", str(t / "x.zarr"), "--spacing-mm", "1e8"],
     "dots 1e+08 mm apart leave fewer than 2 across the narrowest camera's field of view (0.88 mm)"),
    (lambda t: ["synth", "--rig", _huge_sensor(t), "--out", str(t / "x.zarr")],
     "camera[0].sensor_px[0]: input should be less than or equal to 32768 (got 100000)"),
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "3000000000"],
     "out of memory (Unable to allocate"),
    (lambda t: ["synth", "--rig", TINY, "--out", _link_to_a_folder(t), "--overwrite"],
     "link.zarr is a symbolic link (to "),
    # inputs that would have run for minutes or hours, or rendered nothing
    (lambda t: ["synth", "--rig", TINY, "--out", str(t / "x.zarr"), "--displacement-px", "1e7"],
     "a displacement of 1e+07 px is more than the volume's extent (291 px"),
    (lambda t: ["acquire", "--rig", TINY, "--out", str(t / "x.zarr"), "--pairs", "3", "--sim-pool", "100000"],
     "--sim-pool must be from 1 to 1000 pairs, got 100000"),
    (lambda t: ["synth", "--rig", _rig_with(t, "particle_counts = 50000.0", "particle_counts = 1e300"), "--out",
                str(t / "x.zarr")], "render.particle_counts: input should be less than or equal to 1000000000"),
    (lambda t: ["monitor", "--rig", TINY, "--iterations", "0"], "--iterations: must be at least 1"),
    (lambda t: ["evaluate", str(t / "r.zarr"), "--plot", str(t / "nowhere" / "q.png")],
     "nowhere does not exist; create it first"),
]


def _rig_with(t, old, new):
    (t / "changed.toml").write_text(Path(TINY).read_text().replace(old, new))
    return str(t / "changed.toml")


def _link_to_a_folder(t):
    (t / "link.zarr").symlink_to(_user_folder(t))
    return str(t / "link.zarr")


def _huge_sensor(t):
    text = re.sub(r"sensor_px = \[[^\]]*\]", "sensor_px = [100000, 64]", Path(TINY).read_text())
    (t / "huge.toml").write_text(text)
    return str(t / "huge.toml")


def _not_utf8(t):
    (t / "latin1.toml").write_bytes("# rig of the lab in Orl\xe9ans\n".encode("latin-1"))
    return str(t / "latin1.toml")


@pytest.mark.parametrize(("argv", "expected"), BAD_INPUTS)
def test_bad_input_is_one_line(capsys, tmp_path, argv, expected):
    rc, out, err = _run(capsys, *argv(tmp_path))
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("lfpiv: error: ") and expected in err, err
    assert not (tmp_path / "x.zarr").exists()  # nothing half-made
    if (tmp_path / "mydata").exists():
        assert (tmp_path / "mydata" / "notes.txt").read_text() == "keep me"


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("x,y,z\n1,2,3\n", "first line must be the header 'x_mm,y_mm,z_mm'"),
        ("x_mm,y_mm,z_mm\n0,0,0\n0,zero,0\n", "points.csv:3: expected three numbers"),
        ("x_mm,y_mm,z_mm\n0,0\n", "points.csv:2: expected three numbers"),
        ("x_mm,y_mm,z_mm\n", "no particles after the header"),
        ("x_mm,y_mm,z_mm\n0,0,150\n", "inside the focal length of camera 'cam0'"),
    ],
)
def test_bad_points_csv(capsys, tmp_path, content, expected):
    csv = tmp_path / "points.csv"
    csv.write_text(content)
    rc, _, err = _run(capsys, "synth", "--rig", TINY, "--out", str(tmp_path / "x.zarr"), "--particles", str(csv))
    assert rc == 2 and err.count("\n") == 1 and expected in err, err


def test_a_rig_file_and_points_saved_with_a_byte_order_mark_are_read(capsys, tmp_path):
    rig = tmp_path / "bom.toml"
    rig.write_bytes(b"\xef\xbb\xbf" + Path(TINY).read_bytes())
    csv = tmp_path / "points.csv"
    csv.write_bytes(b"\xef\xbb\xbfx_mm,y_mm,z_mm\r\n0.0,0.0,0.0\r\n")
    rc, _, err = _run(capsys, "synth", "--rig", rig, "--out", tmp_path / "x.zarr", "--particles", csv, "--quiet")
    assert rc == 0, err
    assert RunStore.open(tmp_path / "x.zarr").truth()["particles"].shape == (1, 2, 1, 3)


def test_a_smoothing_that_would_fail_is_refused_before_the_volumes_are_replaced(capsys, tmp_path):
    run = tmp_path / "r.zarr"
    _synth(capsys, run, "--pairs", "1", "--rays", "300")
    assert _run(capsys, "reconstruct", run, "--iterations", "2", "--quiet")[0] == 0
    rc, _, err = _run(capsys, "reconstruct", run, "--iterations", "2", "--smooth", "1e9", "--quiet")
    assert rc == 2 and err == "lfpiv: error: smooth must be from 0 to 10 voxels, got 1000000000.0\n"
    assert RunStore.open(run).reconstructed_pairs() == [0]  # the volumes made before are kept


def test_demo_with_a_missing_device_keeps_the_previous_demo(capsys, tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / ".lfpiv-demo").write_text("")
    (out / "run.zarr").mkdir()  # what an earlier demo left, which a demo that runs replaces
    rc, _, err = _run(capsys, "demo", "--out", out, "--device", "cuda:7", "--monitor", "no")
    assert rc == 2 and "device 'cuda:7' is not available" in err
    assert (out / "run.zarr").is_dir()


def test_a_truth_cut_short_is_one_line_not_a_traceback(capsys, tmp_path):
    run = tmp_path / "r.zarr"
    _synth(capsys, run, "--pairs", "1", "--rays", "300")
    del zarr.open_group(str(run), mode="r+")["truth/brightness"]  # what a Ctrl-C while writing the truth left
    rc, _, err = _run(capsys, "info", run)
    assert rc == 2 and err.count("\n") == 1 and "truth/ has no brightness" in err and "--overwrite" in err


def test_existing_run_is_never_overwritten_silently(capsys, tmp_path):
    run = tmp_path / "keep.zarr"
    _synth(capsys, run, "--pairs", "1")
    before = RunStore.open(run).frames("cam0")[...]
    rc, _, err = _run(capsys, "synth", "--rig", TINY, "--out", str(run), "--pairs", "1", "--seed", "9")
    assert rc == 2 and "already exists; choose another output path or pass --overwrite" in err
    assert np.array_equal(RunStore.open(run).frames("cam0")[...], before)
    # acquire refuses it before the simulated lab starts rendering, with that one line only
    rc, _, err = _run(capsys, "acquire", "--rig", TINY, "--out", str(run), "--pairs", "1")
    assert rc == 2 and err.splitlines() == [f"lfpiv: error: {run} already exists; choose another output path or "
                                            "pass --overwrite"]
    _synth(capsys, run, "--pairs", "1", "--seed", "9", "--overwrite")
    assert not np.array_equal(RunStore.open(run).frames("cam0")[...], before)


def test_console_script_exit_code_and_no_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "lfpiv", "synth", "--rig", str(tmp_path / "no.toml"), "--out",
                        str(tmp_path / "x.zarr")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [f"lfpiv: error: rig file {tmp_path / 'no.toml'} not found; "
                                             "pass the path of a rig TOML file (see examples/)"]
    h = subprocess.run([sys.executable, "-m", "lfpiv", "--help"], capture_output=True, text=True, timeout=120)
    assert h.returncode == 0 and "synth" in h.stdout and "demo" in h.stdout


def test_a_full_disk_while_synthesizing_names_the_store_and_keeps_what_was_committed(capsys, tmp_path, monkeypatch):
    """The adversarial sweep's find (a real full disk, a tmpfs): synth said "cannot use: No space
    left on device" without the path."""
    path = tmp_path / "r.zarr"
    monkeypatch.setattr(RunStore, "write_frame", no_space(RunStore.write_frame, 4))
    rc, _, err = _run(capsys, "synth", "--rig", TINY, "--out", path, "--pairs", "4", "--rays", "50", "--quiet")
    assert rc == 2 and one_error(err) and f"cannot use {path}: No space left on device" in err, err
    s = RunStore.open(path)
    assert s.state == "aborted" and s.committed_pairs == 2 and RunStore.check(path) == []
