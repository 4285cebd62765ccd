"""`lfpiv correlate`, `lfpiv export` and the vector lines of `evaluate`, end to end on a tiny run store."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from lfcore.flows import Uniform
from lfcore.runstore import RunStore
from lfcore.volume import VolumeGrid
from lfpiv.cli import main
from lfpiv.jobs.evaluate import evaluate_vectors
from tests.blobs import blob_pair
from tests.conftest import run_cli as _run

DT = 2e-3
SHIFT_VOX = np.array([0.4, -0.3, 0.6])  # x, y, z voxels over dt
WINDOWS = "32x32x16,16x16x8"



def _make_run(path, rig, with_volumes=True, pairs=2, reconstructed=2):
    """A synthetic run of the tiny rig whose volumes are Gaussian blobs moved by a uniform flow."""
    grid = VolumeGrid.from_rig(rig)
    vel = SHIFT_VOX * np.asarray(grid.voxel_mm) * 1e-3 / DT
    s = RunStore.create(path, rig, pairs, timing={"dt_s": DT, "rate_hz": 10.0}, software_version="test")
    s.write_truth(np.zeros((pairs, 2, 1, 3)), np.zeros((pairs, 2, 1)), Uniform(velocity_m_s=tuple(vel)).params())
    if with_volumes:
        s.create_volumes(grid, method="gaussian blobs", settings={})
        for p in range(reconstructed):
            a, b = blob_pair(grid.shape, lambda q: np.broadcast_to(SHIFT_VOX, q.shape), seed=p, density=0.025)
            s.write_volume(p, 0, a)
            s.write_volume(p, 1, b)
    s.commit(pairs)
    s.set_state("complete")
    return s, grid, vel


@pytest.fixture(scope="module")
def correlated(tmp_path_factory, tiny_rig):
    """One run correlated once for the tests that read its vectors."""
    path = tmp_path_factory.mktemp("corr") / "run.zarr"
    _, grid, vel = _make_run(path, tiny_rig)
    rc = main(["correlate", str(path), "--windows", WINDOWS, "--device", "cpu", "--quiet"])
    assert rc == 0
    return path, grid, vel


def test_correlate_writes_vectors(correlated):
    path, grid, vel = correlated
    s = RunStore.open(path)
    assert s.correlated_pairs() == [0, 1]
    v = s.vectors()
    nz, ny, nx = grid.shape  # (29, 68, 82) voxels
    shape = (2, (nz - 8) // 2 + 1, (ny - 16) // 4 + 1, (nx - 16) // 4 + 1)
    assert v["u"].shape == shape and v["flags"].shape == shape and v["peak_ratio"].shape == shape
    assert len(v["x_mm"]) == shape[3] and len(v["z_mm"]) == shape[1]
    # the grid's world coordinates: window centres in the volume's frame
    assert np.allclose(np.diff(v["x_mm"]), 4 * grid.voxel_mm[0])
    assert np.allclose(np.diff(v["z_mm"]), 2 * grid.voxel_mm[2])
    assert grid.origin_mm[0] < v["x_mm"][0] < v["x_mm"][-1] < -grid.origin_mm[0]
    for c, name in enumerate("uvw"):
        err = v[name] - vel[c]
        assert np.sqrt(np.mean(err**2)) < 0.05 * abs(vel[c]) / abs(SHIFT_VOX[c]), name  # < 0.05 voxel
    a = v["attrs"]
    assert a["dt_s"] == DT and a["windows"] == [[32, 32, 16], [16, 16, 8]] and a["overlap"] == [0.75] * 3
    assert a["settings"]["deform_iterations"] == 2 and a["settings"]["device"] == "cpu"
    g = s.group["vectors"]
    assert g["u"].attrs["units"] == "m/s" and g["x_mm"].attrs["units"] == "mm"
    assert g["u"].attrs["axes"] == ["pair", "z", "y", "x"]


def test_evaluate_vectors_reports_errors_against_the_truth(correlated):
    path, _, _ = correlated
    lines = dict(evaluate_vectors(RunStore.open(path)))
    assert set(lines) == {"vectors", "velocity error", "outliers", "divergence error"}
    assert "2 pair(s) of 17 x 14 x 11 vectors" in lines["vectors"] and "32x32x16, 16x16x8" in lines["vectors"]
    vox = [float(x) for x in re.search(r"\(([\d.]+), ([\d.]+), ([\d.]+) voxel\)", lines["velocity error"]).groups()]
    assert max(vox) < 0.05
    assert lines["outliers"].startswith("0.0% of the vectors")
    assert "1/s" in lines["divergence error"]


def test_evaluate_pairs_selects_the_vectors_too(correlated, capsys):
    path, _, _ = correlated
    assert "1 pair(s) of" in dict(evaluate_vectors(RunStore.open(path), slice(1, 2)))["vectors"]
    assert main(["evaluate", str(path), "--pairs", "1"]) == 0
    assert "vectors: 1 pair(s) of 17 x 14 x 11" in capsys.readouterr().out


def test_evaluate_without_vectors(tmp_path, tiny_rig):
    s, _, _ = _make_run(tmp_path / "r.zarr", tiny_rig)
    assert evaluate_vectors(s) == [("vectors", f"none yet (run 'lfpiv correlate {s.path}')")]


def test_the_old_name_of_evaluate_vectors_still_works_and_says_where_it_went(tmp_path, tiny_rig):
    from lfpiv.commands.correlate import evaluate_vectors as old

    s, _, _ = _make_run(tmp_path / "r.zarr", tiny_rig, with_volumes=False)
    with pytest.warns(DeprecationWarning, match=r"^lfpiv\.commands\.correlate\.evaluate_vectors is now "
                                                r"lfpiv\.jobs\.evaluate\.evaluate_vectors \(deprecated since"):
        assert old(s) == evaluate_vectors(s)



def test_export_netcdf(correlated, tmp_path, capsys):
    """netCDF-4, CF-1.8, in SI: the time dimension VTK's CF reader needs, positions in metres."""
    import netCDF4

    path, _, vel = correlated
    rc, out, err = _run(capsys, "export", path, "--format", "netcdf", "--out", tmp_path / "nc")
    assert rc == 0 and "vectors.nc" in out
    v = RunStore.open(path).vectors()
    with netCDF4.Dataset(tmp_path / "nc" / "vectors.nc") as nc:
        nc.set_auto_mask(False)
        assert nc.variables["u"].dimensions == ("time", "z", "y", "x")
        assert np.allclose(nc.variables["u"][:], v["u"]) and np.allclose(nc.variables["x"][:], v["x_mm"] * 1e-3)
        assert nc.variables["w"].units == "m s-1" and nc.variables["x"].units == "m"
        assert np.abs(nc.variables["divergence"][:]).mean() < 20.0  # 1/s; noise on a uniform field
        assert nc.variables["pair"][:].tolist() == [0, 1]
        assert np.allclose(nc.variables["time"][:], [0.0, 0.1]) and nc.variables["time"].units.startswith("seconds")


def test_export_never_writes_through_a_link(correlated, tmp_path, capsys):
    path, _, _ = correlated
    (tmp_path / "precious.txt").write_text("keep")
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "vectors.nc").symlink_to(tmp_path / "precious.txt")
    (tmp_path / "vtk").mkdir()
    (tmp_path / "vtk" / "vectors_pair0001.vti").symlink_to(tmp_path / "nothing.vti")
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    for fmt, out, expected in (("netcdf", "nc", "vectors.nc is a symbolic link, and export does not write through"),
                               ("vtk", "vtk", "vectors_pair0001.vti is a symbolic link"),
                               ("vtk", "gone", "is a symbolic link to nothing")):
        rc, _, err = _run(capsys, "export", path, "--format", fmt, "--out", tmp_path / out, "--overwrite")
        assert rc == 2 and expected in err, err
    assert (tmp_path / "precious.txt").read_text() == "keep" and not (tmp_path / "nothing.vti").exists()
    assert not (tmp_path / "nowhere").exists()


def test_export_vtk(correlated, tmp_path, capsys):
    path, _, _ = correlated
    # a series left from another export (of more pairs) is replaced, not mixed in
    (tmp_path / "vtk").mkdir()
    (tmp_path / "vtk" / "vectors_pair0007.vti").write_text("old")
    (tmp_path / "vtk" / "notes.txt").write_text("keep")
    rc, _, err = _run(capsys, "export", path, "--format", "vtk", "--out", tmp_path / "vtk")
    assert rc == 2 and "already holds vectors_pair0007.vti of an earlier export; pass --overwrite" in err
    assert (tmp_path / "vtk" / "vectors_pair0007.vti").read_text() == "old"
    rc, out, _ = _run(capsys, "export", path, "--format", "vtk", "--out", tmp_path / "vtk", "--overwrite")
    assert rc == 0
    (tmp_path / "vtk" / "notes.txt").unlink()
    files = sorted(p.name for p in (tmp_path / "vtk").iterdir())
    assert files == ["vectors.pvd", "vectors_pair0000.vti", "vectors_pair0001.vti"]
    raw = (tmp_path / "vtk" / "vectors_pair0001.vti").read_bytes()
    head, data = raw.split(b'<AppendedData encoding="raw">\n   _', 1)
    head = head.decode()
    v = RunStore.open(path).vectors()
    nz, ny, nx = v["u"].shape[1:]
    assert f'WholeExtent="0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"' in head
    arrays = re.findall(r'type="(\w+)" Name="(\w+)" NumberOfComponents="(\d)" format="appended" offset="(\d+)"', head)
    assert [a[1] for a in arrays] == ["velocity", "vorticity", "divergence", "q_criterion", "peak_ratio", "flags"]
    off = int(arrays[0][3])
    n = int(np.frombuffer(data[off:off + 4], np.uint32)[0])
    velocity = np.frombuffer(data[off + 4:off + 4 + n], np.float32).reshape(nz, ny, nx, 3)
    assert np.allclose(velocity, np.stack([v[c][1] for c in "uvw"], axis=-1))
    origin = [float(t) for t in re.search(r'Origin="([^"]+)"', head).group(1).split()]
    assert np.allclose(origin, [v["x_mm"][0] * 1e-3, v["y_mm"][0] * 1e-3, v["z_mm"][0] * 1e-3])  # metres
    assert 'timestep="0.1"' in (tmp_path / "vtk" / "vectors.pvd").read_text()


def test_correlate_selected_pairs_and_options(tmp_path, tiny_rig, capsys):
    _make_run(tmp_path / "r.zarr", tiny_rig, pairs=3, reconstructed=2)
    rc, out, err = _run(capsys, "correlate", tmp_path / "r.zarr", "--windows", "16x16x8", "--overlap", "0.5,0.5,0.75",
                        "--pairs", "1", "--iterations", "1", "--median-filter", "--threshold", "3", "--quiet")
    assert rc == 0, err
    assert "1 pair(s) of" in out and "vectors/s" in out
    s = RunStore.open(tmp_path / "r.zarr")
    assert s.correlated_pairs() == [1] and np.isnan(s.vectors()["u"][0]).all()
    a = s.vectors()["attrs"]
    assert a["overlap"] == [0.5, 0.5, 0.75] and a["settings"]["median_filter"] is True
    assert a["settings"]["median_test"] == {"epsilon": 0.1, "threshold": 3.0}


def test_correlate_with_a_search_radius(tmp_path, tiny_rig, capsys):
    """The direct correlation around the predictor from the command line: same flow, settings recorded."""
    _, grid, vel = _make_run(tmp_path / "s.zarr", tiny_rig, pairs=1, reconstructed=1)
    rc, out, err = _run(capsys, "correlate", tmp_path / "s.zarr", "--windows", WINDOWS, "--search-radius", "3",
                        "--first-overlap", "0.5", "--device", "cpu", "--quiet")
    assert rc == 0, err
    s = RunStore.open(tmp_path / "s.zarr")
    v = s.vectors()
    a = v["attrs"]["settings"]
    assert a["search_radius"] == [3, 3, 3] and a["first_overlap"] == [0.5, 0.5, 0.5]
    for comp, truth in zip("uvw", vel, strict=True):
        err_m_s = np.asarray(v[comp][0], dtype=np.float64) - truth
        assert np.sqrt(np.mean(err_m_s**2)) < 0.05 * np.abs(vel).max(), comp


def _no_volumes(t, rig):
    _make_run(t / "nv.zarr", rig, with_volumes=False)
    return t / "nv.zarr"


def _three_pairs(t, rig):
    _make_run(t / "p.zarr", rig, pairs=3, reconstructed=2)
    return t / "p.zarr"


BAD = [
    (lambda t, r: [_three_pairs(t, r)], "window 320x320x64 (x by y by z) is larger than the volume along x (320 > 82"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x64"], "larger than the volume along z (64 > 29"),
    (lambda t, r: [_three_pairs(t, r), "--overlap", "1"], "--overlap: overlap must be at least 0 and below 1"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "32x32"], "--windows: '32x32' is not a window size"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "32x32x2"], "--windows: window 32x32x2 is too small"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x8,32x32x8"],
     "--windows: window 32x32x8 is larger than the one before it; list the passes largest first"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x8", "--pairs", "x"], "--pairs: 'x' is not a pair"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x8", "--pairs", "1:3"], "pair(s) 2 are not reconstructed"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x8", "--pairs", "7"], "--pairs selects no pair"),
    (lambda t, r: [_three_pairs(t, r), "--device", "cuda:7"], "device 'cuda:7' is not available"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "16x16x8", "--search-radius", "x"], "--search-radius: 'x' is not"),
    (lambda t, r: [_three_pairs(t, r), "--windows", "32x32x16,16x16x8", "--search-radius", "12"],
     "search_radius must be 2 to 8 voxels"),
    (lambda t, r: [_no_volumes(t, r)], "has no reconstructed volumes; run 'lfpiv reconstruct"),
    (lambda t, r: [t / "none.zarr"], "does not exist"),
]


@pytest.mark.parametrize(("argv", "expected"), BAD)
def test_bad_correlate_input_is_one_line(capsys, tmp_path, tiny_rig, argv, expected):
    rc, out, err = _run(capsys, "correlate", *argv(tmp_path, tiny_rig), "--quiet")
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("lfpiv: error: ") and expected in err, err


def test_bad_export_input_is_one_line(capsys, tmp_path, tiny_rig):
    _make_run(tmp_path / "r.zarr", tiny_rig)
    rc, _, err = _run(capsys, "export", tmp_path / "r.zarr", "--format", "vtk", "--out", tmp_path / "o")
    assert rc == 2 and err.count("\n") == 1 and "has no vectors; run 'lfpiv correlate" in err
    rc, _, err = _run(capsys, "export", tmp_path / "r.zarr", "--format", "csv", "--out", tmp_path / "o")
    assert rc == 2 and err.count("\n") == 1 and "invalid choice: 'csv'" in err


def test_console_script_help_and_exit_code(tmp_path, tiny_rig):
    h = subprocess.run([sys.executable, "-m", "lfpiv", "correlate", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert h.returncode == 0 and "x by y by z voxels" in " ".join(h.stdout.split())
    _make_run(tmp_path / "r.zarr", tiny_rig)
    r = subprocess.run([sys.executable, "-m", "lfpiv", "correlate", str(tmp_path / "r.zarr"), "--overlap", "1"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    shutil.rmtree(tmp_path / "r.zarr")


def test_an_interrupted_replacement_leaves_the_old_vectors_whole_and_goes_on(tmp_path, tiny_rig, capsys,
                                                                            monkeypatch):
    import lfpiv.jobs.correlate as correlation

    path = tmp_path / "r.zarr"
    _make_run(path, tiny_rig)
    assert _run(capsys, "correlate", path, "--windows", "16x16x8", "--quiet")[0] == 0
    before = RunStore.open(path).vectors()
    real = correlation._correlate_pair
    done = []

    def interrupted_at_pair_1(correlator, target, pair, *args, **kwargs):
        if pair == 1:
            raise KeyboardInterrupt
        done.append(pair)
        return real(correlator, target, pair, *args, **kwargs)

    monkeypatch.setattr(correlation, "_correlate_pair", interrupted_at_pair_1)
    rc, _, err = _run(capsys, "correlate", path, "--windows", WINDOWS, "--quiet")
    assert rc == 130
    assert "note: the vectors of 2 pair(s) made with other settings (windows differ) are replaced once the new " \
           "ones are complete" in err
    assert "the 1 pair(s) of new vectors are kept aside and the vectors made before with other settings are " \
           "unchanged" in err
    s = RunStore.open(path)
    now = s.vectors()
    assert now["attrs"]["windows"] == [[16, 16, 8]] and s.correlated_pairs() == [0, 1]
    assert all(np.array_equal(now[n], before[n], equal_nan=True) for n in ("u", "v", "w", "flags"))
    assert s.pending("vectors").attrs["correlated_pairs"] == [0]

    done.clear()
    monkeypatch.setattr(correlation, "_correlate_pair", lambda *a, **k: (done.append(a[2]), real(*a, **k))[1])
    rc, _, err = _run(capsys, "correlate", path, "--windows", WINDOWS, "--skip-done", "--quiet")
    assert rc == 0, err
    assert done == [1]
    s = RunStore.open(path)
    assert s.vectors()["attrs"]["windows"] == [[32, 32, 16], [16, 16, 8]] and s.correlated_pairs() == [0, 1]
    assert s.pending("vectors") is None


def test_a_full_disk_while_exporting_names_the_folder(correlated, tmp_path, capsys, monkeypatch):
    """The adversarial sweep's find (a real full disk, a tmpfs): export said "cannot use: No space
    left on device" without the folder."""
    import errno

    import lfpiv.jobs.export as export

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(export, "_write", full)
    out = tmp_path / "x"
    rc, _, err = _run(capsys, "export", correlated[0], "--format", "vtk", "--out", out)
    assert rc == 2 and err.count("\n") == 1 and f"cannot use {out}: No space left on device" in err, err
