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

import warp as wp

__all__ = ["DeviceError", "available_devices", "resolve_device", "warp"]


class DeviceError(ValueError):
    """A compute device that does not exist on this machine."""


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


def available_devices() -> list[str]:
    """Aliases of every device Warp finds, CPU first (e.g. ``['cpu', 'cuda:0']``)."""
    return [d.alias for d in warp().get_devices()]


def resolve_device(device: str | None = None) -> str:
    """Validate a device name and return Warp's alias for it.

    Raises
    ------
    DeviceError
        If the device does not exist, with the list of devices that do.
    """
    found = available_devices()
    if device in (None, "auto"):
        return "cuda:0" if "cuda:0" in found else "cpu"
    name = "cuda:0" if device == "cuda" else device
    if name not in found:
        raise DeviceError(f"device '{device}' is not available here; choose one of: {', '.join(found)}")
    return name
