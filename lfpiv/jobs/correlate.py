"""Correlating a run store's reconstructed pairs into ``vectors/`` (``lfpiv correlate``), in this process
or on Dask workers."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.correlate import CorrelationConfig, CorrelationError, Correlator, WindowGrid, pass_grids
from lfcore.device import MemoryBudgetError, available_bytes, resolve_device
from lfcore.runstore import RunStore, RunStoreError
from lfcore.slab_correlate import (
    BYTES_PER_SLAB_VOXEL,
    SlabCorrelator,
    correlation_bytes,
    correlator_bytes,
    slabs_for_budget,
)
from lfcore.vectors import MedianTest, centres_mm, displacement_to_velocity, flags_from_masks
from lfcore.volume import VolumeGrid
from lfpiv.errors import UsageError
from lfpiv.overlap import prefetched
from lfpiv.pair_runner import SLAB_SHARE, run_pairs, select_pairs, slabs_asked

__all__ = ["CorrelateJob", "CorrelationRun", "PairVectors", "correlate_pair_task", "correlate_run",
           "correlation_config", "fitting_windows", "pairs_to_correlate"]

# Settings that say where the vectors were computed, not what they are: a run correlated on
# another device (or FFT engine, which follows the device) keeps its earlier pairs.
_PLACE = ("device", "fft")


@dataclass(frozen=True)
class CorrelateJob:
    """What a worker needs to correlate pairs of a run (:mod:`lfpiv.batch`)."""

    path: str
    shape: tuple[int, int, int]
    config: CorrelationConfig
    device: str | None
    token: str
    #: the coordinator's writer token, which lets a cluster's workers write while it holds the lock
    writer: str | None = None
    #: the group the vectors go to: ``vectors``, or ``vectors.pending`` while they replace others
    into: str = "vectors"
    #: depth slabs: None or 1 in memory, a number of slabs, or ``"auto"`` (see :func:`correlate_run`)
    slabs: int | str | None = None


@dataclass(frozen=True)
class PairVectors:
    """What correlating one pair found, without the vectors (they are in the store)."""

    pair: int
    outliers: int
    device: str
    fft: str
    #: depth slabs the pair was correlated in (1: in memory)
    slabs: int = 1
    #: the most bytes of volumes and correlator buffers held at once
    peak_bytes: int = 0
    #: of those, the bytes per voxel of the deepest slab (:data:`BYTES_PER_SLAB_VOXEL`)
    slab_bytes: int = 0


@dataclass(frozen=True)
class CorrelationRun:
    """The summary of :func:`correlate_run`."""

    pairs: list[int]
    grid: WindowGrid
    outliers: int
    seconds: float
    device: str
    #: the most depth slabs a pair was correlated in (1: in memory)
    slabs: int = 1
    #: the most bytes of volumes and correlator buffers a pair held at once
    peak_bytes: int = 0
    #: of those, the bytes per voxel of the deepest slab
    slab_bytes: int = 0
    #: the same bytes per voxel of the whole box (:data:`BYTES_PER_SLAB_VOXEL`)
    box_bytes: int = 0


def _settings(cfg: CorrelationConfig, device: str, fft: str) -> dict[str, Any]:
    return {"deform_iterations": cfg.deform_iterations, "zero_pad": cfg.zero_pad,
            "median_test": {"epsilon": cfg.median_test.epsilon, "threshold": cfg.median_test.threshold},
            "median_filter": cfg.median_filter, "interpolation": cfg.interpolation,
            "smooth_predictor": cfg.smooth_predictor,
            "peak_exclusion": cfg.peak_exclusion, "device": device, "fft": fft,
            "search_radius": None if cfg.search_radius is None else list(cfg.search_radius),
            "first_overlap": None if cfg.first_overlap is None else list(cfg.first_overlap)}


def _same_vectors(store: RunStore, g: Any, volumes_id: str | None, windows: list[list[int]], overlap: list[float],
                  dt_s: float, coords: tuple[np.ndarray, np.ndarray, np.ndarray], settings: dict[str, Any]) -> bool:
    """Whether the stored ``vectors/`` group ``g`` holds vectors of these settings, on this grid,
    from the current volumes (vectors of volumes since replaced are not kept). Its attributes are
    checked (a damaged one is a one-line error): a group created but never begun (killed before
    its attributes were written) holds none."""
    if "correlated_pairs" not in g.attrs:
        return False
    old = store.vector_attrs(group=g)
    return (old.get("volumes_id") == volumes_id and old["windows"] == windows and old["overlap"] == overlap
            and float(old["dt_s"]) == dt_s
            and all(np.array_equal(g[n][...], c) for n, c in zip(("x_mm", "y_mm", "z_mm"), coords, strict=True))
            and {k: v for k, v in old["settings"].items() if k not in _PLACE}
            == {k: v for k, v in settings.items() if k not in _PLACE})


def _correlator(shape: tuple[int, int, int], cfg: CorrelationConfig, device: str | None,
                slabs: int | str | None = None) -> Correlator | SlabCorrelator:
    """The correlator of a run's pairs, in memory or in depth slabs (``slabs``: a number of slabs,
    or ``"auto"``: as many as the memory needs, 1 where the pair fits)."""
    try:
        n = _slab_count(slabs, shape, cfg, resolve_device(device))
        if n > 1:
            return SlabCorrelator(shape, cfg, n, device=device)
        return Correlator(shape, config=cfg, device=device)
    except CorrelationError as exc:
        raise UsageError(str(exc)) from None


def _slab_count(slabs: int | str | None, shape: tuple[int, int, int], cfg: CorrelationConfig, device: str) -> int:
    """Depth slabs to correlate volumes of ``shape`` in: ``slabs`` as given (None: 1), or for
    ``"auto"`` 1 where the whole pair fits in the memory free, else the fewest whose deepest slab
    fits in :data:`SLAB_SHARE` of it."""
    nz = shape[0]
    asked = slabs_asked(slabs, nz)
    if asked is not None:
        return asked
    free = available_bytes(device)
    pass_grids(shape, cfg)  # windows that do not fit say so first
    if correlation_bytes(nz, shape, cfg, device) <= free:
        return 1
    try:
        return slabs_for_budget(shape, cfg, int(SLAB_SHARE * free), device=device)
    except MemoryBudgetError as exc:
        raise UsageError(f"--slabs auto: {exc}") from None


def _read_pair(store: RunStore, pair: int) -> tuple[np.ndarray, np.ndarray]:
    """The volumes of frames A and B of ``pair``, every chunk stored and intact (a damaged or
    missing one is a one-line error, never zeros that would make vectors)."""
    return store.read_volume(pair, 0), store.read_volume(pair, 1)


@dataclass(frozen=True)
class _Target:
    """Where a pair's vectors go: the run, its grid and ``vectors/`` arrays opened once."""

    store: RunStore
    grid: VolumeGrid
    dt_s: float
    arrays: dict[str, Any]

    @classmethod
    def of(cls, store: RunStore) -> _Target:
        return cls(store, store.volume_grid(), store.dt_s, store.vector_arrays())


def _read_planes(store: RunStore, pair: int) -> Any:
    """``read(lo, hi)``: planes lo .. hi - 1 of the volumes of frames A and B of ``pair``, every
    chunk that holds them stored and intact."""
    return lambda lo, hi: (store.read_volume(pair, 0, planes=(lo, hi)), store.read_volume(pair, 1, planes=(lo, hi)))


def _correlate_pair(correlator: Correlator | SlabCorrelator, target: _Target, pair: int,
                    volumes: tuple[np.ndarray, np.ndarray] | None, progress: Any = None) -> PairVectors:
    """Correlate one pair's volumes (A, B; None: read slab by slab from the store by a
    :class:`SlabCorrelator`) and write its vectors (not the bookkeeping) into ``vectors/``."""
    if isinstance(correlator, SlabCorrelator):
        field = correlator(_read_planes(target.store, pair), progress=progress)
        slabs, peak = len(correlator.slabs), correlator.peak_bytes
        per_voxel = BYTES_PER_SLAB_VOXEL * max(s.depth for s in correlator.slabs) * int(np.prod(correlator.shape[1:]))
    else:
        field = correlator(*volumes, progress=progress)
        slabs, peak = 1, correlator_bytes(correlator) + sum(int(v.nbytes) for v in volumes)
        per_voxel = BYTES_PER_SLAB_VOXEL * int(np.prod(correlator.shape))
    vel = displacement_to_velocity(field.displacement, target.grid.voxel_mm, target.dt_s)
    target.store.write_vectors(pair, vel, flags_from_masks(field.outlier, field.replaced), field.peak_ratio,
                               record=False, arrays=target.arrays)
    return PairVectors(pair=pair, outliers=int(field.outlier.sum()), device=correlator.device, fft=correlator.fft,
                       slabs=slabs, peak_bytes=peak, slab_bytes=per_voxel)


def correlate_pair_task(job: CorrelateJob, pair: int) -> PairVectors:
    """Worker task: correlate ``pair`` of the run into its ``vectors/``."""
    from lfpiv.batch import open_run_on_worker, this_worker_device, worker_state

    def build() -> tuple[_Target, RunStore, Correlator]:
        # the vector arrays are opened once: the group's attributes are rewritten by the
        # coordinator as pairs finish, and re-reading them for every write could meet a
        # half-replaced file on a network file system (volumes/ stays as it is meanwhile)
        store = open_run_on_worker(job.path, job.writer)
        if job.into != "vectors":
            store.resume("vectors")
        return (_Target.of(store), store, _correlator(job.shape, job.config, this_worker_device(job.device),
                                                      job.slabs))

    target, store, correlator = worker_state(job.token, build)
    volumes = None if isinstance(correlator, SlabCorrelator) else _read_pair(store, pair)
    return _correlate_pair(correlator, target, pair, volumes)


def fitting_windows(shape: tuple[int, int, int]) -> tuple[tuple[int, int, int], ...]:
    """Two passes for volumes of ``shape`` (z, y, x): the first window the largest power of two up
    to 32 voxels that fits twice into the volume along each axis, the second half of it.

    Returns
    -------
    tuple
        ((x, y, z), (x, y, z)) voxels, largest first.
    """
    first = []
    for n in shape[::-1]:  # x, y, z
        w = 32
        while w > 4 and 2 * w > n:
            w //= 2
        first.append(w)
    return tuple(first), tuple(w // 2 for w in first)  # type: ignore[return-value]


def correlation_config(*, windows: tuple[tuple[int, int, int], ...], overlap: tuple[float, float, float],
                       deform_iterations: int = 2, zero_pad: bool = False, median_filter: bool = False,
                       epsilon: float = 0.1, threshold: float = 2.0, interpolation: str = "cubic",
                       search_radius: tuple[int, int, int] | None = None,
                       first_overlap: tuple[float, float, float] | None = None) -> CorrelationConfig:
    """The correlation of ``lfpiv correlate``'s options (see :class:`lfcore.correlate.CorrelationConfig`).

    ``windows`` are (x, y, z) voxels per pass, largest first; ``epsilon`` and ``threshold`` are
    the normalized median test's.

    Raises
    ------
    UsageError
        Settings that contradict each other, in one line.
    """
    try:
        return CorrelationConfig(windows=windows, overlap=overlap, deform_iterations=deform_iterations,
                                 zero_pad=zero_pad, median_filter=median_filter,
                                 median_test=MedianTest(epsilon=epsilon, threshold=threshold),
                                 interpolation=interpolation, search_radius=search_radius,
                                 first_overlap=first_overlap)
    except CorrelationError as exc:
        raise UsageError(str(exc)) from None


def pairs_to_correlate(store: RunStore, pairs: slice | None = None, *, option: str = "--pair-range") -> list[int]:
    """The reconstructed pairs that ``pairs`` (the ``--pair-range``, named ``option`` in messages;
    None: all) selects.

    Raises
    ------
    RunStoreError
        A run without volumes, or with none reconstructed.
    UsageError
        A selected pair that is not reconstructed.
    """
    store.volumes()  # a run without volumes says so
    done = store.reconstructed_pairs()
    if not done:
        raise RunStoreError(f"{store.path} has no reconstructed pairs yet; run 'lfpiv reconstruct {store.path}' first")
    if pairs is None:
        return done
    wanted = select_pairs(pairs, store.n_pairs, option=option)
    missing = [p for p in wanted if p not in done]
    if missing:
        raise UsageError(f"{option}: pair(s) {', '.join(map(str, missing[:5]))}{' ...' if len(missing) > 5 else ''} "
                         f"are not reconstructed (reconstructed: {', '.join(map(str, done[:10]))})")
    return wanted


def correlate_run(store: RunStore, cfg: CorrelationConfig, pairs: list[int], *, device: str | None = None,
                  progress: bool = True, skip_done: bool = False, client: Any = None,
                  slabs: int | str | None = None) -> CorrelationRun:
    """Correlate the volumes of ``pairs`` into the run's ``vectors/``.

    Vectors already there with the same windows, overlap and settings are kept and added to;
    otherwise new vectors replace them once every pair is written, and until then ``vectors/``
    stays as it was (an interrupted replacement is kept in ``vectors.pending/`` and goes on when
    the same settings are given again). With ``skip_done``, pairs those vectors already hold are
    left out. ``client``, a Dask client (:func:`lfpiv.batch.dask_client`), spreads the pairs
    over its workers, each correlating on its own ``device``.

    ``slabs`` correlates each pair in depth slabs read from the store slab by slab
    (:mod:`lfcore.slab_correlate`; the in-memory vectors, without the whole volumes): a number of
    slabs, or ``"auto"``, in memory where the pair fits and otherwise in as many slabs as the
    memory needs; None (default): in memory. The slabs do not change the vectors' settings.

    Raises
    ------
    UsageError
        Windows that do not fit the volume or settings the device cannot run.
    """
    grid = store.volume_grid()
    if client is not None and slabs not in (None, "auto"):
        _slab_count(slabs, grid.shape, cfg, "cpu")  # a bad count says so here, not on a worker
    correlator = _correlator(grid.shape, cfg, device, slabs) if client is None else None
    try:
        g = pass_grids(grid.shape, cfg)[-1]
    except CorrelationError as exc:
        raise UsageError(str(exc)) from None
    x_mm, y_mm, z_mm = centres_mm(g.centres(), grid.origin_mm, grid.voxel_mm)
    dt_s = store.dt_s
    # on a cluster the workers resolve the device; recorded from the first pair they finish
    place = (correlator.device, correlator.fft) if correlator is not None else (device or "auto", cfg.fft)
    settings = _settings(cfg, *place)
    windows, overlap = [list(w) for w in cfg.windows], list(cfg.overlap)

    def same(g: Any) -> bool:
        return g is not None and _same_vectors(store, g, store.volumes_id, windows, overlap, dt_s, (x_mm, y_mm, z_mm),
                                               settings)

    def differences(g: Any) -> list[str]:
        try:
            old = store.vector_attrs(group=g)
        except RunStoreError:  # for a note: an unfinished replacement's attributes, damaged or never written
            return ["attributes"]
        changed = ["volumes since replaced"] if old.get("volumes_id") != store.volumes_id else []
        changed += [k for k, v in (("windows", windows), ("overlap", overlap)) if old.get(k) != v]
        s = old.get("settings", {})
        return changed + [k for k in sorted(set(s) | set(settings)) if k not in _PLACE and s.get(k) != settings.get(k)]

    found: list[PairVectors] = []

    def written(p: int, res: PairVectors) -> None:
        if not found:
            # the device and FFT engine that computed the latest pairs (a worker resolves its own)
            g = store.writing("vectors")
            s = g.attrs["settings"]
            if (s.get("device"), s.get("fft")) != (res.device, res.fft):
                g.attrs["settings"] = {**s, "device": res.device, "fft": res.fft}
        store.record_vectors([p])
        found.append(res)

    def here(todo: list[int]) -> None:
        # a pair in slabs makes every pass once per slab
        per_pair = len(cfg.passes) * (len(correlator.slabs) if isinstance(correlator, SlabCorrelator) else 1)
        with tqdm(total=len(todo) * per_pair, unit="pass", disable=not progress, desc="correlating") as bar:
            # the next pair's volumes are read while this one is correlated
            target = _Target.of(store)
            if isinstance(correlator, SlabCorrelator):  # read slab by slab, never a whole volume
                for p in todo:
                    written(p, _correlate_pair(correlator, target, p, None, progress=bar.update))
                return
            for p, vols in prefetched(todo, partial(_read_pair, store)):
                written(p, _correlate_pair(correlator, target, p, vols, progress=bar.update))

    def remote(into: str) -> tuple[Any, CorrelateJob]:
        from lfpiv.batch import new_token

        return correlate_pair_task, CorrelateJob(path=str(Path(store.path).resolve()), shape=grid.shape, config=cfg,
                                                 device=device, token=new_token(), writer=store.writer_token,
                                                 into=into, slabs=slabs)

    t0 = time.perf_counter()
    run_pairs(store, "vectors", pairs, matches=same, differences=differences,
              create=lambda: store.create_vectors(x_mm, y_mm, z_mm, dt_s=dt_s, windows=windows, overlap=overlap,
                                                 settings=settings),
              skip_done=skip_done, here=here, remote=remote, client=client, on_done=written, desc="correlating",
              progress=progress)
    dev = found[0].device if found else place[0]
    return CorrelationRun(pairs=[r.pair for r in found], grid=g, outliers=sum(r.outliers for r in found),
                          seconds=time.perf_counter() - t0, device=dev, slabs=max((r.slabs for r in found), default=1),
                          peak_bytes=max((r.peak_bytes for r in found), default=0),
                          slab_bytes=max((r.slab_bytes for r in found), default=0),
                          box_bytes=BYTES_PER_SLAB_VOXEL * grid.n_voxels)
