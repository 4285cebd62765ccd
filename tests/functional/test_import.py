"""``lfpiv import`` on files written by other libraries (tifffile, Pillow, imageio, lvpyio), never by
lfpiv: pixels come back exactly, the imported run reconstructs to the volumes of the original,
lost frames are drops rows, bad files are one line with nothing half-written, and an interrupted
import goes on."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.cli import main
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run

TINY = str(EXAMPLES / "tiny.toml")
ROWS, COLS = 160, 192


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A synthetic run of the tiny rig and its frames (pairs, 2, rows, columns)."""
    path = tmp_path_factory.mktemp("orig") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "3", "--ppm", "0.3", "--seed", "4",
                 "--quiet"]) == 0
    return path, RunStore.open(path).frames("cam0")[...]


def _tiffs(folder: Path, frames: np.ndarray) -> list[Path]:
    """One 16-bit TIFF per frame, frames A and B alternating, as camera software writes them."""
    import tifffile

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for i, img in enumerate(frames.reshape(-1, ROWS, COLS)):
        files.append(folder / f"frame{i + 1}.tif")  # frame1 .. frame6: natural order, not frame1, frame10 ...
        tifffile.imwrite(files[-1], img)
    return files


def test_tiffs_import_exactly_and_reconstruct_to_the_original_volumes(original, tmp_path, capsys):
    src, frames = original
    files = _tiffs(tmp_path / "tiffs", frames)
    before = {f: f.read_bytes() for f in files}
    out = tmp_path / "imported.zarr"
    rc, text, err = _run(capsys, "import", "--rig", TINY, "--out", out, "--frames",
                         f"cam0={tmp_path / 'tiffs' / '*.tif'}", "--dt-us", "2000", "--rate-hz", "10", "--quiet",
                         "--checksum", "sha256")
    assert rc == 0, err
    assert "3 pair(s) x 1 camera(s) from 6 file(s), 0 frame(s) lost" in text
    run = RunStore.open(out)
    assert run.state == "complete" and run.committed_pairs == 3 and run.drops() == []
    assert np.array_equal(run.frames("cam0")[...], frames)  # every pixel
    assert run.frame_ids("cam0").tolist() == [[0, 1], [2, 3], [4, 5]]
    assert np.allclose(run.timestamps_ns("cam0")[:, 1] - run.timestamps_ns("cam0")[:, 0], 2e6)
    assert run.timing["dt_s"] == pytest.approx(2e-3) and run.timing["rate_hz"] == 10.0
    sources = run.attrs["import"]["sources"]
    assert [Path(s["path"]).name for s in sources] == [f.name for f in files]
    for s, f in zip(sources, files, strict=True):
        assert s["size"] == f.stat().st_size and s["sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
    assert {f: f.read_bytes() for f in files} == before  # the sources are only read
    rc, info, _ = _run(capsys, "info", out)
    assert "imported  6 file(s) (interleaved layout) from cam0:" in info
    # the same volumes as the original run's, from the same pixels
    for path in (src, out):
        assert _run(capsys, "reconstruct", path, "--iterations", "3", "--quiet")[0] == 0
    assert np.array_equal(RunStore.open(out).volumes()[...], RunStore.open(src).volumes()[...])


def test_an_existing_store_is_never_replaced_without_overwrite(original, tmp_path, capsys):
    _, frames = original
    _tiffs(tmp_path / "t", frames[:1])
    argv = ["import", "--rig", TINY, "--out", tmp_path / "r.zarr", "--frames", str(tmp_path / "t" / "*.tif"),
            "--dt-us", "2000", "--quiet"]
    assert _run(capsys, *argv)[0] == 0
    rc, _, err = _run(capsys, *argv)
    assert rc == 2 and "already exists" in err and err.count("\n") == 1
    assert _run(capsys, *argv, "--overwrite")[0] == 0


def test_pillow_12_bit_files_multi_page_stacks_and_double_frame_layouts(original, tmp_path, capsys):
    import tifffile
    from PIL import Image

    _, frames = original
    twelve = (frames >> 4).astype(np.uint16)  # 12-bit data in 16-bit containers
    rig = tmp_path / "tiny12.toml"
    rig.write_text(Path(TINY).read_text().replace('focus_mm = [0.0, 0.0, 0.0]',
                                                  'focus_mm = [0.0, 0.0, 0.0]\nbit_depth = 12'))
    cases = {}
    # Pillow: one 16-bit TIFF per frame
    (tmp_path / "pil").mkdir()
    for i, img in enumerate(twelve.reshape(-1, ROWS, COLS)):
        Image.fromarray(img).save(tmp_path / "pil" / f"f{i:02d}.tif")
    cases["pil"] = ["--frames", str(tmp_path / "pil" / "*.tif")]
    # one multi-page stack of every frame, A and B alternating
    tifffile.imwrite(tmp_path / "stack.tif", twelve.reshape(-1, ROWS, COLS))
    cases["stack"] = ["--frames", str(tmp_path / "stack.tif")]
    # double-frame: a two-page TIFF per pair, and one image twice the sensor's height (A on top)
    (tmp_path / "two").mkdir()
    (tmp_path / "tall").mkdir()
    for p in range(len(twelve)):
        tifffile.imwrite(tmp_path / "two" / f"pair{p}.tif", twelve[p])
        Image.fromarray(np.concatenate([twelve[p, 0], twelve[p, 1]])).save(tmp_path / "tall" / f"pair{p}.tif")
    cases["two"] = ["--frames", str(tmp_path / "two" / "*.tif"), "--layout", "double-frame"]
    cases["tall"] = ["--frames", str(tmp_path / "tall" / "*.tif"), "--layout", "double-frame"]
    # separate: frames A and frames B in files of their own
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for p in range(len(twelve)):
        tifffile.imwrite(tmp_path / "a" / f"p{p}.tif", twelve[p, 0])
        tifffile.imwrite(tmp_path / "b" / f"p{p}.tif", twelve[p, 1])
    cases["separate"] = ["--frames", str(tmp_path / "a" / "*.tif"), "--frames-b", str(tmp_path / "b" / "*.tif"),
                         "--layout", "separate"]
    for name, argv in cases.items():
        out = tmp_path / f"{name}.zarr"
        rc, _, err = _run(capsys, "import", "--rig", rig, "--out", out, *argv, "--dt-us", "2000", "--quiet")
        assert rc == 0, (name, err)
        assert np.array_equal(RunStore.open(out).frames("cam0")[...], twelve), name


def test_pngs_from_imageio(original, tmp_path, capsys):
    import imageio.v3 as iio

    _, frames = original
    (tmp_path / "png").mkdir()
    for i, img in enumerate(frames[:2].reshape(-1, ROWS, COLS)):
        iio.imwrite(tmp_path / "png" / f"img{i + 1}.png", img)
    rc, _, err = _run(capsys, "import", "--rig", TINY, "--out", tmp_path / "p.zarr", "--frames",
                      str(tmp_path / "png"), "--dt-us", "2000", "--quiet")
    assert rc == 0, err
    assert np.array_equal(RunStore.open(tmp_path / "p.zarr").frames("cam0")[...], frames[:2])


def test_a_davis_set_from_lvpyio_with_its_times(original, tmp_path, capsys):
    lv = pytest.importorskip("lvpyio")
    _, frames = original
    buffers = []
    for p in range(len(frames)):
        buf = lv.arrays_to_buffer([frames[p, 0], frames[p, 1]])
        for k, f in enumerate(buf.frames):  # pairs at 20 Hz, frames 500 us apart, as DaVis records them
            f.attributes["AcqTimeSeries"] = f"{p * 50000 + k * 500:.0f} \u00b5s"
        buffers.append(buf)
    lv.write_set(buffers, str(tmp_path / "Rec"))
    rc, text, err = _run(capsys, "import", "--rig", TINY, "--out", tmp_path / "d.zarr", "--davis",
                         str(tmp_path / "Rec.set"), "--quiet")
    assert rc == 0, err
    run = RunStore.open(tmp_path / "d.zarr")
    assert np.array_equal(run.frames("cam0")[...], frames)
    assert run.timing["dt_s"] == pytest.approx(500e-6) and run.timing["rate_hz"] == pytest.approx(20.0, rel=1e-6)
    assert "dt 500 us, pairs at 20 Hz" in text


def test_lost_frames_are_drops_rows(original, tmp_path, capsys):
    import tifffile

    _, frames = original
    files = _tiffs(tmp_path / "odd", frames)
    files[-1].unlink()  # the last frame B never came: an odd number of frames
    rc, text, err = _run(capsys, "import", "--rig", TINY, "--out", tmp_path / "o.zarr", "--frames",
                         str(tmp_path / "odd" / "*.tif"), "--dt-us", "2000", "--quiet")
    assert rc == 0, err
    run = RunStore.open(tmp_path / "o.zarr")
    assert run.n_pairs == run.committed_pairs == 3 and "1 frame(s) lost" in text
    [drop] = run.drops()
    assert (drop["camera"], drop["pair"], drop["frame"]) == ("cam0", 2, 1) and "unpaired frame" in drop["reason"]
    assert np.array_equal(run.frames("cam0")[2, 0], frames[2, 0]) and run.frame_ids("cam0")[2].tolist() == [4, -1]
    # two cameras, one of which has a pair fewer: its frames of the last pair are lost, with the reason
    two = tmp_path / "two.toml"
    text = Path(TINY).read_text()
    cam = text[text.index("[[camera]]"):text.index("[laser]")]
    two.write_text(text.replace("[laser]", cam.replace('name = "cam0"', 'name = "cam1"') + "[laser]"))
    (tmp_path / "c1").mkdir()
    for i, img in enumerate(frames[:2].reshape(-1, ROWS, COLS)):
        tifffile.imwrite(tmp_path / "c1" / f"{i}.tif", img)
    _tiffs(tmp_path / "c0", frames)
    rc, _, err = _run(capsys, "import", "--rig", two, "--out", tmp_path / "t.zarr", "--frames",
                      f"cam0={tmp_path / 'c0' / '*.tif'}", "--frames", f"cam1={tmp_path / 'c1' / '*.tif'}",
                      "--dt-us", "2000", "--quiet")
    assert rc == 0, err
    drops = RunStore.open(tmp_path / "t.zarr").drops()
    assert [(d["camera"], d["pair"], d["frame"]) for d in drops] == [("cam1", 2, 0), ("cam1", 2, 1)]
    assert all("holds 2 pair(s)" in d["reason"] for d in drops)


def _corrupt(t: Path, frames: np.ndarray) -> list[str]:
    files = _tiffs(t / "bad", frames[:1])
    files[1].write_bytes(b"II*\x00" + bytes(range(256)) * 4)  # a TIFF header, then noise
    return ["--frames", str(t / "bad" / "*.tif")]


def _truncated(t: Path, frames: np.ndarray) -> list[str]:
    files = _tiffs(t / "cut", frames[:1])
    files[1].write_bytes(files[1].read_bytes()[: files[1].stat().st_size // 2])
    return ["--frames", str(t / "cut" / "*.tif")]


def _mixed(t: Path, frames: np.ndarray) -> list[str]:
    import tifffile

    files = _tiffs(t / "mix", frames[:1])
    tifffile.imwrite(files[1], frames[0, 1, :80])
    return ["--frames", str(t / "mix" / "*.tif")]


def _too_many_bits(t: Path, frames: np.ndarray) -> list[str]:
    import tifffile

    rig = t / "tiny10.toml"
    rig.write_text(Path(TINY).read_text().replace('focus_mm = [0.0, 0.0, 0.0]',
                                                  'focus_mm = [0.0, 0.0, 0.0]\nbit_depth = 10'))
    files = _tiffs(t / "bits", frames[:1])
    tifffile.imwrite(files[0], np.full((ROWS, COLS), 3000, np.uint16))
    return ["--frames", str(t / "bits" / "*.tif"), "--rig", str(rig)]


@pytest.mark.parametrize(("make", "expected"), [
    (_corrupt, "frame2.tif"),
    (_truncated, "frame2.tif"),
    (_mixed, "192 x 80 px"),
    (_too_many_bits, "more than the camera's bit_depth of 10"),
    (lambda t, f: ["--frames", str(t / "none" / "*.tif")], "no file matches"),
    (lambda t, f: ["--frames", f"cam9={t}/*.tif"], "camera 'cam9' is not in the rig"),
])
def test_bad_files_are_one_line_and_nothing_is_written(original, tmp_path, capsys, make, expected):
    argv = make(tmp_path, original[1])
    rig = argv[argv.index("--rig") + 1] if "--rig" in argv else TINY
    argv = [a for i, a in enumerate(argv) if a != "--rig" and (i == 0 or argv[i - 1] != "--rig")]
    rc, out, err = _run(capsys, "import", "--rig", rig, "--out", tmp_path / "x.zarr", *argv, "--dt-us", "2000",
                        "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1 and err.startswith("lfpiv: error: "), err
    assert expected in err, err
    assert not (tmp_path / "x.zarr").exists()  # nothing half-written


def test_an_interrupted_import_goes_on_with_skip_done(original, tmp_path, capsys, monkeypatch):
    import lfpiv.jobs.import_ as job

    _, frames = original
    _tiffs(tmp_path / "t", frames)
    argv = ["import", "--rig", TINY, "--out", tmp_path / "r.zarr", "--frames", str(tmp_path / "t" / "*.tif"),
            "--dt-us", "2000", "--quiet"]
    real = job.read_sources
    calls = []

    def interrupted(path, sources, **kw):
        calls.append(path)
        if len(calls) == 5:  # the first frame of the last pair
            raise KeyboardInterrupt
        return real(path, sources, **kw)

    monkeypatch.setattr(job, "read_sources", interrupted)
    monkeypatch.setattr(job, "cpu_threads", lambda: 1)  # one file at a time: the pairs before it are whole
    rc, _, _ = _run(capsys, *argv)
    assert rc == 130
    run = RunStore.open(tmp_path / "r.zarr")
    assert run.state == "aborted" and 1 <= run.committed_pairs <= 2
    kept = run.committed_pairs
    monkeypatch.setattr(job, "read_sources", real)
    rc, _, err = _run(capsys, *argv)
    assert rc == 2 and "already exists" in err
    calls.clear()
    monkeypatch.setattr(job, "read_sources", lambda path, sources, **kw: (calls.append(path), real(path, sources,
                                                                                                   **kw))[1])
    rc, text, err = _run(capsys, *argv, "--skip-done")
    assert rc == 0, err
    run = RunStore.open(tmp_path / "r.zarr")
    assert run.state == "complete" and run.committed_pairs == 3 and np.array_equal(run.frames("cam0")[...], frames)
    assert len(calls) == 2 * (3 - kept)  # only the pairs it lacked were read again
    assert len(run.attrs["import"]["sources"]) == 6
    import google_crc32c

    for s in run.attrs["import"]["sources"]:  # the default checksum is CRC32C
        assert s["crc32c"] == google_crc32c.value(Path(s["path"]).read_bytes()).to_bytes(4, "big").hex()


def test_a_calibration_from_the_lab_s_own_files_equals_the_one_the_rig_took(tmp_path, capsys):
    """White images and target planes taken by the simulated rig, written out as a camera's software
    would (16-bit TIFF) with the stage positions in a CSV, make the same calibration again from the
    files alone: grids, planes and fitted models."""
    import tifffile

    from calibration.store import CalibrationStore

    demo = str(EXAMPLES / "demo.toml")
    rig_made = tmp_path / "rig.zarr"
    assert main(["calibrate", "mla", "--rig", demo, "--out", str(rig_made), "--quiet"]) == 0
    assert main(["calibrate", "volume", "--rig", demo, "--planes", "5", "--step-mm", "0.2", "--out", str(rig_made),
                 "--quiet"]) == 0
    assert main(["calibrate", "fit", str(rig_made), "--quiet"]) == 0
    capsys.readouterr()
    took = CalibrationStore.open(rig_made)
    whites, images = [], []
    for cam in took.cameras:
        tifffile.imwrite(tmp_path / f"white_{cam}.tif", np.rint(took.white(cam)).astype(np.uint16))
        whites += ["--white", f"{cam}={tmp_path / f'white_{cam}.tif'}"]
        (tmp_path / cam).mkdir()
        for p, img in enumerate(took.plane_frames(cam)[...]):
            tifffile.imwrite(tmp_path / cam / f"plane{p + 1}.tif", img)
        images += ["--images", f"{cam}={tmp_path / cam / '*.tif'}"]
    stage = took.stage_mm(took.cameras[0])
    (tmp_path / "positions.csv").write_text("plane,stage_mm\n" + "".join(f"{p + 1},{float(s)!r}\n"
                                                                        for p, s in enumerate(stage)))
    files_made = tmp_path / "files.zarr"
    rc, out, err = _run(capsys, "calibrate", "mla", "--rig", demo, *whites, "--out", files_made, "--quiet")
    assert rc == 0, err
    rc, out, err = _run(capsys, "calibrate", "volume", "--rig", demo, *images, "--positions",
                        tmp_path / "positions.csv", "--out", files_made, "--quiet")
    assert rc == 0 and "took 5 plane(s)" in out, err
    rc, out, err = _run(capsys, "calibrate", "fit", files_made, "--quiet")
    assert rc == 0, err
    made = CalibrationStore.open(files_made)
    for cam in took.cameras:
        a, b = took.grid(cam), made.grid(cam)
        assert b.pitch_px == pytest.approx(a.pitch_px, abs=1e-4) and b.rotation_deg == pytest.approx(a.rotation_deg,
                                                                                                     abs=1e-3)
        assert np.array_equal(made.plane_frames(cam)[...], took.plane_frames(cam)[...])
        assert np.array_equal(made.stage_mm(cam), took.stage_mm(cam))
        ma, mb = took.model(cam), made.model(cam)
        assert mb["rms_px"] == pytest.approx(ma["rms_px"], abs=0.01)
        assert np.allclose(mb["camera"]["rotation_deg"], ma["camera"]["rotation_deg"], atol=0.01)
        assert mb["camera"]["magnification"] == pytest.approx(ma["camera"]["magnification"], rel=1e-4)
    assert made.target() == took.target()


def test_white_images_from_files_are_judged_against_the_camera_s_bit_depth(tmp_path, capsys):
    """A white image 83% clipped at 4095 was accepted while full scale came from [render]; with the
    camera's own bit_depth = 12 it is refused, and a hot pixel is rejected, not taken for a lenslet."""
    import tifffile

    from calibration.store import CalibrationStore
    from lfcore.white import WhiteImageConfig, white_image
    from lfpiv.rigfile import load_rig

    rig12 = tmp_path / "tiny12.toml"
    rig12.write_text(Path(TINY).read_text().replace('focus_mm = [0.0, 0.0, 0.0]',
                                                    'focus_mm = [0.0, 0.0, 0.0]\nbit_depth = 12'))
    rig = load_rig(rig12)
    cam = rig.camera[0]
    white = white_image(cam, render=rig.render, config=WhiteImageConfig(level_counts=2500.0))
    white = np.minimum(white, 4095).astype(np.uint16)
    hot = white.copy()
    hot[7, 9] = 4000  # a hot pixel between micro-images
    tifffile.imwrite(tmp_path / "white.tif", hot)
    rc, out, err = _run(capsys, "calibrate", "mla", "--rig", rig12, "--white", tmp_path / "white.tif", "--out",
                        tmp_path / "c.zarr", "--quiet")
    assert rc == 0, err
    assert "1 hot pixel(s) of the white image replaced" in err and "cam0: hex grid" in out
    assert CalibrationStore.open(tmp_path / "c.zarr").white("cam0")[7, 9] < 4000
    clipped = np.minimum(white.astype(np.int64) * 8, 4095).astype(np.uint16)
    assert np.mean(clipped == 4095) > 0.5
    tifffile.imwrite(tmp_path / "clipped.tif", clipped)
    rc, out, err = _run(capsys, "calibrate", "mla", "--rig", rig12, "--white", f"cam0={tmp_path / 'clipped.tif'}",
                        "--out", tmp_path / "d.zarr", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "saturated" in err and "full scale 4095" in err, err
    assert not (tmp_path / "d.zarr").exists()


def test_positions_that_miss_planes_are_one_line(tmp_path, capsys):
    import tifffile

    (tmp_path / "t").mkdir()
    for p in range(3):
        tifffile.imwrite(tmp_path / "t" / f"p{p}.tif", np.zeros((ROWS, COLS), np.uint16))
    (tmp_path / "pos.csv").write_text("stage_mm\n24.8\n25.0\n")
    rc, out, err = _run(capsys, "calibrate", "volume", "--rig", TINY, "--images", str(tmp_path / "t" / "*.tif"),
                        "--positions", tmp_path / "pos.csv", "--out", tmp_path / "c.zarr", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "holds 3 image(s) but the positions list 2 plane(s)" in err, err
    assert not (tmp_path / "c.zarr").exists()
    (tmp_path / "pos.csv").write_text("plane\n1\n2\n3\n")
    rc, _, err = _run(capsys, "calibrate", "volume", "--rig", TINY, "--images", str(tmp_path / "t" / "*.tif"),
                      "--positions", tmp_path / "pos.csv", "--out", tmp_path / "c.zarr", "--quiet")
    assert rc == 2 and "naming the column stage_mm" in err


def test_imported_files_to_every_export_each_opened_by_its_reader(original, tmp_path, capsys):
    """TIFFs in; reconstruct, correlate; every export read back by the reader users open it with
    (VTK's netCDF CF reader and XML image reader, ParaView's Tecplot reader, LaVision's lvpyio,
    scipy's loadmat) with the store's velocities, in metres."""
    vtk = pytest.importorskip("vtk")
    from scipy.io import loadmat
    from vtk.util.numpy_support import vtk_to_numpy

    _, frames = original
    _tiffs(tmp_path / "t", frames[:2])
    run = tmp_path / "r.zarr"
    assert _run(capsys, "import", "--rig", TINY, "--out", run, "--frames", str(tmp_path / "t" / "*.tif"),
                "--dt-us", "2000", "--rate-hz", "10", "--quiet")[0] == 0
    assert _run(capsys, "reconstruct", run, "--iterations", "5", "--quiet")[0] == 0
    assert _run(capsys, "correlate", run, "--windows", "32x32x16,16x16x8", "--overlap", "0.5", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0 and "no truth" in out and "outliers:" in out and "velocity error" not in out, err
    v = RunStore.open(run).vectors()
    nz, ny, nx = v["u"].shape[1:]
    x_m, y_m, z_m = (v[f"{a}_mm"] * 1e-3 for a in "xyz")
    formats = ("netcdf", "vtk", "tecplot", "davis", "mat")
    lv = pytest.importorskip("lvpyio")
    for fmt in formats:
        rc, out, err = _run(capsys, "export", run, "--format", fmt, "--out", tmp_path / fmt)
        assert rc == 0, (fmt, err)
    # netCDF-4 through VTK's CF reader, as ParaView opens it
    r = vtk.vtkNetCDFCFReader()
    r.SetFileName(str(tmp_path / "netcdf" / "vectors.nc"))
    r.UpdateInformation()
    for k in range(r.GetNumberOfVariableArrays()):
        r.SetVariableArrayStatus(r.GetVariableArrayName(k), 1)
    r.UpdateTimeStep(0.1)
    img = r.GetOutput()
    assert img.GetDimensions() == (nx, ny, nz)
    assert np.allclose(img.GetSpacing(), [x_m[1] - x_m[0], y_m[1] - y_m[0], z_m[1] - z_m[0]])
    assert np.allclose(vtk_to_numpy(img.GetPointData().GetArray("u")).reshape(nz, ny, nx), v["u"][1], atol=1e-7)
    # a VTK ImageData file of the series
    xr = vtk.vtkXMLImageDataReader()
    xr.SetFileName(str(tmp_path / "vtk" / "vectors_pair0001.vti"))
    xr.Update()
    vel = vtk_to_numpy(xr.GetOutput().GetPointData().GetArray("velocity")).reshape(nz, ny, nx, 3)
    assert np.allclose(vel[..., 2], v["w"][1], atol=1e-7) and np.allclose(xr.GetOutput().GetOrigin(),
                                                                           [x_m[0], y_m[0], z_m[0]])
    # Tecplot ASCII through ParaView's reader
    vtk.vtkObject.GlobalWarningDisplayOff()  # it warns that it ignores SOLUTIONTIME and STRANDID
    try:
        tr = vtk.vtkTecplotReader()
        tr.SetFileName(str(tmp_path / "tecplot" / "vectors.dat"))
        tr.Update()
    finally:
        vtk.vtkObject.GlobalWarningDisplayOn()
    zone = tr.GetOutput().GetBlock(1)
    assert np.allclose(vtk_to_numpy(zone.GetPointData().GetArray("v")), np.nan_to_num(v["v"][1]).ravel(), atol=1e-6)
    # DaVis through lvpyio: one 3D3C vector field per pair
    s = lv.read_set(str(tmp_path / "davis" / "vectors.set"))
    try:
        f = s[1][0]
        assert f.is_3c and len(f) == nz and f.shape == (ny, nx)
        m = f.as_masked_array(plane=nz // 2)
        ok = ~np.ma.getmaskarray(m)["u"]
        assert np.allclose(m["u"][ok], v["u"][1, nz // 2][ok], atol=1e-6)
    finally:
        s.close()
    # MATLAB, meshgrid order (ny, nx, nz, pairs)
    mat = loadmat(tmp_path / "mat" / "vectors.mat")
    assert mat["u"].shape == (ny, nx, nz, 2)
    assert np.allclose(np.nan_to_num(mat["u"][..., 1]), np.nan_to_num(np.transpose(v["u"][1], (1, 2, 0))))
    assert np.allclose(mat["x"][0, :, 0], x_m)
