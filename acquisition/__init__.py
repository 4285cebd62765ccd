"""Device protocols and real drivers: GenICam cameras (harvesters), the Quantum Composers 9520 /
BNC 575 pulse generator and Zaber stages (pyserial), the PIV timing plan, synchronised
double-frame recording into the run store, and the ring buffer the live pipeline reads.

Real drivers and the simulated devices of :mod:`sim` implement the same protocols
(:mod:`acquisition.protocols`); the application reaches the drivers through
:func:`acquisition.stage.stage_for` and :func:`acquisition.pulse_generator.pulse_generator_for`.
"""

__all__ = [
    "genicam",          # GenICam cameras through harvesters
    "protocols",        # Camera, PulseGenerator, Stage, Frame, TimingPlan, DeviceError
    "pulse_generator",  # the pulse-generator driver and its laser-safety signal handling
    "ring",             # the pair ring buffer
    "serial_link",      # the line-oriented serial link of both serial drivers
    "session",          # synchronised double-frame recording
    "stage",            # the Zaber stage driver
    "timing",           # the PIV timing plan
]
