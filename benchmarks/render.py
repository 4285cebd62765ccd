"""Render throughput: rays per second on each device, and one 29 MP frame.

Run from the repository root::

    python benchmarks/render.py                 # every device Warp finds
    python benchmarks/render.py --device cpu --frame-fraction 0.01

Cases
-----
throughput
    Point particles spread through the one-camera example's volume (2048 x 2048 sensor),
    traced with 1e5 rays each without diffraction, timed after a warm-up launch so compilation
    is excluded. The baseline
    is a vectorised NumPy tracer of the same optics measured in the same run; the ratio is
    Warp's rays/s over NumPy's.
frame
    One frame of the two-camera example's 29 MP camera at 0.5 PPM with 1e5 rays per
    particle, with everything on (50 um particles, diffraction, sensor noise, the copy back to
    the host). With
    ``--frame-fraction f < 1`` only that fraction of the particles is rendered and the time is
    scaled up (a CPU cannot do the full frame in a sensible time); the output says so.

The goal on an H100 is at least 1e9 rays/s (record results in benchmarks/RESULTS.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore import mla  # noqa: E402
from lfcore.device import available_devices  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.render import LightFieldRenderer  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402


def numpy_trace(cam, points_world: np.ndarray, rays: int, rng: np.random.Generator) -> np.ndarray:
    """Reference tracer in NumPy (same thin-lens optics, no diffraction): the baseline."""
    nc, nr = cam.sensor_px
    img = np.zeros(nr * nc)
    pc = cam.world_to_camera(points_world)
    so, f, si, fml = cam.object_distance_mm, cam.main_focal_length_mm, cam.image_distance_mm, cam.mla_focal_length_mm
    for p in pc:
        rad = 0.5 * cam.aperture_mm * np.sqrt(rng.random(rays))
        th = 2 * np.pi * rng.random(rays)
        a = np.stack([rad * np.cos(th), rad * np.sin(th)], axis=1)
        s = (a - p[:2]) / (so - p[2]) - a / f
        q = a + si * s
        c = mla.nearest_lenslet(cam, q)
        xy = c + fml * s
        cr = mla.sensor_to_pixel(cam, xy)
        ok = (cr[:, 0] >= 0) & (cr[:, 0] < nc) & (cr[:, 1] >= 0) & (cr[:, 1] < nr)
        idx = cr[ok, 1].astype(int) * nc + cr[ok, 0].astype(int)
        img += np.bincount(idx, minlength=nr * nc)
    return img.reshape(nr, nc)


def throughput(device: str, n_particles: int, rays: int) -> float:
    rig = load_rig(ROOT / "examples" / "one_camera.toml")
    # point particles, no diffraction: the same physics as the NumPy baseline
    cfg = rig.render.model_copy(update={"rays_per_particle": rays, "diffraction": False, "particle_diameter_um": 0.0})
    r = LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device=device)
    pts = seed_particles(rig.volume, n_particles, np.random.default_rng(0))
    r.irradiance(pts[:2], 1.0, seed=0)  # compile and warm up
    t = time.perf_counter()
    r.irradiance(pts, 1000.0, seed=1)
    return n_particles * rays / (time.perf_counter() - t)


def baseline(n_particles: int, rays: int) -> float:
    rig = load_rig(ROOT / "examples" / "one_camera.toml")
    pts = seed_particles(rig.volume, n_particles, np.random.default_rng(0))
    t = time.perf_counter()
    numpy_trace(rig.camera[0], pts, rays, np.random.default_rng(1))
    return n_particles * rays / (time.perf_counter() - t)


def frame(device: str, fraction: float, rays: int) -> tuple[float, int, int]:
    rig = load_rig(ROOT / "examples" / "two_cameras.toml")
    cam = rig.camera[0]
    cfg = rig.render.model_copy(update={"rays_per_particle": rays})
    n = particle_count(rig, ppm=0.5)
    k = max(1, round(n * fraction))
    pts = seed_particles(rig.volume, k, np.random.default_rng(2))
    r = LightFieldRenderer(cam, cfg, wavelength_nm=rig.laser.wavelength_nm, device=device)
    r.frame(pts[:1], 1.0, seed=0)
    t = time.perf_counter()
    r.frame(pts, cfg.particle_counts, seed=3)
    return (time.perf_counter() - t) * n / k, n, k


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", action="append", help="device(s) to measure (default: all)")
    ap.add_argument("--particles", type=int, default=None, help="particles in the throughput case")
    ap.add_argument("--rays", type=int, default=100_000, help="rays per particle (default 1e5)")
    ap.add_argument("--frame-fraction", type=float, default=None,
                    help="fraction of the 29 MP frame's particles to render (default: 1 on GPU, 0.01 on CPU)")
    args = ap.parse_args()
    devices = args.device or available_devices()
    n_base = 20
    base = baseline(n_base, args.rays)
    print(f"baseline  numpy reference tracer: {base:.3g} rays/s ({n_base} particles x {args.rays:g} rays)")
    print(f"{'device':<8} {'rays/s':>10} {'x numpy':>8} {'29 MP frame':>14}  note")
    for dev in devices:
        n = args.particles or (200 if dev == "cpu" else 20_000)
        rate = throughput(dev, n, args.rays)
        frac = args.frame_fraction or (0.01 if dev == "cpu" else 1.0)
        secs, n_all, k = frame(dev, frac, args.rays)
        note = f"{n_all} particles at 0.5 PPM" + ("" if k == n_all else f"; {k} rendered, time scaled x{n_all / k:.0f}")
        goal = "" if dev == "cpu" else f"; goal 1e9 rays/s {'met' if rate >= 1e9 else 'missed'}"
        print(f"{dev:<8} {rate:>10.3g} {rate / base:>8.1f} {secs:>12.2f} s  {note}{goal}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
