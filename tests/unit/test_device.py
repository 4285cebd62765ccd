"""Device selection and launches split over the CPU's cores."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import lfcore.device as dev
from lfcore.device import DeviceError, RowOffset, Rows, launch_rows, resolve_device

dev.warp()


@wp.kernel
def _probe(first: int, out: wp.array2d(dtype=int), pairs: wp.array(dtype=int)):
    # Each thread writes its global row and column; the first row of a pair writes the pair.
    w, c = wp.tid()
    out[w, c] = (first + w) * 100 + c
    if w % 2 == 0 and c == 0:
        pairs[w // 2] = first + w


def _run(rows: int, device: str, align: int) -> tuple[np.ndarray, np.ndarray]:
    out = wp.full((rows, 5), -1, dtype=int, device=device)
    pairs = wp.full((rows + 1) // 2, -1, dtype=int, device=device)
    launch_rows(_probe, rows, [RowOffset(1000), Rows(out), Rows(pairs, div=2)], device, rest=(5,), align=align)
    return out.numpy(), pairs.numpy()


@pytest.mark.parametrize("threads", [1, 2, 3, 8])
@pytest.mark.parametrize("rows", [1, 2, 7, 10, 33])
def test_split_launch_covers_every_row_once(device, monkeypatch, threads, rows):
    monkeypatch.setattr(dev, "cpu_threads", lambda: threads)
    out, pairs = _run(rows, device, align=2)
    expect = (1000 + np.arange(rows))[:, None] * 100 + np.arange(5)[None, :]
    assert np.array_equal(out, expect)
    assert np.array_equal(pairs, 1000 + 2 * np.arange((rows + 1) // 2))


def test_rows_slices_scaled_and_shared_elements():
    a = np.arange(10)
    assert list(dev._block_input(Rows(a), 2, 5)) == [2, 3, 4]
    assert list(dev._block_input(Rows(a, scale=2), 2, 5)) == [4, 5, 6, 7, 8, 9]
    assert list(dev._block_input(Rows(a, scale=2), 4, 6)) == [8, 9]  # clipped to the array
    assert list(dev._block_input(Rows(a, div=2), 2, 5)) == [1, 2]
    assert dev._block_input(RowOffset(7), 3, 9) == 10
    assert dev._block_input(1.5, 3, 9) == 1.5


def test_cpu_threads_from_the_environment(monkeypatch):
    dev.cpu_threads.cache_clear()
    try:
        monkeypatch.setenv("LFPIV_CPU_THREADS", "3")
        assert dev.cpu_threads() == 3
        dev.cpu_threads.cache_clear()
        monkeypatch.setenv("LFPIV_CPU_THREADS", "many")
        with pytest.raises(DeviceError, match="LFPIV_CPU_THREADS must be a whole number"):
            dev.cpu_threads()
    finally:
        dev.cpu_threads.cache_clear()


def test_unknown_device_names_the_ones_that_exist():
    with pytest.raises(DeviceError, match="not available here; choose one of: cpu"):
        resolve_device("cuda:7")
