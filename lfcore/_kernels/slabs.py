"""Kernels of depth-slab reconstruction (:mod:`lfcore.slabs`): the slabs' projections summed, and a
slab's intensities scattered into a dense buffer."""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def accumulate(total: wp.array(dtype=float), part: wp.array(dtype=float)):
    """total[i] += part[i] (one thread per pixel: no atomics)."""
    i = wp.tid()
    total[i] = total[i] + part[i]


@wp.kernel
def scatter_range(voxels: wp.array(dtype=wp.int32), e: wp.array(dtype=float), shift: wp.int64, n: wp.int64,
                  out: wp.array(dtype=float)):
    """out[v + shift] = e[j] for the voxels v = voxels[j] with 0 <= v + shift < n (a slab's flat
    indices moved into a buffer's numbering; in 64 bits, as the box's may pass 2**31)."""
    j = wp.tid()
    k = wp.int64(voxels[j]) + shift
    if k >= wp.int64(0) and k < n:
        out[int(k)] = e[j]  # the buffer itself is numbered in int32
