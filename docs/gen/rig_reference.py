"""The rig-file reference, generated from the rig model (:mod:`lfcore.rig`) at every docs build.

Every table of a rig file is a pydantic model and every key one of its fields: the key's type,
default and allowed range come from the field, its meaning from the ``#:`` comment above it
and its unit from its name (``_mm``, ``_um``, ...). A field without a ``#:`` comment fails the
build, naming it, so a new key cannot reach a release undocumented.

Run on its own (``python docs/gen/rig_reference.py``) it prints the page.
"""

from __future__ import annotations

import ast
import inspect
import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markup import doc_comment, plain, rst_to_markdown  # noqa: E402

__all__ = ["rig_reference"]

#: Units by the end of a key's name, longest first.
_SUFFIX_UNITS = (
    ("_e_per_count", "e-/count"), ("_counts", "counts"), ("_mm", "mm"), ("_um", "µm"), ("_us", "µs"),
    ("_nm", "nm"), ("_hz", "Hz"), ("_deg", "degrees"), ("_px", "pixels"), ("_fps", "frames/s"), ("_s", "s"),
)
#: Units of keys whose names do not carry one.
_NAMED_UNITS = {"baud": "bit/s", "bit_depth": "bits", "rays_per_particle": "rays", "pvr": "pixels per voxel"}

#: Keys a model takes in its input but does not keep as a field (a ``mode="before"`` validator
#: turns them into fields); (type, unit, default, range, meaning) each.
_INPUT_ONLY = {
    "PinholeCamera": {
        "object_distance_mm": ("number", "mm", "—", "> focal_length_mm",
                               "Lens to focal plane: instead of `magnification` (M = -F / (so - F)); not both"),
    },
}


def _unit(key: str) -> str:
    if key in _NAMED_UNITS:
        return _NAMED_UNITS[key]
    for suffix, unit in _SUFFIX_UNITS:
        if key.endswith(suffix):
            return unit
    return ""


def _number(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _bounds(metadata: list[Any]) -> list[str]:
    """Ranges of annotated_types constraints, e.g. ["> 0", "≤ 16"]."""
    out = []
    lo = next((m for m in metadata if isinstance(m, at.Gt | at.Ge)), None)
    hi = next((m for m in metadata if isinstance(m, at.Lt | at.Le)), None)
    if isinstance(lo, at.Ge) and isinstance(hi, at.Le):
        return [f"{_number(lo.ge)} to {_number(hi.le)}"]
    if lo is not None:
        out.append(f"> {_number(lo.gt)}" if isinstance(lo, at.Gt) else f"≥ {_number(lo.ge)}")
    if hi is not None:
        out.append(f"< {_number(hi.lt)}" if isinstance(hi, at.Lt) else f"≤ {_number(hi.le)}")
    for m in metadata:
        if isinstance(m, at.MinLen):
            out.append(f"at least {m.min_length}")
    return out


def _split_annotated(ann: Any) -> tuple[Any, list[Any]]:
    """(bare type, constraints) of a possibly ``Annotated`` type."""
    if get_origin(ann) is typing.Annotated:
        base, *extra = get_args(ann)
        meta: list[Any] = []
        for e in extra:
            meta += list(e.metadata) if isinstance(e, FieldInfo) else [e]
        inner, more = _split_annotated(base)
        return inner, meta + more
    return ann, []


def _describe(ann: Any, metadata: list[Any]) -> tuple[str, str]:
    """(type, allowed range) of a field's annotation, in a rig file's words."""
    ann, more = _split_annotated(ann)
    metadata = list(metadata) + more
    origin = get_origin(ann)
    if origin in (Union, types.UnionType):
        args = [a for a in get_args(ann) if a is not type(None)]
        kind, rng = _describe(args[0], metadata) if len(args) == 1 else ("table", "")
        return kind, rng
    if origin is Literal:
        return "text", "one of " + ", ".join(f'`"{v}"`' for v in get_args(ann))
    if origin is tuple:
        args = get_args(ann)
        if len(args) == 2 and args[1] is Ellipsis:
            kind, rng = _describe(args[0], [])
            return f"array of {kind}", rng
        kinds = {_describe(a, []) for a in args}
        if len(kinds) == 1:
            (kind, rng), = kinds
            plural = {"number": "numbers", "whole number": "whole numbers"}.get(kind, kind)
            return f"array of {len(args)} {plural}", (f"each {rng}" if rng else "")
        return "array", ""
    if origin is dict:
        kind, rng = _describe(get_args(ann)[1], [])
        return f"table of {kind}s", (f"each {rng}" if rng else "")
    if inspect.isclass(ann) and issubclass(ann, BaseModel):
        return "table", ""
    kind = {bool: "true / false", int: "whole number", float: "number", str: "text"}.get(ann, str(ann))
    return kind, ", ".join(_bounds(metadata))


def _toml(value: Any) -> str:
    """A default as a rig file would write it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, int | float):
        return _number(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML form for the default {value!r}")


def _field_comments(cls: type[BaseModel], tree: ast.Module, lines: list[str]) -> dict[str, str]:
    """The ``#:`` comment above each field of ``cls`` in its module's source."""
    node = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    return {st.target.id: doc_comment(lines, st.lineno) for st in node.body
            if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name)}


def _table(cls: type[BaseModel], tree: ast.Module, lines: list[str], *, skip: tuple[str, ...] = ()) -> list[str]:
    comments = _field_comments(cls, tree, lines)
    rows = ["| key | type | unit | default | allowed | meaning |", "| --- | --- | --- | --- | --- | --- |"]
    for key, field in cls.model_fields.items():
        if key in skip:
            continue
        meaning = comments.get(key, "")
        if not meaning:
            raise RuntimeError(f"{cls.__module__}.{cls.__name__}.{key}: no #: comment above the field; write one (it "
                               "is the key's meaning in the rig-file reference)")
        kind, rng = _describe(field.annotation, list(field.metadata))
        default = ("**required**" if field.default is PydanticUndefined else "not set" if field.default is None
                   else f"`{_toml(field.default)}`")
        instead = [k for k, row in _INPUT_ONLY.get(cls.__name__, {}).items() if f"`{key}`" in row[-1]]
        if instead and field.default is PydanticUndefined:
            default += f" (or `{instead[0]}`)"
        meaning = plain(rst_to_markdown(meaning))
        rows.append(f"| `{key}` | {kind} | {_unit(key)} | {default} | {plain(rng)} | {meaning} |")
    for key, (kind, unit, default, rng, meaning) in _INPUT_ONLY.get(cls.__name__, {}).items():
        rows.append(f"| `{key}` | {kind} | {unit} | {default} | {plain(rng)} | {plain(meaning)} |")
    return rows


def _doc(cls: type) -> str:
    return rst_to_markdown(inspect.cleandoc(cls.__doc__ or ""))


def rig_reference() -> str:
    """The rig-file reference page, Markdown."""
    from lfcore import rig as rig_module
    from lfcore.rig import Camera, PinholeCamera, Rig

    source = inspect.getsource(rig_module)
    tree, lines = ast.parse(source), source.splitlines()
    out = [
        "# Rig-file reference",
        "",
        "A rig file is TOML: top-level keys, then one table per part of the rig. This page is generated "
        "from the rig model (`lfcore/rig.py`) each time the documentation is built, so it lists every key "
        "the current code accepts. Runnable examples are in [Example rigs](examples.md).",
        "",
        "- An unknown key is an error naming it (and the key it probably meant); so is an impossible value.",
        "- Values are read as written: a quoted number (`pixel_pitch_um = \"5.5\"`) or a fractional count "
        "is an error, while a whole number written as a float (`rays_per_particle = 4e3`) is a whole number.",
        "- Arrays of three are world (x, y, z) unless the key says otherwise; `sensor_px` is [columns, rows].",
        "- Units: millimetres in the world, micrometres for sensor and lenslet pitches, microseconds for "
        "pulse timing (see [Conventions](conventions.md)).",
        "",
        "## Top level",
        "",
        _doc(Rig),
        "",
    ]
    tables = [k for k, f in Rig.model_fields.items()
              if k != "camera" and inspect.isclass(f.annotation) and issubclass(f.annotation, BaseModel)]
    out += _table(Rig, tree, lines, skip=("camera", *tables))
    out += [""]
    for key, field in Rig.model_fields.items():
        if key == "camera":
            out += ["## `[[camera]]`: a light-field camera", "", _doc(Camera), "",
                    "One `[[camera]]` table per camera, in the order the run store keeps them; the first camera "
                    "sets the voxel size (`[volume]` `pvr`) and the seeding density's lenslets (PPM).", ""]
            out += _table(Camera, tree, lines)
            out += ["", "## `[[camera]]` with `kind = \"pinhole\"`: a Tomo-PIV camera", "", _doc(PinholeCamera), ""]
            out += _table(PinholeCamera, tree, lines)
            out += [""]
        elif key in tables:
            model = field.annotation
            required = field.default is PydanticUndefined
            out += [f"## `[{key}]`", "", _doc(model), "",
                    "This table is required." if required else "The whole table is optional.", ""]
            out += _table(model, tree, lines)
            out += [""]
    return "\n".join(out)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    print(rig_reference())
