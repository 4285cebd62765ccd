"""What the run store and the calibration store share: a zarr v3 directory whose root attributes
name its format and version and hold the rig it was made with.

Like :mod:`lfcore.runstore`, this owns an on-disk format, so it is allowed to open files.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar

import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from lfcore.rig import Rig, RigError

__all__ = ["CHECKSUM", "DEFAULT_COMPRESSOR", "RigStore", "array_attrs", "damaged_metadata", "described_array"]


def array_attrs(units: str, axes: list[str], description: str) -> dict[str, Any]:
    """The attributes every stored array carries, so that plain zarr or xarray users can read it."""
    return {"units": units, "axes": axes, "description": description}


#: zarr v3's ``crc32c`` codec: the CRC-32C of every encoded chunk appended to it, checked by
#: every read, which fails on a chunk damaged since it was written.
CHECKSUM = Crc32cCodec()
#: zarr's own default compressor for zarr v3 arrays (Zstandard, level 0), where a checksum is added.
DEFAULT_COMPRESSOR = ZstdCodec(level=0)


def described_array(group: zarr.Group, name: str, units: str, axes: list[str], description: str, *,
                    checksum: bool = False, **create: Any) -> zarr.Array:
    """Create array ``name`` in ``group`` with its axes as zarr v3 ``dimension_names`` (which
    xarray reads) and the :func:`array_attrs` attributes.

    Parameters
    ----------
    group
        The group to create it in.
    name, units, axes, description
        Its name, units, one name per axis, and what it holds.
    checksum
        Append :data:`CHECKSUM` to the codecs (after the compressors given, or zarr's default
        :data:`DEFAULT_COMPRESSOR`), so that a damaged chunk fails to read instead of decoding.
    **create
        Passed to :meth:`zarr.Group.create_array` (shape, chunks, dtype, fill_value, ...).
    """
    if checksum:
        given = create.get("compressors", DEFAULT_COMPRESSOR)
        create["compressors"] = (*(given if isinstance(given, (list, tuple)) else (given,)), CHECKSUM)
    a = group.create_array(name, dimension_names=list(axes), **create)
    a.attrs.update(array_attrs(units, list(axes), description))
    return a


def damaged_metadata(where: str, exc: json.JSONDecodeError) -> str:
    """How a message names a zarr.json that is not valid JSON (cut short or overwritten):
    ``where`` is the folder it is in."""
    return f"{where}/zarr.json is damaged (not valid JSON: {exc.msg} at character {exc.pos})"


class RigStore:
    """Base of the stores: a zarr v3 group with ``format``, ``format_version`` and ``rig`` attrs.

    Subclasses set :attr:`FORMAT`, :attr:`FORMAT_VERSION`, :attr:`KIND` (how messages name the
    store), :attr:`HINT` (what to give instead of a missing path) and :attr:`Error` (a
    ``ValueError`` subclass whose message is one line saying what to do).
    """

    FORMAT: ClassVar[str]
    FORMAT_VERSION: ClassVar[int]
    KIND: ClassVar[str]
    HINT: ClassVar[str]
    Error: ClassVar[type[ValueError]] = ValueError
    #: KIND of every store class by FORMAT, so that opening one kind of store as another says
    #: which kind it is
    _kinds: ClassVar[dict[str, str]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "FORMAT" in cls.__dict__:
            RigStore._kinds[cls.FORMAT] = cls.KIND

    def __init__(self, group: zarr.Group, path: Path) -> None:
        self.group = group
        self.path = path

    @classmethod
    def _open_root(cls, path: Path, mode: str) -> zarr.Group:
        # The checks every open makes, in the order a user's mistake is likely.
        if not path.exists():
            raise cls.Error(f"{path} does not exist; {cls.HINT}")
        try:
            root = zarr.open_group(str(path), mode=mode, zarr_format=3)
        except json.JSONDecodeError as exc:  # a zarr.json cut short or overwritten
            raise cls.Error(f"{damaged_metadata(str(path), exc)}, so the {cls.KIND} cannot be opened; restore that "
                            "file from a copy") from None
        except Exception as exc:  # zarr raises several types for "not a group"
            raise cls.Error(f"{path} is not an {cls.KIND} (no zarr v3 group there: {type(exc).__name__})") from None
        fmt = root.attrs.get("format")
        if fmt != cls.FORMAT:
            other = RigStore._kinds.get(fmt)
            if other is not None:
                raise cls.Error(f"{path} is an {other}, not an {cls.KIND}; {cls.HINT}")
            raise cls.Error(f"{path} is a zarr group but not an {cls.KIND} (format {fmt!r})")
        version = root.attrs.get("format_version", 1)  # the first format had no other
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise cls.Error(f"{path}: format_version is {version!r}, not a format lfpiv writes (its zarr.json was "
                            f"edited or damaged); restore it from a copy, or set it to {cls.FORMAT_VERSION}")
        if version > cls.FORMAT_VERSION:
            raise cls.Error(f"{path} was written by a newer lfpiv (format_version "
                            f"{root.attrs['format_version']}); upgrade lfpiv")
        return root

    @property
    def attrs(self) -> dict[str, Any]:
        """A copy of the root attributes."""
        return dict(self.group.attrs)

    @property
    def rig(self) -> Rig:
        """The rig the store was made with, validated like a rig file."""
        try:
            return Rig.from_dict(self.group.attrs["rig"], source=f"{self.path} (rig)")
        except RigError as exc:
            raise self.Error(str(exc)) from None

    @property
    def cameras(self) -> list[str]:
        """Camera names in rig order."""
        return [c["name"] for c in self.group.attrs["rig"]["camera"]]
