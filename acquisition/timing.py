"""The PIV timing plan: when the pulse generator fires each laser cavity and triggers the cameras.

Pure computation, no I/O. :func:`plan_timing` turns the ``[laser]``, ``[timing]`` and
``[pulse_generator]`` tables of a rig into a :class:`~acquisition.protocols.TimingPlan` that a
pulse-generator driver programs as it is.

Frame straddling. A double-pulsed Nd:YAG laser has two cavities; each fires when its
flashlamp has pumped the rod and its Q-switch opens, ``qswitch_delay_us`` after the flashlamp
trigger. A PIV camera in double-exposure mode, triggered once per pair, exposes frame A for
``camera_exposure_us``, then needs ``camera_interframe_us`` to move the charge of frame A out
of the way, then exposes frame B until frame A has been read out (about one frame time,
``1 / camera_max_fps``). Pulse 1 is placed :data:`STRADDLE_MARGIN_US` before frame A ends and
pulse 2 exactly ``dt`` later, which must be at least the same margin after frame B starts::

    T0          _|-|______________________________________________________________
    flashlamp 1 ____|--|__________________________________________________________  s
    Q-switch 1  _______________________|-|________________________________________  pulse 1 = s + q
    flashlamp 2 __________________________________|--|____________________________  s + dt
    Q-switch 2  _____________________________________________________|-|__________  pulse 2 = pulse 1 + dt
    camera      ____________|------------|________________________________________  s + q - E + m, width E
    frame A                 [===========]                                           closes m after pulse 1
    frame B                              [I][==============================...       pulse 2 >= m inside

Here ``q`` is the Q-switch delay, ``E`` the exposure of frame A, ``I`` the interframe time,
``m`` the straddle margin and ``s`` the shift that makes every delay non-negative (needed
when the exposure is longer than the Q-switch delay, so the camera must be triggered before
flashlamp 1). The camera trigger pulse is ``E`` wide, so it works both for cameras that time
the exposure themselves (edge trigger) and for those whose exposure follows the pulse width.
The plan assumes the camera starts exposing on the trigger edge (no trigger latency).

Impossible plans raise :class:`TimingError` with one line that names the key and the fix.
"""

from __future__ import annotations

from lfcore.rig import Rig

from .protocols import ChannelSetting, TimingPlan

__all__ = ["STRADDLE_MARGIN_US", "TimingError", "plan_timing"]

#: Safety margin, microseconds, between a laser pulse and the edge of the frame it must fall in:
#: pulse 1 comes this long before frame A closes, pulse 2 at least this long after frame B opens.
#: It absorbs trigger jitter (tens of ns on a digital delay generator, up to a few hundred ns in
#: a camera's trigger input) and the Q-switch build-up time of the laser (a few ns).
STRADDLE_MARGIN_US = 0.5


class TimingError(ValueError):
    """A timing plan that cannot work; the message is one line naming the cause and the fix."""


def plan_timing(rig: Rig, pulses: int = 0) -> TimingPlan:
    """Plan the frame-straddling sequence of one double-frame recording.

    Parameters
    ----------
    rig
        The rig; its ``laser``, ``timing`` and ``pulse_generator.channels`` are used.
    pulses
        Number of pairs (T0 periods) to fire; 0 (default) runs until the generator is disarmed.

    Returns
    -------
    TimingPlan
        Period, dt, one :class:`ChannelSetting` per role (flashlamp1, qswitch1, flashlamp2,
        qswitch2, camera) with non-negative delays after T0, the derived pulse times and frame
        windows, and notes that explain them.

    Raises
    ------
    TimingError
        When the rate exceeds the laser's or the camera's limit, ``dt`` is shorter than the
        camera's interframe time plus margins or longer than frame B, the exposure is shorter
        than the margins, or the whole sequence does not fit in one T0 period.
    """
    laser, timing = rig.laser, rig.timing
    channels = rig.pulse_generator.channels
    m = STRADDLE_MARGIN_US
    if pulses < 0:
        raise TimingError(f"pulses = {pulses} is negative; give the number of pairs, or 0 to run until disarmed")
    if laser.rate_hz > laser.max_rate_hz:
        raise TimingError(
            f"laser.rate_hz = {laser.rate_hz:g} Hz is above laser.max_rate_hz = {laser.max_rate_hz:g} Hz; "
            "lower laser.rate_hz"
        )
    if 2 * laser.rate_hz > timing.camera_max_fps:
        raise TimingError(
            f"2 x laser.rate_hz = {2 * laser.rate_hz:g} frames/s is above timing.camera_max_fps = "
            f"{timing.camera_max_fps:g} (two frames per pair); lower laser.rate_hz to at most "
            f"{timing.camera_max_fps / 2:g} Hz"
        )
    exposure, interframe, dt, q = (timing.camera_exposure_us, timing.camera_interframe_us,
                                   timing.dt_us, timing.qswitch_delay_us)
    if exposure < 2 * m:
        raise TimingError(
            f"timing.camera_exposure_us = {exposure:g} us is shorter than twice the {m:g} us straddle margin; "
            f"raise camera_exposure_us to at least {2 * m:g} us so frame A can hold pulse 1"
        )
    dt_min = interframe + 2 * m
    if dt < dt_min:
        raise TimingError(
            f"timing.dt_us = {dt:g} us is below timing.camera_interframe_us = {interframe:g} us plus 2 x {m:g} us "
            f"margin, so both pulses would land in one frame; raise dt_us to at least {dt_min:g} us"
        )
    frame_us = 1e6 / timing.camera_max_fps  # frame B stays open until frame A is read out
    dt_max = interframe + frame_us
    if dt > dt_max:
        raise TimingError(
            f"timing.dt_us = {dt:g} us puts pulse 2 after frame B closes (frame B lasts about "
            f"1/timing.camera_max_fps = {frame_us:.0f} us); lower dt_us to at most {dt_max:.0f} us"
        )

    # Times relative to flashlamp 1, microseconds; shifted below so that none is negative.
    p1 = q
    p2 = p1 + dt
    cam = p1 - (exposure - m)  # frame A = [cam, cam + exposure] ends m after pulse 1
    shift = max(0.0, -cam)
    fl_w, qs_w = laser.flashlamp_width_us, laser.qswitch_width_us
    events = {
        "flashlamp1": (0.0, fl_w),
        "qswitch1": (p1, qs_w),
        "flashlamp2": (dt, fl_w),
        "qswitch2": (p2, qs_w),
        "camera": (cam, exposure),
    }
    events = {role: (delay + shift, width) for role, (delay, width) in events.items()}
    p1, p2, cam = p1 + shift, p2 + shift, cam + shift
    frame_a = (cam, cam + exposure)
    frame_b = (frame_a[1] + interframe, frame_a[1] + interframe + frame_us)

    period_us = 1e6 / laser.rate_hz
    span = max(max(d + w for d, w in events.values()), frame_b[1])
    if span >= period_us:
        raise TimingError(
            f"the sequence (timing.qswitch_delay_us + timing.dt_us + exposure, widths and frame B) lasts "
            f"{span:.1f} us, longer than the T0 period 1/laser.rate_hz = {period_us:.1f} us; "
            "lower laser.rate_hz or timing.dt_us"
        )

    settings = tuple(
        ChannelSetting(channel=channels[role], role=role, delay_s=_s(d), width_s=_s(w))
        for role, (d, w) in events.items()
    )
    notes = [
        f"T0 period {period_us:.3f} us ({laser.rate_hz:g} Hz), "
        + (f"{pulses} pairs (burst)" if pulses else "continuous until disarmed"),
        f"pulse 1 at {p1:.3f} us, pulse 2 at {p2:.3f} us after T0 (dt = {dt:g} us)",
        f"frame A {frame_a[0]:.3f}-{frame_a[1]:.3f} us, frame B from {frame_b[0]:.3f} us "
        f"(interframe {interframe:g} us, straddle margin {m:g} us)",
    ]
    if shift > 0:
        notes.append(f"every output delayed by {shift:.3f} us so the camera trigger does not precede T0")
    return TimingPlan(
        period_s=_s(period_us),
        dt_s=_s(dt),
        channels=settings,
        pulses=pulses,
        notes=tuple(notes),
        pulse_times_s=(_s(p1), _s(p2)),
        frame_windows_s=((_s(frame_a[0]), _s(frame_a[1])), (_s(frame_b[0]), _s(frame_b[1]))),
    )


def _s(us: float) -> float:
    """Microseconds to seconds, rounded to 1 ps so printed plans do not show float noise."""
    return round(us * 1e-6, 12)
