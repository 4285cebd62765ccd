"""Synthetic particle images: Monte-Carlo ray tracing of light-field cameras, Gaussian particle
images of pinhole (Tomo-PIV) cameras, and sensor exposure.

Each particle sends ``rays_per_particle`` rays, uniformly over the main-lens aperture, through
the thin main lens and the MLA to the sensor (:mod:`lfcore._kernels.render`). The rays carry
the particle's signal (counts) in equal shares and are integrated over the pixel they land on.
A small Gaussian stands in for diffraction: the main lens' spot on the MLA and the lenslet's
spot on the sensor, each with sigma = 0.42 lambda N for its f-number N. Exposure then adds a
background, photon shot noise (Poisson in electrons), Gaussian read noise, and rounds and
saturates to the sensor's bit depth, returning uint16. A light-field camera's response, where
``[render]`` turns it on (main-lens fall-off, micro-image vignetting, dust shadows, a dark offset
with fixed-pattern noise: :func:`lfcore.flatfield.sensor_response`), scales the light per pixel
and replaces the uniform background; all off, the images are as before.

A pinhole camera (:class:`PinholeRenderer`) sees each particle as a Gaussian spot of
``render.particle_image_px`` diameter (1/e^2 of the peak; sigma a quarter of it) centred where the
particle projects (:mod:`lfcore.pinhole`, distortion included), its light integrated over each
pixel (:mod:`lfcore._kernels.pinhole`): the usual synthetic Tomo-PIV image, with the whole volume
within the depth of field. Its exposure is the light-field camera's, saturating at the lower of
``render.bit_depth`` and the camera's own ``bit_depth``. :func:`renderer_for` gives the renderer of
either kind.

Images are arrays indexed (row, column) as read from the sensor; see :mod:`lfcore.mla`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lfcore._deprecation import keyword_options
from lfcore.chief_ray import diffraction_sigma_mm
from lfcore.device import PrivateCopies, RowOffset, Rows, launch_rows, resolve_device, warp
from lfcore.rig import AnyCamera, Camera, PinholeCamera, RenderConfig, is_pinhole, require_lightfield

__all__ = ["LightFieldRenderer", "PinholeRenderer", "derive_seed", "renderer_for"]

#: Rays one thread traces, and the most threads of one launch (larger jobs are split into
#: several launches of about a second each, which also paces the progress callback).
RAYS_PER_THREAD = {"cpu": 1024, "cuda": 64}
MAX_THREADS_PER_LAUNCH = {"cpu": 1 << 14, "cuda": 1 << 24}


def derive_seed(seed: int, *keys: int) -> int:
    """A 31-bit seed for one (camera, pair, frame, ...) derived reproducibly from a run seed."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0] & 0x7FFFFFFF)


class _Renderer:
    """What both kinds of renderer share: the sensor's buffers, allocated once, and the exposure.

    A subclass sets ``camera``, ``render``, ``device`` and ``wp`` and calls :meth:`_buffers`, and
    its ``_trace`` fills ``self._quanta`` (fixed-point counts) with the particles' light.
    """

    camera: AnyCamera
    render: RenderConfig
    device: str

    def _buffers(self) -> None:
        from lfcore._kernels import render as kr

        self._k = kr
        shape = (self.camera.sensor_px[1], self.camera.sensor_px[0])
        self._quanta = self.wp.zeros(shape, dtype=self.wp.int64, device=self.device)
        self._counts = self.wp.zeros(shape, dtype=float, device=self.device)
        self._frame = self.wp.zeros(shape, dtype=self.wp.uint16, device=self.device)
        self._parts = PrivateCopies()  # images of the CPU blocks (see _trace)

    def _trace(self, points_mm: np.ndarray, counts: np.ndarray, seed: int,
               progress: Callable[[int], None] | None = None) -> None:  # pragma: no cover - per kind
        raise NotImplementedError

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the images."""
        return (self.camera.sensor_px[1], self.camera.sensor_px[0])

    @keyword_options("seed", "progress", since="0.1.0")
    def irradiance(self, points_mm: np.ndarray, counts: float | np.ndarray, *, seed: int = 0,
                   progress: Callable[[int], None] | None = None) -> np.ndarray:
        """Noise-free signal of particles on the sensor.

        Parameters
        ----------
        points_mm
            (n, 3) world positions in mm, (x, y, z).
        counts
            Signal per particle in counts, scalar or (n,).
        seed
            Seed of the ray sampling.
        progress
            Called with the number of particles finished after each launch.

        Returns
        -------
        numpy.ndarray
            (rows, columns) float32 counts, no background or noise.
        """
        self._trace(points_mm, counts, seed, progress)
        self.wp.launch(self._k.quanta_to_counts, dim=self.shape, device=self.device,
                       inputs=[self._quanta, 1.0 / self._k.QUANTA_PER_COUNT, self._counts])
        return self._counts.numpy().copy()  # on the CPU, .numpy() is a view of the reused buffer

    @keyword_options("seed", "progress", since="0.1.0")
    def frame(self, points_mm: np.ndarray, counts: float | np.ndarray, *, seed: int = 0,
              progress: Callable[[int], None] | None = None) -> np.ndarray:
        """A raw 16-bit image, as the camera would deliver it.

        Same parameters as :meth:`irradiance`; returns (rows, columns) uint16 counts with
        background, shot and read noise, rounded and saturated at :attr:`full_scale`.
        """
        self._trace(points_mm, counts, seed, progress)
        r = self.render
        if self._response() is not None:  # the camera's response: per-pixel gain and dark offset
            gain, dark = self._response()
            launch_rows(self._k.expose_response, self.shape[0],
                        [self._quanta, 1.0 / self._k.QUANTA_PER_COUNT, gain, dark, r.gain_e_per_count,
                         int(r.shot_noise), r.read_noise_counts, self.full_scale, derive_seed(seed, 0x5E25),
                         RowOffset(0), self._frame], self.device, rest=self.shape[1:])
            return self._frame.numpy().copy()
        launch_rows(self._k.expose, self.shape[0],
                    [self._quanta, 1.0 / self._k.QUANTA_PER_COUNT, r.background_counts, r.gain_e_per_count,
                     int(r.shot_noise), r.read_noise_counts, self.full_scale, derive_seed(seed, 0x5E25),
                     RowOffset(0), self._frame], self.device, rest=self.shape[1:])
        return self._frame.numpy().copy()

    def _response(self) -> tuple[object, object] | None:
        """The camera's response (:func:`lfcore.flatfield.sensor_response`) as device arrays (gain,
        dark), made on first use; None where ``[render]`` has none or the camera is a pinhole one."""
        if not self.render.has_response or is_pinhole(self.camera):
            return None
        if getattr(self, "_response_maps", None) is None:
            from lfcore.flatfield import sensor_response

            resp = sensor_response(self.camera, self.render)
            self._response_maps = (self.wp.array(resp.gain, dtype=float, device=self.device),
                                   self.wp.array(resp.dark, dtype=float, device=self.device))
        return self._response_maps

    @property
    def full_scale(self) -> float:
        """Counts at which a pixel saturates: 2**bit_depth - 1 of ``[render]``."""
        return float(2**self.render.bit_depth - 1)

    def _particles(self, points_mm: np.ndarray, counts: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) world positions and (n,) counts, checked: finite, counts >= 0, and in front of
        the lens beyond its focal length (else nothing can image them)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        cnt = np.broadcast_to(np.asarray(counts, dtype=np.float64), (len(pts),))
        if not np.all(np.isfinite(pts)) or not np.all(np.isfinite(cnt)) or np.any(cnt < 0):
            raise ValueError("particle positions must be finite and their counts finite and >= 0")
        if len(pts) and np.any(self.camera.world_to_camera(pts)[:, 2]
                               >= self.camera.object_distance_mm - self.camera.lens_focal_length_mm):
            raise ValueError(f"a particle lies inside the focal length of camera '{self.camera.name}'")
        return pts, cnt


class LightFieldRenderer(_Renderer):
    """Renders one camera's raw light-field images; device buffers are allocated once.

    Parameters
    ----------
    camera
        The camera to render.
    render
        Ray count, particle size, noise and bit depth.
    wavelength_nm
        Laser wavelength, for the diffraction blur.
    device
        Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``) or None for the first GPU, else CPU.
    """

    @keyword_options("wavelength_nm", "device", since="0.1.0")
    def __init__(self, camera: Camera, render: RenderConfig, *, wavelength_nm: float = 532.0,
                 device: str | None = None) -> None:
        from lfcore._kernels.optics import camera_params

        require_lightfield(camera, "the light-field renderer")
        self.wp = warp()
        self.camera = camera
        self.render = render
        self.device = resolve_device(device)
        lam = wavelength_nm if render.diffraction else 0.0  # no diffraction: no blur
        self.params = camera_params(camera, diffraction_sigma_mm(lam, camera.image_side_f_number),
                                    diffraction_sigma_mm(lam, camera.lenslet_f_number))
        self._buffers()

    def _trace(self, points_mm: np.ndarray, counts: np.ndarray, seed: int,
               progress: Callable[[int], None] | None = None) -> None:
        wp, kr = self.wp, self._k
        pts, cnt = self._particles(points_mm, counts)
        self._quanta.zero_()
        rays = self.render.rays_per_particle
        if len(pts) == 0:
            return
        cam_pts = self.camera.world_to_camera(pts)
        quanta = np.rint(cnt * kr.QUANTA_PER_COUNT / rays).astype(np.int64)
        kind = "cpu" if self.device == "cpu" else "cuda"
        # Rays land with atomic adds, plain adds on the CPU: there each CPU block fills an image
        # of its own, added after (integer quanta, so the sum does not depend on the order).
        images = self._parts.open(self._quanta)
        per_thread = min(RAYS_PER_THREAD[kind], rays)
        chunks = -(-rays // per_thread)
        batch = max(1, MAX_THREADS_PER_LAUNCH[kind] // chunks)
        radius = 0.5e-3 * self.render.particle_diameter_um
        for start in range(0, len(pts), batch):
            stop = min(start + batch, len(pts))
            p_dev = wp.array(cam_pts[start:stop].astype(np.float32), dtype=wp.vec3, device=self.device)
            q_dev = wp.array(quanta[start:stop], dtype=wp.int64, device=self.device)
            launch_rows(kr.trace_particles, (stop - start) * chunks,
                        [self.params, p_dev, q_dev, radius, rays, per_thread, chunks, derive_seed(seed, start),
                         RowOffset(0), images], self.device)
            if progress is not None:
                progress(stop - start)
        self._parts.close(self._quanta)


#: Particles one launch of the pinhole renderer takes (about a second of a CPU core's work), which
#: also paces the progress callback.
PARTICLES_PER_LAUNCH = 1 << 16


class PinholeRenderer(_Renderer):
    """Renders one pinhole (Tomo-PIV) camera's images: a Gaussian spot per particle.

    Parameters
    ----------
    camera
        The pinhole camera to render.
    render
        Particle image diameter (``particle_image_px``), noise and bit depth.
    wavelength_nm
        Unused (the particle image diameter stands for the diffraction spot); kept so that both
        renderers are made alike (:func:`renderer_for`).
    device
        Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``) or None for the first GPU, else CPU.
    """

    @keyword_options("wavelength_nm", "device", since="0.1.0")
    def __init__(self, camera: PinholeCamera, render: RenderConfig, *, wavelength_nm: float = 532.0,
                 device: str | None = None) -> None:
        from lfcore._kernels import pinhole as kp

        if not is_pinhole(camera):
            raise ValueError(f"camera '{camera.name}' is a light-field camera; render it with LightFieldRenderer")
        self._kp = kp
        self.wp = warp()
        self.camera = camera
        self.render = render
        self.device = resolve_device(device)
        self.params = kp.pinhole_params(camera)
        #: Gaussian sigma of a particle's image, pixels (a quarter of its 1/e^2 diameter)
        self.sigma_px = 0.25 * render.particle_image_px
        self._half = int(np.ceil(4.0 * self.sigma_px)) + 1  # the window holds all but ~1e-7 of the light
        self._buffers()

    @property
    def full_scale(self) -> float:
        """Counts at which a pixel saturates: 2**bits - 1 of the lower of ``[render]``'s bit depth
        and the camera's own."""
        return float(2 ** min(self.render.bit_depth, self.camera.bit_depth) - 1)

    def _trace(self, points_mm: np.ndarray, counts: np.ndarray, seed: int,
               progress: Callable[[int], None] | None = None) -> None:
        """Gaussian images of the particles in ``self._quanta`` (``seed`` is unused: a pinhole image
        has no ray sampling, only the exposure's noise)."""
        wp, kp = self.wp, self._kp
        pts, cnt = self._particles(points_mm, counts)
        self._quanta.zero_()
        if len(pts) == 0:
            return
        quanta = cnt * self._k.QUANTA_PER_COUNT
        # spots land with atomic adds, plain adds on the CPU: each CPU block fills its own image
        images = self._parts.open(self._quanta)
        for start in range(0, len(pts), PARTICLES_PER_LAUNCH):
            stop = min(start + PARTICLES_PER_LAUNCH, len(pts))
            p_dev = wp.array(pts[start:stop].astype(np.float32), dtype=wp.vec3, device=self.device)
            q_dev = wp.array(quanta[start:stop], dtype=wp.float64, device=self.device)
            launch_rows(kp.splat_particles, stop - start,
                        [self.params, Rows(p_dev), Rows(q_dev), float(self.sigma_px), self._half, images],
                        self.device)
            if progress is not None:
                progress(stop - start)
        self._parts.close(self._quanta)


def renderer_for(camera: AnyCamera, render: RenderConfig, *, wavelength_nm: float = 532.0,
                 device: str | None = None) -> LightFieldRenderer | PinholeRenderer:
    """The renderer of ``camera``'s kind: :class:`LightFieldRenderer` or :class:`PinholeRenderer`
    (same parameters as either)."""
    cls = PinholeRenderer if is_pinhole(camera) else LightFieldRenderer
    return cls(camera, render, wavelength_nm=wavelength_nm, device=device)

