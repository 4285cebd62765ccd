"""Vector post-processing: outlier detection and replacement, physical units, derived fields.

A displacement field is an array (nz, ny, nx, 3) on a regular grid of window centres, indexed
(z, y, x) like the volumes, whose last axis holds the components (x, y, z). Displacements are
in voxels; velocities in m/s; world coordinates in mm; derivatives in 1/s.

Outliers are found with the normalized median test of Westerweel & Scarano (2005), extended
to 3D: for each vector and each component u, with u_m the median of its (up to) 26 neighbours
and r_m the median of the neighbours' residuals |u_i - u_m|, the normalized residual is
``|u - u_m| / (r_m + epsilon)``. A vector is an outlier when any component's normalized
residual exceeds ``threshold`` (defaults: epsilon 0.1 voxel, threshold 2), or when it is
missing (NaN: a window without signal). Beyond the grid's edges the neighbourhood is completed
by point reflection about the tested vector (2 u - u_opposite), so that an edge vector in a
velocity gradient is not flagged for its one-sided neighbourhood. Outliers are replaced by the median of their valid
neighbours; the flags of both steps are kept. Both run as Warp kernels (one thread a vector,
:mod:`lfcore._kernels.vectors`) on the CPU or a GPU: NumPy's ``nanmedian`` over the 26
neighbours of 1e5 vectors takes seconds, which a live GPU pipeline cannot afford.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lfcore._deprecation import keyword_options

__all__ = [
    "FLAG_OUTLIER",
    "FLAG_REPLACED",
    "REPLACE_SWEEPS",
    "MedianTest",
    "centres_mm",
    "displacement_to_velocity",
    "divergence",
    "flags_from_masks",
    "median_filter",
    "normalized_median_test",
    "q_criterion",
    "replace_outliers",
    "smooth",
    "velocity_gradient",
    "vorticity",
]

#: Sweeps :func:`replace_outliers` makes at most by default (each fills the outliers next to a
#: valid or already filled vector).
REPLACE_SWEEPS = 10
#: Bits of the ``flags`` array: the vector failed the outlier test; it was replaced.
FLAG_OUTLIER = 1
FLAG_REPLACED = 2


@dataclass(frozen=True)
class MedianTest:
    """Settings of the normalized median test.

    Attributes
    ----------
    epsilon
        Acceptable fluctuation in voxels, added to the median residual (0.1 voxel).
    threshold
        Largest normalized residual of a valid vector (2).
    """

    epsilon: float = 0.1
    threshold: float = 2.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.epsilon) and self.epsilon >= 0):
            raise ValueError(f"the median test's epsilon must be >= 0 voxel, got {self.epsilon}")
        if not (np.isfinite(self.threshold) and self.threshold > 0):
            raise ValueError(f"the median test's threshold must be positive, got {self.threshold}")


def _check_field(field: np.ndarray) -> np.ndarray:
    f = np.asarray(field, dtype=np.float64)
    if f.ndim != 4 or f.shape[-1] != 3:
        raise ValueError(f"a vector field is an array (nz, ny, nx, 3), got shape {f.shape}")
    return f


def _device_field(field: np.ndarray, device: str | None):
    from lfcore.device import resolve_device, warp

    wp = warp()
    d = resolve_device(device)
    return wp, d, wp.array(np.ascontiguousarray(field, dtype=np.float32), dtype=wp.vec3, device=d)


@keyword_options("test", since="0.1.0")
def normalized_median_test(field: np.ndarray, *, test: MedianTest = MedianTest(),
                           device: str | None = "cpu") -> np.ndarray:
    """Outliers of a displacement field by the normalized median test over 26 neighbours.

    Parameters
    ----------
    field
        (nz, ny, nx, 3) displacements (x, y, z) in voxels; NaN marks a missing vector.
    test
        epsilon (voxels) and threshold.
    device
        Warp device of the test kernel (one thread a vector).

    Returns
    -------
    numpy.ndarray
        (nz, ny, nx) bool, True for outliers (missing vectors included). A vector without any
        valid neighbour cannot be tested and is kept unless it is missing.
    """
    from lfcore._kernels import vectors as kv

    f = _check_field(field)
    wp, d, dev = _device_field(f, device)
    out = wp.empty(f.shape[:3], dtype=wp.int32, device=d)
    wp.launch(kv.median_test, dim=f.shape[:3], device=d, inputs=[dev, float(test.epsilon), float(test.threshold), out])
    return out.numpy() != 0


def replace_outliers(field: np.ndarray, outlier: np.ndarray, *, max_iterations: int = REPLACE_SWEEPS,
                     device: str | None = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Replace outliers by the median of their valid neighbours.

    Outliers surrounded only by outliers are filled in later sweeps, from vectors replaced in
    earlier ones (at most ``max_iterations`` sweeps).

    Parameters
    ----------
    field
        (nz, ny, nx, 3) displacements or velocities.
    outlier
        (nz, ny, nx) bool, the vectors to replace.
    device
        Warp device of the replacement kernel.

    Returns
    -------
    field, replaced
        The new field (float64; NaN where nothing could replace an outlier) and the
        (nz, ny, nx) bool mask of the vectors that were replaced.
    """
    from lfcore._kernels import vectors as kv

    f = _check_field(field).copy()
    bad = np.asarray(outlier, dtype=bool).copy()
    if bad.shape != f.shape[:3]:
        raise ValueError(f"outlier mask {bad.shape} does not match the field {f.shape[:3]}")
    f[bad] = np.nan
    replaced = np.zeros_like(bad)
    if not bad.any():
        return f, replaced
    wp, d, cur = _device_field(f, device)
    nxt = wp.empty_like(cur)
    filled = wp.empty(f.shape[:3], dtype=wp.int32, device=d)
    for _ in range(max_iterations):
        if not bad.any():
            break
        wp.launch(kv.replace_sweep, dim=f.shape[:3], device=d,
                  inputs=[cur, wp.array(bad.astype(np.int32), dtype=wp.int32, device=d), nxt, filled])
        fill = filled.numpy() != 0
        if not fill.any():
            break
        replaced |= fill
        bad &= ~fill
        cur, nxt = nxt, cur
    out = cur.numpy().astype(np.float64)
    keep = ~replaced & ~np.asarray(outlier, dtype=bool)
    out[keep] = f[keep]  # untouched vectors keep their full precision
    return out, replaced


def median_filter(field: np.ndarray, *, size: int = 3) -> np.ndarray:
    """The chapter's median filter: each component replaced by its median over size^3 vectors.

    Applied to every vector (it smooths as well as rejects), with the grid's edge values
    repeated beyond it. ``size`` 3 is the chapter's 3 x 3 filter, taken over 3 x 3 x 3 in 3D.
    """
    f = _check_field(field)
    if size < 1:
        raise ValueError(f"median filter size must be at least 1, got {size}")
    return np.stack([ndimage.median_filter(f[..., c], size=size, mode="nearest") for c in range(3)], axis=-1)


def smooth(field: np.ndarray, *, sigma: float = 1.0) -> np.ndarray:
    """Gaussian smoothing of each component over the grid (sigma in grid spacings).

    Used on the predictor between deformation passes: iterating with an unfiltered predictor
    feeds each vector's random error back into the next deformation and stops the iteration
    from converging (Schrijer & Scarano 2008). The field is continued point-symmetrically past
    its edges, so linear fields pass unchanged everywhere.
    """
    f = _check_field(field)
    if sigma <= 0:
        return f.copy()
    # point-symmetric padding (2 edge - mirror image) continues linear fields past the edge
    r = max(1, int(np.ceil(2.0 * sigma)))
    pads = [(min(r, n - 1),) * 2 for n in f.shape[:3]] + [(0, 0)]
    p = np.pad(f, pads, mode="reflect", reflect_type="odd") if max(f.shape[:3]) > 1 else f
    out = np.stack([ndimage.gaussian_filter(p[..., c], sigma, mode="nearest", truncate=2.0) for c in range(3)], axis=-1)
    return out[tuple(slice(a, a + n) for (a, _), n in zip(pads[:3], f.shape[:3], strict=True))]


def flags_from_masks(outlier: np.ndarray, replaced: np.ndarray) -> np.ndarray:
    """uint8 flags: :data:`FLAG_OUTLIER` and :data:`FLAG_REPLACED` bits."""
    return (np.asarray(outlier, bool) * FLAG_OUTLIER | np.asarray(replaced, bool) * FLAG_REPLACED).astype(np.uint8)


def displacement_to_velocity(displacement_vox: np.ndarray, voxel_mm: tuple[float, float, float],
                             dt_s: float) -> np.ndarray:
    """Velocity in m/s from displacements in voxels over ``dt_s`` seconds.

    Parameters
    ----------
    displacement_vox
        (..., 3) displacements (x, y, z) in voxels.
    voxel_mm
        (dx, dy, dz) voxel edges in mm.
    dt_s
        Time between the two volumes in s.
    """
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt must be a positive time in s, got {dt_s}")
    return np.asarray(displacement_vox, dtype=np.float64) * np.asarray(voxel_mm, dtype=np.float64) * 1e-3 / dt_s


def centres_mm(centres_vox: tuple[np.ndarray, np.ndarray, np.ndarray], origin_mm: tuple[float, float, float],
               voxel_mm: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World coordinates (mm) of window centres given as 1-D voxel coordinates (x, y, z).

    ``origin_mm`` is the world (x, y, z) of the centre of voxel [0, 0, 0].
    """
    return tuple(o + v * np.asarray(c, dtype=np.float64)  # type: ignore[return-value]
                 for c, o, v in zip(centres_vox, origin_mm, voxel_mm, strict=True))


def velocity_gradient(velocity: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Velocity gradient tensor by second-order central differences (one-sided at the edges).

    Parameters
    ----------
    velocity
        (nz, ny, nx, 3) velocity (u, v, w) in m/s.
    x_mm, y_mm, z_mm
        1-D world coordinates of the grid in mm.

    Returns
    -------
    numpy.ndarray
        (nz, ny, nx, 3, 3) in 1/s: ``g[..., i, j] = d u_i / d x_j``. Derivatives along an axis
        with a single grid point are zero.
    """
    u = _check_field(velocity)
    coords = {0: np.asarray(z_mm, float) * 1e-3, 1: np.asarray(y_mm, float) * 1e-3, 2: np.asarray(x_mm, float) * 1e-3}
    for ax, c in coords.items():
        if c.shape != (u.shape[ax],):
            raise ValueError(f"coordinates of axis {'zyx'[ax]} have shape {c.shape}, expected ({u.shape[ax]},)")
    g = np.zeros((*u.shape, 3))
    for j, ax in enumerate((2, 1, 0)):  # d/dx, d/dy, d/dz
        if u.shape[ax] < 2:
            continue
        edge = 2 if u.shape[ax] > 2 else 1
        g[..., :, j] = np.gradient(u, coords[ax], axis=ax, edge_order=edge)
    return g


def vorticity(velocity: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Vorticity (nz, ny, nx, 3), components (x, y, z), in 1/s (see :func:`velocity_gradient`)."""
    g = velocity_gradient(velocity, x_mm, y_mm, z_mm)
    return np.stack([g[..., 2, 1] - g[..., 1, 2], g[..., 0, 2] - g[..., 2, 0], g[..., 1, 0] - g[..., 0, 1]], axis=-1)


def divergence(velocity: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """du/dx + dv/dy + dw/dz (nz, ny, nx) in 1/s; its magnitude is the chapter's divergence error."""
    g = velocity_gradient(velocity, x_mm, y_mm, z_mm)
    return g[..., 0, 0] + g[..., 1, 1] + g[..., 2, 2]


def q_criterion(velocity: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Q = (|Omega|^2 - |S|^2) / 2 (nz, ny, nx) in 1/s^2; positive where rotation dominates strain."""
    g = velocity_gradient(velocity, x_mm, y_mm, z_mm)
    gt = np.swapaxes(g, -1, -2)
    s, o = 0.5 * (g + gt), 0.5 * (g - gt)
    return 0.5 * (np.sum(o * o, axis=(-2, -1)) - np.sum(s * s, axis=(-2, -1)))
