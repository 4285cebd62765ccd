"""Is a run store whole? (``lfpiv check``): every chunk checked against what the run says it holds."""

from __future__ import annotations

from pathlib import Path

from lfcore.runstore import RunStore

__all__ = ["check_run"]


def check_run(path: str | Path) -> list[str]:
    """Every problem of the run at ``path``, one line each, or [] when it is whole.

    Reads every chunk of the committed pairs' frames, ids and time stamps, of drops and truth, and
    of the volumes and vectors of the pairs they list as done (each chunk's CRC32C checked as it is
    decoded), and checks that every recorded item has its chunks and the layout its data types and
    shapes (:meth:`lfcore.runstore.RunStore.verify`). A store that cannot be opened gives the one
    line saying why. Read-only: it takes no lock and changes nothing.
    """
    return RunStore.check(path)
