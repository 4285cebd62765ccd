"""What the studies do to a case: synthetic pairs rendered, reconstructed, correlated and measured
against their truth, all in memory.

The steps are the instrument's own: the particle world of ``lfpiv synth`` and the simulated lab
(:class:`lfcore.world.ParticleWorld`), its renderer (:func:`lfpiv.jobs.synth.render_pair`), the
reconstruction of ``lfpiv reconstruct`` (:class:`lfcore.reconstruct.FrameReconstructor`), the
correlation of ``lfpiv correlate`` (:class:`lfcore.correlate.Correlator`) and the measures of
``lfpiv evaluate`` (:mod:`lfcore.metrics`). Nothing is written to a run store: a study's cases
are many small runs, and what a study keeps is its figures (:mod:`lfpiv.studies.runner`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lfcore import metrics
from lfcore.correlate import CorrelationConfig, Correlator, VectorField
from lfcore.flatfield import FlatField, correct, flat_field
from lfcore.flows import Flow, flow_from_params
from lfcore.operator import Projector
from lfcore.plan import cache_serves, new_cache, projector_for
from lfcore.reconstruct import WEIGHTS, FrameReconstructor, ReconResult, ReconSettings
from lfcore.render import renderer_for
from lfcore.rig import Camera, RenderConfig, Rig, is_pinhole
from lfcore.vectors import centres_mm, displacement_to_velocity
from lfcore.volume import VolumeGrid
from lfcore.world import ParticleWorld
from lfpiv.jobs.synth import render_pair

__all__ = ["Pair", "Reconstructor", "Scene", "Vectors", "correlate_pair", "simulated_flats", "true_displacement"]


@dataclass(frozen=True)
class Pair:
    """One synthetic double-frame pair.

    Attributes
    ----------
    index
        The pair's number in its scene (fixes its seeding and its time).
    particles
        (2, n, 3) world positions (x, y, z) in mm at the two pulses.
    brightness
        (2, n) counts each particle deposits.
    images
        Per camera, (2, rows, columns) uint16 frames A and B.
    t0_s
        Time of the first pulse on the flow's clock, s.
    """

    index: int
    particles: np.ndarray
    brightness: np.ndarray
    images: tuple[np.ndarray, ...]
    t0_s: float

    def frame(self, f: int) -> list[np.ndarray]:
        """The images of frame ``f`` (0 = A, 1 = B), one per camera."""
        return [img[f] for img in self.images]


class Scene:
    """Particles in a known flow, seen by a rig's cameras: the synthetic pairs of a case.

    Parameters
    ----------
    rig
        Cameras, volume, laser and render settings (the first camera sets the PPM and the
        displacement's pixels, as in ``lfpiv synth``).
    flow, ppm, displacement_px, omega, seed
        As :class:`lfcore.world.ParticleWorld`.
    ppp
        Seeding in particles per pixel of the first camera instead of ``ppm`` (a rig of pinhole
        cameras, Tomo-PIV's measure).
    rays_per_particle
        Overrides the rig's ``render.rays_per_particle``.
    device
        Warp device of the renderers.
    """

    def __init__(self, rig: Rig, *, flow: str = "uniform", ppm: float = 0.5, displacement_px: float | None = None,
                 omega: float = 1.0, seed: int = 1, rays_per_particle: int | None = None,
                 device: str | None = None, ppp: float | None = None) -> None:
        self.rig = rig
        self.world = ParticleWorld(rig, flow=flow, ppm=None if ppp is not None else ppm,
                                   displacement_px=displacement_px, seed=seed, omega=omega, ppp=ppp)
        self.flow: Flow = flow_from_params(self.world.flow_params)
        self.seed = seed
        render = rig.render
        if rays_per_particle is not None:
            render = render.model_copy(update={"rays_per_particle": int(rays_per_particle)})
        # each camera's own renderer: ray-traced light fields, or Gaussian images of pinhole cameras
        self.renderers = [renderer_for(cam, render, wavelength_nm=rig.laser.wavelength_nm, device=device)
                          for cam in rig.camera]

    @property
    def dt_s(self) -> float:
        return float(self.world.dt_s)

    def pair(self, k: int) -> Pair:
        """Pair ``k``: a fresh seeding, moved by the flow over dt, rendered by every camera."""
        particles, brightness = self.world.pair(k)
        images = render_pair(self.renderers, particles, brightness, seed=self.seed, pair=k)
        return Pair(index=k, particles=particles, brightness=brightness, images=tuple(images),
                    t0_s=self.world.t0_s(k))


class Reconstructor:
    """Reconstructions of frames by several methods and settings on one projector.

    Parameters
    ----------
    cameras
        The cameras reconstructed jointly (all light-field, or all pinhole:
        :func:`lfcore.plan.projector_for`).
    grid
        The voxel grid.
    device
        Warp device.
    cache
        Keep each weight kind's weights across frames where the planner says a cache serves
        (:func:`lfcore.plan.cache_serves`): repeated reconstructions of the same frames then trace
        each voxel once. Leave it off
        where the time of a reconstruction is measured, so that it includes its weights.
    render
        The rendering the frames were made with: where it gives the light-field cameras a response
        (``lens_falloff``, ...), every frame is flat-field corrected, as ``lfpiv reconstruct
        --flat-field`` does, by a white and a dark image rendered through the same response
        (:func:`simulated_flats`). None: the frames as they are.
    """

    def __init__(self, cameras: Sequence[Camera], grid: VolumeGrid, *, device: str | None = None,
                 cache: bool = False, render: RenderConfig | None = None) -> None:
        self.flats = simulated_flats(cameras, render) if render is not None and render.has_response else None
        self.projector: Projector = projector_for(list(cameras), grid, device=device)
        self.grid = grid
        self.use_cache = cache
        self._caches: dict[str, object] = {}  # per weight kind, the first reconstructor's cache
        self._frames: dict[ReconSettings, FrameReconstructor] = {}

    @property
    def device(self) -> str:
        return self.projector.device

    def _frames_of(self, settings: ReconSettings) -> FrameReconstructor:
        if settings not in self._frames:
            cache = None
            kind = WEIGHTS[settings.method]
            if self.use_cache and cache_serves(self.projector.kind, settings)[0]:
                if kind not in self._caches:
                    # no stored elimination table (checks=0): it costs seconds to build for each projector
                    self._caches[kind] = new_cache(self.projector, method=kind, checks=0)
                cache = self._caches[kind]
            self._frames[settings] = FrameReconstructor(self.projector, settings, cache=cache)
        return self._frames[settings]

    def __call__(self, images: Sequence[np.ndarray], settings: ReconSettings) -> tuple[ReconResult, float]:
        """One volume from one raw image per camera.

        Returns
        -------
        result
            The reconstruction (its ``volume`` a host array of its own).
        seconds
            Wall time of the whole reconstruction (preprocessing, elimination, weights,
            iterations, smoothing).
        """
        frames = self._frames_of(settings)
        t = time.perf_counter()
        if self.flats is not None:
            images = [img if f is None else correct(img, f) for img, f in zip(images, self.flats, strict=True)]
        res = frames.reconstruct(list(images))
        return res, time.perf_counter() - t


def simulated_flats(cameras: Sequence[Camera], render: RenderConfig, *, wavelength_nm: float = 532.0
                    ) -> list[FlatField | None]:
    """Per camera, the flat field a calibration of ``render``'s response would measure: a white
    image and a dark frame rendered through it (:func:`lfcore.white.white_image`, an empty frame),
    over the white light of the perfect camera (:func:`lfcore.flatfield.flat_field`); None for a
    pinhole camera, which has no response."""
    from lfcore.chief_ray import diffraction_sigma_mm
    from lfcore.white import WhiteImageConfig, white_image, white_irradiance

    out: list[FlatField | None] = []
    for k, cam in enumerate(cameras):
        if is_pinhole(cam):
            out.append(None)
            continue
        white = white_image(cam, render=render, config=WhiteImageConfig(seed=k), wavelength_nm=wavelength_nm)
        dark = renderer_for(cam, render, wavelength_nm=wavelength_nm).frame(np.zeros((0, 3)), 0.0, seed=k)
        sigma = diffraction_sigma_mm(wavelength_nm if render.diffraction else 0.0, cam.lenslet_f_number) / cam.pixel_mm
        out.append(flat_field(dark, white, reference=white_irradiance(cam, blur_sigma_px=sigma)))
    return out


@dataclass(frozen=True)
class Vectors:
    """A correlated pair and its truth, both as displacements in voxels.

    Attributes
    ----------
    field
        The correlation's result (displacements of B relative to A, voxels).
    truth
        (nz, ny, nx, 3) the flow's displacement over dt at the window centres at mid-pair time,
        in voxels (x, y, z).
    velocity, truth_velocity
        The same in m/s.
    x_mm, y_mm, z_mm
        1-D world coordinates of the vector grid.
    """

    field: VectorField
    truth: np.ndarray
    velocity: np.ndarray
    truth_velocity: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray

    @property
    def error(self) -> np.ndarray:
        """(nz, ny, nx, 3) measured minus true displacement, voxels."""
        return self.field.displacement - self.truth


def true_displacement(flow: Flow, grid: VolumeGrid, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray,
                      t_mid_s: float, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The flow on a vector grid at mid-pair time: (velocity in m/s, displacement over dt in voxels),
    each (nz, ny, nx, 3) with components (x, y, z)."""
    vel = metrics.grid_velocity(flow, x_mm, y_mm, z_mm, t_mid_s)
    return vel, vel * dt_s * 1e3 / np.asarray(grid.voxel_mm)


class _Correlators:
    """One correlator per (volume shape, settings), built once and kept (its buffers with it)."""

    def __init__(self) -> None:
        self._made: dict[tuple, Correlator] = {}

    def get(self, shape: tuple[int, int, int], config: CorrelationConfig, device: str | None) -> Correlator:
        key = (tuple(shape), config, device)
        if key not in self._made:
            if len(self._made) > 8:  # a long study: keep the memory of a few
                self._made.clear()
            self._made[key] = Correlator(shape, config=config, device=device)
        return self._made[key]


_CORRELATORS = _Correlators()


def correlate_pair(volume_a: np.ndarray, volume_b: np.ndarray, grid: VolumeGrid, config: CorrelationConfig, *,
                   flow: Flow, t0_s: float, dt_s: float, device: str | None = None) -> Vectors:
    """Correlate one pair's volumes and put the truth beside the vectors.

    Parameters
    ----------
    volume_a, volume_b
        (nz, ny, nx) float32 volumes of frames A and B on ``grid``.
    grid
        Their voxel grid.
    config
        The correlation.
    flow, t0_s, dt_s
        The truth: the flow, the first pulse's time and the time between the pulses.
    device
        Warp device.
    """
    field = _CORRELATORS.get(grid.shape, config, device)(volume_a, volume_b)
    x, y, z = centres_mm((field.x, field.y, field.z), grid.origin_mm, grid.voxel_mm)
    vel, disp = true_displacement(flow, grid, x, y, z, t0_s + 0.5 * dt_s, dt_s)
    return Vectors(field=field, truth=disp, velocity=displacement_to_velocity(field.displacement, grid.voxel_mm, dt_s),
                   truth_velocity=vel, x_mm=x, y_mm=y, z_mm=z)
