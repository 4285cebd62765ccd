"""Opening run stores for the commands and for Python users (:func:`lfpiv.open_run`)."""

from __future__ import annotations

from pathlib import Path

from lfcore.runstore import RunStore

__all__ = ["RunStore", "check_new", "open_run"]


def open_run(path: str | Path, *, mode: str = "r") -> RunStore:
    """Open a run store: ``mode="r"`` to read (the default), ``"r+"`` to add volumes or vectors.

    Raises
    ------
    lfcore.runstore.RunStoreError
        One line naming the path and the problem: no such folder, not an lfpiv run store, an
        incomplete one.
    """
    return RunStore.open(path, mode=mode)


def check_new(path: str | Path, overwrite: bool = False) -> None:
    """Refuse, before any work, an output path that is taken (unless ``overwrite`` and it is an
    lfpiv run store); see :meth:`lfcore.runstore.RunStore.check_new`."""
    RunStore.check_new(path, overwrite=overwrite)
