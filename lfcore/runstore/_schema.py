"""The run store's attributes as validated models: what each attribute of the layout holds
(docs/reference/run-store.md), checked whenever it is read.

A run's ``zarr.json`` files are plain JSON that anyone may edit, and a disk or a copy may damage
them. Nothing read from them is trusted: every reader goes through :func:`validated` (one
attribute, or a whole group's), which turns a value of the wrong type, sign, length or range into
one line naming the store, the attribute, what it holds and what it should hold, as a
:class:`~lfcore.runstore.RunStoreError`; :func:`problems` lists every such line of a group for
:meth:`lfcore.runstore.RunStore.verify`.

Numbers are strict: ``"0.002"`` is text, not a time, and ``true`` is not a count. Attributes a
layout added later (``volumes_id``, ``operator``, ``plan``, the coordinate arrays' companions)
are optional, so stores made before them read as before; attributes the layout does not name are
kept, unchecked.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from lfcore.flows import FLOW_NAMES
from lfcore.runstore._common import STATES, RunStoreError

__all__ = ["GROUPS", "ParticlesAttrs", "RootAttrs", "TimingAttrs", "TruthAttrs", "VectorsAttrs", "VolumesAttrs",
           "describe", "problems", "validated"]

# --- the types the attributes are made of --------------------------------------------------
PositiveS = Annotated[float, Field(gt=0, allow_inf_nan=False)]
PositiveNumber = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Count = Annotated[int, Field(ge=0)]
Pairs = list[Count]


def _three(item: Any) -> Any:
    return Annotated[list[item], Field(min_length=3, max_length=3)]


class _Attrs(BaseModel):
    """Strict (no text read as a number, no ``true`` as a count), frozen; attributes the layout
    does not name are kept as they are."""

    model_config = ConfigDict(strict=True, frozen=True, extra="allow", populate_by_name=True)


class TimingAttrs(_Attrs):
    """The root attribute ``timing``: the run's timing plan (a recorded run's adds what the pulse
    generator read back, ``planned``, ``pulses``, ...)."""

    dt_s: PositiveS | None = Field(None, description="a positive, finite time in s (frame A to frame B)")
    rate_hz: PositiveNumber | None = Field(None, description="a positive, finite pair rate in Hz, or null where "
                                                              "unknown")
    planned: dict[str, Any] | None = Field(None, description="a table (the timing asked for)")


class SourceAttrs(_Attrs):
    """One source file of an imported run."""

    path: str = Field(description="the text of a file's path")
    size: Count = Field(description="a number of bytes (a whole number from 0)")
    crc32c: str | None = Field(None, description="a CRC32C as hexadecimal text")
    sha256: str | None = Field(None, description="a SHA-256 as hexadecimal text")


class ImportAttrs(_Attrs):
    """The root attribute ``import`` of an imported run: its plan and every source file."""

    plan: dict[str, Any] = Field(description="a table (the layout, cameras and checksum of the import)")
    sources: list[SourceAttrs] = Field(description="a list of tables (path, size, checksum)")


class RootAttrs(_Attrs):
    """The root group's attributes."""

    format: Literal["lfpiv-run"] = Field(description="the text 'lfpiv-run'")
    format_version: Annotated[int, Field(ge=1)] = Field(1, description="a layout version (a whole number from 1)")
    rig: dict[str, Any] = Field(description="a table (the rig as loaded)")
    timing: TimingAttrs = Field(description="a table of the run's timing (dt_s, rate_hz, ...)")
    software_version: str | None = Field(None, description="the text of an lfpiv version")
    created: str | None = Field(None, description="a UTC time as text")
    state: Literal[STATES] = Field(description=f"one of {', '.join(STATES)}")  # type: ignore[valid-type]
    committed_pairs: Count = Field(description="a number of pairs (a whole number from 0)")
    hardware: str | None = Field(None, description="text ('sim', 'real' or 'import')")
    abort_reason: str | None = Field(None, description="text (why the run stopped)")
    import_: ImportAttrs | None = Field(None, alias="import", description="a table (plan and sources)")


class OperatorAttrs(_Attrs):
    """``volumes/`` attribute ``operator``: what applied the reconstruction operator."""

    projector: str | None = Field(None, description="text (stored, matrix-free, or both)")
    bytes: Count | None = Field(None, description="a number of bytes (a whole number from 0)")
    ms_per_iteration: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = Field(
        None, description="a time in ms (a finite number from 0)")
    frames: Count | None = Field(None, description="a number of frames (a whole number from 0)")
    operators: list[str] | None = Field(None, description="a list of the operators' names")


class ConvergenceAttrs(_Attrs):
    """``volumes/`` attribute ``convergence``: how the frames' iterations went."""

    frames: Count | None = Field(None, description="a number of frames (a whole number from 0)")
    iterations: Annotated[list[Count], Field(min_length=3, max_length=3)] | None = Field(
        None, description="the least, most and total iterations of the frames (three whole numbers from 0)")
    voxels: Annotated[list[Count], Field(min_length=3, max_length=3)] | None = Field(
        None, description="the least, most and total voxels left at the end (three whole numbers from 0)")
    stopped: dict[str, Count] | None = Field(None, description="a table of the frames per reason they stopped")
    per_frame: dict[str, list[Any]] | None = Field(
        None, description='a table of "pair,frame" to [iterations, voxels left, the reason it stopped]')


class _Derived(_Attrs):
    """What ``volumes/`` and ``vectors/`` (and their pending replacements) share."""

    settings: dict[str, Any] = Field(description="a table of the settings that made them")
    volumes_id: str | None = Field(None, description="the text of a volumes/ name, or null")
    planned_pairs: Pairs = Field([], description="a list of pair numbers (whole numbers from 0)")


class VolumesAttrs(_Derived):
    """The attributes of ``volumes/`` (and ``volumes.pending/``)."""

    origin_mm: _three(Finite) = Field(description="three finite world coordinates (x, y, z) in mm")
    voxel_mm: _three(PositiveNumber) = Field(description="three positive, finite voxel edges (x, y, z) in mm")
    method: str = Field(description="the text of a reconstruction method")
    reconstructed_pairs: Pairs = Field(description="a list of pair numbers (whole numbers from 0)")
    operator: OperatorAttrs | None = Field(None, description="a table (what applied the operator: projector, bytes, "
                                                              "ms_per_iteration, frames, operators)")
    plan: dict[str, Any] | None = Field(None, description="a table (the planner's choice)")
    convergence: ConvergenceAttrs | None = Field(None, description="a table (the frames' iterations, voxels left "
                                                                   "and why they stopped)")
    frames_written: list[Annotated[list[Count], Field(min_length=2, max_length=2)]] = Field(
        [], alias="_frames_written", description="a list of [pair, frame] numbers")


class VectorsAttrs(_Derived):
    """The attributes of ``vectors/`` (and ``vectors.pending/``)."""

    dt_s: PositiveS = Field(description="a positive, finite time in s (frame A to frame B)")
    windows: Annotated[list[_three(Annotated[int, Field(gt=0)])], Field(min_length=1)] = Field(
        description="a list of windows, each three positive whole numbers of voxels (x, y, z)")
    overlap: _three(Annotated[float, Field(ge=0, lt=1)]) = Field(
        description="three overlaps (x, y, z), each from 0 up to (not including) 1")
    correlated_pairs: Pairs = Field(description="a list of pair numbers (whole numbers from 0)")


class ParticlesAttrs(_Derived):
    """The attributes of ``particles/`` (and ``particles.pending/``)."""

    origin_mm: _three(Finite) = Field(description="three finite world coordinates (x, y, z) in mm")
    voxel_mm: _three(PositiveNumber) = Field(description="three positive, finite voxel edges (x, y, z) in mm")
    method: str = Field(description="the text of a reconstruction method")
    particle_pairs: Pairs = Field(description="a list of pair numbers (whole numbers from 0)")


#: A flow parameter: a number, a vector of numbers, or null (``period_s`` of a steady ring).
FlowParam = Annotated[float, Field(allow_inf_nan=False)] | list[Annotated[float, Field(allow_inf_nan=False)]] | None


class FlowAttrs(_Attrs):
    """The truth's ``flow``: its name and parameters (:meth:`lfcore.flows.Flow.params`); the
    flow is made from them as well (:func:`lfcore.flows.flow_from_params`) when the truth is read."""

    __pydantic_extra__: dict[str, FlowParam]  # every parameter a number, or a vector of them
    EXTRA: ClassVar[str] = "a number, a vector of numbers, or null (a flow parameter)"

    name: Literal[(*FLOW_NAMES, "static-points")] = Field(  # type: ignore[valid-type]
        description=f"one of the flows lfpiv knows ({', '.join(FLOW_NAMES)}, static-points)")
    case: str | None = Field(None, description="the text of an oscillatory case (A1 ... B4)")


class TruthAttrs(_Attrs):
    """The attributes of ``truth/``."""

    flow: FlowAttrs = Field(description="a table (the flow's name and parameters, each a number or a vector)")
    ppm: PositiveNumber | None = Field(None, description="a positive seeding density (particles per microlens), "
                                                          "or null")
    ppp: PositiveNumber | None = Field(None, description="a positive seeding density (particles per pixel), or null")
    seed: int | None = Field(None, description="a whole number (the random seed), or null")
    render: dict[str, Any] | None = Field(None, description="a table (the render settings)")
    device: str | None = Field(None, description="text (the device that rendered the frames)")


#: Each group's model and how a message names the group's attributes and their file.
GROUPS: dict[str, tuple[type[_Attrs], str, str]] = {
    "": (RootAttrs, "attribute ", "the root zarr.json"),
    "volumes": (VolumesAttrs, "volumes/ attribute ", "volumes/zarr.json"),
    "volumes.pending": (VolumesAttrs, "volumes.pending/ attribute ", "volumes.pending/zarr.json"),
    "vectors": (VectorsAttrs, "vectors/ attribute ", "vectors/zarr.json"),
    "vectors.pending": (VectorsAttrs, "vectors.pending/ attribute ", "vectors.pending/zarr.json"),
    "truth": (TruthAttrs, "truth/ attribute ", "truth/zarr.json"),
    "particles": (ParticlesAttrs, "particles/ attribute ", "particles/zarr.json"),
    "particles.pending": (ParticlesAttrs, "particles.pending/ attribute ", "particles.pending/zarr.json"),
}

#: What to do about a damaged attribute of each group, after "restore it from a copy of the run".
_OR = {"volumes": ", or remove {path}/volumes to reconstruct again",
       "vectors": ", or remove {path}/vectors to correlate again",
       "volumes.pending": ", or remove {path}/volumes.pending (an unfinished replacement)",
       "vectors.pending": ", or remove {path}/vectors.pending (an unfinished replacement)",
       "particles": ", or remove {path}/particles to find them again",
       "particles.pending": ", or remove {path}/particles.pending (an unfinished replacement)",
       "truth": ""}


def _shown(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _field(model: type[BaseModel], key: str) -> tuple[str, Any] | None:
    """The field of ``model`` stored under ``key`` (its alias, or its name): (name, FieldInfo)."""
    for name, info in model.model_fields.items():
        if (info.alias or name) == key:
            return name, info
    return None


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The models an attribute's annotation holds: itself, or in a union or a list."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in getattr(annotation, "__args__", ()) for m in _models(a)]


def _line(path: str | Path, group: str, error: Mapping[str, Any], attrs: Any) -> tuple[str, str]:
    """(the attribute's dotted name, the line) of one of pydantic's errors."""
    model, prefix, file = GROUPS[group]
    names: list[str] = []
    value: Any = attrs
    expected = "what the layout gives it"
    missing = error["type"] == "missing"
    current: type[BaseModel] | None = model
    items: type[BaseModel] | None = None  # the model of the items of the list just entered
    used = 0
    for key in error["loc"]:
        if isinstance(key, int) and items is not None and isinstance(value, list) and 0 <= key < len(value):
            names[-1] += f"[{key}]"
            value, current, items = value[key], items, None
            used += 1
            continue
        if current is None or not isinstance(key, str) or not isinstance(value, Mapping):
            break
        found = _field(current, key)
        if found is None:
            extra = getattr(current, "EXTRA", None)  # what the attributes the model does not name must be
            if extra is not None and key in value:
                names.append(key)
                expected, value, current, items = extra, value.get(key), None, None
                used += 1
            break
        _, info = found
        names.append(key)
        expected = info.description or expected
        value = value.get(key)
        used += 1
        models = _models(info.annotation)
        current = models[0] if models and isinstance(value, Mapping) else None
        items = models[0] if models and isinstance(value, list) else None
    if not names:  # the group's attributes are not a table at all
        return "", (f"{path}: {file} holds {_shown(attrs)} as attributes, not a table (it was edited or damaged); "
                    "restore it from a copy of the run")
    name = ".".join(names)
    held = "is missing" if missing and used == len(error["loc"]) else f"is {_shown(value)}"
    fix = "restore it from a copy of the run" + _OR.get(group, "").format(path=path)
    return name, f"{path}: {prefix}{name} {held}, not {expected} ({file} was edited or damaged); {fix}"


def problems(path: str | Path, group: str, attrs: Any, *, skip: tuple[str, ...] = ()) -> list[str]:
    """Every attribute of ``group`` (``""``: the root; ``"volumes"``, ``"vectors"``, their
    ``.pending`` replacements, ``"truth"``) that is not what the layout gives it: one line each,
    naming the store, the attribute, what it holds and what it should hold; [] if all are.
    ``skip``: attributes whose problems are reported elsewhere."""
    model = GROUPS[group][0]
    try:
        model.model_validate(dict(attrs) if isinstance(attrs, Mapping) else attrs)
    except ValidationError as exc:
        out: dict[str, str] = {}
        for e in exc.errors():
            name, line = _line(path, group, e, attrs)
            if name.split(".")[0] not in skip:
                out.setdefault(name, line)
        return list(out.values())
    return []


def validated(path: str | Path, group: str, attrs: Any, key: str | None = None) -> Any:
    """``attrs`` of ``group`` (see :func:`problems`), or with ``key`` only that attribute, as
    stored, once checked.

    Raises
    ------
    RunStoreError
        The first attribute that is not what the layout gives it, one line.
    """
    if key is None:
        attrs = dict(attrs) if isinstance(attrs, Mapping) else attrs
        found = problems(path, group, attrs)
        if found:
            raise RunStoreError(found[0])
        return attrs
    model = GROUPS[group][0]
    field = _field(model, key)
    assert field is not None, key
    if not isinstance(attrs, Mapping):
        raise RunStoreError(_line(path, group, {"type": "model_type", "loc": ()}, attrs)[1])
    if key not in attrs:
        if field[1].is_required():
            raise RunStoreError(_line(path, group, {"type": "missing", "loc": (key,)}, attrs)[1])
        return field[1].get_default(call_default_factory=True)
    value = attrs[key]
    try:
        _adapter(model, key).validate_python(value, strict=True)
    except ValidationError as exc:
        e = exc.errors()[0]
        raise RunStoreError(_line(path, group, {**e, "loc": (key, *e["loc"])}, attrs)[1]) from None
    return value


@cache
def _adapter(model: type[BaseModel], key: str) -> TypeAdapter:
    _, info = _field(model, key)  # type: ignore[misc]
    return TypeAdapter(Annotated[info.annotation, *info.metadata] if info.metadata else info.annotation)


def describe() -> list[tuple[str, str, str]]:
    """(group, attribute, what it holds) of every attribute of the layout's models, for the docs."""
    out = []
    for group, (model, _, _) in GROUPS.items():
        if group.endswith(".pending"):
            continue
        for name, info in model.model_fields.items():
            out.append((group or "(root)", info.alias or name, info.description or ""))
    return out
