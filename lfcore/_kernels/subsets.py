"""Ordered subsets of stored weights: each voxel's row split by the subset of its pixels, and the
scaled simultaneous update of one subset (:mod:`lfcore.subsets`)."""

from __future__ import annotations

import warp as wp

from lfcore._kernels.mart import multiplied, row_sum, row_sum4
from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def count_subsets(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    subset_of: wp.array(dtype=wp.int32),
    n_subsets: int,
    counts: wp.array(dtype=wp.int64),
    sums: wp.array(dtype=float),
):
    """Row t's entries and weight sum per subset: ``counts[t * S + k]``, ``sums[t * S + k]`` (zeroed first)."""
    t = wp.tid()
    i = offsets[t]
    end = offsets[t + 1]
    while i < end:
        k = t * n_subsets + subset_of[pix[i]]
        counts[k] = counts[k] + wp.int64(1)
        sums[k] = sums[k] + w[i]
        i += wp.int64(1)


@wp.kernel
def split_rows(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    subset_of: wp.array(dtype=wp.int32),
    n_subsets: int,
    cursor: wp.array(dtype=wp.int64),
    out_pix: wp.array(dtype=wp.int32),
    out_w: wp.array(dtype=float),
):
    """Row t's entries to their subsets' rows: entry i goes to ``cursor[t * S + k]`` (then advanced) of the
    joined output, k its pixel's subset; the order within a subset stays the row's."""
    t = wp.tid()
    i = offsets[t]
    end = offsets[t + 1]
    while i < end:
        k = t * n_subsets + subset_of[pix[i]]
        d = cursor[k]
        out_pix[d] = pix[i]
        out_w[d] = w[i]
        cursor[k] = d + wp.int64(1)
        i += wp.int64(1)


@wp.kernel
def smart_update_scaled(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    ratio: wp.array(dtype=float),
    relaxation: float,
    scale: wp.array(dtype=float),
    e: wp.array(dtype=float),
):
    """One subset's update E_j <- E_j exp(mu c_j sum_{i in subset} w_ij ratio_i), a thread per voxel:
    :func:`lfcore._kernels.mart.smart_update` with the voxel's subset scale ``c_j`` (its whole weight
    over the subset's), so one subset's step is as long as a full one (the CPU's form)."""
    t0 = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return
    e[j] = multiplied(ej, scale[j] * row_sum4(offsets, pix, w, ratio, t0), relaxation)


@wp.kernel
def smart_update_scaled_tiled(
    offsets: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int32),
    w: wp.array(dtype=float),
    first: int,
    ratio: wp.array(dtype=float),
    relaxation: float,
    scale: wp.array(dtype=float),
    e: wp.array(dtype=float),
):
    """:func:`smart_update_scaled` with a block of threads per voxel (the GPU's form, launched tiled)."""
    t0, lane = wp.tid()
    j = first + t0
    ej = e[j]
    if ej == 0.0:
        return
    s = row_sum(offsets, pix, w, ratio, t0, lane, wp.block_dim())
    total = wp.tile_sum(wp.tile(s))
    if lane == 0:
        e[j] = multiplied(ej, scale[j] * total[0], relaxation)
