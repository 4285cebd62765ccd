"""Device roles of the rig as :class:`typing.Protocol` classes, and the :class:`Frame` record.

Real drivers (``acquisition.genicam``, ``acquisition.pulse_generator``, ``acquisition.stage``)
and the simulated devices of ``sim`` implement the same protocols, so the acquisition session,
the calibration runner and the live monitor never know which they drive.

Frame numbering. A light-field PIV camera in double-exposure (frame-straddling) mode delivers
two frames per trigger: frame A, exposed around the first laser pulse, then frame B around the
second. ``Frame.frame_id`` counts every frame the camera produced since :meth:`Camera.start`,
starting at ``Camera.first_frame_id``, so that pair ``k`` holds frames
``first_frame_id + 2k`` (A) and ``first_frame_id + 2k + 1`` (B). A frame the camera produced but
never delivered leaves a gap in ``frame_id``; the session turns every gap into a drop record.

A trigger the camera missed makes no frames and leaves no gap in ``frame_id``; only the time
stamps show it, and only where they come from the camera's clock (``Frame.device_clock``): two
consecutive frames A then lie two trigger periods apart instead of one. The session uses that
to keep the pairing right (see :mod:`acquisition.session`).

A camera whose driver discards incomplete images itself (harvesters does) may say how many it
discarded in an ``int`` attribute ``incomplete_frames``; the session then names the ``frame_id``
gaps they leave "incomplete frame" rather than "frame_id gap".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from lfcore.errors import DeviceError  # the one device error of every layer

__all__ = ["Camera", "ChannelSetting", "DeviceError", "Frame", "PulseGenerator", "Stage", "TimingPlan"]


@dataclass(frozen=True, slots=True)
class Frame:
    """One image delivered by a camera.

    Attributes
    ----------
    data
        uint16 array of shape (rows, columns), row 0 at the top of the sensor.
    camera
        Name of the camera in the rig file.
    frame_id
        Frame counter since acquisition start (see the module docstring).
    timestamp_ns
        Exposure time stamp in nanoseconds: the camera's clock where it has one, otherwise the
        host's ``time.time_ns()`` when the frame was fetched.
    complete
        False when the transport delivered a partial image (lost packets); the session records
        such a frame as a drop with the reason "incomplete".
    device_clock
        True when ``timestamp_ns`` comes from the camera's own clock (latched at the same point
        of every exposure, so differences are multiples of the trigger period); False for host
        fetch times, which carry transport and scheduling delays and prove nothing about
        triggers.
    """

    data: np.ndarray
    camera: str
    frame_id: int
    timestamp_ns: int
    complete: bool = True
    device_clock: bool = False


@runtime_checkable
class Camera(Protocol):
    """A light-field camera, real (GenICam) or simulated.

    Life cycle: ``open`` → ``configure`` → ``start`` → ``fetch`` … → ``stop`` → ``close``.
    ``close`` is safe to call in any state and more than once.
    """

    name: str

    @property
    def sensor_px(self) -> tuple[int, int]:
        """(columns, rows) of the delivered image."""
        ...

    @property
    def first_frame_id(self) -> int:
        """``frame_id`` of the first frame after :meth:`start`."""
        ...

    def open(self) -> None:
        """Connect to the device."""
        ...

    def configure(self, *, triggered: bool, frames_per_trigger: int, exposure_us: float,
                  dt_us: float | None = None) -> None:
        """Set up external triggering (or free run) and the exposure.

        Parameters
        ----------
        triggered
            True: one trigger on the camera's trigger line starts a burst of
            ``frames_per_trigger`` frames. False: free run (for cameras without trigger
            features, such as the GenTL simulator).
        frames_per_trigger
            2 for double-frame PIV (frame straddling), 1 otherwise.
        exposure_us
            Exposure of the first frame of a burst, microseconds.
        dt_us
            Time between the two laser pulses of a pair, microseconds, for cameras that must
            check that frame B catches the second pulse (see
            :meth:`acquisition.genicam.GenICamCamera.configure`); None when not known.
        """
        ...

    def start(self) -> None:
        """Start acquisition; frames produced from now on are delivered by :meth:`fetch`."""
        ...

    def fetch(self, timeout_s: float) -> Frame | None:
        """The oldest delivered frame not yet fetched, or None after ``timeout_s`` seconds."""
        ...

    def stop(self) -> None:
        """Stop acquisition. Frames already delivered may still be fetched."""
        ...

    def close(self) -> None:
        """Release the device."""
        ...


@dataclass(frozen=True, slots=True)
class ChannelSetting:
    """One output channel of the pulse generator.

    Attributes
    ----------
    channel
        Output channel number, 1-based (A = 1).
    role
        What the output drives, e.g. "flashlamp1", "qswitch1", "flashlamp2", "qswitch2",
        "camera".
    delay_s, width_s
        Delay after the generator's T0 and pulse width, seconds.
    polarity
        "NORM" (active high) or "INV".
    """

    channel: int
    role: str
    delay_s: float
    width_s: float
    polarity: str = "NORM"


@dataclass(frozen=True, slots=True)
class TimingPlan:
    """Everything the pulse generator is programmed with for one double-frame recording.

    Attributes
    ----------
    period_s
        T0 period, the inverse of the double-pulse rate.
    dt_s
        Time between the two laser pulses of a pair.
    channels
        One entry per output used.
    pulses
        Number of T0 periods (pairs) to fire; 0 means run until disarmed.
    notes
        Human-readable lines explaining the plan (derived times, shifts, margins).
    pulse_times_s
        Laser pulse 1 and pulse 2 after T0, seconds (empty if the planner does not derive them).
    frame_windows_s
        Exposure windows (start, end) of frame A and frame B after T0, seconds.
    """

    period_s: float
    dt_s: float
    channels: tuple[ChannelSetting, ...]
    pulses: int = 0
    notes: tuple[str, ...] = field(default=())
    pulse_times_s: tuple[float, ...] = field(default=())
    frame_windows_s: tuple[tuple[float, float], ...] = field(default=())

    def channel_for(self, role: str) -> ChannelSetting:
        """The channel that drives ``role``."""
        for c in self.channels:
            if c.role == role:
                return c
        raise KeyError(role)


@runtime_checkable
class PulseGenerator(Protocol):
    """The pulse generator that fires both laser cavities and triggers the cameras.

    Safety contract: after :meth:`disarm` or :meth:`close`, and after any error raised by a
    method, every output is disabled. Implementations are context managers whose ``__exit__``
    disarms.
    """

    def open(self) -> None:
        """Open the port and check that the instrument answers."""
        ...

    def identify(self) -> str:
        """The instrument's identification string."""
        ...

    def program(self, plan: TimingPlan) -> None:
        """Load a timing plan, outputs disabled."""
        ...

    def arm(self) -> None:
        """Enable the outputs of the plan and start T0: the laser fires from now on."""
        ...

    def disarm(self) -> None:
        """Stop T0 and disable every output. Never raises for a device that answers."""
        ...

    def verify(self) -> None:
        """Read the programmed settings (and, armed, the outputs) back; a difference means the
        instrument was reset, power-cycled or changed from its front panel: disarm and raise
        :class:`DeviceError`. Called about once a second during a recording."""
        ...

    @property
    def armed(self) -> bool:
        """True between :meth:`arm` and :meth:`disarm`."""
        ...

    def close(self) -> None:
        """Disarm (best effort) and release the port."""
        ...


@runtime_checkable
class Stage(Protocol):
    """The motorised stage that carries the calibration target along one axis, millimetres.

    Implementations are context managers: entering opens the port, leaving stops a move under way
    if an error is leaving, then releases the port.
    """

    def open(self) -> None:
        """Open the port, check that the device answers and read its travel limits."""
        ...

    def describe(self) -> str:
        """One line naming the stage (its product and device id, serial, firmware)."""
        ...

    @property
    def travel_mm(self) -> tuple[float, float]:
        """(min, max) positions the stage accepts, mm (known once open)."""
        ...

    def home(self) -> None:
        """Move to the home sensor and zero the position; blocks until done."""
        ...

    def move_to(self, position_mm: float) -> float:
        """Move to an absolute position, block until the stage is idle; return the readback."""
        ...

    def position_mm(self) -> float:
        """Current position read back from the stage."""
        ...

    def stop(self) -> None:
        """Decelerate to a stop now."""
        ...

    def close(self) -> None:
        """Release the port."""
        ...

    def __enter__(self) -> Stage: ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None: ...
