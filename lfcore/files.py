"""How every file lfpiv writes replaces the one before it: whole, or not at all.

A file is written beside its final name (``.NAME.partial`` in the same folder), flushed to the
disk, and renamed over the final name; the rename is atomic within a folder. An interrupt, a
kill, a full disk or a power cut leaves the old file or the new one under the final name, never a
stub or a 0-byte file. Plots, screenshots, reports, study outputs and exports all go through
:func:`replacing`.

With :mod:`lfcore.runstore` and :mod:`lfcore.zarrstore`, the one module of :mod:`lfcore` that
writes files: the primitive the stores and every writer above them share.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["partial_path", "replace_file", "replacing"]


def partial_path(path: str | Path) -> Path:
    """Where :func:`replacing` writes ``path`` before it is complete: ``.NAME.partial`` beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}.partial")


def _fsync(path: Path, *, folder: bool = False) -> None:
    """Flush ``path`` (a file, or with ``folder`` a folder's entries) to the disk."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if folder else 0))
    except OSError:
        if folder:  # some file systems cannot open a folder: its rename is as durable as they make it
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not folder:
            raise
    finally:
        os.close(fd)


def _naming(exc: OSError, path: Path, tmp: Path) -> OSError:
    """``exc`` naming ``path`` (what the user gave) where it names nothing or the partial file."""
    if exc.filename is None or str(exc.filename) == str(tmp):
        return OSError(exc.errno, exc.strerror or str(exc), str(path))
    return exc


@contextlib.contextmanager
def replacing(path: str | Path, *, durable: bool = True) -> Iterator[Path]:
    """A partial path beside ``path`` to write; it becomes ``path`` when the block ends without error.

    Parameters
    ----------
    path
        The file to write (or replace).
    durable
        Flush the new file, and the folder's rename, to the disk before returning (``fsync``),
        so that a power cut too leaves the old or the new file whole.

    Yields
    ------
    pathlib.Path
        The partial file (``.NAME.partial`` beside ``path``) that the block writes; the writer
        must not derive the file's format from its suffix.

    Raises
    ------
    OSError
        What the write, the flush or the rename raised (a full disk, a read-only folder, ...),
        naming ``path`` where it named no file or the partial one. The partial file is removed
        and an earlier file at ``path`` is left whole (``os.replace`` replaces a symbolic link
        itself, never writing through it).
    """
    path = Path(path)
    tmp = partial_path(path)
    try:
        try:
            yield tmp
            if durable:
                _fsync(tmp)
            os.replace(tmp, path)
        except OSError as exc:
            raise _naming(exc, path, tmp) from None
        if durable:
            _fsync(path.parent, folder=True)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def replace_file(path: str | Path, data: bytes | str, *, encoding: str = "utf-8", durable: bool = True) -> Path:
    """Write ``data`` (bytes, or text in ``encoding``) to ``path`` through :func:`replacing`.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    with replacing(path, durable=durable) as tmp:
        tmp.write_bytes(data.encode(encoding) if isinstance(data, str) else data)
    return path
