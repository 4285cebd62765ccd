"""`lfpiv synth --time-resolved` and `lfpiv track --along-pairs` end to end on a tiny time-resolved
series of a known uniform flow: tracks through every frame, their fit, the field against the truth,
the export, and the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.runstore import RunStore, is_time_resolved
from lfcore.volume import VolumeGrid
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import Announced, stop_at_announce
from tests.helpers import copy_run as _copy
from tests.helpers import velocity_rms as _rms

NOISE_VOXELS = np.array([0.1, 0.1, 0.2])  # about IPR's position error on one light-field camera


@pytest.fixture(scope="module")
def series_run(tmp_path_factory):
    """Four pairs (eight frames) of a uniform flow on the tiny rig as a time-resolved series, with
    particles made from the truth plus a known noise (a stand-in for 'lfpiv particles', which the
    particle tests cover: here what is tested is what tracking makes of a known noise)."""
    import contextlib
    import io

    from lfpiv.cli import main

    run = tmp_path_factory.mktemp("series") / "s.zarr"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([str(a) for a in ("synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "4",
                                      "--ppm", "0.3", "--flow", "uniform", "--displacement-px", "4",
                                      "--time-resolved", "--rays", "50", "--quiet")]) == 0
    s = RunStore.open(run, mode="r+")
    grid = VolumeGrid.from_rig(s.rig)
    truth = s.truth()["particles"]
    lo, hi = s.rig.volume.bounds_mm
    rng = np.random.default_rng(7)
    s.create_particles(grid, method="truth plus noise", settings={"noise_voxels": NOISE_VOXELS.tolist()})
    for p in range(truth.shape[0]):
        frames = []
        for f in range(2):
            xyz = truth[p, f]
            xyz = xyz[np.all((xyz >= lo) & (xyz <= hi), axis=1)]  # the box's particles, as IPR keeps
            xyz = xyz + rng.normal(size=xyz.shape) * NOISE_VOXELS * np.asarray(grid.voxel_mm)
            frames.append(np.column_stack([xyz, np.ones(len(xyz)), np.zeros(len(xyz))]))
        s.write_particles(p, frames)
    return run




def test_a_time_resolved_series_is_synthesized(series_run):
    s = RunStore.open(series_run)
    assert is_time_resolved(s.timing)
    assert s.timing["rate_hz"] == pytest.approx(1.0 / (2.0 * s.timing["dt_s"]))
    truth = s.truth()["particles"]
    # the same particles from frame to frame: each frame the last one moved by the flow (those that
    # left the box come back in at the opposite face)
    step = np.diff(truth.reshape(-1, *truth.shape[2:]), axis=0)
    moved = np.median(step, axis=1)
    assert np.allclose(step[np.all(np.abs(step - moved[:, None]) < 1e-6, axis=2)].mean(axis=0), moved[0], atol=1e-9)
    assert np.mean(np.all(np.abs(step - moved[:, None]) < 1e-6, axis=2)) > 0.9
    assert np.allclose(s.truth()["t0_s"], np.arange(4) * 2 * s.timing["dt_s"])


def test_tracks_along_the_pairs_beat_each_pair_on_its_own(series_run, tmp_path, capsys):
    pairwise = _copy(series_run, tmp_path, "p.zarr")
    along = _copy(series_run, tmp_path, "a.zarr")
    assert _run(capsys, "track", pairwise, "--pair-by-pair", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", along, "--along-pairs", "--quiet")
    assert rc == 0, err
    assert "through the 8 frames" in out and "along the pairs" in out
    s = RunStore.open(along)
    series = s.read_series_tracks()
    assert series.shape[1] == 8
    lengths = np.bincount(series[:, 0].astype(int))
    # most particles that stay in the box (do not leave it and come back at the opposite face) are
    # followed through all eight frames
    truth = s.truth()["particles"].reshape(-1, s.truth()["particles"].shape[2], 3)
    step = np.diff(truth, axis=0)
    stay = np.all(np.abs(step - np.median(step, axis=1)[:, None]) < 1e-6, axis=(0, 2))
    assert np.count_nonzero(lengths == 8) >= 0.8 * np.count_nonzero(stay)
    assert s.vectors()["attrs"]["settings"]["along_pairs"]["pairs"] == [0, 3]
    # every pair's tracks are the fitted positions at its frames, in vectors/tracks as pair tracking writes them
    assert all(len(s.read_tracks(p)) > 20 for p in range(4))
    errs = []
    for run in (pairwise, along):
        rc, out, err = _run(capsys, "evaluate", run)
        assert rc == 0, err
        errs.append(_rms(out))
    assert np.all(errs[1] < errs[0])  # the fit through the frames averages the positions' noise
    # the tracks through the series: their fitted positions nearer the truth than the particles
    voxel = np.asarray(VolumeGrid.from_rig(s.rig).voxel_mm)
    fitted = np.isfinite(series[:, 5])
    before, after = [], []
    for f, xyz, fit in zip(series[fitted, 1].astype(int), series[fitted, 2:5], series[fitted, 5:8], strict=True):
        near = truth[f][np.argmin(np.sum((truth[f] - xyz) ** 2, axis=1))]
        before.append((xyz - near) / voxel)
        after.append((fit - near) / voxel)
    before, after = np.sqrt(np.mean(np.square(before), axis=0)), np.sqrt(np.mean(np.square(after), axis=0))
    assert np.allclose(before, NOISE_VOXELS, rtol=0.2)
    assert np.all(after < 0.8 * before)
    # the tracks export as pair tracking's do
    rc, out, err = _run(capsys, "export", along, "--format", "tracks-csv", "--out", tmp_path / "csv")
    assert rc == 0, err
    assert len((tmp_path / "csv" / "tracks.csv").read_text().splitlines()) == 1 + sum(len(s.read_tracks(p))
                                                                                    for p in range(4))
    # and the tracks through the series, one row a point, with their times
    rc, out, err = _run(capsys, "export", along, "--format", "series-csv", "--out", tmp_path / "csv")
    assert rc == 0, err
    table = np.loadtxt(tmp_path / "csv" / "series_tracks.csv", delimiter=",", skiprows=1)
    assert np.allclose(table[:, [0, 1, 3, 4, 5]], series[:, :5], atol=1e-6)  # mm to 6 decimals
    assert np.allclose(table[:, 2], series[:, 1] * s.timing["dt_s"])
    assert np.allclose(table[:, 6:], series[:, 5:], equal_nan=True, atol=1e-6)
    # a run tracked pair by pair has none: one line, exit 2
    rc, out, err = _run(capsys, "export", pairwise, "--format", "series-csv", "--out", tmp_path / "csv2")
    assert rc == 2 and "--along-pairs" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_along_pairs_refuses_too_few_frames(series_run, tmp_path, capsys):
    run = _copy(series_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--along-pairs", "--pair-range", "0")
    assert rc == 2 and "--min-frames" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(run).has_vectors


def test_along_pairs_refuses_a_run_that_is_not_time_resolved(tmp_path, capsys):
    run = tmp_path / "d.zarr"
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", run, "--pairs", "2", "--ppm", "0.1",
                "--flow", "uniform", "--rays", "20", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", run, "--along-pairs")
    # no particles yet: that is said first; with particles, the timing
    assert rc == 2 and "Traceback" not in err
    s = RunStore.open(run, mode="r+")
    grid = VolumeGrid.from_rig(s.rig)
    s.create_particles(grid, method="truth", settings={})
    for p in range(2):
        t = s.truth()["particles"][p]
        s.write_particles(p, [np.column_stack([t[f], np.ones((len(t[f]), 2))]) for f in range(2)])
    rc, out, err = _run(capsys, "track", run, "--along-pairs")
    assert rc == 2 and "--along-pairs" in err and "time-resolved" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not RunStore.open(run).has_vectors
    assert not is_time_resolved(RunStore.open(run).timing)
    # with no option it is tracked pair by pair, and the line says why
    rc, out, err = _run(capsys, "track", run, "--quiet")
    assert rc == 0 and "pair by pair: not a time-resolved run" in out, (out, err)
    assert "along_pairs" not in RunStore.open(run).vectors()["attrs"]["settings"]


def test_synth_refuses_a_rate_that_contradicts_a_time_resolved_series(tmp_path, capsys):
    rc, out, err = _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", tmp_path / "x.zarr",
                        "--time-resolved", "--rate-hz", "10", "--dt-ms", "2", "--quiet")
    assert rc == 2 and "--time-resolved" in err and "250" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "x.zarr").exists()
    rc, out, err = _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", tmp_path / "y.zarr",
                        "--time-resolved", "--rate-hz", "250", "--dt-ms", "2", "--pairs", "1", "--ppm", "0.1",
                        "--rays", "20", "--quiet")
    assert rc == 0, err


def test_the_python_api_tracks_along_the_pairs_as_the_command_does(series_run, tmp_path, capsys):
    import lfpiv

    by_api = _copy(series_run, tmp_path, "api.zarr")
    by_cli = _copy(series_run, tmp_path, "cli.zarr")
    done = lfpiv.track(by_api, along_pairs={"fit_frames": 5}, progress=False)
    assert done.series_frames == 8 and done.series_tracks > 0 and done.pairs == [0, 1, 2, 3]
    assert _run(capsys, "track", by_cli, "--along-pairs", "--fit-frames", "5", "--quiet")[0] == 0
    assert np.array_equal(RunStore.open(by_api).read_series_tracks(), RunStore.open(by_cli).read_series_tracks(),
                          equal_nan=True)
    from lfpiv.errors import UsageError

    with pytest.raises(UsageError, match="fit_frames"):
        lfpiv.track(by_api, along_pairs={"fit_frames": 2}, progress=False)


def test_along_pairs_from_a_later_pair_gives_each_pair_its_own_frames(series_run, tmp_path, capsys):
    """--pair-range 1:4: the series' frames are the run's (2 p and 2 p + 1 for pair p), so each pair's
    tracks start on that pair's frame A and end on its frame B (the truth's particles there, within
    the noise), and no pair is left without tracks."""
    run = _copy(series_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--along-pairs", "--pair-range", "1:4", "--quiet")
    assert rc == 0, err
    s = RunStore.open(run)
    truth = s.truth()["particles"]
    voxel = np.asarray(VolumeGrid.from_rig(s.rig).voxel_mm)
    for p in (1, 2, 3):
        rows = s.read_tracks(p)
        assert len(rows) > 20, p
        for f, xyz in ((0, rows[:, :3]), (1, rows[:, 3:6])):
            # each fitted end's nearest true particle of its own frame, in voxels (a pair's step is ~4 px)
            d = np.min(np.linalg.norm((xyz[:, None, :] - truth[p, f][None]) / voxel, axis=2), axis=1)
            assert np.median(d) < 0.5, (p, f, np.median(d))


def test_the_series_options_pair_by_pair_are_refused(series_run, tmp_path, capsys):
    """--link-voxels, --min-frames, --fit-frames, --fit-order (and the rest) only shape tracks along a series:
    given with --pair-by-pair, or where the default goes pair by pair (--predictor previous), they
    would be ignored, so they are refused (one line, exit 2)."""
    run = _copy(series_run, tmp_path)
    for option, value in (("--link-voxels", "2,2,2"), ("--min-frames", "5"), ("--fit-frames", "4"),
                          ("--fit-order", "1"), ("--pool-pairs", "1"), ("--bridge-frames", "2")):
        rc, out, err = _run(capsys, "track", run, option, value, "--pair-by-pair", "--quiet")
        assert rc == 2 and option in err and "--pair-by-pair" in err, (option, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    rc, out, err = _run(capsys, "track", run, "--relink", "--pair-by-pair", "--quiet")
    assert rc == 2 and "--relink" in err and "--pair-by-pair" in err, err
    rc, out, err = _run(capsys, "track", run, "--relink", "--predictor", "previous", "--quiet")
    assert rc == 2 and "--relink" in err and "pair by pair (--predictor previous" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(run).has_vectors
    # with --along-pairs they apply, and the defaults are the command's along the pairs (ALONG_DEFAULTS:
    # relinked, 4 pairs pooled either side), then SeriesSettings' own
    rc, out, err = _run(capsys, "track", run, "--along-pairs", "--fit-order", "1", "--fit-frames", "3")
    assert rc == 0, err
    assert "of order 1 in time through 3 frames" in out and "at least 4 frames" in out
    assert "carried on by the pair tracking's links" in out and "pooled the tracks of up to 4 pair(s)" in out, out
    recorded = RunStore.open(run).vectors()["attrs"]["settings"]["along_pairs"]
    assert recorded["degree"] == 1 and recorded["relink"] is True and recorded["pool_pairs"] == 4
    assert "bridge_frames" not in recorded
    # each default turned off: --no-relink, --pool-pairs 0 (recorded as vectors tracked before them were)
    off = _copy(series_run, tmp_path, "off.zarr")
    rc, out, err = _run(capsys, "track", off, "--no-relink", "--pool-pairs", "0", "--quiet")
    assert rc == 0 and "carried on by" not in out and "pooled" not in out, out
    recorded = RunStore.open(off).vectors()["attrs"]["settings"]["along_pairs"]
    assert "relink" not in recorded and "pool_pairs" not in recorded
    bridged = _copy(series_run, tmp_path, "b.zarr")
    rc, out, err = _run(capsys, "track", bridged, "--along-pairs", "--bridge-frames", "2", "--relink", "--quiet")
    assert rc == 0, err
    assert "gaps of up to 2 missing frame(s) bridged" in out, out
    assert "carried on by the pair tracking's links" in out, out
    assert RunStore.open(bridged).vectors()["attrs"]["settings"]["along_pairs"]["bridge_frames"] == 2
    assert RunStore.open(bridged).vectors()["attrs"]["settings"]["along_pairs"]["relink"] is True


def test_pooling_the_neighbouring_pairs_tracks(series_run, tmp_path, capsys):
    """--pool-pairs offers each pair's fitted field its neighbours' tracks (moved by the pattern's
    translation): the command says how many pairs took them and records the setting; with 0 the
    settings are as before (no pool_pairs key, so vectors tracked before it still match)."""
    own, pooled = _copy(series_run, tmp_path, "o.zarr"), _copy(series_run, tmp_path, "p.zarr")
    assert _run(capsys, "track", own, "--along-pairs", "--pool-pairs", "0", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "track", pooled, "--along-pairs", "--pool-pairs", "1", "--quiet")
    assert rc == 0, err
    assert "of the 4 pairs' fields" in out and "translation per pair" in out, out
    assert RunStore.open(pooled).vectors()["attrs"]["settings"]["along_pairs"]["pool_pairs"] == 1
    assert "pool_pairs" not in RunStore.open(own).vectors()["attrs"]["settings"]["along_pairs"]
    errs = []
    for run in (own, pooled):
        rc, out, err = _run(capsys, "evaluate", run)
        assert rc == 0, err
        errs.append(_rms(out))
    # a uniform flow: its own tracks fix it already, and the held-out tracks keep it from getting worse
    assert np.all(errs[1] <= errs[0] * 1.1 + 0.005), errs
    # the pair's own tracks are stored either way
    assert all(len(RunStore.open(pooled).read_tracks(p)) == len(RunStore.open(own).read_tracks(p)) for p in range(4))


def test_pool_pairs_needs_a_fitted_field(series_run, tmp_path, capsys):
    run = _copy(series_run, tmp_path)
    rc, out, err = _run(capsys, "track", run, "--along-pairs", "--pool-pairs", "1", "--field", "bins", "--quiet")
    assert rc == 2 and "--field fit or divfree" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not RunStore.open(run).has_vectors
    # not given, the default pooling goes with the fitted fields only: a binned field pools nothing
    rc, out, err = _run(capsys, "track", run, "--field", "bins", "--quiet")
    assert rc == 0 and "along the pairs" in out and "pooled" not in out, (out, err)
    assert "pool_pairs" not in RunStore.open(run).vectors()["attrs"]["settings"]["along_pairs"]


def test_tracking_pair_by_pair_after_along_the_pairs_names_the_difference(series_run, tmp_path, capsys):
    """The vectors of a run tracked along its pairs, tracked again pair by pair: the note names what
    differs (along_pairs, recorded before and not now, and the field: divfree along the pairs, fit pair by
    pair), not 'source'."""
    run = _copy(series_run, tmp_path)
    assert _run(capsys, "track", run, "--quiet")[0] == 0  # the default on a time-resolved run
    assert "along_pairs" in RunStore.open(run).vectors()["attrs"]["settings"]
    rc, out, err = _run(capsys, "track", run, "--pair-by-pair", "--quiet")
    assert rc == 0, err
    assert "(field, along_pairs differ)" in err, err
    assert "along_pairs" not in RunStore.open(run).vectors()["attrs"]["settings"]


def test_export_help_names_every_format(capsys):
    """lfpiv export's description says what each --format writes: series-csv included."""
    from lfpiv.jobs.export import FORMATS

    with pytest.raises(SystemExit):
        _run(capsys, "export", "--help")
    out = " ".join(capsys.readouterr().out.split()).replace("- ", "-")  # argparse wraps at hyphens
    description = out.split("positional arguments")[0]
    for fmt, names in FORMATS.items():
        assert f"{fmt} " in description and names[0] in description, fmt


def test_the_python_api_along_pairs_none_tracks_pair_by_pair(series_run, tmp_path):
    """``lfpiv.track(run, along_pairs=None)`` (an option left unset) tracks pair by pair, as False does."""
    import lfpiv

    run = _copy(series_run, tmp_path)
    done = lfpiv.track(run, along_pairs=None, progress=False)
    assert done.series_frames == 0 and done.pairs == [0, 1, 2, 3]
    assert "along_pairs" not in RunStore.open(run).vectors()["attrs"]["settings"]


def test_synth_rate_hz_is_the_flows_clock_and_the_recorded_rig(tmp_path, capsys):
    """--rate-hz 3 on a rig whose laser runs at 10 Hz makes the run a rig at 3 Hz makes (the jet
    changes in time, so the pairs' particles depend on when each pair is taken); the recorded rig is
    the rig given."""
    rig3 = tmp_path / "tiny3.toml"
    text = (EXAMPLES / "tiny.toml").read_text()
    assert "rate_hz = 10.0" in text
    rig3.write_text(text.replace("rate_hz = 10.0", "rate_hz = 3.0"))
    common = ("--pairs", "3", "--ppm", "0.1", "--flow", "jet", "--rays", "10", "--quiet")
    assert _run(capsys, "synth", "--rig", EXAMPLES / "tiny.toml", "--out", tmp_path / "given.zarr", "--rate-hz", "3",
                *common)[0] == 0
    assert _run(capsys, "synth", "--rig", rig3, "--out", tmp_path / "rig.zarr", *common)[0] == 0
    given, by_rig = RunStore.open(tmp_path / "given.zarr"), RunStore.open(tmp_path / "rig.zarr")
    assert given.timing["rate_hz"] == by_rig.timing["rate_hz"] == 3.0
    assert given.rig.laser.rate_hz == 10.0
    assert np.array_equal(given.truth()["particles"], by_rig.truth()["particles"])


def test_no_option_tracks_a_time_resolved_run_along_its_pairs(series_run, tmp_path, capsys):
    """With no option (auto) a time-resolved run's consecutive pairs are tracked along the pairs as
    --along-pairs tracks them; the line says which and why, vectors/ records it and --skip-done (with
    no option or --along-pairs) finds it done."""
    auto, asked = _copy(series_run, tmp_path, "auto.zarr"), _copy(series_run, tmp_path, "asked.zarr")
    rc, out, err = _run(capsys, "track", auto, "--quiet")
    assert rc == 0, err
    assert "along the pairs: a time-resolved run, pairs 0 to 3" in out and "through the 8 frames" in out, out
    assert _run(capsys, "track", asked, "--along-pairs", "--quiet")[0] == 0
    a, b = RunStore.open(auto).vectors()["attrs"], RunStore.open(asked).vectors()["attrs"]
    assert a["settings"] == b["settings"] and a["settings"]["along_pairs"]["pairs"] == [0, 3]
    for p in range(4):
        assert np.array_equal(RunStore.open(auto).read_tracks(p), RunStore.open(asked).read_tracks(p))
    for more in ((), ("--along-pairs",)):
        rc, out, err = _run(capsys, "track", auto, *more, "--skip-done", "--quiet")
        assert rc == 0 and "nothing to do" in out, (more, out, err)


def test_along_the_pairs_the_default_field_is_the_divergence_free_fit(series_run, tmp_path, capsys):
    """Along the pairs with no --field the field is divfree (ALONG_FIELD), recorded and said; a --field
    given is kept; pair by pair the default stays fit. On a known uniform flow the divergence-free
    field is as near the truth as fit's."""
    from lfpiv.jobs.track import ALONG_FIELD

    assert ALONG_FIELD == "divfree"
    auto, fit, pairwise = (_copy(series_run, tmp_path, n) for n in ("auto.zarr", "fit.zarr", "pw.zarr"))
    rc, out, err = _run(capsys, "track", auto, "--quiet")
    assert rc == 0 and "divfree field" in out and ", along the pairs" in out, (out, err)
    assert RunStore.open(auto).vectors()["attrs"]["settings"]["field"] == "divfree"
    rc, out, err = _run(capsys, "track", fit, "--field", "fit", "--quiet")
    assert rc == 0 and "fit field" in out, (out, err)
    assert RunStore.open(fit).vectors()["attrs"]["settings"]["field"] == "fit"
    rc, out, err = _run(capsys, "track", pairwise, "--pair-by-pair", "--quiet")
    assert rc == 0 and "fit field" in out, (out, err)
    assert RunStore.open(pairwise).vectors()["attrs"]["settings"]["field"] == "fit"
    errs = []
    for run in (auto, fit):
        rc, out, err = _run(capsys, "evaluate", run)
        assert rc == 0, err
        errs.append(_rms(out))
    assert np.all(errs[0] <= errs[1] + 0.01), errs  # voxels, per axis
    # --skip-done with no option finds the divfree field done
    rc, out, err = _run(capsys, "track", auto, "--skip-done", "--quiet")
    assert rc == 0 and "nothing to do" in out, (out, err)


def test_no_option_goes_pair_by_pair_where_it_cannot_follow(series_run, tmp_path, capsys):
    """Auto is never an error: workers, --predictor previous and too few frames for a track
    (--min-frames 4 against one pair's 2) are tracked pair by pair, the line says why, and vectors/
    records no along_pairs."""
    run = _copy(series_run, tmp_path)
    for args, why in ((("--workers", "1"), "--workers or --scheduler given"),
                      (("--predictor", "previous"), "--predictor previous"),
                      (("--pair-range", "1"), "2 frame(s) chosen, fewer than the 4")):
        rc, out, err = _run(capsys, "track", run, *args, "--quiet")
        assert rc == 0 and f"pair by pair: {why}" in out, (args, out, err)
        assert "through the" not in out and ", along the pairs" not in out
        assert "along_pairs" not in RunStore.open(run).vectors()["attrs"]["settings"]


def test_the_along_line_is_said_once_before_the_pairs_are_tracked(series_run, tmp_path, capsys):
    """The line saying along the pairs or pair by pair comes before the long work (announce is
    handed it before anything is written) and once on the command's output."""
    from lfpiv.jobs.track import along_defaults, series_settings, track_run, track_settings

    run = _copy(series_run, tmp_path)
    said, announce = stop_at_announce()

    settings = track_settings(search_voxels=(4, 4, 4))
    with pytest.raises(Announced):
        track_run(RunStore.open(run, mode="r+"), settings, progress=False, along_mode="auto", announce=announce,
                  along_pairs=series_settings(**along_defaults(settings.field)))
    assert said == ["along the pairs: a time-resolved run, pairs 0 to 3 (--pair-by-pair to track each pair on "
                    "its own)"]
    assert not (run / "vectors").exists()  # said before the pairs were tracked
    rc, out, err = _run(capsys, "track", run, "--search-voxels", "4,4,4", "--quiet")
    assert rc == 0, err
    lines = out.splitlines()
    assert sum(x.startswith(("along the pairs: a time", "pair by pair: ")) for x in lines) == 1, out
    assert lines[0].startswith("along the pairs: a time-resolved run"), out
