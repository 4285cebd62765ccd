"""`lfpiv track`'s predictors, fields, workers and bad input, and the tracks through `lfpiv export`,
end to end on tiny synthetic runs of a known uniform flow."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import copy_run as _copy
from tests.helpers import velocity_rms as _rms


@pytest.fixture(scope="module")
def particles_run(tmp_path_factory):
    """Two pairs of a uniform flow (4 px, 0.3 PPM) on the tiny rig with their particles (one IPR round)."""
    import contextlib
    import io

    from lfpiv.cli import main

    run = tmp_path_factory.mktemp("track") / "u.zarr"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([str(a) for a in ("synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "2", "--ppm",
                                      "0.3", "--flow", "uniform", "--displacement-px", "4", "--quiet")]) == 0
        assert main(["particles", str(run), "--quiet", "--rounds", "1"]) == 0
    return run




def test_the_volumes_predictor_and_the_smooth_field(particles_run, tmp_path, capsys):
    run = _copy(particles_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--predictor", "volumes")
    # a run without volumes where the predictor needs them: one line, exit 2, nothing written
    assert rc == 2 and "no reconstructed volumes" in err and "lfpiv reconstruct" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not RunStore.open(run).has_vectors
    assert _run(capsys, "reconstruct", run, "--iterations", "5", "--pair-range", "0", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", run, "--predictor", "volumes", "--quiet")
    assert rc == 2 and "pair 1 has no reconstructed volumes" in err and not RunStore.open(run).has_vectors
    rc, out, err = _run(capsys, "track", run, "--predictor", "volumes", "--field", "smooth", "--pair-range", "0",
                        "--quiet")
    assert rc == 0, err
    assert "smooth field, predictor volumes" in out
    s = RunStore.open(run)
    settings = s.vectors()["attrs"]["settings"]
    assert (settings["predictor"], settings["field"], settings["source"]) == ("volumes", "smooth", "particle tracks")
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    rms = _rms(out)
    # the particles' own position errors, averaged: as the binned field of the same particles or better
    assert rms[0] < 0.2 and rms[1] < 0.2 and rms[2] < 0.4
    # --predictor previous cannot run on workers: one line, exit 2, the vectors left as they were
    before = s.read_vectors(0)["u"].copy()
    rc, out, err = _run(capsys, "track", run, "--predictor", "previous", "--workers", "1")
    assert rc == 2 and "--predictor previous" in err and "Traceback" not in err
    assert np.array_equal(RunStore.open(run).read_vectors(0)["u"], before, equal_nan=True)


def test_the_fitted_field(particles_run, tmp_path, capsys):
    run = _copy(particles_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--field", "fit", "--quiet")
    assert rc == 0, err
    assert "fit field, predictor none" in out
    s = RunStore.open(run)
    assert s.vectors()["attrs"]["settings"]["field"] == "fit"
    held = s.read_vectors(0)
    # the bins' centres outside the box (the last bins reach past it) hold none, those inside one
    assert np.isfinite(held["u"]).any() and np.isnan(held["u"]).any()
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    rms = _rms(out)
    # a uniform flow: the fit's trend, far better than the particles' own position errors
    assert rms[0] < 0.1 and rms[1] < 0.1 and rms[2] < 0.2


def test_the_divergence_free_field(particles_run, tmp_path, capsys):
    run = _copy(particles_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--field", "divfree", "--quiet")
    assert rc == 0, err
    assert "divfree field, predictor none" in out
    assert RunStore.open(run).vectors()["attrs"]["settings"]["field"] == "divfree"
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    rms = _rms(out)
    # a uniform flow is free of divergence and its trend: as the fit's field (above)
    assert rms[0] < 0.1 and rms[1] < 0.1 and rms[2] < 0.2


def test_the_previous_pairs_predictor_tracks_a_series(particles_run, tmp_path, capsys):
    run = _copy(particles_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--predictor", "previous", "--quiet")
    assert rc == 0, err
    assert "/vectors: 2 pair(s)" in out and "predictor previous" in out
    s = RunStore.open(run)
    true_mm = s.truth()["particles"][1, 1, 0] - s.truth()["particles"][1, 0, 0]
    kept = s.read_tracks(1)
    kept = kept[kept[:, 6] == 0]
    assert len(kept) > 0.6 * len(s.read_particles(1, 0))
    assert np.all(np.abs(np.median(kept[:, 3:6] - kept[:, :3], axis=0) - true_mm) < 0.3 * np.asarray(
        s.particle_attrs()["voxel_mm"]))


def test_workers_track_as_this_process_does(particles_run, tmp_path, capsys):
    here, there = _copy(particles_run, tmp_path, "a.zarr"), _copy(particles_run, tmp_path, "b.zarr")
    assert _run(capsys, "track", here, "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", there, "--quiet", "--workers", "1")
    assert rc == 0, err
    assert "by 1 local worker(s)" in out
    a, b = RunStore.open(here), RunStore.open(there)
    for p in (0, 1):
        assert np.array_equal(a.read_tracks(p), b.read_tracks(p))
        assert np.array_equal(a.read_vectors(p)["u"], b.read_vectors(p)["u"], equal_nan=True)
    rc, out, _ = _run(capsys, "track", there, "--quiet", "--workers", "1", "--skip-done")
    assert rc == 0 and "nothing to do" in out
    # the volumes predictor's correlation on a worker: the tracks of this process's
    for run in (here, there):
        assert _run(capsys, "reconstruct", run, "--iterations", "5", "--quiet")[0] == 0
    assert _run(capsys, "track", here, "--quiet", "--predictor", "volumes", "--bin", "32x32x8")[0] == 0
    rc, out, err = _run(capsys, "track", there, "--quiet", "--predictor", "volumes", "--bin", "32x32x8",
                        "--workers", "1")
    assert rc == 0, err
    a, b = RunStore.open(here), RunStore.open(there)
    assert b.vectors()["attrs"]["settings"]["predictor"] == "volumes"
    for p in (0, 1):
        assert np.array_equal(a.read_tracks(p), b.read_tracks(p))


def test_tracks_and_their_vectors_exported_for_paraview(particles_run, tmp_path, capsys):
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    run = _copy(particles_run, tmp_path)
    assert _run(capsys, "track", run, "--quiet")[0] == 0
    s = RunStore.open(run)
    dt = float(s.timing["dt_s"])
    rc, out, err = _run(capsys, "export", run, "--format", "tracks-vtk", "--out", tmp_path / "vtp")
    assert rc == 0, err
    assert "tracks_pair0000.vtp" in out and "tracks.pvd" in out
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(tmp_path / "vtp" / "tracks_pair0001.vtp"))
    r.Update()
    poly, tracks = r.GetOutput(), s.read_tracks(1)
    assert poly.GetNumberOfLines() == len(tracks) > 0 and poly.GetNumberOfPoints() == 2 * len(tracks)
    pts = vtk_to_numpy(poly.GetPoints().GetData())
    assert np.allclose(pts[0::2], tracks[:, :3] * 1e-3, atol=1e-11)  # metres
    vel = vtk_to_numpy(poly.GetPointData().GetArray("velocity"))
    assert np.allclose(vel[1::2], (tracks[:, 3:6] - tracks[:, :3]) * 1e-3 / dt, rtol=1e-5, atol=1e-9)
    assert vtk_to_numpy(poly.GetCellData().GetArray("outlier")).tolist() == tracks[:, 6].astype(int).tolist()
    rc, out, err = _run(capsys, "export", run, "--format", "tracks-csv", "--out", tmp_path / "csv")
    assert rc == 0, err
    table = np.loadtxt(tmp_path / "csv" / "tracks.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(table) == len(s.read_tracks(0)) + len(tracks)
    assert np.allclose(table[table[:, 0] == 1][:, 1:7], tracks[:, :6], atol=1e-6)
    # an earlier export is replaced only when asked
    rc, _, err = _run(capsys, "export", run, "--format", "tracks-csv", "--out", tmp_path / "csv")
    assert rc == 2 and "--overwrite" in err
    # the vectors it writes, through the vector exports' own readers
    rc, _, err = _run(capsys, "export", run, "--format", "vtk", "--out", tmp_path / "vti")
    assert rc == 0, err
    xr = vtk.vtkXMLImageDataReader()
    xr.SetFileName(str(tmp_path / "vti" / "vectors_pair0001.vti"))
    xr.Update()
    v = s.read_vectors(1)
    nz, ny, nx = v["u"].shape
    got = vtk_to_numpy(xr.GetOutput().GetPointData().GetArray("velocity")).reshape(nz, ny, nx, 3)
    assert np.allclose(got[..., 0], v["u"], equal_nan=True, atol=1e-7)
    xarray = pytest.importorskip("xarray")
    assert _run(capsys, "export", run, "--format", "netcdf", "--out", tmp_path / "nc")[0] == 0
    with xarray.open_dataset(tmp_path / "nc" / "vectors.nc") as ds:
        assert ds.sizes["time"] == 2 and np.allclose(np.asarray(ds["u"])[1], v["u"], equal_nan=True, atol=1e-7)


def test_tracks_export_needs_tracks(particles_run, tmp_path, capsys):
    run = _copy(particles_run, tmp_path)
    rc, _, err = _run(capsys, "export", run, "--format", "tracks-vtk", "--out", tmp_path / "o")
    assert rc == 2 and "Traceback" not in err and not (tmp_path / "o").exists()


def test_a_frame_too_crowded_to_pair_is_refused(tmp_path, capsys):
    from lfcore.volume import VolumeGrid

    run = tmp_path / "c.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.1",
                "--quiet")[0] == 0
    s = RunStore.open(run, mode="r+")
    grid = VolumeGrid.from_rig(s.rig)
    # a particle on every eighth voxel: about 17 in each 4 x 4 x 2 voxel search
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(grid.origin_mm), np.asarray(grid.origin_mm) + np.asarray(grid.voxel_mm) * (
        np.asarray(grid.shape[::-1]) - 1)
    n = int(np.prod(grid.shape)) // 8
    table = np.column_stack([rng.uniform(lo, hi, (n, 3)), np.ones(n), np.zeros(n)])
    s.create_particles(grid, method="drt-mart", settings={})
    s.write_particles(0, [table, table])
    rc, out, err = _run(capsys, "track", run)
    assert rc == 2 and "too many to pair" in err and "--search-voxels" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not RunStore.open(run).has_vectors


def test_a_run_without_particles_and_cameras_without_the_model_asked_for(tmp_path, capsys):
    run = tmp_path / "t.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tomo_4_cameras.toml", "--out", run, "--pairs", "1", "--ppp",
                "0.01", "--quiet")[0] == 0
    # nothing to track yet: one line, exit 2, nothing written
    rc, _, err = _run(capsys, "track", run)
    assert rc == 2 and "lfpiv particles" in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(run).has_vectors
    # pinhole cameras have no DRT model of a particle: one line naming the camera and the fix
    rc, _, err = _run(capsys, "particles", run, "--method", "drt-mart")
    assert rc == 2 and "pinhole camera" in err and "--method mlos-smart" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not RunStore.open(run).has_particles
