"""Coarse-to-fine elimination: a few cheap iterations on a coarser grid choose the fine voxels to test.

Zero-voxel elimination on a fine grid keeps every voxel whose sub-apertures all land on lit pixels.
Where the particle images are dense (the Mc crop: 54% of the pixels lit) that is 6% of the box for
particles that fill 0.3% of it, and testing those survivors is most of elimination's time (each runs
all of its checks). Ghosts are where lines of sight from lit pixels cross; a few multiplicative
line-of-sight iterations on a grid ``factor`` times coarser along every axis (``factor**3`` fewer
voxels, each with about as many weights as a fine one) already tell most ghosts from particles.
Only the fine voxels inside the coarse voxels still bright after them are then tested, by the
fine grid's own elimination (:meth:`lfcore.projector.LightFieldProjector.eliminate` ``within``),
and they start from their coarse voxel's intensity.

The functions here are pure index arithmetic on the grids; :class:`lfcore.reconstruct.FrameReconstructor`
runs the coarse iterations (:attr:`lfcore.reconstruct.ReconSettings.coarse`).
"""

from __future__ import annotations

import numpy as np

from lfcore.volume import VolumeGrid

#: The most a coarse voxel may span along each axis: at 4 fine voxels a coarse voxel's centre is
#: 1.5 fine voxels from its corner ones, whose light lands on other pixels (measured on the Mc
#: crop: at 3, 99.7% of the true particles' coarse voxels pass the coarse elimination).
MAX_COARSE = 4
#: The fewest voxels of a box that coarse-to-fine elimination runs on; a smaller box is eliminated
#: whole. A small box's whole-grid elimination is cheap (the tiny rig's 161,000 voxels: 0.2 s), and
#: its coarse grid is a few planes deep: there the coarse iterations lost 5-9% of the true particles
#: (against 1.2% on the Mc crop's 7.9 M voxels) and Q fell from 0.786 to 0.769.
COARSE_MIN_VOXELS = 1_000_000


def coarse_grid(grid: VolumeGrid, factor: int) -> VolumeGrid:
    """The grid whose voxels are ``factor`` fine voxels of ``grid`` along every axis.

    Parameters
    ----------
    grid
        The fine grid.
    factor
        Fine voxels per coarse voxel along each axis (2 or more).

    Returns
    -------
    VolumeGrid
        ceil(n / factor) voxels along each axis of ``grid``'s (z, y, x) shape, ``factor`` times its
        voxel size; coarse voxel (k, j, i) holds fine voxels (factor k .. factor k + factor - 1, ...)
        and its centre is theirs (the last coarse voxel along an axis may reach past the box).
    """
    f = int(factor)
    if f < 2:
        raise ValueError(f"a coarse grid needs a factor of 2 or more, got {factor}")
    shape = tuple(-(-n // f) for n in grid.shape)
    voxel = np.asarray(grid.voxel_mm, dtype=np.float64)
    origin = np.asarray(grid.origin_mm, dtype=np.float64) + 0.5 * (f - 1) * voxel  # (x, y, z), as the grid's
    return VolumeGrid(shape=shape, voxel_mm=tuple(float(v) for v in f * voxel),
                      origin_mm=tuple(float(v) for v in origin))


def children(coarse: np.ndarray, grid: VolumeGrid, factor: int, *, z0: int = 0, z1: int | None = None) -> np.ndarray:
    """The fine voxels inside coarse voxels.

    Parameters
    ----------
    coarse
        (m,) flat indices of voxels of ``coarse_grid(grid, factor)``.
    grid
        The fine grid.
    factor
        As :func:`coarse_grid`.
    z0, z1
        Only the fine voxels of planes ``z0 .. z1 - 1`` (a depth slab, :mod:`lfcore.slabs`), numbered
        from plane ``z0`` (the slab's own numbering); None: to the last plane.

    Returns
    -------
    numpy.ndarray
        (n,) int32 flat indices of ``grid`` (or of its planes ``z0 .. z1 - 1``), ascending, each once
        (at most ``factor**3`` per coarse voxel; fewer where a coarse voxel reaches past the box or the
        planes).
    """
    f = int(factor)
    z0 = int(z0)
    z1 = grid.shape[0] if z1 is None else int(z1)
    cshape = tuple(-(-n // f) for n in grid.shape)
    cz, cy, cx = np.unravel_index(np.asarray(coarse, dtype=np.int64), cshape)
    if z0 > 0 or z1 < grid.shape[0]:  # the coarse voxels that reach into the planes
        near = (cz * f < z1) & (cz * f + f > z0)
        cz, cy, cx = cz[near], cy[near], cx[near]
    o = np.arange(f)
    fz = cz[:, None, None, None] * f + o[None, :, None, None]
    fy = cy[:, None, None, None] * f + o[None, None, :, None]
    fx = cx[:, None, None, None] * f + o[None, None, None, :]
    fz, fy, fx = np.broadcast_arrays(fz, fy, fx)
    inside = (fz >= z0) & (fz < z1) & (fy < grid.shape[1]) & (fx < grid.shape[2])
    flat = np.ravel_multi_index((fz[inside] - z0, fy[inside], fx[inside]), (z1 - z0, *grid.shape[1:]))
    return np.unique(flat).astype(np.int32)


def parents(fine: np.ndarray, grid: VolumeGrid, factor: int, *, z0: int = 0) -> np.ndarray:
    """The coarse voxel of each fine voxel.

    Parameters
    ----------
    fine
        (n,) flat indices of ``grid``, or of its planes from ``z0`` on numbered from that plane (a
        depth slab's own numbering, :mod:`lfcore.slabs`).
    grid, factor
        As :func:`coarse_grid`.
    z0
        The plane ``fine`` is numbered from.

    Returns
    -------
    numpy.ndarray
        (n,) int64 flat indices of ``coarse_grid(grid, factor)``.
    """
    f = int(factor)
    cshape = tuple(-(-n // f) for n in grid.shape)
    z, y, x = np.unravel_index(np.asarray(fine, dtype=np.int64), (grid.shape[0] - int(z0), *grid.shape[1:]))
    return np.ravel_multi_index(((z + int(z0)) // f, y // f, x // f), cshape)
