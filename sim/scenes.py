"""Continuously lit calibration scenes for :meth:`sim.world.SimWorld.show`.

:func:`white_scene` is a uniformly lit diffuser in front of every camera (the white image of
:mod:`lfcore.white`). Each scene is a callable ``scene(camera_index) -> uint16 (rows, columns)``
with a ``key`` that changes whenever what it shows changes, so the simulated cameras render it
once and serve the cached image on every trigger.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from lfcore.render import derive_seed
from lfcore.rig import Rig
from lfcore.white import WhiteImageConfig, white_image

__all__ = ["dot_target_scene", "white_scene"]


def white_scene(rig: Rig, config: WhiteImageConfig | None = None) -> tuple[Callable[[int], np.ndarray], object]:
    """A white diffuser seen by every camera of ``rig``.

    Parameters
    ----------
    rig
        The rig (cameras' optics, render noise settings, laser wavelength for diffraction).
    config
        Level, vignetting, dead lenslets; each camera gets its own seed derived from
        ``config.seed`` (default: :class:`WhiteImageConfig` defaults).

    Returns
    -------
    scene : callable
        ``scene(camera_index)`` -> (rows, columns) uint16 white image.
    key : object
        The cache key to pass to :meth:`SimWorld.show` with the scene.
    """
    config = WhiteImageConfig() if config is None else config

    def scene(ci: int) -> np.ndarray:
        cfg = dataclasses.replace(config, seed=derive_seed(config.seed, 0x3417E, ci))
        return white_image(rig.camera[ci], rig.render, cfg, rig.laser.wavelength_nm)

    return scene, ("white", config)


def dot_target_scene(rig: Rig, z_mm: float, *, spacing_mm: float | None = None, points_per_dot: int = 300,
                     rays_per_point: int = 32, dot_counts: float = 1.5e6, seed: int = 0,
                     device: str | None = None) -> tuple[Callable[[int], np.ndarray], object]:
    """The calibration target (white dots on a matt black board) in the world plane z = ``z_mm``.

    The dots lie on a square grid ``spacing_mm`` apart (default 3 mm, the chapter's board, or a
    quarter of the volume's smaller transverse size for small rigs), centred on the volume
    centre, each a disc of 0.15 spacing radius rendered as ``points_per_dot`` points through the
    light-field renderer (few rays each).

    Returns
    -------
    scene, key
        As :func:`white_scene`; the key changes with ``z_mm``.
    """
    from lfcore.render import LightFieldRenderer

    vol = rig.volume
    if spacing_mm is None:
        spacing_mm = min(3.0, 0.25 * min(vol.size_mm[0], vol.size_mm[1]))
    reach = 0.6 * max(vol.size_mm[0], vol.size_mm[1])
    n = int(reach / spacing_mm)
    g = np.arange(-n, n + 1) * spacing_mm
    cx, cy = np.meshgrid(g + vol.centre_mm[0], g + vol.centre_mm[1], indexing="xy")
    rng = np.random.default_rng(derive_seed(seed, 0xD075))
    r = 0.15 * spacing_mm * np.sqrt(rng.random((cx.size, points_per_dot)))
    a = 2 * np.pi * rng.random((cx.size, points_per_dot))
    pts = np.stack([cx.reshape(-1, 1) + r * np.cos(a), cy.reshape(-1, 1) + r * np.sin(a),
                    np.full(r.shape, float(z_mm))], axis=-1).reshape(-1, 3)
    render = rig.render.model_copy(update={"rays_per_particle": int(rays_per_point)})

    def scene(ci: int) -> np.ndarray:
        rend = LightFieldRenderer(rig.camera[ci], render, rig.laser.wavelength_nm, device)
        return rend.frame(pts, dot_counts / points_per_dot, seed=derive_seed(seed, 0xD075, ci))

    return scene, ("dots", round(float(z_mm), 6), spacing_mm)
