"""`lfpiv particles` and the particle lines of `lfpiv evaluate`, end to end on a tiny synthetic run."""

from __future__ import annotations

import re

import numpy as np
import pytest

from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run


def _scores(out):
    """``lfpiv evaluate``'s particle scores over all pairs: recall, ghosts (%) and the RMS position
    error x, y, z (voxels)."""
    m = re.search(r"^all\s+(\d+)\s+(\d+)\s+([\d.]+)\s+(\d+) \(([\d.]+)%\)\s+([\d.]+), ([\d.]+), ([\d.]+)", out, re.M)
    assert m, out
    return float(m.group(3)), float(m.group(5)), [float(m.group(k)) for k in (6, 7, 8)]


def test_synth_particles_evaluate(tmp_path, capsys):
    run = tmp_path / "run.zarr"
    rc, _, err = _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.3")
    assert rc == 0, err
    rc, out, err = _run(capsys, "particles", run, "--quiet")
    assert rc == 0, err
    assert "wrote" in out and "/particles: 1 pair(s)" in out
    s = RunStore.open(run)
    truth = s.truth()["particles"]
    for f in (0, 1):
        found = s.read_particles(0, f)
        assert found.shape[1] == 5 and np.all(np.isfinite(found))
        assert 0.8 * len(truth[0, f]) <= len(found) <= 1.2 * len(truth[0, f])
    assert s.particle_attrs()["method"] == "drt-mart"
    # --noise-model and --residual-mask auto: recorded as what they chose for this light-field camera
    recorded = s.particle_attrs()["settings"]
    assert recorded["noise_model"] == "shot" and recorded["residual_mask"] == 3.0
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    recall, ghosts, rms = _scores(out)
    # measured 0.86 recall, 14% ghosts, 0.13, 0.10, 0.23 voxel on this run (tiny rig, 0.3 PPM, one camera);
    # thirteenth session, auto's shot + 3: 0.833, 11.9%, 0.113, 0.095, 0.181 (flat + 0: 0.851, 12.9%, 0.105, 0.078,
    # 0.179)
    assert recall > 0.7 and ghosts < 25.0
    assert max(rms[:2]) < 0.25 and rms[2] < 0.4
    rc, out, _ = _run(capsys, "info", run)
    assert rc == 0 and re.search(r"^particles\s+1 pair\(s\) \(0\) reconstructed \(drt-mart IPR", out, re.M), out
    assert "3 round(s), shot fit, residual mask 3)" in out, out
    # done already with these settings: nothing to do, nothing rewritten
    rc, out, _ = _run(capsys, "particles", run, "--quiet", "--skip-done")
    assert rc == 0 and "nothing to do" in out


def test_bad_threshold_is_one_line_exit_2(tmp_path, capsys):
    run = tmp_path / "run.zarr"
    _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.1")
    rc, out, err = _run(capsys, "particles", run, "--threshold", "1")
    assert rc == 2
    assert "threshold" in err and "Traceback" not in err
    assert not RunStore.open(run).has_particles
    # a noise floor without the shot noise model would be ignored: refused instead (the flat model given:
    # auto chooses shot for this light-field camera)
    rc, out, err = _run(capsys, "particles", run, "--noise-floor", "0.1", "--noise-model", "flat")
    assert rc == 2 and err.count("\n") == 1 and "--noise-model shot" in err and "Traceback" not in err, err
    assert not RunStore.open(run).has_particles
    rc, out, err = _run(capsys, "particles", run, "--residual-mask", "-1")
    assert rc == 2 and "--residual-mask" in err and "Traceback" not in err, err
    assert not RunStore.open(run).has_particles


def test_track_a_uniform_flow_into_vectors(tmp_path, capsys):
    run = tmp_path / "u.zarr"
    rc, _, err = _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.3",
                      "--flow", "uniform", "--displacement-px", "4", "--quiet")
    assert rc == 0, err
    rc, out, err = _run(capsys, "track", run)
    assert rc == 2 and "no particles" in err and "lfpiv particles" in err  # nothing to track yet
    assert _run(capsys, "particles", run, "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", run, "--quiet")
    assert rc == 0, err
    assert "/vectors: 1 pair(s) of 6 x 5 x 4 bins" in out
    s = RunStore.open(run)
    v = s.vectors()
    assert v["attrs"]["settings"]["source"] == "particle tracks"
    assert v["u"].shape == (1, 4, 5, 6) and np.isfinite(v["u"]).any()
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    m = re.search(r"velocity error: RMS u, v, w .* m/s \(([\d.]+), ([\d.]+), ([\d.]+) voxel\)", out)
    assert m, out
    # measured 0.098, 0.060, 0.217 voxel: the particles' own position errors, over the bins with tracks
    assert float(m.group(1)) < 0.2 and float(m.group(2)) < 0.2 and float(m.group(3)) < 0.4
    tracks = s.read_tracks(0)
    assert tracks.shape[1] == 7 and len(tracks) > 0.6 * len(s.read_particles(0, 0))
    kept = tracks[tracks[:, 6] == 0]
    true_mm = s.truth()["particles"][0, 1, 0] - s.truth()["particles"][0, 0, 0]  # a uniform flow: every particle's
    assert np.all(np.abs(np.median(kept[:, 3:6] - kept[:, :3], axis=0) - true_mm) < 0.3 * np.asarray(
        s.particle_attrs()["voxel_mm"]))
    rc, out, _ = _run(capsys, "track", run, "--quiet", "--skip-done", "--csv", tmp_path / "tracks.csv")
    assert rc == 0 and "nothing to do" in out and f"tracks.csv: {len(tracks)} tracks" in out
    table = np.loadtxt(tmp_path / "tracks.csv", delimiter=",", skiprows=1, ndmin=2)
    assert table.shape == (len(tracks), 11) and np.allclose(table[:, 1:7], tracks[:, :6], atol=1e-6)
    rc, _, err = _run(capsys, "track", run, "--quiet", "--csv", tmp_path / "tracks.csv")
    assert rc == 2 and "exists" in err


def test_the_python_api(tmp_path, capsys):
    import lfpiv

    run = tmp_path / "api.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.2",
                "--flow", "uniform", "--displacement-px", "4", "--quiet")[0] == 0
    done = lfpiv.particles(run, rounds=1, progress=False)
    assert done.pairs == [0] and len(done.counts) == 2
    tracked = lfpiv.track(run, bin_voxels=(32, 32, 8), progress=False)
    assert tracked.pairs == [0] and tracked.tracks > 0
    ev = lfpiv.evaluate(run)
    assert len(ev.particles) == 2 and all(e.match.recall > 0.6 for e in ev.particles)
    assert ev.vectors is not None and ev.vectors.rms_voxels is not None
    assert lfpiv.open_run(run).particle_attrs()["settings"]["rounds"] == 1


def test_a_mixed_rig_has_its_particles_reconstructed(tmp_path, capsys):
    run = tmp_path / "mix.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "mixed_cameras.toml", "--out", run, "--pairs", "1", "--ppm",
                "0.3", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "particles", run, "--quiet", "--rounds", "1")
    assert rc == 0, err
    rc, out, err = _run(capsys, "evaluate", run)
    m = re.search(r"^all\s+(\d+)\s+(\d+)\s+([\d.]+)\s+(\d+) \(([\d.]+)%\)\s+([\d.]+), ([\d.]+), ([\d.]+)", out, re.M)
    assert rc == 0 and m, out
    # measured at 0.5 PPM (3 rounds): recall 0.95, 7.6% ghosts, RMS 0.23, 0.18, 0.25 voxel (one light-field and
    # two pinhole cameras, jointly)
    assert float(m.group(3)) > 0.8 and float(m.group(5)) < 20.0
    assert max(float(m.group(k)) for k in (6, 7, 8)) < 0.4


def test_local_workers_give_the_particles_of_one_process(tmp_path, capsys):
    import shutil

    run, other = tmp_path / "w.zarr", tmp_path / "w2.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "2", "--ppm", "0.2",
                "--quiet")[0] == 0
    shutil.copytree(run, other)
    assert _run(capsys, "particles", run, "--quiet", "--rounds", "1")[0] == 0
    # pair 0 here, then pair 1 on a worker: --skip-done goes on where the first command stopped
    assert _run(capsys, "particles", other, "--quiet", "--rounds", "1", "--pair-range", "0")[0] == 0
    rc, out, err = _run(capsys, "particles", other, "--quiet", "--rounds", "1", "--skip-done", "--workers", "1")
    assert rc == 0, err
    assert "wrote" in out and "1 pair(s)" in out and "by 1 local worker(s)" in out
    a, b = RunStore.open(run), RunStore.open(other)
    assert b.particle_pairs() == [0, 1]
    voxel = np.asarray(a.particle_attrs()["voxel_mm"])
    for p in (0, 1):
        for f in (0, 1):
            here, there = a.read_particles(p, f), b.read_particles(p, f)
            assert there.shape == here.shape
            assert np.all(np.abs(there[:, :3] - here[:, :3]) < 0.01 * voxel)


def test_particles_attributes_are_validated_on_read(tmp_path, capsys):
    """particles/ has a schema like volumes/: an edited particle_pairs is one line naming it."""
    import json

    import pytest

    from lfcore.runstore import RunStoreError
    from lfcore.runstore._schema import problems

    run = tmp_path / "run.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.2")[0] == 0
    assert _run(capsys, "particles", run, "--quiet")[0] == 0
    s = RunStore.open(run)
    assert problems(run, "particles", s.group["particles"].attrs) == []
    meta = run / "particles" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["particle_pairs"] = "0"
    meta.write_text(json.dumps(doc))
    with pytest.raises(RunStoreError, match="particles/ attribute particle_pairs"):
        RunStore.open(run).done_pairs("particles", RunStore.open(run).group["particles"])


def test_particles_of_unsure_position_are_reported_as_left_out(tmp_path, capsys):
    run, other = tmp_path / "u.zarr", tmp_path / "u2.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.3",
                "--quiet")[0] == 0
    import shutil

    shutil.copytree(run, other)
    rc, out, err = _run(capsys, "particles", run, "--quiet", "--rounds", "1")
    assert rc == 0, err
    assert "left out as unsure" not in out
    rc, out, err = _run(capsys, "particles", other, "--quiet", "--rounds", "1", "--max-std", "0.1")
    assert rc == 0, err
    m = re.search(r"^left out as unsure \(--max-std 0\.1 voxel\): (\d+) particles \(([\d.]+)% of those fitted\)$",
                  out, re.M)
    assert m, out
    every, sure = RunStore.open(run), RunStore.open(other)
    n_every = sum(len(every.read_particles(0, f)) for f in (0, 1))
    n_sure = sum(len(sure.read_particles(0, f)) for f in (0, 1))
    # the same fit either way: what --max-std leaves out is what it reports
    assert int(m.group(1)) == n_every - n_sure > 0
    assert sure.particle_attrs()["settings"]["max_position_std"] == 0.1


def test_particles_from_ray_candidates_end_to_end(tmp_path, capsys):
    # the one-camera rig focused beyond its box (where to focus a light-field camera for particles)
    run = tmp_path / "rays.zarr"
    rc, _, err = _run(capsys, "synth", "--rig", EXAMPLES / "one_camera_off_focus.toml", "--out", run, "--pairs", "1",
                      "--ppm", "0.3", "--quiet")
    assert rc == 0, err
    rc, out, err = _run(capsys, "particles", run, "--quiet", "--candidates", "rays")
    assert rc == 0, err
    s = RunStore.open(run)
    assert s.particle_attrs()["settings"]["candidate_source"] == "rays"
    rc, out, err = _run(capsys, "evaluate", run)
    assert rc == 0, err
    recall, ghosts, rms = _scores(out)
    print("recall", recall, "ghosts %", ghosts, "rms", rms)
    assert recall > 0.85 and ghosts < 10.0
    assert max(rms[:2]) < 0.2 and rms[2] < 0.35
    # the same settings: nothing to do; the reconstruction's candidates are other settings
    rc, out, _ = _run(capsys, "particles", run, "--quiet", "--skip-done", "--candidates", "rays")
    assert rc == 0 and "nothing to do" in out


def test_ray_candidates_refuse_the_quick_reconstructions_options(tmp_path, capsys):
    """--threshold, --candidate-iterations, --candidate-protocol, --candidate-weights and
    --candidate-smoothing shape the quick reconstruction's candidates only: with --candidates rays
    they would be ignored, so they are refused (one line, exit 2, nothing written)."""
    run = tmp_path / "r.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.1",
                "--rays", "20", "--quiet")[0] == 0
    for option, value in (("--threshold", "0.1"), ("--candidate-iterations", "5"), ("--candidate-protocol", "fixed"),
                          ("--candidate-weights", "line-of-sight"), ("--candidate-smoothing", "3")):
        rc, out, err = _run(capsys, "particles", run, "--candidates", "rays", option, value, "--quiet")
        assert rc == 2 and option in err and "--candidates" in err, (option, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(run).has_particles


def test_ray_candidates_refuse_the_quick_reconstructions_options_in_the_python_api(tmp_path, capsys):
    """The Python API shares the command's check: a quick reconstruction's option given with ray-bundling
    candidates is refused before anything is written, not silently ignored."""
    import lfpiv
    from lfpiv.errors import UsageError

    run = tmp_path / "r.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "1", "--ppm", "0.1",
                "--rays", "20", "--quiet")[0] == 0
    with pytest.raises(UsageError, match="--candidate-iterations"):
        lfpiv.particles(run, candidate_source="rays", candidate_iterations=5, progress=False)
    assert not RunStore.open(run).has_particles
