"""Reconstructing a run store's pairs into ``volumes/`` (``lfpiv reconstruct``), in this process or on Dask workers."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.device import MemoryBudgetError
from lfcore.operator import PROJECTORS, MatrixFreeUnsupported
from lfcore.plan import (
    BYTES_PER_BOX_VOXEL,
    PINHOLE_METHODS,
    Plan,
    PlanError,
    build_reconstructor,
    plan_reconstruction,
    unsupported_method,
)
from lfcore.plan import default_method as cameras_default_method
from lfcore.reconstruct import MAX_SUB_APERTURES, FrameReconstructor, ReconResult, ReconSettings
from lfcore.rig import Rig, is_pinhole, voxel_shape_warnings
from lfcore.runstore import RunStore, RunStoreError
from lfcore.slabs import SlabReconstructor
from lfcore.volume import VolumeGrid
from lfpiv.errors import UsageError
from lfpiv.overlap import WriteBehind
from lfpiv.pair_runner import run_pairs, select_pairs

__all__ = ["BYTES_PER_BOX_VOXEL", "MAX_SUB_APERTURES", "OPERATOR_ATTR", "PINHOLE_METHODS", "PLAN_ATTR", "PROJECTORS",
           "PairDone", "ReconJob", "ReconResult", "ReconSettings", "default_method", "operator_figures",
           "recon_settings", "reconstruct_pair_task", "reconstruct_run", "voxel_shape_notes"]

log = logging.getLogger(__name__)

#: The attribute of ``volumes/`` that holds what the operator took (see :func:`operator_figures`).
OPERATOR_ATTR = "operator"
#: The attribute of ``volumes/`` that holds the plan the volumes were made by
#: (:meth:`lfcore.plan.Plan.as_dict`: device, cameras, operator, cache, slabs and the reasons).
PLAN_ATTR = "plan"


def recon_settings(**options: Any) -> ReconSettings:
    """:class:`lfcore.reconstruct.ReconSettings` of the given options (method, iterations,
    relaxation, form, ...), or a one-line :class:`UsageError` naming what is wrong."""
    try:
        return ReconSettings(**options)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def default_method(rig: Rig, cameras: Sequence[str] | None = None) -> str:
    """The reconstruction of the cameras named (None: all of the rig's): ``mlos-smart`` where they
    are all pinhole cameras, ``drt-mart`` otherwise (a mixed rig's light-field cameras by DRT-MART's
    weights, its pinhole cameras by their line of sight, jointly)."""
    return cameras_default_method([c for c in rig.camera if cameras is None or c.name in cameras])


def voxel_shape_notes(rig: Rig, cameras: Sequence[str] | None, pvr: Sequence[float] | None) -> list[str]:
    """Warnings for crossed cameras reconstructed on voxels far deeper than wide.

    ``cameras`` are the names reconstructed (None: all of the rig's), ``pvr`` the ``--pvr``
    given (None: the rig's)."""
    cams = [c for c in rig.camera if cameras is None or c.name in cameras]
    return voxel_shape_warnings(cams, rig.volume.pvr if pvr is None else pvr)


@dataclass(frozen=True)
class ReconJob:
    """What a worker needs to reconstruct pairs of a run (:mod:`lfpiv.batch`): picklable, small."""

    path: str
    rig: Rig
    cameras: tuple[str, ...]
    grid: VolumeGrid
    settings: ReconSettings
    device: str | None
    token: str
    #: the coordinator's writer token, which lets a cluster's workers write while it holds the lock
    writer: str | None = None
    #: the group the volumes go to: ``volumes``, or ``volumes.pending`` while they replace others
    into: str = "volumes"
    #: depth slabs: None or 1 in memory, a number of slabs, or ``"auto"`` (see :func:`reconstruct_run`)
    slabs: int | str | None = None


def _plan(cams: Sequence[Any], grid: VolumeGrid, settings: ReconSettings, device: str | None,
          slabs: int | str | None = None) -> Plan:
    """The planner's choice (:func:`lfcore.plan.plan_reconstruction`) for a run's frames on ``device``,
    or its one-line refusal as a :class:`UsageError`; logged (``lfpiv reconstruct -v``)."""
    try:
        plan = plan_reconstruction(cams, grid, settings, device=device, slabs=slabs)
    except PlanError as exc:
        raise UsageError(str(exc)) from None
    for line in plan.lines():
        log.info(line)
    return plan


def _operator(cams: Sequence[Any], grid: VolumeGrid, settings: ReconSettings, device: str | None,
              slabs: int | str | None = None) -> tuple[Plan, FrameReconstructor | SlabReconstructor]:
    """The plan of a run's frames and its reconstructor (its projector, weight cache and device
    buffers, built once per stream), on a device with room for the box, or for one depth slab of it
    at a time (``slabs``: a number of slabs, or ``"auto"``: as many as the memory needs, 1 if the box
    fits)."""
    plan = _plan(cams, grid, settings, device, slabs)
    try:
        return plan, build_reconstructor(plan, cams, grid, settings)
    except PlanError as exc:
        raise UsageError(str(exc)) from None


def _reconstruct_frame(frames: FrameReconstructor | SlabReconstructor, store: RunStore, names: Sequence[str],
                       pair: int, frame: int, progress: Any = None, data: Any = None,
                       log: Any = None) -> ReconResult:
    """Reconstruct one frame of a pair from the run's images. A reconstructor in slabs writes
    its volume into ``data`` (the volumes' zarr array; None: the store's) slab by slab and returns
    it empty, telling ``log`` (if given) each stage as it ends; one in memory returns it for the
    caller to write."""
    images = [store.read_frame(n, pair, frame) for n in names]  # a damaged or missing frame is an error
    try:
        if frames.in_slabs:
            out = store.writing("volumes")["data"] if data is None else data

            def write(z0: int, z1: int, planes: np.ndarray) -> None:
                out[pair, frame, z0:z1] = planes

            return frames.reconstruct(images, write=write, progress=progress, log=log)
        return frames.reconstruct(images, progress=progress)
    except (MemoryBudgetError, MatrixFreeUnsupported) as exc:
        raise UsageError(f"pair {pair} frame {'AB'[frame]}: {exc}") from None


def operator_figures(results: Sequence[ReconResult], before: dict[str, Any] | None = None) -> dict[str, Any]:
    """What the operator took over the frames of a set of volumes: the ``volumes/`` attribute
    :data:`OPERATOR_ATTR`, the figures of ``before`` (the attribute as it was, or None) with
    those of ``results`` added.

    Returns
    -------
    dict
        ``projector``: what applied the operator (``"stored"`` weights or the ``"matrix-free"``
        templates; ``"matrix-free, stored"`` where ``auto`` used each for some frames);
        ``bytes``: the largest frame's operator memory (the weights, or the templates and the
        voxels' indices); ``ms_per_iteration``: the mean over the frames of the milliseconds an
        iteration took; ``frames``: how many frames the figures are of.
    """
    before = before or {}
    n0 = int(before.get("frames", 0))
    n = n0 + len(results)
    ran = set(filter(None, str(before.get("projector", "")).split(", "))) | {r.projector for r in results}
    ms = (n0 * float(before.get("ms_per_iteration", 0.0)) + sum(r.ms_per_iteration for r in results)) / max(n, 1)
    return {"projector": ", ".join(sorted(ran)),
            "bytes": max([int(before.get("bytes", 0)), *(int(r.weight_bytes) for r in results)]),
            "ms_per_iteration": round(ms, 3), "frames": n}


def operators_ran(results: Sequence[ReconResult], before: dict[str, Any] | None = None) -> list[str]:
    """The operator kinds (:data:`lfcore.operator.ALL_KINDS`) over the frames of a set of volumes:
    those of ``before`` (the ``operators`` entry of the attribute, or None) and of ``results``."""
    old = (before or {}).get("operators") or []
    return sorted(set(old) | {k for r in results for k in r.operator.split(", ") if k})


def _record(store: RunStore, written: list[tuple[int, int]], results: Sequence[ReconResult],
            plan: Plan | None) -> None:
    """Record the (pair, frame) volumes ``written`` and add the frames of ``results`` to the
    operator figures of the volumes being written, with the ``plan`` they were made by, in one write
    of their attributes (by the one process that writes the store's bookkeeping)."""
    def attrs(now: Any) -> dict[str, Any]:
        figures = operator_figures(results, now.get(OPERATOR_ATTR))
        figures["operators"] = operators_ran(results, now.get(OPERATOR_ATTR))
        return {OPERATOR_ATTR: figures, **({} if plan is None else {PLAN_ATTR: plan.as_dict()})}

    store.record_volumes(written, attrs=attrs)


def _summary(res: ReconResult) -> ReconResult:
    # a run's results are kept for its summary line, its volumes are in the store: holding
    # them all would take a whole run's volumes of memory (482 MiB a frame for the M case)
    return replace(res, volume=np.zeros((0, 0, 0), np.float32))


@dataclass(frozen=True)
class PairDone:
    """What a worker's task gives back of a pair: both frames' results (without their volumes, which
    are in the store) and the plan the worker made them by."""

    results: list[ReconResult]
    plan: Plan


def reconstruct_pair_task(job: ReconJob, pair: int) -> PairDone:
    """Worker task: reconstruct both frames of ``pair`` into the run store; the results come
    back without their volumes, which stay in the store."""
    from lfpiv.batch import open_run_on_worker, this_worker_device, worker_state

    def build() -> tuple[RunStore, Any, tuple[Plan, FrameReconstructor | SlabReconstructor]]:
        store = open_run_on_worker(job.path, job.writer)
        if job.into != "volumes":
            store.resume("volumes")
        cams = [job.rig.camera_named(n) for n in job.cameras]
        # the volumes array opened once: its group's attributes are rewritten by the coordinator
        # as pairs finish, and re-reading them for every write could meet a half-replaced file
        # on a network file system
        return (store, store.writing("volumes")["data"],
                _operator(cams, job.grid, job.settings, this_worker_device(job.device), job.slabs))

    store, data, (plan, frames) = worker_state(job.token, build)
    out = []
    # frame A is written while frame B is reconstructed; both are written when the task returns
    with WriteBehind() as writer:
        for f in (0, 1):
            res = _reconstruct_frame(frames, store, job.cameras, pair, f, data=data)
            if res.slabs == 1:  # a volume in slabs is in the store already
                writer.submit(data.__setitem__, (pair, f), res.volume)
            out.append(_summary(res))
    return PairDone(out, plan)


def reconstruct_run(store: RunStore, settings: ReconSettings, *, pvr: Sequence[float] | None = None,
                    margin_mm: Sequence[float] = (0.0, 0.0, 0.0), pairs: slice | None = None,
                    cameras: Sequence[str] | None = None, device: str | None = None,
                    progress: bool = True, rig: Rig | None = None,
                    calibration: dict[str, Any] | None = None, skip_done: bool = False,
                    client: Any = None, option: str = "--pair-range", slabs: int | str | None = None
                    ) -> list[ReconResult]:
    """Reconstruct both frames of the selected pairs and store them in ``volumes/``.

    Existing volumes with the same grid, cameras, settings and calibration are kept and added
    to; otherwise new volumes replace them once every selected pair is written, and until then
    ``volumes/`` stays as it was (an interrupted replacement is kept in ``volumes.pending/`` and
    goes on when the same settings are given again). With ``skip_done``, the selected pairs
    already reconstructed with these settings are not reconstructed again (a run resumed after
    an interruption).

    ``rig`` replaces the rig stored in the run (e.g. the run's rig with the fitted camera models
    of a calibration, :func:`lfpiv.jobs.calibrate.calibrated_rig`); ``calibration`` says which
    calibration that is and is kept in the ``volumes/`` settings (None: the run's own rig).

    ``client``, a Dask client (:func:`lfpiv.batch.dask_client`), spreads the pairs over its
    workers, which resolve ``device`` each for itself. ``option`` names the pair range in
    messages.

    ``slabs`` reconstructs each volume in depth slabs (:mod:`lfcore.slabs`; the same volume, with
    no buffer of the whole box): a number of slabs, or ``"auto"``, in memory where the box fits and
    otherwise in as many slabs as the memory needs; None (default): in memory. Volumes in slabs
    are written into the store slab by slab.

    Each volume is written into the store while the next frame is reconstructed.

    Returns
    -------
    list of ReconResult
        One per frame reconstructed (with a client, in the order the pairs finished), without
        its volume (an empty array): the volumes are in the store, and a run's worth of them
        would not fit in memory.

    Raises
    ------
    UsageError
        No committed pairs, a pair that was not recorded, an unknown camera, a bad PVR, or a
        box too big for the device's memory.
    """
    rig = store.rig if rig is None else rig
    if store.committed_pairs == 0:
        raise UsageError(f"{store.path} has no recorded pairs (committed_pairs = 0); nothing to reconstruct")
    # by default every recorded pair: a run cut short (Ctrl-C, a fault) has fewer than it planned
    chosen = (select_pairs(pairs, store.n_pairs, option=option) if pairs is not None
              else list(range(store.committed_pairs)))
    late = [p for p in chosen if p >= store.committed_pairs]
    if late:
        raise UsageError(f"pair {late[0]} was never recorded (the run has {store.committed_pairs} committed "
                         f"pair(s)); choose {option} within 0:{store.committed_pairs}")
    names = list(cameras) if cameras else [c.name for c in rig.camera]
    unknown = [n for n in names if n not in store.cameras]
    if unknown:
        raise UsageError(f"--cameras: no camera '{unknown[0]}' in this run (it has {', '.join(store.cameras)})")
    cams = [rig.camera_named(n) for n in names]
    # pinhole cameras alone: MLOS-SMART or MART; beside light-field ones, every method (the
    # light-field cameras take its weights, the pinhole ones their line of sight)
    tomo = unsupported_method(cams, settings.method)
    if tomo is not None:
        raise UsageError(f"camera '{tomo}' is a pinhole camera: --method {settings.method} needs light-field "
                         "cameras; use --method mlos-smart (the default for pinhole cameras) or mart")
    pinhole = [c.name for c in cams if is_pinhole(c)]
    if settings.projector == "matrix-free" and pinhole:  # said before the store is touched
        raise UsageError(f"--projector matrix-free: camera '{pinhole[0]}' is a pinhole camera, and the templates are "
                         "for light-field cameras alone; use --projector auto or stored")
    try:
        grid = VolumeGrid.from_rig(rig, pvr=None if pvr is None else tuple(pvr), margin_mm=tuple(margin_mm))
    except ValueError as exc:
        raise UsageError(f"--pvr/--margin-mm: {exc}") from None
    # the cluster's workers hold the device; this process may have none (a login node)
    plan, frames = _operator(cams, grid, settings, device, slabs) if client is None else (None, None)
    # where the weights lived does not change a volume, so it does not make volumes/ a different set
    kept = {k: v for k, v in settings.as_dict().items() if k != "weight_storage"}
    meta = {**kept, "pvr": list(pvr or rig.volume.pvr), "margin_mm": list(margin_mm),
            "cameras": names, "calibration": calibration}

    def differences(g: Any) -> list[str]:
        try:
            old = _recorded(store.volume_attrs(group=g)["settings"]) if "data" in g else {}
        except RunStoreError:  # for a note: the attributes of an unfinished replacement, damaged
            return ["attributes"]
        changed = [k for k in sorted(set(old) | set(meta)) if old.get(k) != meta.get(k)]
        return (["voxel grid"] if "data" in g and store.grid_of(g) != grid else []) + changed

    results: list[ReconResult] = []

    def written(p: int, done: PairDone) -> None:
        _record(store, [(p, 0), (p, 1)], done.results, done.plan)
        results.extend(done.results)

    def remote(into: str) -> tuple[Any, ReconJob]:
        from lfpiv.batch import new_token

        return reconstruct_pair_task, ReconJob(path=str(Path(store.path).resolve()), rig=rig, cameras=tuple(names),
                                               grid=grid, settings=settings, device=device, token=new_token(),
                                               writer=store.writer_token, into=into, slabs=slabs)

    run_pairs(store, "volumes", chosen, matches=lambda g: _made_with(store, g, grid, meta), differences=differences,
              create=lambda: store.create_volumes(grid, method=settings.method, settings=meta), skip_done=skip_done,
              here=lambda todo: _reconstruct_here(frames, plan, store, names, todo, settings, results, progress),
              remote=remote, client=client, on_done=written, desc="reconstructing", progress=progress,
              postfix=lambda p, done: _shown(p, done.results),
              kept=lambda: f"the {len(results)} volume(s) written before are kept" if results else "")
    return results


def _reconstruct_here(frames: FrameReconstructor | SlabReconstructor, plan: Plan, store: RunStore,
                      names: Sequence[str], chosen: list[int], settings: ReconSettings, results: list[ReconResult],
                      progress: bool) -> None:
    """Reconstruct both frames of the ``chosen`` pairs in this process, adding to ``results``;
    each volume is written (and recorded) while the next frame is reconstructed."""
    total = len(chosen) * 2 * max(settings.iterations, 1)
    with (WriteBehind() as writer,
          tqdm(total=total, unit="it", disable=not progress, desc="reconstructing", leave=False) as bar):
        for p in chosen:
            for f in (0, 1):
                # a slab-by-slab frame can spend long stages (each slab's elimination) without an
                # iteration: the progress line says which ended last
                res = _reconstruct_frame(frames, store, names, p, f, bar.update,
                                         log=lambda line, p=p, f=f: bar.set_postfix_str(f"pair {p} {'AB'[f]}: {line}"))
                # the volume, then its bookkeeping and operator figures, on the writer's thread
                writer.submit(_write_frame, store, p, f, res, plan)
                results.append(_summary(res))
                if settings.iterations == 0:
                    bar.update(1)
                bar.set_postfix(_shown(p, [res]))


def _shown(pair: int, res: Sequence[ReconResult]) -> dict[str, str]:
    """What the progress bar shows of the last frame of ``res`` (pair ``pair``): its active
    voxels, projector, operator memory and milliseconds per iteration."""
    last = res[-1]
    return {"pair": str(pair), "active": f"{last.active_fraction:.2%}", "projector": last.projector,
            "mem": f"{last.weight_bytes / 2**20:.1f}MiB", "ms_it": f"{last.ms_per_iteration:.1f}"}


def _write_frame(store: RunStore, pair: int, frame: int, res: ReconResult, plan: Plan) -> None:
    """Write a frame's volume (none of one written slab by slab) and record it with its operator
    figures and the plan it was made by."""
    if res.slabs == 1:
        store.write_volume(pair, frame, res.volume, record=False)
    _record(store, [(pair, frame)], [res], plan)


def _made_with(store: RunStore, group: Any, grid: VolumeGrid, meta: dict[str, Any]) -> bool:
    """True when ``group`` (volumes or their pending replacement, None if absent) holds volumes
    on ``grid`` made with the settings ``meta``."""
    return (group is not None and "data" in group and store.grid_of(group) == grid
            and _recorded(store.volume_attrs(group=group)["settings"]) == meta)


def _recorded(settings: dict[str, Any]) -> dict[str, Any]:
    """Volumes' recorded settings, with those of settings added since at the value they had
    (volumes made before ``projector`` was recorded were made by ``auto``'s stored weights, those
    before ``prune`` with every voxel to the last iteration)."""
    return {"projector": "auto", "prune": 0.0, "prune_every": 10, **settings}
