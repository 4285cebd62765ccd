"""Tracking a run's particles into ``vectors/`` (``lfpiv track``): each pair's frame A particles
paired with frame B's (:mod:`lfcore.track`) around a predictor, and a field made from the tracks on
a grid in the layout ``correlate`` writes.

Predictors (``--predictor``) of the first pairing pass:

none
    Zero: the first pass searches as far as the largest displacement expected.
volumes
    A coarse correlation (:func:`lfcore.warm.predictor_field`) of the pair's two volumes where
    ``lfpiv reconstruct`` wrote them (a quick reconstruction will do: ``--iterations 5``).
previous
    The field of the pair tracked just before it in this command (a time-resolved series, where
    the flow changes little from pair to pair); the first pair, and a pair whose previous pair is
    not tracked in the same command, have none.

Along a time-resolved series (``--along-pairs``, :func:`lfcore.runstore.is_time_resolved`: every
frame ``dt`` after the one before), the particles of all the chosen pairs' frames are linked into
tracks through the frames (:func:`lfcore.track.link_series`: the pair tracking starts each track,
its own velocity carries it on), each track of enough frames is fitted by local polynomials in time
(:func:`lfcore.track.fit_series`), and each pair's tracks are the fitted positions at its two frames
(:func:`lfcore.track.pair_tracks`), made into a field as a pair's own tracks are. The tracks through
the series are kept in ``vectors/series_tracks``. With ``--pool-pairs K`` (``"fit"`` and
``"divfree"`` fields) each pair's field is offered the tracks of the K pairs either side, moved by
the flow pattern's translation estimated from the tracks, and takes them where its own held-out
tracks say they help (:func:`lfcore.track.pooled_field_of_tracks`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.runstore import RunStore, RunStoreError, is_time_resolved
from lfcore.track import (
    MAX_CROWDING,
    PoolChoice,
    SeriesSettings,
    SeriesTracks,
    TrackResult,
    TrackSettings,
    field_of_tracks,
    field_predictor,
    fit_series,
    link_series,
    pair_tracks,
    pooled_field_of_tracks,
    search_crowding,
    track_pair,
)
from lfcore.volume import VolumeGrid
from lfcore.warm import Predictor
from lfpiv.errors import UsageError
from lfpiv.pair_runner import AlongChoice, along_option_error, along_pairs_choice, particle_pairs, run_pairs

__all__ = ["ALONG_DEFAULTS", "ALONG_FIELD", "POOLED_FIELDS", "PREDICTORS", "PairTracks", "SeriesSettings", "TrackJob",
           "TrackSettings", "TracksDone", "along_defaults", "series_settings", "track_pair_task", "track_run",
           "track_settings", "tracks_csv"]

#: The first pass's predictors (``lfpiv track --predictor``; see the module docstring).
PREDICTORS = ("none", "volumes", "previous")

#: The fields into which ``--pool-pairs`` pools the neighbouring pairs' tracks.
POOLED_FIELDS = ("fit", "divfree")

#: What ``lfpiv track`` (and :func:`lfpiv.track`) use along the pairs where not given, beside
#: :class:`lfcore.track.SeriesSettings`' own defaults (:func:`along_defaults`): the pair tracking's
#: links for tracks a straight line loses and the tracks of 4 pairs either side offered to each
#: pair's fitted field. Measured in ``benchmarks/RESULTS.md`` (fourteenth session, issue 48).
ALONG_DEFAULTS: dict[str, Any] = {"relink": True, "pool_pairs": 4}

#: The field ``lfpiv track`` makes along the pairs where ``--field`` is not given (pair by pair:
#: :class:`lfcore.track.TrackSettings`' own, ``fit``): the divergence-free fit, which keeps fit's
#: field wherever that predicts held-out tracks better. On the demo's ring from ``lfpiv particles``
#: and ``lfpiv track`` with no options: 4.9% of the peak speed against fit's 5.8%; on the tiny rig's
#: A1 series no worse (1.6% both), at 4-5 times the field's CPU (``benchmarks/RESULTS.md``,
#: fourteenth session, issue 48).
ALONG_FIELD = "divfree"


def along_defaults(field: str | None, **given: Any) -> dict[str, Any]:
    """The :class:`lfcore.track.SeriesSettings` options of ``lfpiv track`` along the pairs: those
    ``given`` as they are, :data:`ALONG_DEFAULTS` for the others (``pool_pairs`` only where
    ``field`` is one of :data:`POOLED_FIELDS`, or None: :data:`ALONG_FIELD`; a binned or smooth
    field pools nothing)."""
    field = ALONG_FIELD if field is None else field
    out = {k: v for k, v in ALONG_DEFAULTS.items() if k != "pool_pairs" or field in POOLED_FIELDS}
    return {**out, **given}


def track_settings(**options: Any) -> TrackSettings:
    """:class:`lfcore.track.TrackSettings` of the given options, or a one-line :class:`UsageError`."""
    try:
        return TrackSettings(**options)
    except (TypeError, ValueError) as exc:
        raise UsageError(str(exc)) from None


def series_settings(**options: Any) -> SeriesSettings:
    """:class:`lfcore.track.SeriesSettings` of the given options, or a one-line :class:`UsageError`."""
    try:
        return SeriesSettings(**options)
    except (TypeError, ValueError) as exc:
        raise UsageError(str(exc)) from None


@dataclass
class TracksDone:
    """What :func:`track_run` did: the pairs tracked now, their tracks, outliers and vectors, the
    predictor and the wall time."""

    pairs: list[int] = field(default_factory=list)
    tracks: int = 0
    outliers: int = 0
    vectors: int = 0
    bins: int = 0
    shape: tuple[int, int, int] = (0, 0, 0)
    predictor: str = "none"
    seconds: float = 0.0
    #: along a series: its frames, the tracks fitted through it (of enough frames) and their mean length
    series_frames: int = 0
    series_tracks: int = 0
    series_length: float = 0.0
    #: along a series with --pool-pairs: the pairs offered their neighbours' tracks, the pairs that took
    #: them, and each offered pair's estimated translation of the pattern per pair (x, y, z), voxels
    pool_offered: int = 0
    pool_taken: int = 0
    pool_shifts: list[tuple[float, float, float]] = field(default_factory=list)
    #: whether the pairs were tracked along the series, and why (:func:`lfpiv.pair_runner.along_pairs_choice`)
    along: AlongChoice = AlongChoice(False, "not asked")
    #: the field made (``settings.field``, or :data:`ALONG_FIELD` along the pairs where none was given)
    field: str = "fit"


@dataclass(frozen=True)
class TrackJob:
    """What a Dask worker needs to track a run's pairs (:mod:`lfpiv.batch`): picklable, small."""

    path: str
    grid: VolumeGrid
    settings: TrackSettings
    predictor: str
    device: str | None


@dataclass(frozen=True)
class PairTracks:
    """A pair's tracks and field: (m, 7) track rows (A's x, y, z, B's x, y, z in mm, outlier) and the
    (z, y, x, 3) field in mm, with its figures (the coordinator writes them)."""

    rows: np.ndarray
    field_mm: np.ndarray
    outliers: int
    seconds: float


def _on_grid(pred: Predictor, source: VolumeGrid, grid: VolumeGrid) -> Predictor:
    """A predictor in voxels of ``source`` (the volumes' grid) as one in voxels of ``grid`` (the particles')."""
    sv, gv = np.asarray(source.voxel_mm), np.asarray(grid.voxel_mm)
    origin = (np.asarray(source.origin_mm) + np.asarray(pred.origin) * sv - np.asarray(grid.origin_mm)) / gv
    return Predictor(pred.displacement * (sv / gv).astype(np.float32), tuple(origin),  # type: ignore[arg-type]
                     tuple(np.asarray(pred.step) * sv / gv))  # type: ignore[arg-type]


def _volumes_predictor(store: RunStore, pair: int, grid: VolumeGrid, device: str | None) -> Predictor | None:
    from lfcore.warm import predictor_field

    pred = predictor_field(store.read_volume(pair, 0), store.read_volume(pair, 1), device=device)
    return None if pred is None else _on_grid(pred, store.volume_grid(), grid)


def _track(store: RunStore, pair: int, grid: VolumeGrid, settings: TrackSettings, predictor: Predictor | None
           ) -> tuple[PairTracks, TrackResult]:
    a_all, b_all = store.read_particles(pair, 0)[:, :3], store.read_particles(pair, 1)[:, :3]
    t0 = time.perf_counter()
    res = track_pair(a_all, b_all, grid, settings=settings, predictor=predictor)
    rows = np.column_stack([a_all[res.a_index], b_all[res.b_index], res.outlier.astype(np.float64)])
    return PairTracks(rows=rows, field_mm=res.field_mm, outliers=int(res.outlier.sum()),
                      seconds=time.perf_counter() - t0), res


def track_pair_task(job: TrackJob, pair: int) -> PairTracks:
    """Worker task: the tracks and field of ``pair``, returned to the coordinator, which writes them
    (the tracks are one table that one process appends to)."""
    from lfpiv.batch import this_worker_device

    store = RunStore.open(job.path)  # it reads particles (and volumes) only
    pred = (_volumes_predictor(store, pair, job.grid, this_worker_device(job.device))
            if job.predictor == "volumes" else None)
    return _track(store, pair, job.grid, job.settings, pred)[0]


def _check_series(store: RunStore, chosen: list[int], client: Any) -> None:
    """A one-line error, before anything is written, where ``--along-pairs`` cannot follow the
    particles through the chosen pairs' frames."""
    timing = store.timing
    if not is_time_resolved(timing):
        dt, rate = timing.get("dt_s"), timing.get("rate_hz")
        gap = f"a pair every {1e3 / float(rate):g} ms" if rate else "no pair rate"
        raise UsageError(f"--along-pairs follows particles through a time-resolved series (every frame dt after the "
                         f"one before: a pair every 2 dt), but {store.path} has dt {float(dt or 0) * 1e3:g} ms and "
                         f"{gap}; track its pairs one by one (--pair-by-pair), or record or synthesize a "
                         f"time-resolved run (lfpiv synth --time-resolved)")
    if client is not None:
        raise UsageError("--along-pairs links every frame's particles in order, each frame from the one before: "
                         "leave out --workers and --scheduler")
    if chosen != list(range(chosen[0], chosen[-1] + 1)):
        gap = next(p for p in range(chosen[0], chosen[-1] + 1) if p not in chosen)
        raise UsageError(f"--along-pairs follows particles through consecutive pairs, but pair {gap} between "
                         f"{chosen[0]} and {chosen[-1]} has no particles; run 'lfpiv particles {store.path}' for it, "
                         "or choose consecutive pairs with --pair-range")


def _series(store: RunStore, chosen: list[int], grid: VolumeGrid, settings: TrackSettings, series: SeriesSettings,
            predictor: Predictor | None) -> SeriesTracks:
    """The tracks through the chosen pairs' frames, fitted; frames numbered in the run (2 p + f)."""
    frames = [store.read_particles(p, f)[:, :3] for p in chosen for f in (0, 1)]
    tracks = fit_series(link_series(frames, grid, settings=settings, series=series, predictor=predictor),
                        series=series)
    tracks.frame = tracks.frame + 2 * chosen[0]
    return tracks


def _series_pair(tracks: SeriesTracks, pair: int, grid: VolumeGrid, settings: TrackSettings,
                 series: SeriesSettings, chosen: list[int] | None = None) -> tuple[PairTracks, PoolChoice | None]:
    """A pair's tracks from the tracks through the series (fitted positions at its two frames) and their
    field; with ``series.pool_pairs``, the tracks of the chosen pairs that many either side offered to it."""
    t0 = time.perf_counter()
    a, b, _ = pair_tracks(tracks, pair, series=series)
    near = [k for k in range(-series.pool_pairs, series.pool_pairs + 1) if k and pair + k in (chosen or [])]
    if near:
        res, pool = pooled_field_of_tracks(
            a, b, [(k, *pair_tracks(tracks, pair + k, series=series)[:2]) for k in near], grid, settings=settings)
    else:
        res, pool = field_of_tracks(a, b, grid, settings=settings), None
    rows = np.column_stack([a, b, res.outlier.astype(np.float64)])
    return PairTracks(rows=rows, field_mm=res.field_mm, outliers=int(res.outlier.sum()),
                      seconds=time.perf_counter() - t0), pool


def _check_volumes(store: RunStore, chosen: list[int]) -> None:
    """A one-line error, before anything is written, where ``--predictor volumes`` lacks volumes."""
    fix = (f"run 'lfpiv reconstruct {store.path}' first (a quick one will do: --iterations 5), or track with "
           "--predictor none or previous")
    try:
        if not store.has_volumes:
            raise UsageError(f"--predictor volumes: {store.path} has no reconstructed volumes; {fix}")
        store.volume_grid()
    except RunStoreError as exc:
        raise UsageError(f"--predictor volumes: {exc}") from None
    have = set(store.reconstructed_pairs())
    missing = [p for p in chosen if p not in have]
    if missing:
        raise UsageError(f"--predictor volumes: pair {missing[0]} has no reconstructed volumes ({len(missing)} of the "
                         f"{len(chosen)} selected pair(s) lack them); {fix}")


def _check_density(store: RunStore, chosen: list[int], grid: VolumeGrid, settings: TrackSettings) -> None:
    """A one-line error, before anything is written, where a frame holds too many particles to pair
    one to one within the first pass's search (:func:`lfcore.track.search_crowding`)."""
    for p in chosen:
        for f in (0, 1):
            n = len(store.read_particles(p, f))
            crowd = search_crowding(n, grid, settings.search_voxels)
            if crowd > MAX_CROWDING:
                raise UsageError(
                    f"pair {p} frame {'AB'[f]} holds {n} particles, about {crowd:.0f} in every first-pass search "
                    f"({','.join(f'{v:g}' for v in settings.search_voxels)} voxels): too many to pair one to one "
                    f"(at most {MAX_CROWDING:g}); give a smaller --search-voxels (with --predictor volumes or previous "
                    f"for the displacement), or reconstruct fewer particles (lfpiv particles --threshold, "
                    f"--min-intensity)")


def _create(store: RunStore, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray, dt_s: float,
            windows: list[list[int]], meta: dict[str, Any]) -> None:
    store.create_vectors(x_mm, y_mm, z_mm, dt_s=dt_s, windows=windows, overlap=[0.0] * 3, settings=meta)
    store.create_tracks()


def tracks_table(store: RunStore, pairs: list[int] | None = None) -> np.ndarray:
    """The stored tracks of ``pairs`` (None: every tracked pair) as (m, 11) rows: pair, frame A's
    x, y, z and frame B's (mm), u, v, w (m/s) and outlier (1 rejected, 0 kept)."""
    dt_s = float(store.timing["dt_s"])
    chosen = store.correlated_pairs() if pairs is None else pairs
    rows = []
    for p in chosen:
        t = store.read_tracks(p)
        vel = (t[:, 3:6] - t[:, 0:3]) * 1e-3 / dt_s
        rows.append(np.column_stack([np.full(len(t), p), t[:, :6], vel, t[:, 6]]))
    return np.concatenate(rows) if rows else np.zeros((0, 11))


def tracks_csv(store: RunStore, path: str | Path, pairs: list[int] | None = None) -> int:
    """Write the stored tracks of ``pairs`` (None: every tracked pair) to a CSV file: pair, frame A's
    x, y, z and frame B's (mm), u, v, w (m/s) and outlier (1 rejected, 0 kept); returns the rows."""
    from lfpiv.formats.tracks import write_tracks_csv

    table = tracks_table(store, pairs)
    write_tracks_csv(path, table)
    return len(table)


def track_run(store: RunStore, settings: TrackSettings, pairs: slice | None = None, *, predictor: str = "none",
              progress: bool = True, skip_done: bool = False, option: str = "--pair-range", client: Any = None,
              device: str | None = None, along_pairs: SeriesSettings | None = None, along_mode: str = "on",
              along_options: Sequence[str] = (), announce: Callable[[str], None] | None = None,
              field_given: bool = True) -> TracksDone:
    """Track the particles of ``pairs`` (None: every pair with particles) into ``vectors/``.

    The field (``settings.field``: each bin's mean, or a smooth field at the bins' centres) is in
    m/s over the pair's time, on the grid of the bins' centres; bins with too few tracks are NaN.
    Vectors of other settings (or of ``correlate``) are replaced once the new ones are complete.

    Parameters
    ----------
    store
        The run, open for writing, with ``particles/``.
    settings
        Searches, passes, bins, the outlier test and the field.
    pairs
        The pairs (None: every pair with particles).
    predictor
        The first pass's predictor, one of :data:`PREDICTORS` (see the module docstring).
    progress, skip_done, option
        A progress bar; leave out the pairs done with these settings; the pair range's name in messages.
    client
        A Dask client (:func:`lfpiv.batch.dask_client`): the pairs are tracked on its workers and
        written here as they come back; None: in this process.
    device
        The Warp device of the volumes predictor's correlation.
    along_pairs
        Track along a time-resolved series instead of pair by pair (``--along-pairs``: see the
        module docstring), with these settings; the pairs must be consecutive, the predictor (of
        the first pair's first step) ``none`` or ``volumes``. None: pair by pair.
    along_mode
        How ``along_pairs`` applies (:func:`lfpiv.pair_runner.along_pairs_choice`): ``"on"`` always
        (refused where it cannot), ``"auto"`` where the run is time-resolved, the pairs consecutive
        and of ``along_pairs.min_frames`` frames or more, no ``client`` and no ``predictor``
        ``"previous"``, else pair by pair; ``"off"`` never. What ran is recorded (``vectors/``'
        settings hold ``along_pairs`` where on) and said in the result's ``along``.
    along_options
        The options given that only apply along the pairs (as spelt), refused where ``"auto"`` goes
        pair by pair.
    field_given
        Whether ``settings.field`` was asked for (``--field``); where not, the pairs tracked along the
        series get :data:`ALONG_FIELD` (pair by pair ``settings.field`` stays).
    announce
        Handed the line saying which ran and why (:meth:`lfpiv.pair_runner.AlongChoice.line`) once,
        after the checks and before the pairs are tracked (the command's ``print``); None: not said.

    Raises
    ------
    UsageError
        A run without particles, none of the selected pairs with particles, ``--predictor volumes``
        on a run (or pair) without volumes, ``--predictor previous`` on workers, or frames too
        crowded to pair; ``along_pairs`` on a run that is not a time-resolved series, on workers or
        on pairs that are not consecutive (``along_mode`` ``"on"``); ``along_options`` where it goes
        pair by pair; each before anything is written.
    """
    if predictor not in PREDICTORS:
        raise UsageError(f"--predictor must be one of {', '.join(PREDICTORS)}, got '{predictor}'")
    attrs, chosen = particle_pairs(store, pairs, option=option)
    grid = VolumeGrid.from_rig(store.rig)
    if (not np.allclose(grid.origin_mm, attrs["origin_mm"]) or not np.allclose(grid.voxel_mm, attrs["voxel_mm"])):
        raise UsageError(f"{store.path}: particles/ was made on another grid than the run's rig gives; run "
                         f"'lfpiv particles {store.path}' again")
    if predictor == "previous" and client is not None:
        raise UsageError("--predictor previous tracks the pairs in order, each from the one before: leave out "
                         "--workers and --scheduler, or choose --predictor volumes")
    mode = along_mode if along_pairs is not None else "off"
    choice = along_pairs_choice(mode, time_resolved=is_time_resolved(store.timing), pairs=chosen,
                                workers=client is not None,
                                min_frames=along_pairs.min_frames if along_pairs is not None else 3,
                                previous=predictor == "previous")
    if not choice.on:
        if along_options:
            raise UsageError(along_option_error(along_options, choice))
        along_pairs = None
    if along_pairs is not None:
        _check_series(store, chosen, client)
        if not field_given:  # along the pairs the default field is the divergence-free fit
            settings = replace(settings, field=ALONG_FIELD)
        if 2 * len(chosen) < along_pairs.min_frames:
            raise UsageError(f"--along-pairs fits tracks of at least {along_pairs.min_frames} frames (--min-frames), "
                             f"but the {len(chosen)} pair(s) chosen hold {2 * len(chosen)}; choose more pairs "
                             f"(--pair-range) or a smaller --min-frames")
        if along_pairs.pool_pairs and settings.field not in POOLED_FIELDS:
            raise UsageError(f"--pool-pairs pools the neighbouring pairs' tracks into a fitted field, but the field is "
                             f"'{settings.field}': choose --field fit or divfree, or leave out --pool-pairs")
        if predictor == "previous":  # along a series each step's field predicts the next already
            raise UsageError("--along-pairs predicts each frame from the frame before it already: choose "
                             "--predictor none or volumes (for the first pair)")
    if predictor == "volumes":
        _check_volumes(store, chosen if along_pairs is None else chosen[:1])
    _check_density(store, chosen, grid, settings)
    if announce is not None:  # before the long work, not after it
        announce(choice.line())
    dt_s = float(store.timing["dt_s"])
    # the bins' grid, from a pair's result on no particles
    empty = track_pair(np.zeros((0, 3)), np.zeros((0, 3)), grid, settings=settings)
    x_mm, y_mm, z_mm = empty.x_mm, empty.y_mm, empty.z_mm
    windows = [[int(v) for v in settings.bin_voxels]]
    meta = {"source": "particle tracks", **settings.as_dict(), "predictor": predictor,
            "particles": attrs.get("settings", {})}
    if along_pairs is not None:  # the series' pairs and how they are followed through it
        meta["along_pairs"] = {**along_pairs.as_dict(), "pairs": [chosen[0], chosen[-1]]}
    out = TracksDone(shape=(len(x_mm), len(y_mm), len(z_mm)), predictor=predictor, along=choice,
                     field=settings.field)

    def matches(g: Any) -> bool:
        return (g is not None and g.attrs.get("settings") == meta and g.attrs.get("windows") == windows
                and float(g.attrs.get("dt_s", -1)) == dt_s and g.attrs.get("volumes_id") == store.volumes_id)

    def differences(g: Any) -> list[str]:
        old = dict(g.attrs.get("settings", {})) if g is not None else {}
        # a key on one side only differs too (along_pairs: tracked along the series before, or now)
        return [k for k in {**meta, **old} if old.get(k) != meta.get(k)] or ["source"]

    def written(p: int, r: PairTracks) -> None:
        store.write_tracks(p, r.rows)
        vel = r.field_mm * 1e-3 / dt_s  # mm over dt to m/s
        flags = np.zeros(vel.shape[:3], np.uint8)
        store.write_vectors(p, vel, flags, np.full(vel.shape[:3], np.nan, np.float32))  # records the pair
        out.pairs.append(p)
        out.tracks += len(r.rows)
        out.outliers += r.outliers
        out.vectors += int(np.isfinite(r.field_mm[..., 0]).sum())
        out.bins += int(np.prod(r.field_mm.shape[:3]))
        out.seconds += r.seconds

    def along(todo: list[int]) -> None:
        t0 = time.perf_counter()
        pred = _volumes_predictor(store, chosen[0], grid, device) if predictor == "volumes" else None
        tracks = _series(store, chosen, grid, settings, along_pairs, pred)  # type: ignore[arg-type]
        lengths = tracks.lengths()
        fitted = lengths >= along_pairs.min_frames  # type: ignore[union-attr]
        out.series_frames = 2 * len(chosen)
        out.series_tracks = int(fitted.sum())
        out.series_length = float(lengths[fitted].mean()) if fitted.any() else 0.0
        store.write_series_tracks(np.column_stack([tracks.track, tracks.frame, tracks.position_mm, tracks.fitted_mm]))
        linked = time.perf_counter() - t0
        with tqdm(total=len(todo), unit="pair", disable=not progress, desc="tracking", leave=False) as bar:
            for p in todo:
                # the tracks' frames are the run's (2 p for pair p's A), not counted from the first chosen pair
                made, pool = _series_pair(tracks, p, grid, settings, along_pairs, chosen)  # type: ignore[arg-type]
                if pool is not None:
                    out.pool_offered += 1
                    out.pool_taken += int(pool.pooled)
                    out.pool_shifts.append(tuple(float(v) for v in np.asarray(pool.shift_mm) / grid.voxel_mm))
                written(p, PairTracks(rows=made.rows, field_mm=made.field_mm, outliers=made.outliers,
                                      seconds=made.seconds + linked))
                linked = 0.0
                bar.update(1)

    def here(todo: list[int]) -> None:
        if along_pairs is not None:
            along(todo)
            return
        last: tuple[int, TrackResult] | None = None
        with tqdm(total=len(todo), unit="pair", disable=not progress, desc="tracking", leave=False) as bar:
            for p in todo:
                t0 = time.perf_counter()
                pred = None
                if predictor == "volumes":
                    pred = _volumes_predictor(store, p, grid, device)
                elif predictor == "previous" and last is not None and last[0] == p - 1:
                    pred = field_predictor(last[1], grid)
                made, res = _track(store, p, grid, settings, pred)
                last = (p, res)
                written(p, PairTracks(rows=made.rows, field_mm=made.field_mm, outliers=made.outliers,
                                      seconds=time.perf_counter() - t0))
                bar.update(1)

    def remote(into: str) -> tuple[Any, TrackJob]:
        return track_pair_task, TrackJob(path=str(Path(store.path).resolve()), grid=grid, settings=settings,
                                         predictor=predictor, device=device)

    run_pairs(store, "vectors", chosen, matches=matches, differences=differences,
              create=lambda: _create(store, x_mm, y_mm, z_mm, dt_s, windows, meta),
              skip_done=skip_done, here=here, remote=remote, client=client, on_done=written, desc="tracking",
              progress=progress, postfix=lambda p, r: {"pair": p, "tracks": len(r.rows)},
              kept=lambda: f"the vectors of {len(out.pairs)} pair(s) written before are kept" if out.pairs else "")
    return out
