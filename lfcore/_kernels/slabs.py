"""Kernels of depth-slab reconstruction (:mod:`lfcore.slabs`): a slab's voxels, the slabs'
projections summed, and a slab's intensities scattered into a dense buffer."""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def voxel_range(first: int, out: wp.array(dtype=wp.int32)):
    """out[i] = first + i: the flat indices of a run of consecutive voxels."""
    i = wp.tid()
    out[i] = first + i


@wp.kernel
def accumulate(total: wp.array(dtype=float), part: wp.array(dtype=float)):
    """total[i] += part[i] (one thread per pixel: no atomics)."""
    i = wp.tid()
    total[i] = total[i] + part[i]


@wp.kernel
def scatter_range(voxels: wp.array(dtype=wp.int32), e: wp.array(dtype=float), lo: int, hi: int,
                  out: wp.array(dtype=float)):
    """out[v - lo] = e[j] for the voxels v = voxels[j] with lo <= v < hi (flat grid indices)."""
    j = wp.tid()
    v = voxels[j]
    if v >= lo and v < hi:
        out[v - lo] = e[j]
