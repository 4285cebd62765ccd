"""The simulated world the simulated cameras look at: seeded particles moving with a known flow
(:class:`lfcore.world.ParticleWorld`, the world ``lfpiv synth`` renders too), or a continuously
lit calibration scene put in their place.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lfcore.world import ParticleWorld

__all__ = ["SimWorld"]


@dataclass
class SimWorld(ParticleWorld):
    """Particles in a known flow, for one rig (see :class:`lfcore.world.ParticleWorld` for the
    parameters), and the scene the simulated cameras see in their place while one is shown."""

    #: A continuously lit scene that replaces the particles while set (calibration: a white
    #: diffuser, the dot target at the stage position). Called as ``scene(camera_index)``, it
    #: returns the uint16 (rows, columns) image that camera sees; ``scene_key`` changes whenever
    #: what it shows changes (the simulated cameras cache one image per key).
    scene: Callable[[int], np.ndarray] | None = field(default=None, repr=False)
    scene_key: object = None

    def show(self, scene: Callable[[int], np.ndarray] | None, key: object = None) -> None:
        """Put a continuously lit scene in front of the cameras (None: back to the particles)."""
        self.scene, self.scene_key = scene, key
