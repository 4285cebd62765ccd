"""The run store's I/O overlapped with the computation of a whole run.

Writing one reconstructed volume of the M case (126 million voxels, 482 MiB of float32) into
the run store takes about 2 s on the development VM, as long as the goal for reconstructing it
on a GPU; reading it back for correlation about 1.5 s. Compression and file writes run in a
background thread (zarr's codecs and file I/O release the interpreter lock) while the device
works on the next frame or pair.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType
from typing import Any, TypeVar

__all__ = ["WriteBehind", "prefetched"]

K = TypeVar("K")
V = TypeVar("V")


class WriteBehind:
    """One write at a time in a background thread, while the caller computes the next result.

    :meth:`submit` first waits for the write before it, so at most one result is held beyond the
    one being computed, and writes happen in the order submitted. A write's error is raised by
    the next :meth:`submit` or :meth:`wait`, or on leaving the ``with`` block; leaving it on an
    error or Ctrl-C still finishes the write under way, so a result already computed reaches
    the store and its bookkeeping.
    """

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lfpiv-write")
        self._pending: Future[None] | None = None

    def submit(self, write: Callable[..., None], *args: Any) -> None:
        """Wait for the previous write, then start ``write(*args)`` in the background."""
        self.wait()
        self._pending = self._pool.submit(write, *args)

    def wait(self) -> None:
        """Wait for the write under way, if any; raise its error."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def __enter__(self) -> WriteBehind:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        try:
            self.wait()
        except BaseException:
            if kind is None:
                raise
            # the error that left the block is the one to report; the write's came after it
        finally:
            self._pool.shutdown(wait=True)


def prefetched(keys: Iterable[K], load: Callable[[K], V]) -> Iterator[tuple[K, V]]:
    """``(key, load(key))`` for each key, the next one loaded in a background thread while the
    caller works on the current one (at most two loaded at a time)."""
    keys = list(keys)
    if not keys:
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="lfpiv-read") as pool:
        ahead = pool.submit(load, keys[0])
        try:
            for i, key in enumerate(keys):
                value = ahead.result()
                if i + 1 < len(keys):
                    ahead = pool.submit(load, keys[i + 1])
                yield key, value
        finally:
            ahead.cancel()
