"""Synthetic runs (``lfpiv synth``): seed particles, move them with a known flow, render every camera's frames.

The result is a run store with the same layout a recording has, plus ``truth/``.
"""

from __future__ import annotations

import contextlib
import csv
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.flows import FLOW_NAMES, default_displacement_px
from lfcore.particles import MAX_PPM, MAX_PPP, seeding_density, sheet_weights
from lfcore.render import LightFieldRenderer, PinholeRenderer, derive_seed, renderer_for
from lfcore.rig import MAX_RAYS_PER_PARTICLE, Rig, is_pinhole
from lfcore.runstore import RunStore, is_time_resolved
from lfcore.world import ParticleWorld
from lfpiv import __version__
from lfpiv.errors import UsageError

__all__ = ["FLOW_NAMES", "MAX_PPM", "MAX_PPP", "MAX_RAYS_PER_PARTICLE", "SynthResult", "default_displacement_px",
           "points_outside", "read_points_csv", "render_pair", "synthesize"]

#: A renderer of either kind of camera (:func:`lfcore.render.renderer_for`).
Renderer = LightFieldRenderer | PinholeRenderer


@dataclass(frozen=True)
class SynthResult:
    """What a synthesis did, for the summary line."""

    store: RunStore
    particles_per_frame: int
    #: rays traced through the light-field cameras (0 for a rig of pinhole cameras only)
    rays: int
    seconds: float
    flow: dict[str, Any]
    #: Gaussian particle images drawn on the pinhole cameras
    particle_images: int = 0


def read_points_csv(path: str | Path) -> np.ndarray:
    """Particle positions from a CSV with a header line naming ``x_mm,y_mm,z_mm``.

    Returns
    -------
    numpy.ndarray
        (n, 3) world positions in mm.

    Raises
    ------
    UsageError
        For a missing file, a wrong header, or a line that is not three finite numbers.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # "CSV UTF-8" from Excel starts with a BOM
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise UsageError(f"particles file {path} not found") from None
    except UnicodeDecodeError as exc:
        raise UsageError(f"particles file {path} is not UTF-8 text (byte {exc.start}); save it as UTF-8 CSV") from None
    if not rows or [c.strip() for c in rows[0]] != ["x_mm", "y_mm", "z_mm"]:
        raise UsageError(f"{path}: the first line must be the header 'x_mm,y_mm,z_mm'")
    pts = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            if len(row) != 3:
                raise ValueError
            p = [float(c) for c in row]
            if not np.all(np.isfinite(p)):
                raise ValueError
        except ValueError:
            raise UsageError(f"{path}:{lineno}: expected three numbers x_mm,y_mm,z_mm, got {','.join(row)!r}") from None
        pts.append(p)
    if not pts:
        raise UsageError(f"{path}: no particles after the header line")
    return np.asarray(pts, dtype=np.float64)


def points_outside(rig: Rig, points: np.ndarray) -> int:
    """How many of ``points`` (n, 3) mm lie outside the rig's measurement volume.

    They are still rendered (a camera sees particles beyond the box), but a reconstruction
    holds only the box, so they show as missing particles or as ghosts at its faces.

    Raises
    ------
    UsageError
        A point no camera can image (inside a camera's focal length).
    """
    _check_in_front(rig, points)
    lo, hi = rig.volume.bounds_mm
    return int(np.count_nonzero(np.any((points < lo) | (points > hi), axis=1)))


def _check_in_front(rig: Rig, points: np.ndarray) -> None:
    for cam in rig.camera:
        depth = cam.world_to_camera(points)[:, 2]
        limit = cam.object_distance_mm - cam.lens_focal_length_mm
        if np.any(depth >= limit):
            i = int(np.argmax(depth))
            raise UsageError(f"particle {i} at {points[i].round(3).tolist()} mm is inside the focal length "
                             f"of camera '{cam.name}'; it cannot be imaged")


def render_pair(renderers: Sequence[Renderer], particles: np.ndarray, brightness: np.ndarray, *,
                seed: int, pair: int, progress: Callable[[int, int], None] | None = None) -> list[np.ndarray]:
    """Both frames of one pair as every camera records them, each frame's rays and noise seeded
    from the run's ``seed``, the pair, the frame and the camera (so any pair can be made again).

    Parameters
    ----------
    renderers
        One renderer per camera, in the rig's order (light-field or pinhole).
    particles, brightness
        (2, n, 3) world positions (x, y, z) in mm at the two pulses and (2, n) their counts.
    seed, pair
        The run's seed and the pair's index.
    progress
        Called with the camera's index and the number of particles finished after each launch.

    Returns
    -------
    list of numpy.ndarray
        Per camera, (2, rows, columns) uint16 frames A and B.
    """
    def step(c: int) -> Callable[[int], None] | None:
        return None if progress is None else lambda k: progress(c, k)

    return [np.stack([r.frame(particles[f], brightness[f], seed=derive_seed(seed, pair, f, c), progress=step(c))
                      for f in range(2)]) for c, r in enumerate(renderers)]


def _named(exc: OSError, path: str | Path) -> OSError:
    """``exc`` naming ``path`` where it names no file (ENOSPC under zarr's writes carries none)."""
    return exc if exc.filename is not None else OSError(exc.errno, exc.strerror or str(exc), str(path))


def _pair_rate(rig: Rig, dt_s: float, rate_hz: float | None, time_resolved: bool) -> float:
    """The run's pair rate, Hz: ``rate_hz``, the rig's, or a time-resolved series' ``1 / (2 dt_s)``;
    a one-line error where a given rate contradicts a time-resolved series."""
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise UsageError(f"--rate-hz must be positive, got {rate_hz:g}")
    if not time_resolved:
        return float(rig.laser.rate_hz if rate_hz is None else rate_hz)
    rate = 1.0 / (2.0 * dt_s)  # frames evenly spaced: A0, B0, A1, ... each dt apart
    if rate_hz is not None and not is_time_resolved({"dt_s": dt_s, "rate_hz": rate_hz}):
        raise UsageError(f"--time-resolved spaces every frame dt = {dt_s * 1e3:g} ms apart, a pair every "
                         f"{2 * dt_s * 1e3:g} ms ({rate:g} Hz), but --rate-hz is {rate_hz:g}; leave out --rate-hz or "
                         f"give {rate:g} (or a --dt-ms of {0.5e3 / rate_hz:g})")
    return rate


def synthesize(rig: Rig, out: str | Path, *, flow: str = "vortex-ring", ppm: float | None = None,
               ppp: float | None = None, pairs: int = 3,
               dt_s: float | None = None, seed: int = 1, omega: float = 1.0,
               displacement_px: float | None = None, points: np.ndarray | None = None,
               rays_per_particle: int | None = None, device: str | None = None, overwrite: bool = False,
               progress: bool = True, attrs: dict[str, Any] | None = None, time_resolved: bool = False,
               rate_hz: float | None = None) -> SynthResult:
    """Render a synthetic run into a new run store.

    Parameters
    ----------
    rig
        Cameras, volume, laser sheet and render settings.
    out
        Path of the run store to create.
    flow
        A name of :data:`lfcore.flows.FLOW_NAMES`; ignored when ``points`` is given.
    ppm
        Seeding density, particles per microlens of the first light-field camera (with neither
        ``ppm`` nor ``ppp``: 0.5, or 0.05 ppp for a rig of pinhole cameras only).
    ppp
        Seeding density instead, particles per pixel of the first pinhole camera (Tomo-PIV's
        usual measure: the chapter's 0.05 and 0.1).
    pairs
        Number of double-frame pairs; pair i starts at i / laser rate.
    dt_s
        Time between frames A and B; the rig's ``timing.dt_us`` if None.
    seed
        Seeds the particles and every ray, so a run is reproducible.
    omega
        Wavelength factor of the Table 4.1 flows.
    displacement_px
        Peak particle displacement over dt in object-side pixels of the first camera
        (pixel pitch / |M|); sets the flow's velocity scale. :func:`default_displacement_px`
        if None.
    points
        (n, 3) positions in mm: render one pair whose frames A and B both show them.
    rays_per_particle
        Overrides the rig's ``render.rays_per_particle``.
    device
        Warp device for rendering.
    overwrite
        Replace an existing store at ``out``.
    progress
        Show a progress bar on stderr.
    attrs
        Extra JSON-compatible attributes for the run's root group.
    time_resolved
        A time-resolved series: frames A0, B0, A1, B1, ... each ``dt_s`` apart (the pair rate
        ``1 / (2 dt_s)``) showing the same particles, advected with the flow from frame to frame
        (:meth:`lfcore.world.ParticleWorld.series`), instead of a fresh seeding per pair.
    rate_hz
        The pair rate, Hz: pair i starts at i / rate (None: the rig's ``laser.rate_hz``, or
        ``1 / (2 dt_s)`` with ``time_resolved``, which refuses any other).
    """
    if pairs < 1:
        raise UsageError(f"--pairs must be at least 1, got {pairs}")
    RunStore.check_new(out, overwrite=overwrite)
    if dt_s is None:  # the rig's, which its own check bounds (timing.dt_us)
        dt_s = rig.timing.dt_us * 1e-6
    elif not (np.isfinite(dt_s) and 1e-9 <= dt_s <= 100.0):
        # the range the rig's timing.dt_us takes: a nanosecond to 100 s
        raise UsageError(f"--dt-ms must be from 1e-06 (a nanosecond) to 1e+05 (100 s), got {dt_s * 1e3:g}")
    render = rig.render
    if rays_per_particle is not None:
        if rays_per_particle < 1:
            raise UsageError(f"--rays must be at least 1, got {rays_per_particle}")
        render = render.model_copy(update={"rays_per_particle": int(rays_per_particle)})
    rate = _pair_rate(rig, dt_s, rate_hz, time_resolved)
    if time_resolved and points is not None:
        raise UsageError("--time-resolved advects a flow's particles from frame to frame; leave out --particles "
                         "(one pair of fixed points) or --time-resolved")

    if points is not None:
        pairs = 1
        pa = np.asarray(points, dtype=np.float64)
        particles = np.stack([pa, pa])[None]
        flow_params: dict[str, Any] = {"name": "static-points", "particles": len(pa)}
    else:
        if displacement_px is not None and not (np.isfinite(displacement_px) and displacement_px > 0):
            raise UsageError(f"--displacement-px must be positive, got {displacement_px}")
        try:
            ppm, ppp = seeding_density(rig, ppm=ppm, ppp=ppp)
        except ValueError as exc:
            raise UsageError(f"--{'ppp' if ppp is not None else 'ppm'}: {exc}") from None
        try:
            # the world the simulated lab's cameras see too: a fresh seeding per pair
            world = ParticleWorld(rig, flow=flow, ppm=ppm, displacement_px=displacement_px, seed=seed, omega=omega,
                                  dt_s=dt_s, ppp=ppp, time_resolved=time_resolved, rate_hz=rate)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        flow_params = world.flow_params
        # the whole run's truth at once: a run too large for memory fails here, before any work
        if time_resolved:  # the same particles through every frame
            particles, brightness = world.series(pairs)
        else:
            particles = np.empty((pairs, 2, world.n_particles, 3))
            brightness = np.empty((pairs, 2, world.n_particles))
            for i in range(pairs):
                particles[i], brightness[i] = world.pair(i)
    _check_in_front(rig, particles.reshape(-1, 3))
    if points is not None:
        brightness = render.particle_counts * sheet_weights(particles.reshape(-1, 3), rig.laser, rig.volume)
        brightness = brightness.reshape(particles.shape[:3])

    renderers = [renderer_for(cam, render, wavelength_nm=rig.laser.wavelength_nm, device=device) for cam in rig.camera]
    timing = {"dt_s": dt_s, "rate_hz": rate}
    try:
        store = RunStore.create(out, rig, pairs, timing=timing, software_version=__version__, overwrite=overwrite)
    except OSError as exc:
        raise _named(exc, out) from None
    n_part = particles.shape[2]
    # the work of a particle: its rays through a light-field camera, one Gaussian image on a pinhole one
    work = [1 if is_pinhole(r.camera) else render.rays_per_particle for r in renderers]
    total_rays = pairs * 2 * n_part * sum(w for w, r in zip(work, renderers, strict=True) if not is_pinhole(r.camera))
    spots = pairs * 2 * n_part * sum(1 for r in renderers if is_pinhole(r.camera))
    start = time.perf_counter()
    bar = tqdm(total=pairs * 2 * n_part * sum(work), unit="ray" if total_rays else "particle", unit_scale=True,
               disable=not progress, desc="rendering", leave=False)
    try:  # from the store's creation on: an interrupted run is marked aborted, truth or not
        if attrs:
            store.group.attrs.update(attrs)
        density = {"ppm": None} if points is not None else {"ppm": ppm} if ppp is None else {"ppm": None, "ppp": ppp}
        store.write_truth(particles, brightness, flow_params, **density, seed=seed,
                          render=render.model_dump(mode="json"), device=renderers[0].device)
        for i in range(pairs):
            images = render_pair(renderers, particles[i], brightness[i], seed=seed, pair=i,
                                 progress=lambda c, k: bar.update(k * work[c]))
            for f in range(2):
                t_ns = round((i / rate + f * dt_s) * 1e9)
                for r, img in zip(renderers, images, strict=True):
                    store.write_frame(r.camera.name, i, f, img[f], frame_id=2 * i + f, timestamp_ns=t_ns)
            store.commit(i + 1)
    except OSError as exc:  # a full disk: the pairs committed so far are kept, the run says so
        with contextlib.suppress(OSError):
            store.set_state("aborted")
        raise _named(exc, store.path) from None
    except BaseException:
        store.set_state("aborted")
        raise
    finally:
        bar.close()
    store.set_state("complete")
    return SynthResult(store=store, particles_per_frame=n_part, rays=total_rays,
                       seconds=time.perf_counter() - start, flow=flow_params, particle_images=spots)
