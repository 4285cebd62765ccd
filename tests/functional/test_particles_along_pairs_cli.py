"""``lfpiv particles --along-pairs`` (Shake-the-Box's prediction) end to end on a tiny time-resolved
series of a known uniform flow: the frames done in time order with the tracks' predictions, the
setting recorded, ``--skip-done`` with it, and the refusals (one line, exit 2, nothing written)."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import Announced, stop_at_announce
from tests.helpers import copy_run as _copy

FAST = ("--candidate-iterations", "10", "--rounds", "1", "--shakes", "6", "--relocate", "0", "--device", "cpu",
        "--quiet")


@pytest.fixture(scope="module")
def series_run(tmp_path_factory):
    """Three pairs (six frames) of a uniform flow on the tiny rig, time-resolved, without particles."""
    import contextlib
    import io

    from lfpiv.cli import main

    run = tmp_path_factory.mktemp("stb") / "s.zarr"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([str(a) for a in ("synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "3",
                                      "--ppm", "0.1", "--flow", "uniform", "--displacement-px", "4",
                                      "--time-resolved", "--rays", "2000", "--quiet")]) == 0
    return run


def _recall(run):
    from lfpiv.jobs.evaluate import evaluate_particles

    return np.array([e.match.recall for e in evaluate_particles(RunStore.open(run))])


def test_along_pairs_predicts_each_frame_from_the_tracks_before_it(series_run, tmp_path, capsys):
    alone = _copy(series_run, tmp_path, "alone.zarr")
    along = _copy(series_run, tmp_path, "along.zarr")
    assert _run(capsys, "particles", alone, "--pair-by-pair", *FAST)[0] == 0
    rc, out, err = _run(capsys, "particles", along, "--along-pairs", "--search-voxels", "4,4,4", *FAST)
    assert rc == 0, err
    assert "along the pairs:" in out and "positions predicted" in out, out
    settings = RunStore.open(along).particle_attrs()["settings"]
    assert settings["along_pairs"] == {"search_voxels": [4.0, 4.0, 4.0], "link_voxels": [1.0, 1.0, 1.0]}
    assert "along_pairs" not in RunStore.open(alone).particle_attrs()["settings"]
    # the first two frames have no tracks to predict them: the same particles as without
    s_alone, s_along = RunStore.open(alone), RunStore.open(along)
    for f in (0, 1):
        assert np.allclose(s_alone.read_particles(0, f), s_along.read_particles(0, f))
    # later frames: a known uniform flow's particles found at least as well as each frame on its own
    ra, rb = _recall(alone), _recall(along)
    print("recall alone", ra.round(3), "along", rb.round(3))
    assert rb[2:].mean() >= ra[2:].mean() - 0.02 and rb.min() > 0.8
    # --skip-done with the same settings: nothing to do; without --along-pairs: the difference named
    rc, out, err = _run(capsys, "particles", along, "--along-pairs", "--search-voxels", "4,4,4", "--skip-done",
                        *FAST)
    assert rc == 0 and "nothing to do" in out, (out, err)


def test_skip_done_carries_the_tracks_on_from_the_pairs_kept(series_run, tmp_path, capsys):
    """Pair 0 done first, then --skip-done over all: pair 0 is kept and its frames predict pair 1's,
    which come out as those of one run through all the pairs."""
    whole = _copy(series_run, tmp_path, "whole.zarr")
    parts = _copy(series_run, tmp_path, "parts.zarr")
    assert _run(capsys, "particles", whole, "--along-pairs", "--pair-range", "0:2", *FAST)[0] == 0
    assert _run(capsys, "particles", parts, "--along-pairs", "--pair-range", "0", *FAST)[0] == 0
    rc, out, err = _run(capsys, "particles", parts, "--along-pairs", "--pair-range", "0:2", "--skip-done", *FAST)
    assert rc == 0, err
    assert "1 pair(s)" in out, out
    for f in (0, 1):
        assert np.allclose(RunStore.open(whole).read_particles(1, f), RunStore.open(parts).read_particles(1, f))


def test_along_pairs_refusals(series_run, tmp_path, capsys):
    run = _copy(series_run, tmp_path)
    for args, words in ((("--search-voxels", "4,4,4", "--pair-by-pair"), ("--search-voxels", "--pair-by-pair")),
                        (("--link-voxels", "2,2,2", "--pair-by-pair"), ("--link-voxels", "--pair-by-pair")),
                        (("--link-voxels", "2,2,2", "--workers", "2"), ("--link-voxels", "--workers")),
                        (("--along-pairs", "--workers", "2"), ("--along-pairs", "--workers")),
                        (("--along-pairs", "--link-voxels", "0,1,1"), ("link_voxels",)),
                        (("--along-pairs", "--search-voxels", "nan,4,2"), ("search_voxels",)),
                        (("--along-pairs", "--link-voxels", "1,inf,1"), ("link_voxels",))):
        rc, out, err = _run(capsys, "particles", run, *args, *FAST)
        assert rc == 2 and all(w in err for w in words), (args, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert not RunStore.open(run).has_particles
    # a run that is not time-resolved
    flat = tmp_path / "flat.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", flat, "--pairs", "2", "--ppm", "0.1",
                "--flow", "uniform", "--rays", "20", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "particles", flat, "--along-pairs", *FAST)
    assert rc == 2 and "time-resolved" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(flat).has_particles


def test_the_python_api_refuses_unknown_along_pairs_settings(series_run, tmp_path):
    import lfpiv
    from lfpiv.errors import UsageError

    run = _copy(series_run, tmp_path)
    with pytest.raises(UsageError, match="search_voxels and link_voxels"):
        lfpiv.particles(run, along_pairs={"link": (1, 1, 1)}, progress=False)
    with pytest.raises(UsageError, match="link_voxels"):
        lfpiv.particles(run, along_pairs={"link_voxels": (0, 1, 1)}, progress=False)
    with pytest.raises(UsageError, match="three positive values"):  # not numbers
        lfpiv.particles(run, along_pairs={"search_voxels": ("a", "b", "c")}, progress=False)
    assert not RunStore.open(run).has_particles


def test_skip_done_resumes_an_interrupted_replacement_from_its_own_pairs(series_run, tmp_path, capsys, monkeypatch):
    """A run whose particles/ holds pair 2 made frame by frame; --along-pairs over 0:3 fails in pair 1,
    its pair 0 kept aside in the pending replacement. The same command with --skip-done goes on from
    the replacement's pair 0 (not the old set, which has none of it): pair 1 comes out as in one run
    through all the pairs."""
    import lfpiv.jobs.particles as job
    from lfpiv.errors import UsageError

    whole = _copy(series_run, tmp_path, "whole.zarr")
    parts = _copy(series_run, tmp_path, "parts.zarr")
    assert _run(capsys, "particles", whole, "--along-pairs", "--pair-range", "0:2", *FAST)[0] == 0
    assert _run(capsys, "particles", parts, "--pair-range", "2", *FAST)[0] == 0
    frame = job._frame

    def failing(ipr, store, names, pair, f, predicted_mm=None, **kw):
        if pair == 1:
            raise UsageError("pair 1 failed")
        return frame(ipr, store, names, pair, f, predicted_mm, **kw)

    monkeypatch.setattr(job, "_frame", failing)
    rc, out, err = _run(capsys, "particles", parts, "--along-pairs", "--pair-range", "0:3", *FAST)
    assert rc == 2 and "kept aside" in err, err
    monkeypatch.setattr(job, "_frame", frame)
    rc, out, err = _run(capsys, "particles", parts, "--along-pairs", "--pair-range", "0:3", "--skip-done", *FAST)
    assert rc == 0, err
    assert "2 pair(s)" in out and "along the pairs:" in out, out
    assert RunStore.open(parts).particle_attrs()["settings"]["along_pairs"]  # the replacement is in place
    for f in (0, 1):
        assert np.allclose(RunStore.open(whole).read_particles(1, f), RunStore.open(parts).read_particles(1, f))


def test_the_python_api_refuses_workers_along_the_pairs_before_any_starts(series_run, tmp_path, monkeypatch):
    """lfpiv.particles(along_pairs=True, workers=2) is refused as the command refuses it, before a
    Dask cluster is started (and nothing written)."""
    import lfpiv
    import lfpiv.batch
    from lfpiv.errors import UsageError

    def no_cluster(*args, **kwargs):
        raise AssertionError("a Dask cluster was started")

    monkeypatch.setattr(lfpiv.batch, "dask_client", no_cluster)
    run = _copy(series_run, tmp_path)
    for given in ({"workers": 2}, {"scheduler": "tcp://localhost:8786"}):
        with pytest.raises(UsageError, match="--workers and --scheduler"):
            lfpiv.particles(run, along_pairs=True, progress=False, **given)
    assert not RunStore.open(run).has_particles


def test_the_python_api_predicts_from_the_third_frame_on(series_run, tmp_path):
    """lfpiv.particles(along_pairs=...): the first two frames have no tracks to predict them; every
    later frame of the uniform flow (37 particles a frame) has about as many predictions as particles."""
    import lfpiv

    run = _copy(series_run, tmp_path)
    done = lfpiv.particles(run, along_pairs={"search_voxels": (4, 4, 4)}, progress=False, device="cpu",
                           candidate_iterations=10, rounds=1, shakes=6, relocate_depth=0)
    assert done.pairs == [0, 1, 2] and len(done.predicted) == 6
    assert done.predicted[:2] == [0, 0]
    counts = np.asarray(done.counts)
    assert np.all(np.asarray(done.predicted[2:]) >= 0.7 * counts[1:-1]), (done.predicted, done.counts)
    assert np.all(np.asarray(done.predicted[2:]) <= 1.3 * counts[1:-1]), (done.predicted, done.counts)
    assert RunStore.open(run).particle_attrs()["settings"]["along_pairs"]["search_voxels"] == [4.0, 4.0, 4.0]


def test_no_option_follows_a_time_resolved_run_along_its_pairs(series_run, tmp_path, capsys):
    """With no option (auto) a time-resolved run's consecutive pairs are followed along the pairs with
    the defaults, as --along-pairs does; the line says which and why, particles/ records it, and
    --skip-done with no option or with --along-pairs finds it done; --pair-by-pair does not."""
    run = _copy(series_run, tmp_path)
    rc, out, err = _run(capsys, "particles", run, *FAST)
    assert rc == 0, err
    assert "along the pairs: a time-resolved run, pairs 0 to 2" in out and "positions predicted" in out, out
    settings = RunStore.open(run).particle_attrs()["settings"]
    assert settings["along_pairs"] == {"search_voxels": [4.0, 4.0, 2.0], "link_voxels": [1.0, 1.0, 1.0]}
    for more in ((), ("--along-pairs",)):
        rc, out, err = _run(capsys, "particles", run, *more, "--skip-done", *FAST)
        assert rc == 0 and "nothing to do" in out, (more, out, err)
    rc, out, err = _run(capsys, "particles", run, "--pair-by-pair", "--skip-done", *FAST)
    assert rc == 0 and "pair by pair: asked (--pair-by-pair)" in out and "along_pairs" in err, (out, err)
    assert "along_pairs" not in RunStore.open(run).particle_attrs()["settings"]


def test_no_option_goes_pair_by_pair_where_it_cannot_follow(series_run, tmp_path, capsys):
    """Auto is never an error: one pair (nothing to predict from), pairs that are not consecutive and a
    run that is not time-resolved are reconstructed frame by frame, the line says why, and nothing
    records along_pairs; an option of along the pairs given there is refused (one line, exit 2)."""
    run = _copy(series_run, tmp_path)
    for pairs, why in (("1", "fewer than the 3"),):
        rc, out, err = _run(capsys, "particles", run, "--pair-range", pairs, *FAST)
        assert rc == 0 and f"pair by pair: 2 frame(s) chosen, {why}" in out, (out, err)
        assert "positions predicted" not in out
        assert "along_pairs" not in RunStore.open(run).particle_attrs()["settings"]
    flat = tmp_path / "flat.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", flat, "--pairs", "2", "--ppm", "0.1",
                "--flow", "uniform", "--rays", "20", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "particles", flat, "--search-voxels", "4,4,4", *FAST)
    assert rc == 2 and "--search-voxels" in err and "not a time-resolved run" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and not RunStore.open(flat).has_particles
    rc, out, err = _run(capsys, "particles", flat, "--pair-range", "0", *FAST)
    assert rc == 0 and "pair by pair: not a time-resolved run" in out, (out, err)
    assert "along_pairs" not in RunStore.open(flat).particle_attrs()["settings"]


def test_the_python_api_defaults_to_auto(series_run, tmp_path, monkeypatch):
    """lfpiv.particles(run) hands the job auto with the default settings, as the command does;
    along_pairs=False is pair by pair, "auto" and True as said, anything else refused."""
    import lfpiv
    import lfpiv.jobs.particles as job

    seen = {}

    def choose(store, settings, pairs=None, **kw):
        seen.update(kw)
        return job.ParticlesDone()

    monkeypatch.setattr(job, "particles_run", choose)
    run = _copy(series_run, tmp_path)
    lfpiv.particles(run, progress=False)
    assert seen["along_mode"] == "auto" and seen["along_pairs"] is not None
    lfpiv.particles(run, progress=False, along_pairs=False)
    assert seen["along_mode"] == "off"
    lfpiv.particles(run, progress=False, along_pairs=True)
    assert seen["along_mode"] == "on"
    from lfpiv.errors import UsageError

    with pytest.raises(UsageError, match="auto, on, off"):
        lfpiv.particles(run, progress=False, along_pairs="sometimes")


def test_the_along_line_is_said_once_before_the_frames_are_done(series_run, tmp_path, capsys):
    """The line saying along the pairs or pair by pair comes before the long work (announce is
    handed it before any frame is reconstructed) and once on the command's output."""
    from lfpiv.jobs.particles import AlongPairs, ipr_settings, particles_run

    run = _copy(series_run, tmp_path)
    said, announce = stop_at_announce()

    with pytest.raises(Announced):
        particles_run(RunStore.open(run, mode="r+"), ipr_settings(), progress=False, along_pairs=AlongPairs(),
                      along_mode="auto", announce=announce)
    assert said == ["along the pairs: a time-resolved run, pairs 0 to 2 (--pair-by-pair to track each pair on "
                    "its own)"]
    assert not (run / "particles").exists()  # said before any frame was reconstructed
    rc, out, err = _run(capsys, "particles", run, "--pair-range", "0:1", *FAST)
    assert rc == 0, err
    lines = out.splitlines()
    assert sum(x.startswith(("along the pairs: ", "pair by pair: ")) for x in lines) == 1, out
    assert lines[0].startswith("pair by pair: 2 frame(s) chosen"), out
