"""What answers of the devices a rig names (``lfpiv devices``): nothing is armed or moved."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any

from acquisition.protocols import DeviceError
from acquisition.pulse_generator import pulse_generator_for
from lfcore.rig import Rig
from lfpiv.rigging import make_stage

__all__ = ["list_devices"]


def list_devices(rig: Rig) -> list[tuple[str, bool]]:
    """What answers of the devices ``rig`` names, one line each with whether it was found.

    Nothing is armed or moved. For ``hardware = "sim"`` the simulated lab is started and its
    emulated devices are queried with the real serial drivers.
    """
    lines: list[tuple[str, bool]] = []
    with ExitStack() as stack:
        if rig.hardware == "sim":
            from sim.lab import SimLab

            lab = stack.enter_context(SimLab(rig, reply_latency_s=0.0))
            pulse_port, stage_port = lab.pulse_port, lab.stage_port
            for cam in lab.cameras:
                cols, rows = cam.sensor_px
                lines.append((f"camera  {cam.name}: simulated light-field camera, {cols} x {rows} px", True))
        else:
            from acquisition.genicam import list_devices as genicam_devices

            pulse_port, stage_port = rig.pulse_generator.port, rig.stage.port
            try:
                seen = genicam_devices(list(rig.gentl_producers) or None)
            except DeviceError as exc:
                seen = []
                lines.append((f"cameras: {exc}", False))
            by_serial = {d.serial_number: d for d in seen}
            for cam in rig.camera:
                if cam.serial is None:
                    lines.append(_unpinned_camera(cam.name, seen, len(rig.camera)))
                    continue
                d = by_serial.get(cam.serial)
                if d is not None:
                    lines.append((f"camera  {cam.name}: {d.vendor} {d.model}, serial {d.serial_number} ({d.access})",
                                  True))
                else:
                    lines.append((f"camera  {cam.name}: serial {cam.serial!r} not found (seen: "
                                  f"{sorted(by_serial) or 'none'}); check the cable, power and the rig's serial",
                                  False))
        for label, port, probe in (("pulse generator", pulse_port, _probe_generator),
                                   ("stage", stage_port, _probe_stage)):
            if port is None:
                lines.append((f"{label}: no port in the rig file", False))
                continue
            try:
                lines.append((f"{label}: {probe(port, rig)} on {port}", True))
            except DeviceError as exc:
                lines.append((f"{label}: {exc}", False))
    return lines


def _unpinned_camera(name: str, seen: list[Any], n_cameras: int) -> tuple[str, bool]:
    """The devices line of a camera with no serial in the rig file."""
    serials = sorted(d.serial_number for d in seen)
    if n_cameras > 1:
        return (f"camera  {name}: no serial in the rig file; set serial to one of {serials or 'none found'} "
                "(with several cameras each needs its own)", False)
    if not seen:
        return f"camera  {name}: no GenICam device found; check the cable, power and gentl_producers", False
    d = seen[0]
    return (f"camera  {name}: {d.vendor} {d.model}, serial {d.serial_number} ({d.access}), the first device "
            f"found; set serial = \"{d.serial_number}\" in the rig file to pin it", True)


def _probe_generator(port: str, rig: Rig) -> str:
    gen = pulse_generator_for(port, rig.pulse_generator)
    try:
        gen.open()
        return gen.identify()
    finally:
        gen.close()


def _probe_stage(port: str, rig: Rig) -> str:
    stage = make_stage(port, rig)
    try:
        stage.open()
        return (f"Zaber stage at {stage.position_mm():.4f} mm, travel {stage.travel_mm[0]:g}..{stage.travel_mm[1]:g} "
                f"mm: {stage.describe()}")
    finally:
        stage.close()
