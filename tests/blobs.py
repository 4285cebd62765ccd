"""Volumes of Gaussian particle blobs moved by a known displacement field, for correlation tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def render_blobs(points_xyz: np.ndarray, shape: tuple[int, int, int],
                 sigma: tuple[float, float, float] = (1.0, 1.0, 1.0), peak: float = 1.0, radius: int = 5) -> np.ndarray:
    """A (z, y, x) float32 volume with a Gaussian blob of ``peak`` at each (x, y, z) voxel coordinate.

    Each blob is evaluated over voxels at least ``radius - 1`` sigma away on every side, so that its
    truncation does not bias its centre.
    """
    nz, ny, nx = shape
    vol = np.zeros(shape, dtype=np.float64)
    p = np.asarray(points_xyz, dtype=np.float64)
    base = np.floor(p).astype(int)
    offs = np.arange(-radius + 1, radius + 1)
    for dz in offs:
        for dy in offs:
            for dx in offs:
                ix, iy, iz = base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz
                ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
                r2 = (((ix - p[:, 0]) / sigma[0]) ** 2 + ((iy - p[:, 1]) / sigma[1]) ** 2
                      + ((iz - p[:, 2]) / sigma[2]) ** 2)
                np.add.at(vol, (iz[ok], iy[ok], ix[ok]), peak * np.exp(-0.5 * r2[ok]))
    return vol.astype(np.float32)


def blob_pair(shape: tuple[int, int, int], displacement: Callable[[np.ndarray], np.ndarray], density: float = 0.02,
              seed: int = 0, sigma: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Volumes A and B of particles at p - d(p)/2 and p + d(p)/2.

    ``displacement`` maps (n, 3) voxel positions (x, y, z) to displacements (n, 3) in voxels;
    ``density`` is particles per voxel. Particles are seeded over a margin around the volume so
    that the edges are as full as the middle.
    """
    rng = np.random.default_rng(seed)
    nz, ny, nx = shape
    m = 6.0
    n = int(density * (nx + 2 * m) * (ny + 2 * m) * (nz + 2 * m))
    p = rng.uniform((-m, -m, -m), (nx + m, ny + m, nz + m), size=(n, 3))
    d = displacement(p)
    return render_blobs(p - 0.5 * d, shape, sigma), render_blobs(p + 0.5 * d, shape, sigma)
