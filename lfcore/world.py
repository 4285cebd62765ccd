"""Seeded particles moving with a known flow: the truth of synthetic runs and of the simulated lab.

Each laser double pulse ``k`` lights a fresh, reproducible seeding (``seed`` and ``k`` fix it)
at its positions at the first pulse and, advected over ``dt`` with the flow, at the second.
Fresh seeding per pair is what a PIV recording of a steady flow looks like to the processing
(particles that left the volume are replaced by new ones) and keeps every pair independent of
how many pairs came before, so the truth of any pair can be made again later. ``lfpiv synth``
and the simulated lab's cameras (:class:`sim.world.SimWorld`) both look at this world.

A time-resolved world (``time_resolved=True``) instead seeds once and advects the same particles
through every frame, A0, B0, A1, B1, ... each ``dt`` apart (:meth:`ParticleWorld.series`): the
truth of a time-resolved series, through which particles can be tracked from frame to frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfcore.flows import Flow, advect, flow_for_displacement
from lfcore.particles import particle_count, seed_particles, seeding_density, sheet_weights
from lfcore.render import derive_seed
from lfcore.rig import Rig

__all__ = ["ParticleWorld"]


@dataclass
class ParticleWorld:
    """Particles in a known flow, for one rig.

    Parameters
    ----------
    rig
        The rig (volume, laser sheet and rate, first camera for the displacement scale, render
        particle counts).
    flow
        A name of :data:`lfcore.flows.FLOW_NAMES`.
    ppm
        Seeding density, particles per microlens of the first light-field camera (see
        :func:`lfcore.particles.seeding_density`: with neither ``ppm`` nor ``ppp``, 0.5 PPM, or
        0.05 ppp for a rig of pinhole cameras only; after construction both hold the density
        used, one of them None).
    displacement_px
        Peak displacement over dt in object-side pixels of the first camera (None: the flow's
        default).
    seed
        Fixes every seeding.
    omega
        Wavelength factor of the Table 4.1 flows.
    dt_s
        Time between the two pulses of a pair, s (None: the rig's ``timing.dt_us``).
    ppp
        Seeding density instead, particles per pixel of the first pinhole camera.
    time_resolved
        Frames evenly spaced in time, ``dt`` apart, pair ``k`` starting at ``2 k dt``, the same
        particles in all of them (:meth:`series`); the vortex ring is then one ring travelling on
        (not a new one each pair).
    rate_hz
        Pairs per second: pair ``k`` starts at ``k / rate_hz`` on the flow's clock, and the vortex ring
        is phase-locked to it (None: the rig's ``laser.rate_hz``; a time-resolved world's pairs are
        ``2 dt`` apart whatever it is).

    Raises
    ------
    ValueError
        An unknown flow, a bad displacement or density.
    """

    rig: Rig
    flow: str = "vortex-ring"
    ppm: float | None = None
    displacement_px: float | None = None
    seed: int = 0
    omega: float = 1.0
    dt_s: float | None = None
    ppp: float | None = None
    time_resolved: bool = False
    rate_hz: float | None = None
    _field: Flow = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.dt_s is None:
            self.dt_s = self.rig.timing.dt_us * 1e-6
        if self.rate_hz is None:
            self.rate_hz = float(self.rig.laser.rate_hz)
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"the pair rate must be positive, got {self.rate_hz}")
        self._field = flow_for_displacement(self.flow, self.rig.volume, self.rig.camera[0].object_pixel_mm,
                                            self.dt_s, displacement_px=self.displacement_px, omega=self.omega,
                                            # phase-locked ring; one ring through a series
                                            period_s=None if self.time_resolved else 1.0 / self.rate_hz)
        self.ppm, self.ppp = seeding_density(self.rig, ppm=self.ppm, ppp=self.ppp)
        self.n_particles = particle_count(self.rig, ppm=self.ppm, ppp=self.ppp)

    @property
    def flow_params(self) -> dict:
        """The flow's name and parameters, as stored in ``truth/``."""
        return self._field.params()

    def t0_s(self, k: int) -> float:
        """Time of the first pulse of double pulse ``k`` on the flow's clock, s (``2 k dt`` in a
        time-resolved world)."""
        if self.time_resolved:
            return 2.0 * k * float(self.dt_s)  # type: ignore[arg-type]
        return k / self.rate_hz  # type: ignore[operator]

    def pair(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Particles of double pulse ``k``.

        Returns
        -------
        particles : numpy.ndarray
            (2, n, 3) world positions (x, y, z) in mm at the first and the second pulse.
        brightness : numpy.ndarray
            (2, n) counts each particle deposits (laser-sheet profile applied).
        """
        rng = np.random.default_rng(derive_seed(self.seed, k))
        a = seed_particles(self.rig.volume, self.n_particles, rng)
        b = advect(self._field, a, self.t0_s(k), self.dt_s)
        particles = np.stack([a, b])
        brightness = self.rig.render.particle_counts * sheet_weights(particles.reshape(-1, 3), self.rig.laser,
                                                                     self.rig.volume)
        return particles, brightness.reshape(2, -1)

    def series(self, pairs: int) -> tuple[np.ndarray, np.ndarray]:
        """The same particles through ``2 pairs`` frames each ``dt`` apart (a time-resolved series):
        seeded once (``seed``) at frame A of pair 0 and advected from frame to frame.

        A particle that leaves the box re-enters it at the opposite face (a new particle there, as
        a flow brings new particles in), so the seeding density stays as it is through the series.

        Returns
        -------
        particles : numpy.ndarray
            (pairs, 2, n, 3) world positions (x, y, z) in mm at frames A and B of each pair.
        brightness : numpy.ndarray
            (pairs, 2, n) counts each particle deposits (laser-sheet profile applied).
        """
        dt = float(self.dt_s)  # type: ignore[arg-type]
        rng = np.random.default_rng(derive_seed(self.seed, 0))
        frames = [seed_particles(self.rig.volume, self.n_particles, rng)]
        lo, hi = (np.asarray(b, dtype=np.float64) for b in self.rig.volume.bounds_mm)
        for f in range(1, 2 * pairs):
            moved = advect(self._field, frames[-1], (f - 1) * dt, dt)
            frames.append(lo + np.mod(moved - lo, hi - lo))  # the outflow comes back as inflow
        particles = np.stack(frames).reshape(pairs, 2, self.n_particles, 3)
        brightness = self.rig.render.particle_counts * sheet_weights(particles.reshape(-1, 3), self.rig.laser,
                                                                     self.rig.volume)
        return particles, brightness.reshape(pairs, 2, -1)
