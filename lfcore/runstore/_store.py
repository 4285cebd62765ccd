"""The run store itself: its parts put together, and how a run is created and opened."""

from __future__ import annotations

import datetime as _dt
import json
import os
import shutil
import weakref
from pathlib import Path
from types import TracebackType
from typing import Any

import zarr

from lfcore._deprecation import keyword_options
from lfcore.rig import Rig
from lfcore.runstore import _lock
from lfcore.runstore._common import FORMAT, FORMAT_VERSION, RunStoreError, StoreGroup
from lfcore.runstore._drops import DROP_FIELDS, Drops, create_drops
from lfcore.runstore._frames import CAMERA_ARRAYS, Frames, create_frames
from lfcore.runstore._integrity import Integrity
from lfcore.runstore._lock import LOCK_NAME, WriterLease, acquire, current_writer, join
from lfcore.runstore._particles import Particles
from lfcore.runstore._replacement import Replacement
from lfcore.runstore._schema import validated
from lfcore.runstore._truth import Truth
from lfcore.runstore._vectors import Vectors
from lfcore.runstore._volumes import Volumes
from lfcore.zarrstore import RigStore, damaged_metadata


class RunStore(Frames, Drops, Truth, Volumes, Vectors, Particles, Replacement, Integrity, RigStore):
    """Read and write access to one run.

    Use :meth:`create` for a new run and :meth:`open` for an existing one. Each kind of data
    has its part: :class:`~lfcore.runstore._frames.Frames` (frames, ids, time stamps, state and
    commits), :class:`~lfcore.runstore._drops.Drops`, :class:`~lfcore.runstore._truth.Truth`,
    :class:`~lfcore.runstore._volumes.Volumes`, :class:`~lfcore.runstore._vectors.Vectors`,
    :class:`~lfcore.runstore._particles.Particles`,
    :class:`~lfcore.runstore._replacement.Replacement` (``*.pending`` replacements) and
    :class:`~lfcore.runstore._integrity.Integrity` (checked reads and :meth:`verify`).

    One process writes a run at a time: :meth:`create` and :meth:`open` for writing take the
    store's writer lock (:mod:`lfcore.runstore._lock`), held until :meth:`close`, the end of a
    ``with`` block, the handle's garbage collection or the process's end, whichever comes first;
    a killed process leaves it free. Readers take no lock.
    """

    FORMAT = FORMAT
    FORMAT_VERSION = FORMAT_VERSION
    KIND = "lfpiv run store"
    HINT = "give the path of a run store (a .zarr directory)"
    Error = RunStoreError

    def __init__(self, group: zarr.Group, path: Path, *, lease: WriterLease | None = None) -> None:
        super().__init__(group if isinstance(group, StoreGroup) else StoreGroup(group._async_group), path)
        self._target = {"volumes": "volumes", "vectors": "vectors", "particles": "particles"}
        self._lease = lease
        # the lock goes with the handle: closed, collected, or at the interpreter's exit
        self._release = weakref.finalize(self, lease.release) if lease is not None else None

    # --- creation and opening -----------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, rig: Rig, n_pairs: int, *, timing: dict[str, Any],
               software_version: str, overwrite: bool = False) -> RunStore:
        """Create an empty run of ``n_pairs`` pairs for every camera of ``rig``, and hold its
        writer lock.

        Raises
        ------
        RunStoreError
            If ``path`` exists and ``overwrite`` is false (nothing recorded is ever replaced
            silently), if another process writes the run ``overwrite`` would replace (naming
            it), or if ``n_pairs`` is not positive.
        """
        path = Path(path)
        if n_pairs < 1:
            raise RunStoreError(f"a run needs at least one pair, got {n_pairs}")
        validated(path, "", {"timing": timing}, "timing")  # never written as what no reader accepts
        cls.check_new(path, overwrite=overwrite)
        if path.exists():  # a run store to replace (check_new made sure): not while another process writes it
            lease = acquire(path)
            for child in path.iterdir():
                if child.name == LOCK_NAME:  # kept: a new file would be a second lock
                    continue
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        else:
            try:
                path.mkdir(parents=True)
            except FileExistsError:  # created by another process since check_new
                raise RunStoreError(f"{path} already exists; choose another output path or pass --overwrite") \
                    from None
            lease = acquire(path)
        try:
            root = StoreGroup(zarr.open_group(str(path), mode="a", zarr_format=3)._async_group)
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
        except BaseException:
            lease.release()
            raise
        return cls(root, path, lease=lease)

    @classmethod
    @keyword_options("overwrite", since="0.1.0")
    def check_new(cls, path: str | Path, *, overwrite: bool = False) -> None:
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
            if not path.parent.exists():  # never a tree of folders made wherever a typo points
                raise RunStoreError(f"{path.parent} does not exist (to hold {path.name}); create it first, or give "
                                    "another output path")
            return
        if not overwrite:
            raise RunStoreError(f"{path} already exists; choose another output path or pass --overwrite")
        try:
            cls._open_root(path, "r")
        except RunStoreError as exc:
            raise RunStoreError(f"{exc}, and --overwrite replaces only run stores; choose another output path") \
                from None
        # said now, not once the devices are open and the recording thread meets the lock
        writer = _lock.current_writer(path)
        if writer is not None and writer.get("pid") != os.getpid() and not _lock._is_ancestor(writer):
            raise RunStoreError(f"{path} is being written by {_lock.describe(writer)}; wait for it to finish or stop "
                                "it, then try again (reading it needs no lock: open it read-only)")

    @classmethod
    @keyword_options("mode", since="0.1.0")
    def open(cls, path: str | Path, *, mode: str = "r", shared_with: str | None = None) -> RunStore:
        """Open an existing run (``mode`` ``"r"`` or ``"r+"``).

        ``"r+"`` takes the run's writer lock (or shares it, see :mod:`lfcore.runstore._lock`)
        and settles a replacement of volumes or vectors killed as it was put in place
        (:meth:`recover`). ``"r"`` takes no lock and always opens.

        Parameters
        ----------
        path
            The run store (a .zarr directory).
        mode
            ``"r"`` to read, ``"r+"`` to write too.
        shared_with
            With ``"r+"``: the :attr:`writer_token` of the process that holds the lock and
            lets this one write too, without taking it (a Dask worker of a cluster writing the
            pairs its coordinator gave out; the coordinator keeps its store open meanwhile).

        Raises
        ------
        RunStoreError
            If ``path`` does not exist or is not an lfpiv run store, if its metadata is
            damaged, or (``"r+"``) if another process writes it, naming that process.
        """
        path = Path(path)
        root = cls._open_root(path, mode)
        lease = None
        if mode != "r":
            lease = join(path, shared_with) if shared_with is not None else acquire(path)
        try:
            missing = cls._missing(root)
            if missing:
                raise RunStoreError(f"{path} is incomplete: {missing} is missing (a store still being created, or a "
                                    "damaged one), so it cannot be read as a run; if it is not being created, copy "
                                    "what you need from it with zarr, or record it again")
            store = cls(root, path, lease=lease)
        except BaseException:
            if lease is not None:
                lease.release()
            raise
        if mode != "r":
            store.recover()
        return store

    @staticmethod
    def _missing(root: zarr.Group) -> str | None:
        """The first attribute or array of the layout that ``root`` lacks (a run store damaged
        by hand or cut off while being created), or None.

        Raises
        ------
        RunStoreError
            If the metadata of one of them (its zarr.json) is damaged.
        """
        for key in ("rig", "timing", "state", "committed_pairs"):
            if key not in root.attrs:
                return f"the root attribute {key!r}"
        try:
            names = [c["name"] for c in root.attrs["rig"]["camera"]]
        except (KeyError, TypeError):
            return "the rig's cameras"
        needed = [f"{n}/{a}" for n in names for a in CAMERA_ARRAYS]
        needed += [f"drops/{f}" for f in DROP_FIELDS]
        for n in needed:
            try:
                if n not in root:
                    return n
            except json.JSONDecodeError as exc:
                raise RunStoreError(f"{damaged_metadata(f'{root.store_path.store.root}/{n}', exc)}, so the run "
                                    "cannot be opened; restore that file from a copy") from None
        return None

    @property
    def attrs(self) -> dict[str, Any]:
        """A copy of the root attributes, checked (:class:`~lfcore.runstore._schema.RootAttrs`).

        Raises
        ------
        RunStoreError
            The first root attribute that is not what the layout gives it, one line naming it.
        """
        return dict(validated(self.path, "", self.group.attrs))

    # --- the writer lock ----------------------------------------------------------------
    @property
    def writer_token(self) -> str | None:
        """The token of the writer lock this handle writes under, for the processes it lets
        write too (``RunStore.open(path, mode="r+", shared_with=token)``); None for a reader."""
        return self._lease.token if self._lease is not None else None

    @property
    def writer(self) -> dict[str, Any] | None:
        """Who writes the run now: ``{"host", "pid", "command", "since", "token"}`` as the writer
        wrote them (``{}`` if it has not yet), or None if no process does."""
        return current_writer(self.path)

    def close(self) -> None:
        """Give back the writer lock (a reader: nothing to give back); the handle can still
        read, but no longer write. Idempotent."""
        if self._release is not None and self._release.alive:
            self._release()
            try:
                self.group = StoreGroup(zarr.open_group(str(self.path), mode="r", zarr_format=3)._async_group)
            except Exception:  # noqa: BLE001 - gone or damaged: writes through it fail anyway
                pass
        self._lease = None

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
