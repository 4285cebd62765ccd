"""Time every Warp kernel of a run: each launch synchronised before and after (so the sum
exceeds the unsynchronised run's time, and what is left of the run is host work)."""

from __future__ import annotations

import collections
import contextlib
import time
from collections.abc import Iterator

import warp as wp


@contextlib.contextmanager
def kernel_clock(device: str) -> Iterator[collections.Counter]:
    """Within the block, seconds per kernel name (and for Warp's library sort and scan) add up
    in the yielded counter."""
    spent: collections.Counter = collections.Counter()
    real = wp.launch, wp.launch_tiled, wp.utils.segmented_sort_pairs, wp.utils.array_scan

    def clocked(fn, name=None):
        def run(*args, **kwargs):
            wp.synchronize_device(device)
            t = time.perf_counter()
            fn(*args, **kwargs)
            wp.synchronize_device(device)
            spent[name or args[0].key.split("_locals_")[-1]] += time.perf_counter() - t
        return run

    wp.launch, wp.launch_tiled = clocked(real[0]), clocked(real[1])
    wp.utils.segmented_sort_pairs = clocked(real[2], "segmented_sort_pairs (library)")
    wp.utils.array_scan = clocked(real[3], "array_scan (library)")
    try:
        yield spent
    finally:
        wp.launch, wp.launch_tiled, wp.utils.segmented_sort_pairs, wp.utils.array_scan = real


def print_clock(spent: collections.Counter, total: float, rest: str) -> None:
    """The kernels, slowest first, and what the run spent beside them (``rest``)."""
    for name, s in spent.most_common():
        print(f"    {name:40s} {s:8.3f} s")
    print(f"    {rest:40s} {total - sum(spent.values()):8.3f} s")
