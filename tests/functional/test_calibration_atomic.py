"""Calibration stores are written atomically (issue 50): an interrupted update leaves the old
content or the new, an interrupted first calibration is refused as such; and the flat field end
to end (issue 49): synth with a camera response -> calibrate mla --dark-frames -> reconstruct."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calibration.store import CalibrationStore, CalibrationStoreError, _settle

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "examples" / "tiny.toml"
RESPONSE = "lens_falloff = 0.4\nmicro_vignetting = 0.3\ndust_spots = 2\ndark_fpn_counts = 4.0\n"


def lfpiv(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "lfpiv", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


def start(*args: str, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "lfpiv", *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def response_rig(tmp_path: Path) -> Path:
    rig = tmp_path / "resp.toml"
    rig.write_text(TINY.read_text().replace("particle_counts = 50000.0", "particle_counts = 50000.0\n" + RESPONSE))
    return rig


MLA = ("--sim-vignetting", "0", "--sim-dead", "0", "--quiet")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_update_keeps_old_or_new(tmp_path, sig):
    rig = response_rig(tmp_path)
    assert lfpiv("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", "--dark-frames", "1", *MLA,
                 cwd=tmp_path).returncode == 0
    before = CalibrationStore.open(tmp_path / "cal.zarr")
    white0 = before.white("cam0")
    for delay in (0.5, 1.5, 3.0):
        proc = start("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", "--dark-frames", "1", *MLA,
                     cwd=tmp_path)
        time.sleep(delay)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        assert "Traceback" not in err and "never retrieved" not in err
        store = CalibrationStore.open(tmp_path / "cal.zarr")
        white, grid, dark = store.white("cam0"), store.grid("cam0"), store.dark("cam0")
        assert white is not None and grid is not None and dark is not None
        assert white.shape == white0.shape and white.max() > 1000  # never zeroed, never gone


def test_interrupted_first_calibration_is_refused(tmp_path):
    rig = response_rig(tmp_path)
    store = CalibrationStore.create(tmp_path / "cal.zarr", __import__("lfpiv.rigfile", fromlist=["x"]).load_rig(rig),
                                    unfinished="calibrate mla")
    del store
    res = lfpiv("calibrate", "report", "cal.zarr", cwd=tmp_path)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "unfinished" in res.stderr
    info = lfpiv("info", "cal.zarr", cwd=tmp_path)
    assert info.returncode == 2 and len(info.stderr.strip().splitlines()) == 1 and "unfinished" in info.stderr
    with pytest.raises(CalibrationStoreError, match="unfinished"):
        CalibrationStore.open(tmp_path / "cal.zarr")
    # run again: finished, and readable
    assert lfpiv("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", *MLA, cwd=tmp_path).returncode == 0
    assert CalibrationStore.open(tmp_path / "cal.zarr").white("cam0").max() > 1000


def test_update_settles_after_a_kill(tmp_path):
    """A committed update killed between its renames is finished on open; an uncommitted one is dropped."""
    from lfpiv.rigfile import load_rig

    rig = load_rig(TINY)
    store = CalibrationStore.create(tmp_path / "cal.zarr", rig)
    store.write_white("cam0", np.full((160, 192), 500))
    cam = tmp_path / "cal.zarr" / "cam0"
    # uncommitted: staged, no commit attribute
    g = store.group["cam0"].create_group("update.staged")
    CalibrationStore._image(g, "white", np.full((160, 192), 900), "new", 1)
    _settle(cam)
    assert CalibrationStore.open(tmp_path / "cal.zarr").white("cam0").max() == 500
    # committed, killed after moving the old white aside
    g = store.group["cam0"].create_group("update.staged")
    CalibrationStore._image(g, "white", np.full((160, 192), 900), "new", 1)
    g.attrs["commit"] = {"replace": ["white"], "remove": []}
    (cam / "update.old").mkdir()
    os.replace(cam / "white", cam / "update.old" / "white")
    assert CalibrationStore.open(tmp_path / "cal.zarr").white("cam0").max() == 900
    assert not (cam / "update.staged").exists() and not (cam / "update.old").exists()


def test_flat_field_end_to_end(tmp_path):
    rig = response_rig(tmp_path)
    assert lfpiv("synth", "--rig", str(rig), "--out", "run.zarr", "--pairs", "1", "--ppm", "0.3", "--quiet",
                 cwd=tmp_path).returncode == 0
    assert lfpiv("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", "--dark-frames", "2", *MLA,
                 cwd=tmp_path).returncode == 0
    res = lfpiv("reconstruct", "run.zarr", "--flat-field", "cal.zarr", "--iterations", "5", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    import zarr

    settings = zarr.open_group(str(tmp_path / "run.zarr" / "volumes"), mode="r").attrs["settings"]
    assert settings["flat_field"]["cameras"]["cam0"]["dark"] is True
    # a calibration of another rig: one line, exit 2
    other = tmp_path / "other.toml"
    other.write_text(rig.read_text().replace("sensor_px = [192, 160]", "sensor_px = [200, 160]"))
    assert lfpiv("calibrate", "mla", "--rig", str(other), "--out", "other.zarr", *MLA, cwd=tmp_path).returncode == 0
    bad = lfpiv("reconstruct", "run.zarr", "--flat-field", "other.zarr", "--quiet", cwd=tmp_path)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "another camera" in bad.stderr


def test_particles_flat_field_end_to_end(tmp_path):
    """lfpiv particles --flat-field: frames of a camera with a response (lens fall-off, micro-image
    vignetting, dust, a dark pattern) corrected as reconstruct corrects them, the particles found against
    the truth, the calibration recorded (another correction is not the same particles), and a calibration
    of another rig refused in one line with nothing written."""
    from lfcore.runstore import RunStore
    from lfpiv.jobs.particles import same_settings

    rig = response_rig(tmp_path)
    assert lfpiv("synth", "--rig", str(rig), "--out", "run.zarr", "--pairs", "1", "--ppm", "0.3", "--quiet",
                 cwd=tmp_path).returncode == 0
    assert lfpiv("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", "--dark-frames", "2", *MLA,
                 cwd=tmp_path).returncode == 0
    other = tmp_path / "other.toml"
    other.write_text(rig.read_text().replace("sensor_px = [192, 160]", "sensor_px = [200, 160]"))
    assert lfpiv("calibrate", "mla", "--rig", str(other), "--out", "other.zarr", *MLA, cwd=tmp_path).returncode == 0
    bad = lfpiv("particles", "run.zarr", "--flat-field", "other.zarr", "--quiet", cwd=tmp_path)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "another camera" in bad.stderr
    assert not RunStore.open(tmp_path / "run.zarr").has_particles

    res = lfpiv("particles", "run.zarr", "--flat-field", "cal.zarr", "--rounds", "1", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    s = RunStore.open(tmp_path / "run.zarr")
    recorded = s.particle_attrs()["settings"]
    assert recorded["flat_field"]["cameras"]["cam0"]["dark"] is True
    raw = {k: v for k, v in recorded.items() if k != "flat_field"}
    assert not same_settings(recorded, raw) and same_settings(recorded, recorded)  # --skip-done tells them apart
    truth = s.truth()["particles"][0]
    vox = np.asarray(s.particle_attrs()["voxel_mm"])  # (x, y, z)
    for f in (0, 1):
        found = s.read_particles(0, f)[:, :3]
        err = np.array([np.min(np.max(np.abs(found - t) / vox, axis=1)) for t in truth[f]])
        # measured on the full run (3 rounds): recall 0.85 and 0.91 (raw frames: 0.87, 0.89)
        assert np.mean(err < 1.0) > 0.75
        assert len(found) < 1.3 * len(truth[f])


def test_white_and_dark_files_of_any_depth_and_bad_ones(tmp_path):
    """8- and 16-bit PNG and TIFF white and dark images are taken alike; a dark image brighter than
    the white, or either of another size: one line, exit 2, nothing written."""
    import tifffile
    from PIL import Image

    from lfcore.white import WhiteImageConfig, white_image
    from lfpiv.rigfile import load_rig

    rig16 = response_rig(tmp_path)
    rig8 = tmp_path / "r8.toml"
    rig8.write_text(rig16.read_text().replace('name = "cam0"', 'name = "cam0"\nbit_depth = 8'))
    rig = load_rig(rig16)
    white = white_image(rig.camera[0], render=rig.render, config=WhiteImageConfig(level_counts=20000.0))
    dark = np.full_like(white, 100)
    Image.fromarray((white / white.max() * 240).astype(np.uint8)).save(tmp_path / "white8.png")
    Image.fromarray((dark / white.max() * 240 + 2).astype(np.uint8)).save(tmp_path / "dark8.png")
    tifffile.imwrite(tmp_path / "white16.tif", white)
    tifffile.imwrite(tmp_path / "dark16.tif", dark)
    Image.fromarray(np.full((150, 192), 200, np.uint8)).save(tmp_path / "small.png")
    Image.fromarray(np.full(white.shape, 230, np.uint8)).save(tmp_path / "bright.png")
    for r, w, d in ((rig8, "white8.png", "dark8.png"), (rig16, "white16.tif", "dark16.tif")):
        res = lfpiv("calibrate", "mla", "--rig", str(r), "--white", w, "--dark", d, "--out", f"{w}.zarr", "--quiet",
                    cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        assert CalibrationStore.open(tmp_path / f"{w}.zarr").dark("cam0") is not None
    for w, d, what in (("white8.png", "bright.png", "brighter than the white"), ("small.png", "dark8.png", "192 x 150"),
                       ("white8.png", "small.png", "192 x 150")):
        res = lfpiv("calibrate", "mla", "--rig", str(rig8), "--white", w, "--dark", d, "--out", "bad.zarr", "--quiet",
                    cwd=tmp_path)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and what in res.stderr, res.stderr
        assert not (tmp_path / "bad.zarr").exists()


def test_monitor_corrects_live_frames(tmp_path):
    """lfpiv monitor --flat-field: the live path corrects every frame on the device and runs to its end."""
    pytest.importorskip("pyqtgraph")
    rig = response_rig(tmp_path)
    assert lfpiv("calibrate", "mla", "--rig", str(rig), "--out", "cal.zarr", "--dark-frames", "1", *MLA,
                 cwd=tmp_path).returncode == 0
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    res = lfpiv("monitor", "--rig", str(rig), "--pairs", "2", "--after", "1", "--screenshot", "shot.png",
                "--flat-field", "cal.zarr", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "2 pair(s) processed" in res.stdout and (tmp_path / "shot.png").stat().st_size > 0


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_in_the_middle_of_a_write_waits_for_it(tmp_path, sig):
    """A real signal arriving while a white image is being written takes effect once the update is in
    place: the new white whole, nothing staged left; SIGINT then raises KeyboardInterrupt as before."""
    from lfpiv.rigfile import load_rig

    store = CalibrationStore.create(tmp_path / "cal.zarr", load_rig(TINY))
    store.write_white("cam0", np.full((160, 192), 500))
    real = CalibrationStore._image
    got: list[int] = []

    def image_then_signal(g, name, image, what, frames):  # the signal lands between the arrays' writes
        out = real(g, name, image, what, frames)
        os.kill(os.getpid(), sig)
        time.sleep(0.05)
        return out

    previous = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        CalibrationStore._image = staticmethod(image_then_signal)
        with pytest.raises(KeyboardInterrupt) if sig == signal.SIGINT else contextlib.nullcontext():
            store.write_white("cam0", np.full((160, 192), 900))
    finally:
        CalibrationStore._image = staticmethod(real)
        signal.signal(signal.SIGTERM, previous)
    assert CalibrationStore.open(tmp_path / "cal.zarr").white("cam0").max() == 900
    assert not (tmp_path / "cal.zarr" / "cam0" / "update.staged").exists()
    assert got == ([signal.SIGTERM] if sig == signal.SIGTERM else [])
