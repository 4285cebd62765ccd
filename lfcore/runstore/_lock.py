"""One writer per run store: an exclusive lock that a killed process cannot leave held.

The lock is a POSIX record lock (``fcntl.lockf``) on the whole of ``<run>/.lfpiv-writer.lock``,
a small file inside the store that also names the holder (host, PID, command, since when, and
a token), so a second writer is refused with one line that says who writes the run. The kernel
releases a process's record locks when it ends, however it ends (SIGKILL included), so a lock is
never stale on a local disk, and nothing has to guess from PIDs.

Where it works (POSIX systems: Linux, macOS): local file systems; NFS (v4, or v3 with
``lockd``/``rpc.statd`` running; not on a mount with ``nolock`` or ``local_lock``, which lock
only within one client), where the server releases the locks of a client that crashed once the
client reboots (v3) or its lease runs out (v4, about 90 s); Lustre mounted with ``flock``
(``localflock`` locks within one node only), GPFS/Spectrum Scale, BeeGFS. Where it cannot: file
systems without POSIX locks (some FUSE file systems, sshfs, object stores): taking the lock
fails, with one line saying so, rather than letting two writers in.

Who shares the lock without taking it:

- every :class:`~lfcore.runstore.RunStore` one process opens for writing (record locks belong
  to processes): the handles share one lock, held until the last is closed;
- a process started by the writer (a descendant of it on the same host, e.g. a local Dask
  worker of ``--workers N``), which writes on its behalf;
- a process that shows the writer's token (:attr:`~lfcore.runstore.RunStore.writer_token`),
  passed to ``RunStore.open(path, mode="r+", shared_with=token)``: a Dask cluster's worker on
  another node, started by the batch system rather than by the writer.

The writer (the coordinator) must keep its store open while the others write. Readers
(``mode="r"``) never take the lock and never wait for it.

Record locks have one trap: closing *any* descriptor of the lock file releases the process's
lock. So this module is the only code that opens it, and it never opens it again while the
process holds it (held locks are looked up by the file's device and inode first).
"""

from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import json
import os
import shlex
import socket
import sys
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lfcore.runstore._common import RunStoreError

#: The lock file's name inside a run store.
LOCK_NAME = ".lfpiv-writer.lock"

# errno values of a lock held by another process; any other error of a lock request means the
# file system has no working POSIX locks (ENOLCK, EOPNOTSUPP, ENOSYS, EINVAL)
_HELD = {errno.EAGAIN, errno.EACCES}


@dataclass
class _Held:
    """This process's lock on one store's lock file."""

    fd: int
    pid: int  # the process that took it (a forked child does not hold its parent's locks)
    info: dict[str, Any]
    count: int = 0


_held: dict[tuple[int, int], _Held] = {}  # by (st_dev, st_ino) of the lock file
_guard = threading.Lock()


class WriterLease:
    """One handle's share of the writer lock of a store (see the module docstring).

    ``owner`` is true when this process holds the kernel lock; false when it writes under
    another process's lock (its ancestor's, or one whose token it was given).
    """

    def __init__(self, key: tuple[int, int] | None, info: dict[str, Any]) -> None:
        self._key = key
        self.info = info
        self.token: str = info.get("token", "")
        self.owner = key is not None

    def release(self) -> None:
        """Give this share back; the lock itself goes with the process's last share. Idempotent."""
        key, self._key = self._key, None
        if key is None:
            return
        with _guard:
            held = _held.get(key)
            if held is None or held.pid != os.getpid():
                return
            held.count -= 1
            if held.count > 0:
                return
            del _held[key]
            try:
                os.ftruncate(held.fd, 0)  # no holder named any more
                fcntl.lockf(held.fd, fcntl.LOCK_UN)
            except OSError:
                pass
            finally:
                os.close(held.fd)


def _stat_key(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino


def _mine(path: Path) -> _Held | None:
    """This process's lock on the lock file at ``path``, or None (call with ``_guard`` held)."""
    key = _stat_key(path)
    held = _held.get(key) if key is not None else None
    return held if held is not None and held.pid == os.getpid() else None


def _command() -> str:
    argv = list(sys.argv) or ["python"]
    argv[0] = Path(argv[0]).name or argv[0]
    cmd = shlex.join(argv)
    return cmd if len(cmd) <= 200 else cmd[:197] + "..."


def _read_info(fd: int) -> dict[str, Any] | None:
    try:
        data = os.pread(fd, 65536, 0)
        info = json.loads(data.decode()) if data else None
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def describe(info: dict[str, Any] | None) -> str:
    """How a message names the process that writes a store."""
    if not info:
        return "another process (it has not written its name yet)"
    return (f"pid {info.get('pid')} on {info.get('host')} ('{info.get('command')}', since "
            f"{info.get('since')})")


def _no_locks(path: Path, exc: OSError) -> RunStoreError:
    return RunStoreError(f"cannot lock {path.parent} for writing: its file system does not support file locks "
                         f"({exc.strerror}); mount it with locking (NFS: lockd running, not 'nolock'; Lustre: "
                         "'-o flock'), or write the run on a local disk")


def _other_writer(root: Path) -> tuple[bool, dict[str, Any] | None]:
    """Whether another process holds the lock of ``root``, and what it says of itself (call
    with ``_guard`` held, and only when this process does not hold it)."""
    path = root / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False, None
    try:
        try:
            fcntl.lockf(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in _HELD:
                return True, _read_info(fd)
            raise _no_locks(path, exc) from None
        return False, None  # free: the shared lock just taken goes with the descriptor
    finally:
        os.close(fd)


def _is_ancestor(info: dict[str, Any] | None) -> bool:
    """Whether the process ``info`` names is an ancestor of this one, on this host."""
    if not info or info.get("host") != socket.gethostname():
        return False
    import psutil

    try:
        return any(p.pid == info.get("pid") for p in psutil.Process().parents())
    except psutil.Error:
        return False


def acquire(root: Path) -> WriterLease:
    """Take the writer lock of the store at ``root`` (or share it: see the module docstring).

    Raises
    ------
    RunStoreError
        If another process writes the store (naming it), or its file system cannot lock.
    """
    path = root / LOCK_NAME
    with _guard:
        held = _mine(path)
        if held is None:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise RunStoreError(f"cannot open {root} for writing: {exc.strerror} ({path}); check its "
                                    "permissions, or open it read-only") from None
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                info = _read_info(fd)
                os.close(fd)  # this process held no lock on it, so nothing is released
                if exc.errno not in _HELD:
                    raise _no_locks(path, exc) from None
                if _is_ancestor(info):
                    assert info is not None
                    return WriterLease(None, info)
                raise RunStoreError(f"{root} is being written by {describe(info)}; wait for it to finish or stop it, "
                                    "then try again (reading it needs no lock: open it read-only)") from None
            info = {"host": socket.gethostname(), "pid": os.getpid(), "command": _command(),
                    "since": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                    "token": uuid.uuid4().hex}
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
            st = os.fstat(fd)
            held = _held[(st.st_dev, st.st_ino)] = _Held(fd=fd, pid=os.getpid(), info=info)
        held.count += 1
        st = os.fstat(held.fd)
        return WriterLease((st.st_dev, st.st_ino), held.info)


def join(root: Path, token: str) -> WriterLease:
    """Write the store at ``root`` under the lock of the process whose :attr:`WriterLease.token`
    is ``token``, without taking it.

    Raises
    ------
    RunStoreError
        If no process holds the lock (the writer ended), or another one than the token's does.
    """
    with _guard:
        held = _mine(root / LOCK_NAME)
        if held is not None and held.info["token"] == token:
            return WriterLease(None, held.info)
        busy, info = (True, held.info) if held is not None else _other_writer(root)
    if not busy:
        raise RunStoreError(f"{root} has no writer any more: the process that shared its lock (token {token[:8]}) "
                            "has ended; run the command again")
    if not info or info.get("token") != token:
        raise RunStoreError(f"{root} is being written by {describe(info)}, not by the process that shared its lock "
                            f"(token {token[:8]}); wait for it to finish, then run the command again")
    return WriterLease(None, info)


def current_writer(root: Path) -> dict[str, Any] | None:
    """What the process writing the store at ``root`` says of itself (host, pid, command, since,
    token), or None if no process writes it now."""
    with _guard:
        held = _mine(root / LOCK_NAME)
        if held is not None:
            return dict(held.info)
        busy, info = _other_writer(root)
    return (info or {}) if busy else None
