"""The simulated lab of a rig: every device the rig names, simulated, with the same interfaces.

The pulse generator and the stage are emulated behind real pseudo-terminals, so the
application drives them with the real serial drivers (:mod:`acquisition.pulse_generator`,
:mod:`acquisition.stage`) exactly as in the lab; the light-field cameras are
:class:`~sim.camera.SimCamera` objects triggered by the emulated generator's camera output and
looking at one shared :class:`~sim.world.SimWorld`.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from typing import Any

import numpy as np

from acquisition.stage import ZABER_PRODUCTS
from lfcore.rig import Rig
from sim.camera import SimCamera
from sim.serial_emulators import PulseGeneratorEmulator, StageEmulator
from sim.world import SimWorld

__all__ = ["SimLab"]


def _emulated(microstep_um: float) -> bool:
    """Whether an emulated Zaber stage has microsteps of this size at resolution 64."""
    return any(p.integrated and abs(p.full_step_um / 64 - microstep_um) < 1e-12 for p in ZABER_PRODUCTS.values())


class SimLab:
    """Emulated pulse generator and stage, and simulated cameras, for ``rig``.

    Use as a context manager; the ports exist between ``__enter__`` and ``__exit__``.

    Parameters
    ----------
    rig
        The rig to simulate.
    world
        What the cameras see (default: a vortex ring at 0.5 PPM, seed 0).
    pool_pairs, rays_per_particle, device
        Passed to every :class:`~sim.camera.SimCamera`.
    camera_faults
        Per camera name, keyword arguments of :class:`~sim.camera.SimCamera` that inject faults
        (``lose_frames``, ``incomplete_frames``, ``lose_rate``, ``fail_after_frames``).
    reply_latency_s
        Reply delay of the serial emulators.
    """

    def __init__(self, rig: Rig, *, world: SimWorld | None = None, pool_pairs: int = 4,
                 rays_per_particle: int | None = None, device: str | None = None,
                 camera_faults: dict[str, dict[str, Any]] | None = None, reply_latency_s: float = 0.002) -> None:
        self.rig = rig
        self.world = world if world is not None else SimWorld(rig)
        self._pool_pairs = pool_pairs
        self._rays = rays_per_particle
        self._device = device
        self._faults = camera_faults or {}
        self._latency = reply_latency_s
        self._stack = ExitStack()
        self.pulse_generator: PulseGeneratorEmulator | None = None
        self.stage: StageEmulator | None = None
        self.cameras: list[SimCamera] = []

    def __enter__(self) -> SimLab:
        try:
            self.pulse_generator = self._stack.enter_context(PulseGeneratorEmulator(latency_s=self._latency))
            st = self.rig.stage
            # the emulated product whose microstep the rig names (the default stage otherwise: the
            # driver reads the real size from the device and reports a rig value that disagrees)
            microstep = st.microstep_um if _emulated(st.microstep_um) else 0.1
            self.stage = self._stack.enter_context(StageEmulator(
                device=st.device, axis=st.axis, microstep_um=microstep, latency_s=self._latency))
            self.cameras = [
                SimCamera(cam.name, self.rig, self.world, self.pulse_generator, pool_pairs=self._pool_pairs,
                          rays_per_particle=self._rays, device=self._device, **self._faults.get(cam.name, {}))
                for cam in self.rig.camera
            ]
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for cam in self.cameras:
            cam.close()
        self._stack.close()

    def show(self, scene: Callable[[int], np.ndarray] | None, key: object = None) -> None:
        """Put a continuously lit scene in front of the cameras (see :meth:`SimWorld.show`) and
        render each camera's image of it now, in the caller's thread.

        A large sensor takes seconds to render; rendered at the first trigger instead, that
        time would count against the capture's wait for frames, as a real camera never needs.
        """
        self.world.show(scene, key)
        if scene is not None:
            for cam in self.cameras:
                cam.prepare_scene()

    @property
    def pulse_port(self) -> str:
        """Pseudo-terminal path of the emulated pulse generator."""
        assert self.pulse_generator is not None, "enter the SimLab first"
        return self.pulse_generator.port

    @property
    def stage_port(self) -> str:
        """Pseudo-terminal path of the emulated stage."""
        assert self.stage is not None, "enter the SimLab first"
        return self.stage.port

    def truth(self, pairs: int) -> tuple[np.ndarray, np.ndarray]:
        """Particles and brightness the cameras showed for triggers ``0 .. pairs - 1``.

        Returns
        -------
        particles : numpy.ndarray
            (pairs, 2, n, 3) world positions in mm.
        brightness : numpy.ndarray
            (pairs, 2, n) counts.
        """
        cam = self.cameras[0]
        pool = [self.world.pair(j) for j in range(cam.pool_pairs)]
        idx = [cam.pool_index(k) for k in range(pairs)]
        return np.stack([pool[j][0] for j in idx]), np.stack([pool[j][1] for j in idx])

    def truth_times_s(self, pairs: int) -> np.ndarray:
        """(pairs,) time of the first pulse of the world pair each trigger ``0 .. pairs - 1``
        showed, s: the time the truth flow of that pair is to be taken at."""
        cam = self.cameras[0]
        return np.array([self.world.t0_s(cam.pool_index(k)) for k in range(pairs)])
