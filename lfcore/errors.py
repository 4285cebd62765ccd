"""The one device error of every layer.

:class:`DeviceError` is raised when a device refused a command, stopped answering, is missing a
feature it needs or is not there at all: a camera, the pulse generator, the stage (the drivers of
:mod:`acquisition`, which re-exports it) or a compute device (:mod:`lfcore.device`). The message
is one line naming the device and what to do. The ``lfpiv`` command reports a hardware fault with
exit code 3, after the laser was disarmed; a compute device that this machine does not have is a
choice the user can change (:class:`ComputeDeviceError`, exit code 2).
"""

from __future__ import annotations

__all__ = ["ComputeDeviceError", "DeviceError"]


class DeviceError(RuntimeError):
    """A device refused a command, stopped answering, lacks a required feature or is missing.

    The message is one line that names the device and what to do.
    """


class ComputeDeviceError(DeviceError, ValueError):
    """A compute device that does not exist on this machine (or a bad CPU thread count): the
    user's choice, not a fault of the hardware."""
