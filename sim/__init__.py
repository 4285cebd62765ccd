"""The simulated lab: devices that satisfy the acquisition protocols, so that everything runs
without hardware (``hardware = "sim"``). Only the application (:mod:`lfpiv.rigging`) wires it.
"""

__all__ = [
    "camera",            # simulated light-field cameras triggered by the emulated generator
    "lab",               # every device of a rig, simulated
    "scenes",            # the white diffuser and the dot target
    "serial_emulators",  # the pulse generator and the stage on pseudo-terminals
    "world",             # the particles the cameras see, and calibration scenes
]
