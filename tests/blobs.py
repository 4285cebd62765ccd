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
    p = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    offs = np.arange(-radius + 1, radius + 1)
    idx = np.floor(p).astype(np.int64)[:, :, None] + offs  # (n, 3, k) voxel indices per axis
    w = np.exp(-0.5 * ((idx - p[:, :, None]) / np.asarray(sigma, dtype=np.float64)[None, :, None]) ** 2)
    for axis, n in enumerate((nx, ny, nz)):  # a blob is separable: zero the weights outside the volume
        w[:, axis] *= (idx[:, axis] >= 0) & (idx[:, axis] < n)
    np.clip(idx[:, 0], 0, nx - 1, out=idx[:, 0])
    np.clip(idx[:, 1], 0, ny - 1, out=idx[:, 1])
    np.clip(idx[:, 2], 0, nz - 1, out=idx[:, 2])
    weight = peak * w[:, 2, :, None, None] * w[:, 1, None, :, None] * w[:, 0, None, None, :]  # (n, kz, ky, kx)
    flat = (idx[:, 2, :, None, None] * ny + idx[:, 1, None, :, None]) * nx + idx[:, 0, None, None, :]
    vol = np.bincount(flat.ravel(), weights=weight.ravel(), minlength=nz * ny * nx)
    return vol.reshape(shape).astype(np.float32)


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
