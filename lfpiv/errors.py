"""Errors the ``lfpiv`` command reports as one line on stderr with exit code 2."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


class UsageError(Exception):
    """Bad input from the user: the message names the problem and the fix."""


def os_error_line(exc: OSError, *, path: object = None) -> str:
    """One line for an I/O error: the path, the real cause and the way on, e.g. "cannot use
    /data/run.zarr/volumes: No space left on device; free some space there, or choose another path".

    ``path`` names the file where ``exc`` names none (zarr's writes on a full disk carry none).
    """
    import errno

    where = exc.filename if exc.filename is not None else path
    cause = exc.strerror or (str(exc.args[-1]) if exc.args else "") or type(exc).__name__
    if exc.filename2 is not None:
        where = f"{where} -> {exc.filename2}"
    fix = {errno.ENOSPC: "free some space there, or choose another path",
           errno.EDQUOT: "free some of your quota there, or choose another path",
           errno.EACCES: "fix its permissions, or choose another path",
           errno.EPERM: "fix its permissions, or choose another path",
           errno.EROFS: "choose a path on a writable file system",
           errno.ENOENT: "check the path (its folder must exist)",
           errno.ENOTDIR: "check the path: a part of it is a file, not a folder",
           errno.EISDIR: "give a file's path, not a folder's",
           errno.EIO: "check the disk (an input/output error is a hardware or file-system fault)"}.get(
        exc.errno or 0, "choose another path, or check its permissions and free space")
    return f"cannot use {where}: {cause}; {fix}" if where is not None else f"{cause}; {fix}"


@contextlib.contextmanager
def naming(path: object) -> Iterator[None]:
    """Inside, an :class:`OSError` that names no file (zarr's writes on a full disk) is raised
    again naming ``path``, where it was writing."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise
