"""The rig's devices, real or simulated, opened for a job (``acquire``, ``monitor``, ``calibrate``,
``devices``).

This is the one module of the application that wires the simulated lab (``hardware = "sim"``):
:func:`open_rig` opens the pulse generator and the cameras of a rig, :func:`make_stage` the
calibration stage, and :func:`sim_lab_options` turns the ``--sim-*`` options into the simulated
lab's settings. Real drivers and simulated devices share the protocols of
:mod:`acquisition.protocols`, so every job that uses them runs unchanged on both.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any

from acquisition.protocols import Camera, PulseGenerator, Stage
from acquisition.pulse_generator import pulse_generator_for
from acquisition.stage import stage_for
from lfcore.rig import Rig
from lfpiv.errors import UsageError

__all__ = ["MAX_SIM_POOL", "Rigging", "make_stage", "open_rig", "sim_lab_options"]

#: Most distinct pairs the simulated lab renders before a recording (trigger k shows entry
#: k % pool): each takes a light field's rendering per camera, seconds on a CPU.
MAX_SIM_POOL = 1000


@dataclass
class Rigging:
    """The opened devices of a rig."""

    pulse_generator: PulseGenerator
    cameras: list[Camera]
    lab: Any = None  # the SimLab for hardware = "sim"
    stage_port: str | None = None


@contextmanager
def open_rig(rig: Rig, *, sim_options: dict[str, Any] | None = None,
             software_pairing: bool = False) -> Iterator[Rigging]:
    """Open the pulse generator and the cameras of ``rig`` (real or simulated).

    The generator is disarmed and every device released on exit, whatever happened.

    Parameters
    ----------
    rig
        The rig; ``rig.hardware`` chooses real drivers or the simulated lab.
    sim_options
        Keyword arguments of :class:`sim.lab.SimLab` (world, pool_pairs, camera_faults, ...), or
        ``{"lab": lab}`` to use an already entered :class:`sim.lab.SimLab`.
    software_pairing
        Real GenICam cameras without a double-exposure (PIV) mode may take one frame per trigger,
        paired in software by their time stamps (``lfpiv acquire --pairing timestamps``).
    """
    with ExitStack() as stack:
        lab = None
        if rig.hardware == "sim":
            from sim.lab import SimLab  # the application is the one layer that may wire the simulated lab

            opts = dict(sim_options or {})
            given = opts.pop("lab", None)  # an already started lab (tests inspect its devices)
            lab = given if given is not None else stack.enter_context(SimLab(rig, **opts))
            pulse_port, stage_port = lab.pulse_port, lab.stage_port
            cameras: list[Camera] = list(lab.cameras)
        else:
            from acquisition.genicam import GenICamCamera

            if rig.pulse_generator.port is None:
                raise UsageError("pulse_generator.port is not set in the rig file; give the serial port "
                                 "of the pulse generator (e.g. /dev/ttyUSB0), or set hardware = \"sim\"")
            pulse_port, stage_port = rig.pulse_generator.port, rig.stage.port
            unnamed = [c.name for c in rig.camera if c.serial is None]
            if unnamed and len(rig.camera) > 1:
                # without serials both would open the first device found
                raise UsageError(f"camera '{unnamed[0]}' has no serial in the rig file; with {len(rig.camera)} "
                                 "cameras each needs its GenICam serial number (lfpiv devices lists them)")
            cameras = [GenICamCamera(c.name, serial=c.serial, producers=list(rig.gentl_producers) or None,
                                     allow_software_pairing=software_pairing) for c in rig.camera]
        gen = pulse_generator_for(pulse_port, rig.pulse_generator)
        stack.callback(gen.close)
        gen.open()
        for cam in cameras:
            stack.callback(cam.close)
            cam.open()
        yield Rigging(gen, cameras, lab, stage_port)


def make_stage(port: str, rig: Rig) -> Stage:
    """The stage driver for ``port`` with the rig's ``[stage]`` settings, not yet open."""
    return stage_for(port, rig.stage)


def sim_lab_options(rig: Rig, *, flow: str, ppm: float | None, pool: int, rays: int | None,
                    ppp: float | None = None) -> dict[str, Any] | None:
    """Keyword arguments of :class:`sim.lab.SimLab` from the ``--sim-*`` options, or None for
    real hardware.

    Parameters
    ----------
    rig
        The rig; only ``hardware = "sim"`` uses the options.
    flow, ppm, ppp
        The flow the simulated cameras see and its seeding, particles per microlens or per pixel
        of the first pinhole camera (neither: see :func:`lfcore.particles.seeding_density`).
    pool
        Distinct pairs rendered when the lab opens and cycled through.
    rays
        Rays per particle of the rendering (None: the rig's).

    Raises
    ------
    UsageError
        A bad flow or density, in one line.
    """
    if rig.hardware != "sim":
        return None
    if not 1 <= pool <= MAX_SIM_POOL:
        raise UsageError(f"--sim-pool must be from 1 to {MAX_SIM_POOL} pairs, got {pool}: each is rendered (for every "
                         "camera) before the recording starts, and trigger k shows entry k % pool")
    from sim.world import SimWorld

    try:
        world = SimWorld(rig, flow=flow, ppm=ppm, ppp=ppp)
    except ValueError as exc:
        raise UsageError(f"--sim-flow/--sim-{'ppp' if ppp is not None else 'ppm'}: {exc}") from None
    return {"world": world, "pool_pairs": pool, "rays_per_particle": rays}
