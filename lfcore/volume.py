"""The reconstruction voxel grid.

Volume arrays are indexed (z, y, x), C order, float32. The voxel edge along each world axis is
PVR * pixel pitch / |M| of the rig's first camera, with the pixel-voxel ratio given per axis
(x, y, z): depth resolution is about ten times coarser than lateral, so (2, 2, 10) is typical.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcore._deprecation import keyword_options
from lfcore.rig import Rig

__all__ = ["VolumeGrid"]


@dataclass(frozen=True)
class VolumeGrid:
    """A regular voxel grid centred on the measurement volume.

    Attributes
    ----------
    shape
        (nz, ny, nx) voxel counts.
    voxel_mm
        (dx, dy, dz) voxel edges in mm.
    origin_mm
        World (x, y, z) of the centre of voxel [0, 0, 0], in mm.
    """

    shape: tuple[int, int, int]
    voxel_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float]

    @classmethod
    @keyword_options("pvr", "margin_mm", since="0.1.0")
    def from_rig(cls, rig: Rig, *, pvr: tuple[float, float, float] | None = None,
                 margin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> VolumeGrid:
        """The grid of ``rig.volume``, with the rig's PVR unless ``pvr`` (x, y, z) is given.

        ``margin_mm`` (x, y, z) grows the box on every side, e.g. to see that nothing is
        reconstructed outside the seeded region.
        """
        pvr = rig.volume.pvr if pvr is None else pvr
        if len(pvr) != 3 or any(not np.isfinite(v) or v <= 0 for v in pvr):
            raise ValueError(f"pvr must be three positive numbers (x, y, z), got {tuple(pvr)}")
        if len(margin_mm) != 3 or any(not np.isfinite(m) or m < 0 for m in margin_mm):
            raise ValueError(f"margin_mm must be three numbers >= 0 (x, y, z), got {tuple(margin_mm)}")
        pix = rig.camera[0].object_pixel_mm
        voxel = np.asarray(pvr, dtype=np.float64) * pix
        size = np.asarray(rig.volume.size_mm, dtype=np.float64) + 2.0 * np.asarray(margin_mm, dtype=np.float64)
        n = np.maximum(1, np.rint(size / voxel)).astype(int)
        origin = np.asarray(rig.volume.centre_mm) - 0.5 * (n - 1) * voxel
        return cls(shape=(int(n[2]), int(n[1]), int(n[0])),
                   voxel_mm=tuple(float(v) for v in voxel),
                   origin_mm=tuple(float(v) for v in origin))

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def planes(self, z0: int, z1: int) -> VolumeGrid:
        """The grid of planes ``z0 .. z1 - 1`` (a depth slab): the same voxels, numbered from plane z0.

        Raises
        ------
        ValueError
            If the planes are not a non-empty range of this grid's.
        """
        if not 0 <= z0 < z1 <= self.shape[0]:
            raise ValueError(f"planes {z0}:{z1} are not a range of the grid's 0:{self.shape[0]}")
        origin = (self.origin_mm[0], self.origin_mm[1], self.origin_mm[2] + z0 * self.voxel_mm[2])
        return VolumeGrid(shape=(int(z1 - z0), self.shape[1], self.shape[2]), voxel_mm=self.voxel_mm,
                          origin_mm=origin)

    @property
    def nbytes(self) -> int:
        """Bytes of one float32 volume."""
        return 4 * self.n_voxels

    def axis_mm(self, axis: str) -> np.ndarray:
        """1-D world coordinates (mm) of the voxel centres along ``'x'``, ``'y'`` or ``'z'``."""
        i = "xyz".index(axis)
        n = self.shape[2 - i]
        return self.origin_mm[i] + self.voxel_mm[i] * np.arange(n)

    def world_to_index(self, points_mm: np.ndarray) -> np.ndarray:
        """World points (..., 3) as (x, y, z) to fractional voxel indices (..., 3) as (z, y, x)."""
        p = (np.asarray(points_mm, dtype=np.float64) - self.origin_mm) / self.voxel_mm
        return p[..., ::-1]
