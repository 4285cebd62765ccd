"""Reconstructing a run store's pairs into ``volumes/`` (``lfpiv reconstruct``), in this process or on Dask workers."""

from __future__ import annotations

import logging
from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.coarse import MAX_COARSE
from lfcore.device import MemoryBudgetError
from lfcore.flatfield import FlatField, correct
from lfcore.operator import PROJECTORS, MatrixFreeUnsupported
from lfcore.plan import (
    BYTES_PER_BOX_VOXEL,
    PINHOLE_METHODS,
    Plan,
    PlanError,
    build_reconstructor,
    camera_kind,
    plan_reconstruction,
    unsupported_method,
)
from lfcore.plan import default_method as cameras_default_method
from lfcore.reconstruct import (
    COARSE_ITERATIONS,
    FIXED,
    LOS_STOP_VOXELS,
    MAX_SUB_APERTURES,
    PROTOCOLS,
    STOP_REASONS,
    STOP_TOLERANCE,
    STOP_VOXELS,
    FrameReconstructor,
    ReconResult,
    ReconSettings,
    light_field_plan,
    protocol_settings,
)
from lfcore.rig import Rig, is_pinhole, voxel_shape_warnings
from lfcore.runstore import RunStore, RunStoreError
from lfcore.slabs import SlabReconstructor
from lfcore.subsets import MAX_SUBSETS, SUBSET_HALVING
from lfcore.volume import VolumeGrid
from lfcore.warm import OWN_PAIR, Predictor, WarmStart, predictor_field
from lfpiv.errors import UsageError
from lfpiv.overlap import WriteBehind
from lfpiv.pair_runner import recorded_pairs, run_pairs

__all__ = ["BYTES_PER_BOX_VOXEL", "CONVERGENCE_ATTR", "DEFAULT_PROTOCOL", "LOS_STOP_VOXELS", "MAX_SUB_APERTURES",
           "MAX_SUBSETS", "OPERATOR_ATTR", "PINHOLE_METHODS", "PLAN_ATTR", "PROJECTORS", "PROTOCOLS", "STOP_TOLERANCE",
           "STOP_VOXELS", "SUBSET_HALVING", "MAX_COARSE", "PairDone", "ReconJob", "ReconResult", "ReconSettings",
           "camera_count", "cameras_kind", "convergence_figures", "default_method", "describe_convergence",
           "iterations_summary", "operator_figures", "plan_words", "protocol_run_settings", "recon_settings",
           "reconstruct_pair_task", "reconstruct_run", "run_method", "voxel_shape_notes"]

log = logging.getLogger(__name__)

#: The attribute of ``volumes/`` that holds what the operator took (see :func:`operator_figures`).
OPERATOR_ATTR = "operator"
#: The attribute of ``volumes/`` that holds the plan the volumes were made by
#: (:meth:`lfcore.plan.Plan.as_dict`: device, cameras, operator, cache, slabs and the reasons).
PLAN_ATTR = "plan"
#: The attribute of ``volumes/`` that holds how the frames' iterations went (see :func:`convergence_figures`).
CONVERGENCE_ATTR = "convergence"
#: The protocol (:data:`lfcore.reconstruct.PROTOCOLS`) of ``lfpiv reconstruct`` without ``--protocol``.
DEFAULT_PROTOCOL = "fast"


def recon_settings(**options: Any) -> ReconSettings:
    """:class:`lfcore.reconstruct.ReconSettings` of the given options (method, iterations,
    relaxation, form, ...), or a one-line :class:`UsageError` naming what is wrong."""
    try:
        return ReconSettings(**options)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def protocol_run_settings(protocol: str, *, iterations: int | None = None, max_iterations: int | None = None,
                          stop_tolerance: float | None = None, n_cameras: int = 1, camera_kind: str | None = None,
                          none_given: Collection[str] = (), **options: Any) -> ReconSettings:
    """The settings of a named protocol (:func:`lfcore.reconstruct.protocol_settings`) changed by the
    options given (those None are the protocol's), or a one-line :class:`UsageError`.

    ``n_cameras`` is the number of cameras reconstructed jointly: on several the protocol's settings
    for rigs of several cameras apply (:data:`lfcore.reconstruct.SEVERAL_CAMERAS`: ``fast`` without
    its ordered subsets) where the options do not give them; ``camera_kind`` (:func:`cameras_kind`)
    ``"light-field"`` with no ``method`` given applies the protocol's plan for several light-field
    cameras instead (:func:`lfcore.reconstruct.light_field_plan`: ``fast`` by MLOS-MART).

    ``iterations`` is a fixed count (the stopping rule off) for every frame (the protocol's warm start
    left out unless ``warm_start`` is given); ``max_iterations`` the stopping rule's
    most (the rule on, at ``stop_tolerance`` or the protocol's or :data:`STOP_TOLERANCE`);
    ``stop_tolerance`` alone the rule's tolerance (0: the protocol's iterations, a fixed count).
    ``none_given``: the options whose None was given as a value (the Python API's
    ``lit_hysteresis=None``: off), not for the protocol's (a command's options left out are None).
    """
    if iterations is not None and max_iterations is not None:
        raise UsageError("--iterations is a fixed count and --max-iterations the stopping rule's most; give one")
    if iterations is not None and stop_tolerance:
        raise UsageError("--iterations is a fixed count, without the stopping rule; drop --stop-tolerance, or give "
                         "--max-iterations instead")
    changes = {k: v for k, v in options.items() if v is not None or k in none_given}
    base = PROTOCOLS.get(protocol, {})
    if iterations is not None:
        changes.update(iterations=iterations, stop_tolerance=0.0)
        # exactly that many for every frame: the protocol's warm start (a fifth of them for a frame B) only
        # where asked for
        changes.setdefault("warm_start", False)
    elif max_iterations is not None:
        tol = stop_tolerance if stop_tolerance is not None else base.get("stop_tolerance") or STOP_TOLERANCE
        if not tol:
            raise UsageError("--max-iterations is the stopping rule's most, and --stop-tolerance 0 turns the rule off; "
                             "give --iterations for a fixed count")
        changes.update(iterations=max_iterations, stop_tolerance=tol)
    elif stop_tolerance is not None:
        changes["stop_tolerance"] = stop_tolerance
    try:
        return protocol_settings(protocol, n_cameras=n_cameras, camera_kind=camera_kind, **changes)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def camera_count(rig: Rig, cameras: Sequence[str] | None = None) -> int:
    """How many of the rig's cameras are reconstructed jointly: those named (None: all of the rig's)."""
    return sum(1 for c in rig.camera if cameras is None or c.name in cameras)


def cameras_kind(rig: Rig, cameras: Sequence[str] | None = None) -> str:
    """The kind of the cameras named (None: all of the rig's), :func:`lfcore.plan.camera_kind`:
    ``"light-field"``, ``"pinhole"`` or ``"joint"`` (a mix)."""
    return camera_kind([c for c in rig.camera if cameras is None or c.name in cameras])


def run_method(rig: Rig, cameras: Sequence[str] | None = None, method: str | None = None) -> str | None:
    """The method to hand :func:`protocol_run_settings`: ``method`` where given; None for light-field
    cameras (the protocol's plan for them picks: ``fast`` on several, MLOS-MART; DRT-MART otherwise);
    the cameras' default (:func:`default_method`) for pinhole and mixed rigs."""
    if method is not None:
        return method
    return None if cameras_kind(rig, cameras) == "light-field" else default_method(rig, cameras)


def plan_words(protocol: str, *, n_cameras: int = 1, camera_kind: str | None = None, **given: Any) -> str:
    """Words for the summary line on which of the protocol's plans ran: ``" (its plan for several
    light-field cameras)"`` where :func:`lfcore.reconstruct.light_field_plan` applies to the options
    ``given`` (those None not given), else ``""``."""
    changes = {k: v for k, v in given.items() if v is not None}
    applies = light_field_plan(protocol, n_cameras=n_cameras, camera_kind=camera_kind, changes=changes)
    return " (its plan for several light-field cameras)" if applies else ""


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
    #: per camera, the flat field its raw frames are corrected by (:func:`lfcore.flatfield.correct`)
    flats: dict[str, FlatField] | None = None
    #: whether the settings' warm start is the protocol's (left out in depth slabs) rather than the user's
    warm_optional: bool = False
    #: accepted and unused: depth slabs run the ordered subsets (it said whether they were the protocol's,
    #: left out in depth slabs)
    subsets_optional: bool = False


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
              slabs: int | str | None = None, warm_optional: bool = False, subsets_optional: bool = False
              ) -> tuple[Plan, FrameReconstructor | SlabReconstructor]:
    """The plan of a run's frames and its reconstructor (its projector, weight cache and device
    buffers, built once per stream), on a device with room for the box, or for one depth slab of it
    at a time (``slabs``: a number of slabs, or ``"auto"``: as many as the memory needs, 1 if the box
    fits). ``warm_optional``: a warm start the protocol asked for (not the user) is left out in depth
    slabs rather than refused. ``subsets_optional`` is accepted and unused: depth slabs run the ordered
    subsets (:mod:`lfcore.slabs`)."""
    plan = _plan(cams, grid, settings, device, slabs)
    try:
        frames = build_reconstructor(plan, cams, grid, settings)
    except PlanError as exc:
        raise UsageError(str(exc)) from None
    if settings.warm_start and frames.in_slabs and not warm_optional:
        raise UsageError(f"--warm-start carries whole volumes from frame to frame, and this box is reconstructed in "
                         f"{plan.slabs} depth slabs; drop --warm-start (--no-warm-start under a protocol that "
                         "warm-starts) or --slabs")
    return plan, frames


def _plans_in_slabs(cams: Sequence[Any], grid: VolumeGrid, settings: ReconSettings, device: str | None) -> bool:
    """Worker task: whether ``--slabs auto`` reconstructs this worker's frames in depth slabs (True also
    where it cannot plan them at all: its tasks refuse as they would)."""
    from lfpiv.batch import this_worker_device

    try:
        return plan_reconstruction(cams, grid, settings, device=this_worker_device(device), slabs="auto").slabs > 1
    except Exception:  # noqa: BLE001 - the worker's own tasks say what is wrong
        return True


def _workers_in_slabs(client: Any, cams: Sequence[Any], grid: VolumeGrid, settings: ReconSettings,
                      device: str | None) -> list[str]:
    """The workers of ``client`` whose ``--slabs auto`` plan (by their own device's memory, now)
    reconstructs the run's frames in depth slabs, by address."""
    workers = sorted(client.scheduler_info().get("workers", {}))
    futures = [client.submit(_plans_in_slabs, cams, grid, settings, device, workers=[w], allow_other_workers=False,
                             pure=False) for w in workers]
    return [w for w, split in zip(workers, client.gather(futures), strict=True) if split]


@dataclass
class Series:
    """Warm starts along the pairs one reconstructor makes (:mod:`lfcore.warm`): each frame A is
    kept, each frame B starts from it carried along its predictor: the pair's own
    (``settings.warm_predictor`` ``"own"``: B depends on its pair alone, in whatever order the pairs
    come), or the one the last pair measured (``"last"``: pairs in order, the first pair's B uniform)."""

    warm: WarmStart
    predictor: Predictor | str | None = None

    @classmethod
    def of(cls, frames: FrameReconstructor | SlabReconstructor, settings: ReconSettings) -> Series | None:
        """The series state of ``frames``, or None where ``settings`` start every frame uniform."""
        if not settings.warm_start or frames.in_slabs:
            return None
        own = settings.warm_predictor == OWN_PAIR
        return cls(WarmStart(frames.projector.grid.shape, device=frames.device), OWN_PAIR if own else None)

    def frame(self, frame: int) -> dict[str, Any]:
        """What :meth:`FrameReconstructor.reconstruct` takes for ``frame`` (0 A, 1 B) of a pair."""
        return {"warm": self.warm, "predictor": self.predictor if frame == 1 else None}

    def measured(self, results: Sequence[ReconResult], device: str) -> None:
        """The pair's predictor for the next pair, from its two volumes (none needed where each pair's
        B measures its own)."""
        if self.predictor != OWN_PAIR:
            self.predictor = predictor_field(results[0].volume, results[1].volume, device=device)


def _reconstruct_frame(frames: FrameReconstructor | SlabReconstructor, store: RunStore, names: Sequence[str],
                       pair: int, frame: int, progress: Any = None, data: Any = None,
                       log: Any = None, series: Series | None = None,
                       flats: dict[str, FlatField] | None = None) -> ReconResult:
    """Reconstruct one frame of a pair from the run's images. A reconstructor in slabs writes
    its volume into ``data`` (the volumes' zarr array; None: the store's) slab by slab and returns
    it empty, telling ``log`` (if given) each stage as it ends; one in memory returns it for the
    caller to write. ``series`` warm-starts it along the pairs (frame A kept, B started from it).
    ``flats``: per camera, the flat field its frame is corrected by (its masked pixels leave the
    operator)."""
    images = [store.read_frame(n, pair, frame) for n in names]  # a damaged or missing frame is an error
    if flats:
        images = [correct(img, flats[n]) if n in flats else img for img, n in zip(images, names, strict=True)]
    try:
        if frames.in_slabs:
            out = store.writing("volumes")["data"] if data is None else data

            def write(z0: int, z1: int, planes: np.ndarray) -> None:
                out[pair, frame, z0:z1] = planes

            return frames.reconstruct(images, write=write, progress=progress, log=log)
        return frames.reconstruct(images, progress=progress, **({} if series is None else series.frame(frame)))
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


def convergence_figures(results: Sequence[ReconResult], before: dict[str, Any] | None = None, *,
                        frames: Sequence[tuple[int, int]] | None = None) -> dict[str, Any]:
    """How the frames' iterations went over a set of volumes: the ``volumes/`` attribute
    :data:`CONVERGENCE_ATTR`, the figures of ``before`` (the attribute as it was, or None) with those
    of ``results`` added.

    ``frames`` names the (pair, frame) of each of ``results``: the figures then keep a row per frame
    (``per_frame``), so a frame made again replaces its row instead of counting twice. Without it, or
    on a ``before`` of an older lfpiv that kept no rows, the figures are added as they come.

    Returns
    -------
    dict
        ``frames``: how many frames the figures are of; ``iterations`` and ``voxels``: the least,
        most and total over the frames of the iterations that ran and of the voxels left in the
        operator at the end (after the pruning); ``stopped``: per reason
        (:data:`lfcore.reconstruct.STOP_REASONS`), the frames that stopped for it; ``per_frame``
        (with ``frames``): ``"pair,frame"`` to [iterations, voxels left, reason].
    """
    before = before or {}
    rows = before.get("per_frame")
    if frames is not None and len(frames) == len(results) and (isinstance(rows, dict) or not before.get("frames")):
        table = {str(k): list(v) for k, v in (rows or {}).items()}
        for (p, f), r in zip(frames, results, strict=True):
            table[f"{int(p)},{int(f)}"] = [int(r.iterations), int(r.final_voxels), str(r.stopped)]
        return {**_convergence_of(list(table.values())), "per_frame": dict(sorted(
            table.items(), key=lambda kv: tuple(int(x) for x in kv[0].split(","))))}

    def spread(key: str, values: list[int]) -> list[int]:
        old = before.get(key)
        lo, hi, total = (int(old[0]), int(old[1]), int(old[2])) if isinstance(old, list) and len(old) == 3 else (
            None, None, 0)
        return [min([v for v in (lo, *values) if v is not None], default=0),
                max([v for v in (hi, *values) if v is not None], default=0), total + sum(values)]

    stopped = {str(k): int(v) for k, v in (before.get("stopped") or {}).items()}
    for r in results:
        stopped[r.stopped] = stopped.get(r.stopped, 0) + 1
    return {"frames": int(before.get("frames", 0)) + len(results),
            "iterations": spread("iterations", [int(r.iterations) for r in results]),
            "voxels": spread("voxels", [int(r.final_voxels) for r in results]),
            "stopped": _reasons_in_order(stopped)}


def _reasons_in_order(stopped: dict[str, int]) -> dict[str, int]:
    return {k: stopped[k] for k in sorted(stopped, key=lambda k: (k not in STOP_REASONS, k))}


def _convergence_of(rows: list[list]) -> dict[str, Any]:
    """:func:`convergence_figures`' totals of per-frame rows [iterations, voxels left, reason]."""
    its, vox = [int(r[0]) for r in rows], [int(r[1]) for r in rows]
    stopped: dict[str, int] = {}
    for r in rows:
        stopped[str(r[2])] = stopped.get(str(r[2]), 0) + 1
    return {"frames": len(rows), "iterations": [min(its, default=0), max(its, default=0), sum(its)],
            "voxels": [min(vox, default=0), max(vox, default=0), sum(vox)], "stopped": _reasons_in_order(stopped)}


def resumed_protocol(path: str | Path) -> str | None:
    """The protocol the run's volumes were made by, for ``--skip-done`` without ``--protocol`` (a run
    is finished as it was begun, not remade by a newer default): the recorded name, ``"fixed"`` for
    volumes recorded before protocols were (``lfpiv reconstruct``'s default then); None where the run
    has no volumes, cannot be read (its opening says why, later), or its volumes were made from
    settings given one by one."""
    try:
        store = RunStore.open(path)
        if not store.has_volumes:
            return None
        recorded = store.volume_attrs()["settings"]
    except (RunStoreError, KeyError, TypeError):
        return None
    name = recorded.get("protocol", "fixed") if isinstance(recorded, dict) else None
    return name if name in PROTOCOLS else None


def recorded_stages(store: RunStore) -> str:
    """What each frame of the run's volumes ran (:func:`stages_of` the plan ``volumes/`` records)."""
    return stages_of(store.volume_attrs().get(PLAN_ATTR)) if store.has_volumes else ""


def stages_of(recorded: object) -> str:
    """What each frame ran, in one line (:meth:`lfcore.plan.Plan.describe_stages` of a recorded plan),
    or ``""`` for a plan recorded without its stages (or a damaged record)."""
    if not isinstance(recorded, dict):
        return ""
    try:
        return Plan.from_dict(recorded).describe_stages()
    except PlanError:
        return ""


def iterations_summary(results: Sequence[ReconResult], settings: ReconSettings) -> str:
    """The summary line's words on the frames' iterations: ``"150-200 iterations a frame (mean 172; at
    most 400 by the stopping rule: converged 4), 2,085-4,457 voxels left of 26,256 active"``, and where
    MLOS-MART handed frames to DRT weights (:attr:`lfcore.reconstruct.ReconResult.handover`), how many and
    why the first did."""
    words = describe_convergence(convergence_figures(results), settings.stop_tolerance, settings.iterations,
                                 active=max((r.active_voxels for r in results), default=0))
    handed = [r.handover for r in results if r.handover]
    if handed:
        frames = "1 frame" if len(handed) == 1 else f"{len(handed)} frames"
        words += f"; {frames} of {len(results)} handed over to DRT weights (the first: {handed[0]})"
    return words


def describe_convergence(figures: dict[str, Any], stop_tolerance: float, most: int, *, active: int = 0) -> str:
    """Words for :func:`convergence_figures`' ``figures`` of frames made with ``stop_tolerance`` and at most
    ``most`` iterations (``lfpiv info`` and the summary line)."""
    n = int(figures.get("frames", 0))
    its, vox = figures.get("iterations") or [0, 0, 0], figures.get("voxels") or [0, 0, 0]
    if not n:
        return "no frame"
    span = f"{its[0]}" if its[0] == its[1] else f"{its[0]}-{its[1]}"
    mean = f"mean {its[2] / n:.0f}; " if its[0] != its[1] else ""
    stopped = figures.get("stopped") or {}
    why = ", ".join(f"{k} {v}" for k, v in stopped.items())
    rule = (f"at most {most} by the stopping rule (tolerance {stop_tolerance:g})" if stop_tolerance > 0 else
            FIXED)
    left = f"{vox[0]:,}" if vox[0] == vox[1] else f"{vox[0]:,}-{vox[1]:,}"
    of = f" of {active:,} active" if active else ""
    return f"{span} iterations a frame ({mean}{rule}; stopped: {why}), {left} voxels left a frame{of}"


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
        went = convergence_figures(results, now.get(CONVERGENCE_ATTR), frames=written)
        return {OPERATOR_ATTR: figures, CONVERGENCE_ATTR: went,
                **({} if plan is None else {PLAN_ATTR: plan.as_dict()})}

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

    def build() -> tuple[RunStore, Any, tuple[Plan, FrameReconstructor | SlabReconstructor], Series | None]:
        store = open_run_on_worker(job.path, job.writer)
        if job.into != "volumes":
            store.resume("volumes")
        cams = [job.rig.camera_named(n) for n in job.cameras]
        # the volumes array opened once: its group's attributes are rewritten by the coordinator
        # as pairs finish, and re-reading them for every write could meet a half-replaced file
        # on a network file system
        plan, frames = _operator(cams, job.grid, job.settings, this_worker_device(job.device), job.slabs,
                                 job.warm_optional, job.subsets_optional)
        # a worker's pairs come in order: each warm-starts from the last one it made
        return store, store.writing("volumes")["data"], (plan, frames), Series.of(frames, job.settings)

    store, data, (plan, frames), series = worker_state(job.token, build)
    out, made = [], []
    # frame A is written while frame B is reconstructed; both are written when the task returns
    with WriteBehind() as writer:
        for f in (0, 1):
            res = _reconstruct_frame(frames, store, job.cameras, pair, f, data=data, series=series,
                                     flats=job.flats)
            if res.slabs == 1:  # a volume in slabs is in the store already
                writer.submit(data.__setitem__, (pair, f), res.volume)
            made.append(res)
            out.append(_summary(res))
    if series is not None:
        series.measured(made, frames.device)
    return PairDone(out, plan)


def _ranges(pairs: list[int]) -> list[str]:
    """Consecutive pairs as ``START:STOP`` ranges (``--pair-range``'s form; one pair as its number)."""
    out: list[str] = []
    for p in pairs:
        if out and out[-1][1] == p:
            out[-1][1] = p + 1
        else:
            out.append([p, p + 1])
    return [f"{a}" if b == a + 1 else f"{a}:{b}" for a, b in out]


def _refuse_lost(store: RunStore, chosen: list[int], cameras: list[str], option: str) -> None:
    """A one-line :class:`UsageError` before anything is computed when a chosen pair lost a
    frame of one of ``cameras`` while recording (``drops/``), naming the ranges of whole pairs
    that ``option`` can reconstruct instead."""
    asked = set(chosen)
    lost = [d for d in store.drops() if d["camera"] in cameras and int(d["pair"]) in asked]
    if not lost:
        return
    bad = sorted({int(d["pair"]) for d in lost})
    whole = _ranges([p for p in chosen if p not in set(bad)])
    shown = ", ".join(map(str, bad[:6])) + (f" and {len(bad) - 6} more" if len(bad) > 6 else "")
    if not whole:
        way = "no pair asked is whole; choose other pairs, or record the run again"
    else:
        more = " ..." if len(whole) > 3 else ""
        add = " (the same settings add to the same volumes)" if len(whole) > 1 else ""
        way = "reconstruct the whole pairs with " + ", then ".join(f"{option} {r}" for r in whole[:3]) + more + add
    raise UsageError(f"{store.path}: pair(s) {shown} lost a frame while recording ({lost[0]['camera']} pair "
                     f"{lost[0]['pair']}: {lost[0]['reason']}) and cannot be reconstructed; {way}")


def reconstruct_run(store: RunStore, settings: ReconSettings, *, pvr: Sequence[float] | None = None,
                    margin_mm: Sequence[float] = (0.0, 0.0, 0.0), pairs: slice | None = None,
                    cameras: Sequence[str] | None = None, device: str | None = None,
                    progress: bool = True, rig: Rig | None = None,
                    calibration: dict[str, Any] | None = None, skip_done: bool = False,
                    client: Any = None, option: str = "--pair-range", slabs: int | str | None = None,
                    flats: dict[str, FlatField] | None = None, flat_field: dict[str, Any] | None = None,
                    protocol: str | None = None, warm_optional: bool | None = None,
                    subsets_optional: bool | None = None) -> list[ReconResult]:
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

    ``flats`` (per camera, :func:`lfpiv.jobs.calibrate.flat_fields`) corrects every raw frame by
    the calibration's dark and white images before it is reconstructed, its masked pixels left out
    of the operator; ``flat_field`` says which calibration that is and is kept in the ``volumes/``
    settings. None: the raw frames as they are (one background level per camera).

    ``protocol`` names the protocol the settings are of (:data:`lfcore.reconstruct.PROTOCOLS`), kept
    in the ``volumes/`` settings (None: settings given as they are). ``warm_optional``: the settings'
    warm start is the protocol's, left out where the volumes are reconstructed in depth slabs
    (None: where ``protocol`` warm-starts and ``--warm-start`` was not asked for, so never without a
    protocol). With a ``client`` and ``slabs`` ``"auto"`` (each worker plans its slabs by its own
    memory) that is decided once, before the pairs are sent out: left out for every frame if any worker
    plans depth slabs, else kept and required of every worker. ``subsets_optional`` is accepted and
    unused (depth slabs run the settings' ordered subsets, its coarse grid and line-of-sight first
    iterations as the volumes in memory do).

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
    # by default every recorded pair: a run cut short (Ctrl-C, a fault) has fewer than it planned
    chosen, names = recorded_pairs(store, pairs, cameras, rig=rig, option=option)
    _refuse_lost(store, chosen, names, option)
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
    if warm_optional is None:
        warm_optional = bool(protocol and PROTOCOLS.get(protocol, {}).get("warm_start"))
    if subsets_optional is None:
        subsets_optional = bool(protocol and PROTOCOLS.get(protocol, {}).get("subsets", 1) > 1)
    plan, frames = (_operator(cams, grid, settings, device, slabs, warm_optional, subsets_optional)
                    if client is None else (None, None))
    if frames is not None and frames.in_slabs and settings.warm_start:
        settings = replace(settings, warm_start=False)  # the protocol's, left out: whole volumes only
    elif frames is None and settings.warm_start and warm_optional and str(slabs).isdigit() and int(slabs) > 1:
        settings = replace(settings, warm_start=False)  # so on the workers' depth slabs too (recorded so)
    elif frames is None and settings.warm_start and warm_optional and slabs == "auto":
        # each worker plans its slabs by its own memory: decided once here, from what every worker
        # plans now, so that what volumes/ records is what every worker runs
        split = _workers_in_slabs(client, cams, grid, settings, device)
        if split:
            log.info(f"--slabs auto: worker {split[0]} reconstructs in depth slabs, where the warm start is not "
                     "run: every frame starts uniform (recorded so)")
            settings = replace(settings, warm_start=False)
        else:  # every worker in memory: warm-started, and a worker that needs slabs later refuses in one line
            warm_optional = False
    # where the weights lived does not change a volume, so it does not make volumes/ a different set
    kept = {k: v for k, v in settings.as_dict().items() if k != "weight_storage"}
    if not settings.warm_start:  # no frame warm-started: the predictor's source changes nothing
        kept["warm_predictor"] = ReconSettings.warm_predictor
    meta = {**kept, "pvr": list(pvr or rig.volume.pvr), "margin_mm": list(margin_mm),
            "cameras": names, "calibration": calibration, "flat_field": flat_field if flats else None,
            "protocol": protocol}
    if not flats and any(not is_pinhole(c) for c in cams):
        log.info("the raw frames are not flat-field corrected (no dark or white images given: one background "
                 "level per camera, the lenses' and micro-images' vignetting and any dust left in)")

    def differences(g: Any) -> list[str]:
        try:
            old = _recorded(store.volume_attrs(group=g)["settings"]) if "data" in g else {}
        except RunStoreError:  # for a note: the attributes of an unfinished replacement, damaged
            return ["attributes"]
        changed = [k for k in sorted(set(old) | set(meta)) if old.get(k) != meta.get(k) and k not in NAMES_ONLY]
        return (["voxel grid"] if "data" in g and store.grid_of(g) != grid else []) + changed

    results: list[ReconResult] = []

    def written(p: int, done: PairDone) -> None:
        _record(store, [(p, 0), (p, 1)], done.results, done.plan)
        results.extend(done.results)

    def remote(into: str) -> tuple[Any, ReconJob]:
        from lfpiv.batch import new_token

        return reconstruct_pair_task, ReconJob(path=str(Path(store.path).resolve()), rig=rig, cameras=tuple(names),
                                               grid=grid, settings=settings, device=device, token=new_token(),
                                               writer=store.writer_token, into=into, slabs=slabs, flats=flats,
                                               warm_optional=warm_optional, subsets_optional=subsets_optional)

    run_pairs(store, "volumes", chosen, matches=lambda g: _made_with(store, g, grid, meta), differences=differences,
              create=lambda: store.create_volumes(grid, method=settings.method, settings=meta), skip_done=skip_done,
              here=lambda todo: _reconstruct_here(frames, plan, store, names, todo, settings, results, progress,
                                                  flats),
              remote=remote, client=client, on_done=written, desc="reconstructing", progress=progress,
              postfix=lambda p, done: _shown(p, done.results),
              kept=lambda: f"the {len(results)} volume(s) written before are kept" if results else "")
    return results


def _reconstruct_here(frames: FrameReconstructor | SlabReconstructor, plan: Plan, store: RunStore,
                      names: Sequence[str], chosen: list[int], settings: ReconSettings, results: list[ReconResult],
                      progress: bool, flats: dict[str, FlatField] | None = None) -> None:
    """Reconstruct both frames of the ``chosen`` pairs in this process, adding to ``results``;
    each volume is written (and recorded) while the next frame is reconstructed."""
    series = Series.of(frames, settings)
    its = max(settings.iterations, 1)
    # with warm starts, every frame B (after the first pair's, by the last pair's predictor) takes the warm count
    cold_b = 0 if series is None or series.predictor == OWN_PAIR else 1
    warm_its = its if series is None else max(settings.warm_count, 1)
    total = len(chosen) * 2 * its if series is None else len(chosen) * its + cold_b * its + (
        len(chosen) - cold_b) * warm_its
    left = total  # the iterations planned for the frames not yet made
    with (WriteBehind() as writer,
          tqdm(total=total, unit="it", disable=not progress, desc="reconstructing", leave=False) as bar):
        for p in chosen:
            made = []
            for f in (0, 1):
                # a slab-by-slab frame can spend long stages (each slab's elimination) without an
                # iteration: the progress line says which ended last
                res = _reconstruct_frame(frames, store, names, p, f, bar.update,
                                         log=lambda line, p=p, f=f: bar.set_postfix_str(f"pair {p} {'AB'[f]}: {line}"),
                                         series=series, flats=flats)
                # the volume, then its bookkeeping and operator figures, on the writer's thread
                writer.submit(_write_frame, store, p, f, res, plan)
                results.append(_summary(res))
                made.append(res)
                if res.iterations == 0:
                    bar.update(1)
                # a frame B planned warm that started uniform (no predictor) runs the cold count: the bar grows
                left -= warm_its if f == 1 and series is not None and (p != chosen[0] or not cold_b) else its
                if bar.n + left > bar.total:
                    bar.total = bar.n + left
                    bar.refresh()
                bar.set_postfix(_shown(p, [res]))
            if series is not None:
                series.measured(made, frames.device)


def _shown(pair: int, res: Sequence[ReconResult]) -> dict[str, str]:
    """What the progress bar shows of the last frame of ``res`` (pair ``pair``): its active
    voxels, projector, operator memory, milliseconds per iteration, the iterations it ran, the
    voxels left at the end and why it stopped."""
    last = res[-1]
    return {"pair": str(pair), "active": f"{last.active_fraction:.2%}", "projector": last.projector,
            "mem": f"{last.weight_bytes / 2**20:.1f}MiB", "ms_it": f"{last.ms_per_iteration:.1f}",
            "its": str(last.iterations), "left": f"{last.final_voxels:,}", "stop": last.stopped}


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
            and _matching(_recorded(store.volume_attrs(group=group)["settings"])) == _matching(meta))


#: Recorded settings that name the others rather than change the volumes: volumes made by the same
#: settings under another protocol's name (or none, before protocols were recorded) are added to.
NAMES_ONLY = ("protocol",)


def _matching(settings: dict[str, Any]) -> dict[str, Any]:
    """The recorded settings that make volumes a different set (all but :data:`NAMES_ONLY`)."""
    return {k: v for k, v in settings.items() if k not in NAMES_ONLY}


def _recorded(settings: dict[str, Any]) -> dict[str, Any]:
    """Volumes' recorded settings, with those of settings added since at the value they had
    (volumes made before ``projector`` was recorded were made by ``auto``'s stored weights, those
    before ``prune`` with every voxel to the last iteration, those before ``warm_start`` from a uniform
    start, those before ``warm_predictor`` warm-started (if at all) by the last pair's field, those
    before ``los_iterations`` on DRT weights from the first iteration, those before ``flat_field`` from
    uncorrected frames, those before ``subsets`` by the plain simultaneous form,
    those before ``stop_tolerance`` with a fixed count, those before ``coarse`` with the whole grid
    eliminated, those before ``coarse_prune`` pruned at ``prune`` after the coarse grid too, those before
    ``lit_hysteresis`` with the plain lit mask, those before ``handover_share`` on line-of-sight weights to the
    end under MLOS-MART, and those before ``protocol`` by settings given one by one)."""
    # volumes warm-started before warm_predictor was recorded were started by the last pair's field
    warm_predictor = "last" if settings.get("warm_start") else ReconSettings.warm_predictor
    return {"projector": "auto", "prune": 0.0, "prune_every": 10, "warm_start": False, "warm_iterations": None,
            "warm_predictor": warm_predictor, "los_iterations": 0, "flat_field": None, "subsets": 1,
            "subset_halving": SUBSET_HALVING,
            "stop_tolerance": 0.0, "stop_voxels": STOP_VOXELS, "stop_every": 10, "coarse": 1,
            "coarse_iterations": COARSE_ITERATIONS, "coarse_prune": 0.0, "lit_hysteresis": None, "protocol": None,
            "handover_share": 0.0, "handover_at": 20, "handover_residual": None, **settings}
