"""The planner: how a volume is reconstructed, decided in one place, with its reasons.

From the rig's cameras, the box, the settings, the device and its memory, :func:`plan_reconstruction`
chooses

- which **operator** applies the projection (:mod:`lfcore.operator`): ray-traced DRT weights,
  line-of-sight weights, the matrix-free templates' images or the templates themselves, a per-frame
  choice between them (``projector = "auto"``), pinhole cameras' or a mixed rig's weights;
- whether a **weight cache** keeps each voxel's rows across the frames of a stream;
- how many **depth slabs** the box is reconstructed in (:mod:`lfcore.slabs`),

and says why (:attr:`Plan.reasons`: ``lfpiv reconstruct -v`` prints them, ``volumes/`` records
them and ``lfpiv info`` shows them). :func:`build_reconstructor` then makes what the plan says,
and :func:`operator_source` gives a stream of frames their operators. This is the one module that
imports the concrete projectors and operators (:class:`~lfcore.projector.LightFieldProjector`,
:class:`~lfcore.pinhole_projector.PinholeProjector`, :class:`~lfcore.pinhole_projector.JointProjector`,
:class:`~lfcore.weight_build.Weights`, :class:`~lfcore.matrix_free.TemplateOperator`,
:class:`~lfcore.weight_cache.WeightCache`); every other module sees the protocols of
:mod:`lfcore.operator` (an import contract in ``pyproject.toml`` keeps it so).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lfcore import coarse as coarse_grids
from lfcore.device import MemoryBudgetError, available_bytes, resolve_device
from lfcore.matrix_free import DrtTemplates, TemplateOperator, template_count
from lfcore.operator import (
    TEMPLATE_IMAGES,
    MatrixFreeUnsupported,
    Operator,
    Projector,
    from_templates,
    max_planes,
)
from lfcore.pinhole_projector import PINHOLE_METHODS, JointProjector, PinholeProjector
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import COARSE_METHODS, WEIGHTS, FrameReconstructor, ReconSettings
from lfcore.rig import is_pinhole
from lfcore.slabs import SlabReconstructor, plan_slabs, slab_halo, slabs_for_budget
from lfcore.volume import VolumeGrid
from lfcore.weight_build import BYTES_PER_WEIGHT
from lfcore.weight_cache import WeightCache

__all__ = ["BYTES_PER_BOX_VOXEL", "IMAGE_SHARE", "PINHOLE_METHODS", "SLAB_SHARE", "TEMPLATE_TRACES", "AutoSource",
           "Plan", "PlanError", "TemplateSource", "WeightSource", "asked_slabs", "build_reconstructor",
           "cache_serves", "camera_kind", "coarse_runs", "default_method", "frame_stages", "new_cache",
           "operator_source", "plan_reconstruction", "projector_for", "unsupported_method"]

#: Bytes per voxel of the box that the elimination pass and the dense result need at once in memory.
BYTES_PER_BOX_VOXEL = 16
#: Of the memory free, the share ``--slabs auto`` gives one depth slab's buffers (the rest is left to
#: the active voxels' weights and intensities, which every slab keeps).
SLAB_SHARE = 0.5
#: ``projector = "auto"``'s costs of the templates' images, in voxels' DRT tracings. A template
#: (one voxel's rays, traced finely across its phase bin) costs about as much as this many voxels'
#: tracing (4.7 measured on the Mc crop's optics, at most 7 on the tiny rig's, CPU) ...
TEMPLATE_TRACES = 8.0
#: ... and a voxel's image, merged from its templates' spots, this share of its own tracing
#: (0.27 on the Mc crop, CPU).
IMAGE_SHARE = 0.3


class PlanError(ValueError):
    """A reconstruction that cannot be planned as asked: one line naming the problem and the fix."""


# --- the cameras and their methods ----------------------------------------------------------------
def camera_kind(cameras: Sequence) -> str:
    """``"pinhole"`` where every camera is a pinhole one, ``"joint"`` for a mix of both kinds,
    ``"light-field"`` otherwise (the :attr:`lfcore.operator.Projector.kind` of their projector)."""
    cameras = list(cameras)
    tomo = [c for c in cameras if is_pinhole(c)]
    if not tomo:
        return "light-field"
    return "joint" if len(tomo) < len(cameras) else "pinhole"


def projector_for(cameras: Sequence, grid: VolumeGrid, *, sub_apertures: int | None = None,
                  device: str | None = None) -> Projector:
    """The projector of ``cameras``' kind (:func:`camera_kind`): a
    :class:`~lfcore.projector.LightFieldProjector` for light-field cameras, a
    :class:`~lfcore.pinhole_projector.PinholeProjector` for pinhole ones and a
    :class:`~lfcore.pinhole_projector.JointProjector` for a mix of both."""
    cameras = tuple(cameras)
    kind = camera_kind(cameras)
    if kind == "light-field":
        return LightFieldProjector(cameras, grid, sub_apertures=sub_apertures, device=device)
    if kind == "joint":
        return JointProjector(cameras, grid, sub_apertures=sub_apertures, device=device)
    return PinholeProjector(cameras, grid, device=device)


def default_method(cameras: Sequence) -> str:
    """The default reconstruction of ``cameras``: ``mlos-smart`` where they are all pinhole
    cameras, ``drt-mart`` otherwise (a mixed rig's light-field cameras by DRT-MART's weights, its
    pinhole cameras by their line of sight, jointly)."""
    cameras = list(cameras)
    return "mlos-smart" if cameras and camera_kind(cameras) == "pinhole" else "drt-mart"


def unsupported_method(cameras: Sequence, method: str) -> str | None:
    """The name of a pinhole camera that rules ``method`` out (pinhole cameras alone take only
    :data:`~lfcore.pinhole_projector.PINHOLE_METHODS`), or None where ``method`` can reconstruct
    ``cameras``."""
    tomo = [c.name for c in cameras if is_pinhole(c)]
    if tomo and len(tomo) == len(cameras) and method not in PINHOLE_METHODS:
        return tomo[0]
    return None


# --- the operator sources: where a stream's frames get their operators -----------------------------
Budget = Callable[[], int]


class WeightSource:
    """Stored weights built by the projector (:meth:`lfcore.operator.Projector.operator`), from a
    weight cache where one serves and they fit: ray-traced DRT weights, line-of-sight weights
    (partly on the fly where ``settings.weight_storage`` allows), pinhole or joint weights.

    Parameters
    ----------
    projector
        The cameras and grid.
    settings
        The method (its weight kind, :data:`lfcore.reconstruct.WEIGHTS`), form and weight storage.
    cache
        Weights kept across frames (:class:`~lfcore.weight_cache.WeightCache`), or None.
    """

    templates = None

    def __init__(self, projector: Projector, settings: ReconSettings, *, cache: WeightCache | None = None) -> None:
        self.projector = projector
        self.settings = settings
        self.cache = cache

    def operator(self, voxels, *, budget: Budget, host: np.ndarray | None = None) -> Operator:
        """The weights of ``voxels``: the cache's rows where it holds this kind and they fit (the
        baseline's, which cover the whole box, are built per frame), else built within ``budget()``
        bytes. ``host``: ``voxels`` on the host where the caller has them."""
        s = self.settings
        kind = WEIGHTS[s.method]
        storage = "stored" if kind == "drt" or s.form == "sequential" else s.weight_storage
        cache = self.cache
        if cache is not None and cache.method == kind and s.method != "mart" and storage != "on-the-fly":
            try:
                return cache.weights(voxels, host=host)
            except MemoryBudgetError:
                if storage == "stored":
                    raise
        return self.projector.operator(voxels, method=kind, budget_bytes=budget(), storage=storage)

    def held_bytes(self, op: Operator) -> int:
        """The cache's pool (a second copy of every traced row) and its elimination table."""
        return 0 if self.cache is None else int(self.cache.device_bytes)

    def prepare(self, *, budget: Budget) -> None:
        """Nothing to build ahead of the first frame."""


class TemplateSource:
    """The matrix-free templates (:mod:`lfcore.matrix_free`), built on the first frame and kept:
    their images of a frame's voxels stored where they fit (``"template images"``), else applied in
    every iteration (``"templates"``), as ``settings.weight_storage`` allows.

    Parameters
    ----------
    projector
        A light-field projector (others have no templates: :class:`~lfcore.operator.MatrixFreeUnsupported`).
    settings
        The weight storage.
    templates
        The templates built already for the projector's box (on another of its depth slabs), used
        instead of building them (:meth:`lfcore.matrix_free.DrtTemplates.on`).
    """

    def __init__(self, projector: Projector, settings: ReconSettings, *,
                 templates: DrtTemplates | None = None) -> None:
        self.projector = projector
        self.settings = settings
        self.templates = None if templates is None else templates.on(projector)

    def operator(self, voxels, *, budget: Budget, host: np.ndarray | None = None,
                 storage: str | None = None) -> Operator:
        """The templates' operator of ``voxels``, the templates built on first use within ``budget()``.

        With ``storage`` (default: ``settings.weight_storage``) ``"auto"`` the templates' images of
        the voxels are stored (:meth:`TemplateOperator.expanded <lfcore.matrix_free.TemplateOperator.expanded>`:
        no ray tracing, iterations at the stored weights' speed) where they fit beside the templates,
        and applied from the templates in every iteration where they do not; ``"stored"``: stored or a
        :class:`~lfcore.device.MemoryBudgetError`; ``"on-the-fly"``: always applied from the templates.
        """
        n = int(voxels.shape[0])
        if self.templates is None:
            self.templates = DrtTemplates(self.projector, budget_bytes=budget())
        mf = TemplateOperator(self.templates, voxels)
        storage = self.settings.weight_storage if storage is None else storage
        if storage == "on-the-fly":
            return mf
        room = budget() - self.templates.nbytes
        # the raw entries (before their merge) bound the stored images from above: where even
        # those would not fit, go on without trying
        if storage == "auto" and BYTES_PER_WEIGHT * mf.entries_per_voxel() * n > room:
            return mf
        try:
            return mf.expanded(budget_bytes=room)
        except MemoryBudgetError:
            if storage == "stored":
                raise
            return mf

    def held_bytes(self, op: Operator) -> int:
        """The templates, held beside their images (an operator of the templates counts them itself)."""
        return self.templates.nbytes if op.kind == TEMPLATE_IMAGES and self.templates is not None else 0

    def prepare(self, *, budget: Budget) -> None:
        """Build the templates now (the live path: not in the first pair's time)."""
        if self.templates is None:
            self.templates = DrtTemplates(self.projector, budget_bytes=budget())


class AutoSource:
    """``projector = "auto"`` for DRT-MART's simultaneous form: per frame, the templates' images
    where they cost less to build than tracing the voxels the weight cache lacks
    (:meth:`templates_pay`) and fit in memory, else the stored traced weights, and the templates
    applied in every iteration where neither fits.

    Parameters
    ----------
    weights, templates
        The two sources it chooses between.
    """

    def __init__(self, weights: WeightSource, templates: TemplateSource) -> None:
        self._weights = weights
        self._templates = templates
        self._n_templates: int | None = None  # how many there would be (0: the cameras have none), once counted
        self._images_fit = True  # False once the templates' images were found too big for the memory

    @property
    def templates(self) -> DrtTemplates | None:
        """The matrix-free templates held for the next frames (None until built, or let go)."""
        return self._templates.templates

    def templates_pay(self, voxels, *, host: np.ndarray | None = None) -> bool:
        """Whether the templates' images serve ``voxels`` ((n,) int32 on the device; ``host``: the
        same on the host, where the caller has them): where building them (the templates once per
        run, :data:`TEMPLATE_TRACES` voxels' tracing each, and the images, :data:`IMAGE_SHARE` of a
        tracing per voxel) costs less than tracing the voxels the weight cache lacks. So a frame with
        many more active voxels than templates (the Mc crop: 385,000-472,000 against 22,757) takes the
        images, a small one (the tiny rig's 26,000 against 4,180) its traced weights. False where the
        cameras have no templates, and once an earlier frame's images did not fit the memory.
        """
        if not self._images_fit:
            return False
        if self._n_templates is None:
            try:
                self._n_templates = template_count(self._templates.projector)
            except MatrixFreeUnsupported:
                self._n_templates = 0
        if self._n_templates == 0:
            return False
        n = int(voxels.shape[0])
        cache = self._weights.cache
        traced = n if cache is None or cache.method != "drt" else cache.uncached(voxels if host is None else host)
        templates = 0.0 if self.templates is not None else TEMPLATE_TRACES * self._n_templates
        return traced > templates + IMAGE_SHARE * n

    def operator(self, voxels, *, budget: Budget, host: np.ndarray | None = None) -> Operator:
        """The frame's operator, as the class says."""
        if host is None and self._weights.cache is not None:
            host = voxels.numpy()  # one copy for the cache's two looks
        if self.templates_pay(voxels, host=host):
            try:  # the images stored, or the traced weights (stored iterate 8-12x faster)
                return self._templates.operator(voxels, budget=budget, storage="stored")
            except MatrixFreeUnsupported:
                pass
            except MemoryBudgetError:  # the images do not fit beside the templates: their room to the weights,
                self._templates.templates = None  # and no more tries on the next frames (a run's are alike)
                self._images_fit = False
        try:
            return self._weights.operator(voxels, budget=budget, host=host)
        except MemoryBudgetError:
            try:
                return self._templates.operator(voxels, budget=budget)
            except (MatrixFreeUnsupported, MemoryBudgetError):
                pass
            raise

    def held_bytes(self, op: Operator) -> int:
        """What the source that made ``op`` holds beside it."""
        return self._templates.held_bytes(op) if from_templates(op) else self._weights.held_bytes(op)

    def prepare(self, *, budget: Budget) -> None:
        """Nothing: whether the templates serve is decided per frame."""


def operator_source(projector: Projector, settings: ReconSettings, *, cache: WeightCache | None = None,
                    templates: DrtTemplates | None = None) -> WeightSource | TemplateSource | AutoSource:
    """Where the frames of ``projector`` get their operators, for ``settings.projector``:
    ``"matrix-free"``: the templates (:class:`TemplateSource`); ``"auto"`` for DRT-MART's
    simultaneous form on light-field cameras: the per-frame choice (:class:`AutoSource`); else the
    stored weights (:class:`WeightSource`, from ``cache`` where it serves)."""
    weights = WeightSource(projector, settings, cache=cache)
    if settings.projector == "matrix-free":
        return TemplateSource(projector, settings, templates=templates)
    if (settings.projector == "auto" and WEIGHTS[settings.method] == "drt" and settings.form == "simultaneous"
            and projector.kind == "light-field"):
        return AutoSource(weights, TemplateSource(projector, settings, templates=templates))
    return weights


# --- the plan ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plan:
    """How a run's volumes are reconstructed, and why.

    Attributes
    ----------
    device
        The Warp device.
    cameras
        ``"light-field"``, ``"pinhole"`` or ``"joint"`` (:func:`camera_kind`).
    operator
        What applies the projection (:data:`lfcore.operator.ALL_KINDS`, or ``"auto"``: per frame
        the template images or the traced weights).
    cache
        Whether a weight cache keeps each voxel's rows across the frames.
    slabs
        Depth slabs each volume is reconstructed in (1: in memory).
    reasons
        One sentence per choice: why.
    stages
        What each frame runs, in order, one phrase each (:func:`frame_stages`): the coarse grid, the
        line-of-sight iterations first, the ordered subsets, the stopping rule or the fixed count. Empty
        in plans recorded before it was.
    """

    device: str
    cameras: str
    operator: str
    cache: bool
    slabs: int
    reasons: tuple[str, ...] = field(default=())
    stages: tuple[str, ...] = field(default=())

    def summary(self) -> str:
        """``"traced weights on cpu, weight cache, in memory"``: the plan in one line."""
        where = "in memory" if self.slabs == 1 else f"in {self.slabs} depth slabs"
        return f"{self.operator} on {self.device}, {'weight cache' if self.cache else 'no weight cache'}, {where}"

    def describe_stages(self) -> str:
        """``"coarse-to-fine elimination on a 3x coarser grid, ...; at most 400 iterations by the stopping
        rule"``: what each frame ran, in one line (``""`` for a plan recorded without its stages)."""
        return "; ".join(self.stages)

    def lines(self) -> list[str]:
        """The plan, its stages and its reasons, one line each (what ``lfpiv reconstruct -v`` logs)."""
        stages = [f"stages: {self.describe_stages()}"] if self.stages else []
        return [f"plan: {self.summary()}", *stages, *(f"  {r}" for r in self.reasons)]

    def as_dict(self) -> dict[str, Any]:
        """The plan as the run store records it (``volumes/`` attribute ``plan``)."""
        return {"device": self.device, "cameras": self.cameras, "operator": self.operator, "cache": self.cache,
                "slabs": self.slabs, "reasons": list(self.reasons), "stages": list(self.stages)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Plan:
        """The plan :meth:`as_dict` recorded.

        Raises
        ------
        PlanError
            ``d`` is not such a record (a damaged or edited attribute).
        """
        try:
            return cls(device=str(d["device"]), cameras=str(d["cameras"]), operator=str(d["operator"]),
                       cache=bool(d["cache"]), slabs=int(d["slabs"]), reasons=tuple(str(r) for r in d["reasons"]),
                       stages=tuple(str(r) for r in d.get("stages", ())))
        except (KeyError, TypeError, ValueError):
            raise PlanError(f"not a recorded plan: {d!r}") from None


def cache_serves(cameras: str, settings: ReconSettings) -> tuple[bool, str]:
    """Whether a weight cache serves a stream of frames of ``cameras`` (:func:`camera_kind`) with
    ``settings``, and why in one sentence.

    A voxel's weights depend on the cameras and the grid only, so a cache traces each voxel once
    over a run where elimination keeps overlapping voxels frame after frame. It does not serve the
    MART baseline (its weights cover the whole box), weights made on the fly, or pinhole cameras
    alone (a handful of weights per voxel, built per frame in less than the iterations take).
    """
    if settings.method == "mart":
        return False, "no weight cache: the MART baseline's weights cover the whole box and are built per frame"
    if settings.weight_storage == "on-the-fly":
        return False, "no weight cache: the weights are made on the fly (--weight-storage on-the-fly)"
    if cameras == "pinhole":
        return False, ("no weight cache: pinhole cameras have a handful of weights per voxel, built per frame in "
                       "less time than the iterations take")
    if settings.projector == "matrix-free":
        return True, ("weight cache: its elimination table only (the templates' operator traces no rows; elimination "
                      "looks the checked pixels up)")
    return True, "weight cache: each voxel's rows are traced once, on the first frame that keeps it"


def _operator_choice(cameras: str, settings: ReconSettings) -> tuple[str, str]:
    """What applies the projection (:attr:`Plan.operator`) and why."""
    kind = WEIGHTS[settings.method]
    if cameras == "pinhole":
        return "pinhole weights", f"{settings.method}: pinhole cameras' line-of-sight weights through their models"
    if cameras == "joint":
        return "joint weights", (f"{settings.method} on a mixed rig: the light-field cameras' {kind} weights and the "
                                 "pinhole cameras' line of sight, joined row by row")
    if kind == "los":
        return "line-of-sight weights", f"{settings.method}: the line-of-sight weights of the MART baseline"
    if settings.projector == "matrix-free":
        what = {"stored": "template images", "on-the-fly": "templates"}.get(settings.weight_storage,
                                                                              "template images or templates")
        return what, ("--projector matrix-free: the templates per depth and lenslet phase, their images of the "
                      "active voxels stored" + {"stored": "", "on-the-fly": " nowhere: applied in every iteration"}.get(
                          settings.weight_storage, " where they fit, else the templates applied in every iteration"))
    if settings.projector == "auto" and settings.form == "simultaneous":
        return "auto", ("--projector auto: per frame, the templates' images where building them costs less than "
                        "tracing the voxels the cache lacks and they fit, else traced weights (the templates applied "
                        "where neither fits)")
    why = "--projector stored" if settings.projector == "stored" else "the sequential form needs stored weights"
    return "traced weights", f"{why}: ray-traced DRT weights, stored"


def asked_slabs(slabs: int | str | None, nz: int) -> int | None:
    """The depth slabs ``slabs`` asks for over a box ``nz`` voxels deep: 1 for None (not given),
    None for ``"auto"`` (the planner chooses from the memory free), else the number, checked.

    Raises
    ------
    PlanError
        Not a whole number, or not from 1 to ``nz``.
    """
    if slabs is None:
        return 1
    if slabs == "auto":
        return None
    try:
        n = int(slabs)
    except (TypeError, ValueError):
        raise PlanError(f"--slabs: expected a whole number of slabs or auto, got {slabs!r}") from None
    if not 1 <= n <= nz:
        raise PlanError(f"--slabs {n}: the box is {nz} voxels deep; give from 1 to {nz} slabs, or auto")
    return n


def plan_reconstruction(cameras: Sequence, grid: VolumeGrid, settings: ReconSettings, *, device: str | None = None,
                        slabs: int | str | None = None, free_bytes: int | None = None, can_split: bool = True) -> Plan:
    """How to reconstruct ``grid`` from ``cameras`` with ``settings`` on ``device``.

    Parameters
    ----------
    cameras
        The cameras reconstructed jointly.
    grid
        The box.
    settings
        The reconstruction's settings.
    device
        Warp device; None for the first GPU, else the CPU.
    slabs
        ``--slabs``: None (not given: in memory), a number of depth slabs, or ``"auto"`` (in memory
        where the box fits, else as many slabs as the memory needs, and always enough that each
        slab's voxels are numbered in int32).
    free_bytes
        The device's free memory; None: read now.
    can_split
        Whether the caller can reconstruct in depth slabs (False for the live path: in memory
        only, and its refusals do not suggest ``--slabs``).

    Returns
    -------
    Plan

    Raises
    ------
    PlanError
        A box that does not fit (one line with the fix), ``slabs`` out of range, or the sequential
        form asked to split.
    """
    device = resolve_device(device)
    kind = camera_kind(cameras)
    nz = grid.shape[0]
    need = BYTES_PER_BOX_VOXEL * grid.n_voxels
    free = available_bytes(device) if free_bytes is None else int(free_bytes)
    operator, why_operator = _operator_choice(kind, settings)
    reasons = [why_operator]
    asked = asked_slabs(slabs, nz)
    fits = need <= free and nz <= max_planes(grid)
    if asked is not None:
        n = asked
        if n > 1:
            reasons.append(f"--slabs {n}: {n} depth slabs, each numbering and holding its own voxels")
    elif fits:
        n = 1
        reasons.append(f"--slabs auto: in memory, the box's buffers ({need / 2**20:.1f} MiB) fit in the "
                       f"{free / 2**20:.1f} MiB free")
    else:
        if settings.form != "simultaneous":
            why = (f"needs {need / 2**30:.1f} GiB on {device}, more than it has free" if need > free else
                   "is more than int32 voxel indices number in one piece")
            raise PlanError(f"a box of {grid.n_voxels:,} voxels {why}, and the sequential form cannot be split into "
                            "depth slabs; use --form simultaneous or a coarser --pvr")
        try:
            # the coarse grid of coarse-to-fine elimination is eliminated in memory before the slabs
            # (where it runs: lfcore.reconstruct.coarse_applies, on light-field cameras' projector)
            coarse = settings.coarse if coarse_runs(kind, grid, settings) else 1
            n = slabs_for_budget(grid, int(SLAB_SHARE * free), halo=slab_halo(settings), coarse=coarse)
        except MemoryBudgetError as exc:
            raise PlanError(f"--slabs auto: {exc}") from None
        why = (f"its buffers ({need / 2**20:.1f} MiB) do not fit in the {free / 2**20:.1f} MiB free" if need > free
               else "it has more voxels than int32 indices number in one piece")
        reasons.append(f"--slabs auto: {n} depth slabs, since {why}")
    if n == 1:
        if need > free:
            hint = "" if slabs is not None or not can_split else ", or --slabs auto to reconstruct it in depth slabs"
            raise PlanError(f"a box of {grid.n_voxels:,} voxels needs {need / 2**30:.1f} GiB on {device}, more than it "
                            f"has free; use a coarser --pvr{hint}")
        if nz > max_planes(grid):
            fix = "use --slabs auto to reconstruct it in depth slabs, or a coarser --pvr" if can_split else \
                "use a coarser --pvr"
            raise PlanError(f"a box of {grid.n_voxels:,} voxels is more than int32 voxel indices number in one piece; "
                            f"{fix}")
    cache, why_cache = cache_serves(kind, settings)
    if n > 1 and cache:
        cache, why_cache = False, "no weight cache: each frame's slabs hold their own weights"
    reasons.append(why_cache)
    return Plan(device=device, cameras=kind, operator=operator, cache=cache, slabs=n, reasons=tuple(reasons),
                stages=frame_stages(kind, grid, settings, slabs=n))


def coarse_runs(cameras: str, grid: VolumeGrid, settings: ReconSettings) -> bool:
    """Whether frames of ``grid`` on cameras of kind ``cameras`` (:func:`camera_kind`) run coarse-to-fine
    elimination: as :func:`lfcore.reconstruct.coarse_applies` decides on their projector (DRT-MART's
    simultaneous form or MLOS-MART, light-field cameras alone, a box of at least :data:`lfcore.coarse.COARSE_MIN_VOXELS`
    voxels)."""
    s = settings
    return (s.coarse > 1 and s.method in COARSE_METHODS and s.form == "simultaneous" and cameras == "light-field"
            and grid.n_voxels >= coarse_grids.COARSE_MIN_VOXELS)


def frame_stages(cameras: str, grid: VolumeGrid, settings: ReconSettings, *, slabs: int = 1) -> tuple[str, ...]:
    """What each frame of ``grid`` runs with ``settings`` on cameras of kind ``cameras``
    (:func:`camera_kind`) in ``slabs`` depth slabs, in order, one phrase each (:attr:`Plan.stages`):
    the coarse-to-fine elimination where it runs (:func:`coarse_runs`; or why not, where asked for),
    the line-of-sight iterations first, MLOS-MART's hand-over to DRT weights (:func:`lfcore.reconstruct.hands_over`;
    in memory only), the ordered subsets, the warm start (never in depth slabs, which run the rest of the plan as
    in memory) and the stopping rule or the fixed count.
    """
    s = settings
    out: list[str] = []
    if s.coarse > 1 and s.method in COARSE_METHODS and s.form == "simultaneous":
        if coarse_runs(cameras, grid, s):
            then = f"; the fine grid's voxels pruned at {s.coarse_prune:.0%}" if s.coarse_prune and s.prune > 0 else ""
            out.append(f"coarse-to-fine elimination on a {s.coarse}x coarser grid ({s.coarse_iterations} line-of-sight "
                       f"iterations{then})")
        else:
            why = "cameras other than light-field ones" if cameras != "light-field" else \
                f"a box of fewer than {coarse_grids.COARSE_MIN_VOXELS:,} voxels"
            out.append(f"elimination on the whole grid (no coarse grid for {why})")
    if s.los_iterations:
        out.append(f"{s.los_iterations} iterations on line-of-sight weights, then DRT weights for the voxels still "
                   "bright")
    if s.handover_share and s.method == "mlos-mart" and s.form == "simultaneous" and slabs == 1:
        bound = f" while the residual is below {s.handover_residual:g}" if s.handover_residual else ""
        out.append(f"DRT weights for the voxels still bright where more than {s.handover_share:.0%} of them are left "
                   f"after {s.handover_at} iterations{bound} (cold frames)")
    if s.subsets > 1:
        out.append(f"{s.subsets} ordered subsets a pass")
    if s.warm_start and slabs == 1:
        by = "their own pair's" if s.warm_predictor == "own" else "the last pair's"
        out.append(f"frames B warm-started from frame A carried along {by} displacement, at most "
                   f"{s.warm_count} iterations")
    out.append(f"at most {s.iterations} iterations by the stopping rule" if s.stopping else
               f"{s.iterations} iterations")
    return tuple(out)


def new_cache(projector: Projector, *, method: str, checks: int | None = None) -> WeightCache:
    """A weight cache of ``projector``'s ``method`` (``"drt"`` or ``"los"``) weights
    (:class:`~lfcore.weight_cache.WeightCache`; ``checks`` as it takes them)."""
    return WeightCache(projector, method=method, checks=checks)


def build_reconstructor(plan: Plan, cameras: Sequence, grid: VolumeGrid, settings: ReconSettings, *,
                        checks: int | None = None) -> FrameReconstructor | SlabReconstructor:
    """What ``plan`` says: the projector of the cameras' kind on ``plan.device``, its weight cache
    where the plan has one (``checks``: its elimination table, as
    :class:`~lfcore.weight_cache.WeightCache` takes it), and the reconstructor of frames in memory
    (:class:`~lfcore.reconstruct.FrameReconstructor`) or in depth slabs
    (:class:`~lfcore.slabs.SlabReconstructor`), built once per stream.

    Raises
    ------
    PlanError
        Slabs the reconstructor refuses (too deep for int32 indices with their halo, or the
        sequential form).
    """
    projector = projector_for(cameras, grid, sub_apertures=settings.sub_apertures, device=plan.device)
    if plan.slabs > 1:
        try:
            return SlabReconstructor(projector, settings, slabs=plan_slabs(grid.shape[0], plan.slabs))
        except ValueError as exc:
            raise PlanError(f"--slabs: {exc}") from None
    cache = new_cache(projector, method=WEIGHTS[settings.method], checks=checks) if plan.cache else None
    return FrameReconstructor(projector, settings, cache=cache)
