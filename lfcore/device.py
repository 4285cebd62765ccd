"""Warp start-up and compute-device selection.

Every Warp kernel in :mod:`lfcore._kernels` runs on the CPU and on CUDA GPUs. Callers name a
device as ``"cpu"``, ``"cuda"`` (the default GPU) or ``"cuda:N"``, or pass ``None``/``"auto"``
for the first GPU if there is one, else the CPU.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

import warp as wp

from lfcore.errors import ComputeDeviceError, DeviceError

__all__ = ["ComputeDeviceError", "DeviceError", "MemoryBudgetError", "PerBlock", "RowOffset", "Rows", "available_bytes",
           "available_devices", "cpu_threads", "launch_rows", "PrivateCopies", "out_of_memory_is_budget_error",
           "private_copies", "resolve_device", "warp"]




class MemoryBudgetError(MemoryError):
    """The work would not fit in the device's memory; the message says what to change."""


@contextlib.contextmanager
def out_of_memory_is_budget_error(device: str, what: str, advice: str):
    """Turn a failed Warp allocation inside the block into a :class:`MemoryBudgetError`.

    Sizes are checked before the large allocations, but other buffers (and other programs on
    the same GPU) take memory too; an allocation that still fails then says what ran out and
    what to change rather than ending in a traceback.

    Parameters
    ----------
    device
        The Warp device the block allocates on.
    what
        What the block does, e.g. ``"the weights of 1,234 voxels"``.
    advice
        What to change, e.g. ``"use a coarser --pvr"``.
    """
    try:
        yield
    except RuntimeError as exc:
        text = str(exc)
        if not text.startswith("Failed to allocate"):
            raise
        size = text.split(" bytes", 1)[0].rsplit(" ", 1)[-1]
        need = f" ({int(size) / 2**30:.1f} GiB more)" if size.isdigit() else ""
        raise MemoryBudgetError(f"{what} ran out of memory on {device}{need}; {advice}") from None


def _cuda_driver_present() -> bool:
    if not sys.platform.startswith("linux"):
        return True
    for name in ("libcuda.so", "libcuda.so.1"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextlib.contextmanager
def _native_stderr_silenced():
    """Hide what native code writes to stderr (file descriptor 2) inside the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@functools.cache
def warp():
    """Initialise Warp once, quietly, and return the module."""
    # Start-up banners, and the native "no CUDA driver" notice on machines that have no NVIDIA
    # driver at all (we checked), are noise to a user of a CPU-only machine.
    wp.config.log_level = wp.LOG_ERROR
    if _cuda_driver_present():
        wp.init()
    else:
        with _native_stderr_silenced():
            wp.init()
    return wp


def host_available_bytes(*, meminfo: str = "/proc/meminfo") -> int:
    """RAM a new allocation can have without swapping: Linux's MemAvailable, which counts the page
    cache the kernel gives back on demand (free pages alone can be a small part of it on a
    workstation that has just read a run store); elsewhere the free pages."""
    try:
        with open(meminfo) as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))


def available_bytes(device: str) -> int:
    """Memory free now on ``device``: the host's available RAM for ``"cpu"``, else the GPU's."""
    if device == "cpu":
        return host_available_bytes()
    return int(warp().get_device(device).free_memory)


def available_devices() -> list[str]:
    """Aliases of every device Warp finds, CPU first (e.g. ``['cpu', 'cuda:0']``)."""
    return [d.alias for d in warp().get_devices()]


def resolve_device(device: str | None) -> str:
    """Validate a device name and return Warp's alias for it.

    Parameters
    ----------
    device
        ``"cpu"``, ``"cuda"``, ``"cuda:N"``, or None or ``"auto"`` for the first GPU, else the CPU.

    Returns
    -------
    str
        Warp's alias (``"cpu"`` or ``"cuda:N"``).

    Raises

    ------
    ComputeDeviceError
        If the device does not exist, with the list of devices that do.
    """
    found = available_devices()
    if device in (None, "auto"):
        return "cuda:0" if "cuda:0" in found else "cpu"
    name = "cuda:0" if device == "cuda" else device
    if name not in found:
        raise ComputeDeviceError(f"device '{device}' is not available here; choose one of: {', '.join(found)}")
    return name


@functools.cache
def cpu_threads() -> int:
    """Threads that one CPU launch is split over: ``LFPIV_CPU_THREADS`` if set, else the cores
    this process may run on."""
    env = os.environ.get("LFPIV_CPU_THREADS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ComputeDeviceError(f"LFPIV_CPU_THREADS must be a whole number of threads, got '{env}'") from None
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@functools.cache
def _pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=max(1, cpu_threads() - 1), thread_name_prefix="lfpiv-cpu-launch")


if hasattr(os, "register_at_fork"):  # a forked child has none of the parent's pool threads
    os.register_at_fork(after_in_child=_pool.cache_clear)


@dataclass(frozen=True)
class Rows:
    """An input of :func:`launch_rows` that the first thread index addresses.

    Each block of rows ``lo .. hi - 1`` gets ``array[lo * scale // div : ceil(hi * scale / div) + extra]``
    (clipped to the array): ``scale=2`` where a row reads two elements (e.g. two windows),
    ``div=2`` where two rows share one element, ``extra=1`` for CSR offsets (row t also reads
    element t + 1).
    """

    array: Any
    scale: int = 1
    div: int = 1
    extra: int = 0


@dataclass(frozen=True)
class PerBlock:
    """An input of :func:`launch_rows` that differs per CPU block: block k gets ``arrays[k]``
    (on a GPU, and in an unsplit launch, ``arrays[0]``); the launch makes at most as many blocks
    as there are arrays. For private accumulation buffers, since CPU atomics are not atomic."""

    arrays: tuple


#: Most memory that the private accumulation images of one split CPU launch may take.
PRIVATE_BYTES = 1 << 30


def private_copies(nbytes: int) -> int:
    """How many private copies of an ``nbytes`` accumulation buffer a split CPU launch should
    add to the caller's own: one per further CPU thread, within :data:`PRIVATE_BYTES`."""
    return max(0, min(cpu_threads() - 1, PRIVATE_BYTES // max(1, int(nbytes))))


class PrivateCopies:
    """Private copies of one accumulation buffer for the blocks of split CPU launches.

    A kernel that accumulates with atomics cannot share its output between CPU blocks (Warp's
    CPU atomics are plain adds). :meth:`open` gives the :class:`PerBlock` input: the buffer
    itself and zeroed copies, as many as :func:`private_copies` allows; after the launches,
    :meth:`close` adds the copies into the buffer. On a GPU the buffer is used alone. The
    copies are allocated on first use and kept for the next launches.
    """

    def __init__(self) -> None:
        self._parts: Any = None
        self._n = 0

    def open(self, out: Any) -> PerBlock:
        """The per-block outputs for launches that accumulate into ``out``."""
        self._n = private_copies(out.numpy().nbytes) if str(out.device) == "cpu" else 0
        if self._n:
            shape = (self._n, *out.shape)
            if self._parts is None or tuple(self._parts.shape) != shape or self._parts.dtype != out.dtype:
                self._parts = wp.zeros(shape, dtype=out.dtype, device=out.device)
            else:
                self._parts.zero_()
        return PerBlock((out, *(self._parts[k] for k in range(self._n))))

    def close(self, out: Any) -> None:
        """Add what the other blocks accumulated into ``out`` (on the CPU, in place)."""
        if self._n:
            total = out.numpy()  # on the CPU, a view of the array
            total += self._parts.numpy().sum(axis=0)
            self._n = 0


@dataclass(frozen=True)
class RowOffset:
    """An integer input of :func:`launch_rows` that gives the first row's global index: each
    block gets ``value + lo``."""

    value: int


def _block_input(item: Any, lo: int, hi: int, block: int = 0) -> Any:
    if isinstance(item, Rows):
        a, b = lo * item.scale // item.div, -(-hi * item.scale // item.div) + item.extra
        return item.array[a:min(b, item.array.shape[0])]
    if isinstance(item, RowOffset):
        return int(item.value) + lo
    if isinstance(item, PerBlock):
        return item.arrays[block]
    return item


def launch_rows(kernel: Any, rows: int, inputs: Sequence[Any], device: str, *, rest: tuple[int, ...] = (),
                align: int = 1, stream: Any = None) -> None:
    """Launch ``kernel`` over ``(rows, *rest)`` threads; on the CPU, over all cores.

    Warp runs a CPU launch on one thread. Here the rows (the first launch dimension) are cut
    into one contiguous block per core and the blocks are launched concurrently: ctypes releases
    the GIL for the length of each native call, so they run in parallel. On a GPU this is one
    ordinary launch.

    Parameters
    ----------
    kernel
        A Warp kernel whose blocks write disjoint memory. Warp's CPU ``atomic_add`` is a plain
        read-modify-write, so a kernel that accumulates with atomics needs its output as a
        :class:`PerBlock` input (see :class:`PrivateCopies`).
    rows
        Size of the first launch dimension.
    inputs
        The kernel's inputs. Wrap every array that the first thread index addresses in
        :class:`Rows`, and an integer that gives the first row's global index in
        :class:`RowOffset`; each block then sees its rows as ``0 .. hi - lo - 1``.
    device
        Warp device alias.
    rest
        The other launch dimensions.
    align
        Block boundaries are multiples of this (e.g. 2 where two rows share one element).
    stream
        CUDA stream of the launch (ignored on the CPU).
    """
    if rows <= 0:
        return
    threads = cpu_threads() if device == "cpu" else 1
    threads = min([threads] + [len(x.arrays) for x in inputs if isinstance(x, PerBlock)])
    blocks = min(threads, rows // max(align, 1))
    if blocks <= 1:
        wp.launch(kernel, dim=(rows, *rest), inputs=[_block_input(x, 0, rows) for x in inputs], device=device,
                  stream=stream)
        return
    per = -(-rows // blocks)
    per = -(-per // align) * align

    def run(block: int, lo: int, hi: int) -> None:
        wp.launch(kernel, dim=(hi - lo, *rest), inputs=[_block_input(x, lo, hi, block) for x in inputs],
                  device=device)

    bounds = [(lo, min(rows, lo + per)) for lo in range(0, rows, per)]
    futures = [_pool().submit(run, k, lo, hi) for k, (lo, hi) in enumerate(bounds) if k > 0]
    try:
        run(0, *bounds[0])
    finally:
        wait(futures)  # never return while a block still writes
    for f in futures:
        f.result()
