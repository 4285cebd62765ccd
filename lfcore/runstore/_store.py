"""The run store itself: its parts put together, and how a run is created and opened."""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Any

import zarr

from lfcore.rig import Rig
from lfcore.runstore._common import FORMAT, FORMAT_VERSION, RunStoreError
from lfcore.runstore._drops import DROP_FIELDS, Drops, create_drops
from lfcore.runstore._frames import CAMERA_ARRAYS, Frames, create_frames
from lfcore.runstore._replacement import Replacement
from lfcore.runstore._truth import Truth
from lfcore.runstore._vectors import Vectors
from lfcore.runstore._volumes import Volumes
from lfcore.zarrstore import RigStore


class RunStore(Frames, Drops, Truth, Volumes, Vectors, Replacement, RigStore):
    """Read and write access to one run.

    Use :meth:`create` for a new run and :meth:`open` for an existing one. Each kind of data
    has its part: :class:`~lfcore.runstore._frames.Frames` (frames, ids, time stamps, state and
    commits), :class:`~lfcore.runstore._drops.Drops`, :class:`~lfcore.runstore._truth.Truth`,
    :class:`~lfcore.runstore._volumes.Volumes`, :class:`~lfcore.runstore._vectors.Vectors`
    and :class:`~lfcore.runstore._replacement.Replacement` (``*.pending`` replacements).
    """

    FORMAT = FORMAT
    FORMAT_VERSION = FORMAT_VERSION
    KIND = "lfpiv run store"
    HINT = "give the path of a run store (a .zarr directory)"
    Error = RunStoreError

    def __init__(self, group: zarr.Group, path: Path) -> None:
        super().__init__(group, path)
        self._target = {"volumes": "volumes", "vectors": "vectors"}

    # --- creation and opening -----------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, rig: Rig, n_pairs: int, *, timing: dict[str, Any],
               software_version: str, overwrite: bool = False) -> RunStore:
        """Create an empty run of ``n_pairs`` pairs for every camera of ``rig``.

        Raises
        ------
        RunStoreError
            If ``path`` exists and ``overwrite`` is false (nothing recorded is ever replaced
            silently), or if ``n_pairs`` is not positive.
        """
        path = Path(path)
        if n_pairs < 1:
            raise RunStoreError(f"a run needs at least one pair, got {n_pairs}")
        cls.check_new(path, overwrite)
        root = zarr.open_group(str(path), mode="w", zarr_format=3)
        root.attrs.update({
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "rig": rig.to_dict(),
            "timing": timing,
            "software_version": software_version,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "state": "recording",
            "committed_pairs": 0,
        })
        create_frames(root, rig, n_pairs)
        create_drops(root)
        return cls(root, path)

    @classmethod
    def check_new(cls, path: str | Path, overwrite: bool = False) -> None:
        """Raise :class:`RunStoreError` unless a new run may be created at ``path``.

        ``overwrite`` replaces only an lfpiv run store, never another file or folder. Call it
        before long work whose result goes to ``path``, so that the user hears at once.
        """
        path = Path(path)
        if path.is_symlink():
            # replacing a run through a link would delete the folder it points to, or write
            # beside a dangling one: say so rather than guess
            raise RunStoreError(f"{path} is a symbolic link (to {os.readlink(path)}); give the real path, or another "
                                "output path")
        if not path.exists():
            return
        if not overwrite:
            raise RunStoreError(f"{path} already exists; choose another output path or pass --overwrite")
        try:
            cls._open_root(path, "r")
        except RunStoreError as exc:
            raise RunStoreError(f"{exc}, and --overwrite replaces only run stores; choose another output path") \
                from None

    @classmethod
    def open(cls, path: str | Path, mode: str = "r") -> RunStore:
        """Open an existing run (``mode`` ``"r"`` or ``"r+"``); ``"r+"`` settles a replacement
        of volumes or vectors killed as it was put in place (:meth:`recover`).

        Raises
        ------
        RunStoreError
            If ``path`` does not exist or is not an lfpiv run store.
        """
        path = Path(path)
        root = cls._open_root(path, mode)
        missing = cls._missing(root)
        if missing:
            raise RunStoreError(f"{path} is incomplete: {missing} is missing (a store still being created, or a "
                                "damaged one), so it cannot be read as a run; if it is not being created, copy what "
                                "you need from it with zarr, or record it again")
        store = cls(root, path)
        if mode != "r":
            store.recover()
        return store

    @staticmethod
    def _missing(root: zarr.Group) -> str | None:
        """The first attribute or array of the layout that ``root`` lacks (a run store damaged
        by hand or cut off while being created), or None."""
        for key in ("rig", "timing", "state", "committed_pairs"):
            if key not in root.attrs:
                return f"the root attribute {key!r}"
        try:
            names = [c["name"] for c in root.attrs["rig"]["camera"]]
        except (KeyError, TypeError):
            return "the rig's cameras"
        needed = [f"{n}/{a}" for n in names for a in CAMERA_ARRAYS]
        needed += [f"drops/{f}" for f in DROP_FIELDS]
        return next((n for n in needed if n not in root), None)

