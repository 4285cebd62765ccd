"""How every writer of :mod:`lfpiv.formats` replaces a file: whole, or not at all."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def replacing(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write; it becomes ``path`` when the block ends without error.

    An earlier file at ``path`` stays whole until the new one is complete (``os.replace`` is
    atomic within a folder, and replaces a symbolic link itself, never writing through it); on
    an error the temporary file is removed.
    """
    tmp = path.with_name(f".{path.name}.partial")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
