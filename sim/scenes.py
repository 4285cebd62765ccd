"""Continuously lit calibration scenes for :meth:`sim.world.SimWorld.show`.

:func:`white_scene` is a uniformly lit diffuser in front of every camera (the white image of
:mod:`lfcore.white`). Each scene is a callable ``scene(camera_index) -> uint16 (rows, columns)``
with a ``key`` that changes whenever what it shows changes, so the simulated cameras render it
once and serve the cached image on every trigger.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from lfcore.render import derive_seed, renderer_for
from lfcore.rig import Rig, is_pinhole
from lfcore.target import DotBoard
from lfcore.white import WhiteImageConfig, white_image

__all__ = ["dark_scene", "dot_target_scene", "white_scene"]


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
        cam = rig.camera[ci]
        if is_pinhole(cam):  # no microlenses, nothing to calibrate from a white image: its dark frame
            blank = renderer_for(cam, rig.render, wavelength_nm=rig.laser.wavelength_nm)
            return blank.frame(np.zeros((0, 3)), 0.0, seed=cfg.seed)
        return white_image(cam, render=rig.render, config=cfg, wavelength_nm=rig.laser.wavelength_nm)

    return scene, ("white", config)


def dark_scene(rig: Rig, seed: int = 0) -> tuple[Callable[[int], np.ndarray], object]:
    """Darkness (lens capped, laser off): what every camera of ``rig`` records is its dark offset,
    fixed pattern and noise (the ``[render]`` response, :func:`lfcore.flatfield.sensor_response`).

    Returns
    -------
    scene, key
        As :func:`white_scene`.
    """

    def scene(ci: int) -> np.ndarray:
        cam = rig.camera[ci]
        blank = renderer_for(cam, rig.render, wavelength_nm=rig.laser.wavelength_nm)
        return blank.frame(np.zeros((0, 3)), 0.0, seed=derive_seed(seed, 0xDA2C, ci))

    return scene, ("dark", seed)


#: The turn between consecutive points of a sunflower spiral, radians (pi (3 - sqrt 5)).
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def dot_target_scene(rig: Rig, z_mm: float, *, spacing_mm: float | None = None, board: DotBoard | None = None,
                     points_per_dot: int = 2048, rays_per_point: int = 32, dot_counts: float = 1.5e6, seed: int = 0,
                     device: str | None = None) -> tuple[Callable[[int], np.ndarray], object]:
    """The calibration target (white dots on a matt black board) with its origin dot at world z = ``z_mm``.

    The dots lie on a square grid (:class:`lfcore.target.DotBoard`): ``board`` gives spacing,
    dot size, the larger marker dot at the origin and the tilt about world y (a tilted board is
    what two cameras 90 degrees apart both see); its origin is put at (``board.centre_mm`` x, y,
    ``z_mm``). Default: an untilted board ``spacing_mm`` apart (default 3 mm, the chapter's
    board, or a quarter of the volume's smaller transverse size for small rigs) centred on the
    volume centre. Each dot is a disc of ``points_per_dot`` points (scaled with its area) through
    the light-field renderer, ``rays_per_point`` rays each (a pinhole camera images each point as a
    Gaussian spot of ``render.particle_image_px``: the dot blurred by the lens). The points lie on a sunflower spiral
    and come in pairs mirrored about the dot centre, so every dot's light is centred exactly on
    it (a board printed without error) and spread evenly over it (random points left a dot in
    sharp focus a few points per lenslet, grainy enough to split it in two). A defocused dot
    spreads over thousands of pixels, so too few rays in all give it a grainy image no real dot
    has; 2048 points of 32 rays cost about as much as the 300 of 256 of before.

    Returns
    -------
    scene, key
        As :func:`white_scene`; the key changes with ``z_mm`` and the board.
    """
    vol = rig.volume
    if board is None:
        if spacing_mm is None:
            spacing_mm = min(3.0, 0.25 * min(vol.size_mm[0], vol.size_mm[1]))
        board = DotBoard(spacing_mm=spacing_mm, centre_mm=vol.centre_mm)
    # Cover the volume's widest extent, stretched by the tilt (a tilted board is foreshortened).
    reach = 0.6 * max(vol.size_mm) / math.cos(math.radians(board.tilt_deg)) + board.spacing_mm
    ij = board.indices(board.half_extent(reach))
    here = dataclasses.replace(board, centre_mm=(board.centre_mm[0], board.centre_mm[1], float(z_mm)),
                               stage_centre_mm=0.0)
    centres = here.dot_centres(ij, 0.0)
    e1, e2, _ = board.axes
    # Every plane draws its own points, rays and noise, as every real frame has its own: with
    # one seed for all, the errors of a dot that stays put in the image (a camera looking along
    # the stage's travel) repeated on every plane and did not average out in the fit.
    plane_key = int(np.float64(z_mm).view(np.uint64))
    rng = np.random.default_rng(derive_seed(seed, 0xD075, plane_key))
    marker = np.all(ij == 0, axis=1)
    pts = []
    per_point = dot_counts / points_per_dot  # equal surface brightness: the marker gets more points
    for c, big in zip(centres, marker, strict=True):
        scale = board.marker_scale if big else 1.0
        half = max(1, int(round(0.5 * points_per_dot * scale**2)))
        # a sunflower (Vogel) spiral, turned at random per dot: the points spread evenly
        k = np.arange(half)
        r = board.radius_mm * scale * np.sqrt((k + 0.5) / half)
        a = _GOLDEN_ANGLE * k + 2 * np.pi * rng.random()
        d = (r * np.cos(a))[:, None] * e1 + (r * np.sin(a))[:, None] * e2
        pts.append(np.concatenate([c + d, c - d]))
    pts = np.concatenate(pts)
    render = rig.render.model_copy(update={"rays_per_particle": int(rays_per_point)})

    def scene(ci: int) -> np.ndarray:
        rend = renderer_for(rig.camera[ci], render, wavelength_nm=rig.laser.wavelength_nm, device=device)
        return rend.frame(pts, per_point, seed=derive_seed(seed, 0xD075, plane_key, ci))

    return scene, ("dots", round(float(z_mm), 6), board, points_per_dot, rays_per_point, dot_counts, seed)
