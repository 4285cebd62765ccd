"""Device selection and launches split over the CPU's cores."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import lfcore.device as dev
from lfcore.device import DeviceError, PerBlock, RowOffset, Rows, launch_rows, resolve_device

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


def test_private_images_stay_within_their_budget(monkeypatch):
    monkeypatch.setattr(dev, "cpu_threads", lambda: 16)
    assert dev.private_copies(4 << 20) == 15
    assert dev.private_copies(dev.PRIVATE_BYTES // 3) == 3  # a 29 MP int64 image: a few copies only
    assert dev.private_copies(2 * dev.PRIVATE_BYTES) == 0
    monkeypatch.setattr(dev, "cpu_threads", lambda: 1)
    assert dev.private_copies(1) == 0


def test_per_block_inputs_bound_the_blocks(device, monkeypatch):
    monkeypatch.setattr(dev, "cpu_threads", lambda: 4)
    parts = tuple(wp.zeros((9, 5), dtype=int, device=device) for _ in range(2))
    pairs = wp.zeros(5, dtype=int, device=device)
    launch_rows(_probe, 9, [RowOffset(0), PerBlock(parts), Rows(pairs, div=2)], device, rest=(5,), align=2)
    expect = np.arange(9)[:, None] * 100 + np.arange(5)[None, :]
    if device == "cpu":  # two arrays, so two blocks (not four): rows 0-5 and 6-8, each in its own array
        got = np.concatenate([parts[0].numpy()[:6], parts[1].numpy()[:3]])
        assert not parts[1].numpy()[3:].any()
    else:  # one launch into the first array
        got = parts[0].numpy()
        assert not parts[1].numpy().any()
    assert np.array_equal(got, expect)


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


# --- the split kernels give what one thread gives ------------------------------------------
def _threads(monkeypatch, n: int) -> None:
    # every module that asks how many CPU threads to use, asked at call time
    monkeypatch.setattr("lfcore.device.cpu_threads", lambda: n)


def _frame_and_reconstruction(tiny_rig):
    from lfcore.particles import seed_particles
    from lfcore.projector import LightFieldProjector
    from lfcore.reconstruct import ReconSettings, reconstruct
    from lfcore.render import LightFieldRenderer
    from lfcore.volume import VolumeGrid

    cam = tiny_rig.camera[0]
    pts = seed_particles(tiny_rig.volume, 40, np.random.default_rng(3))
    render = tiny_rig.render.model_copy(update={"rays_per_particle": 3000})
    frame = LightFieldRenderer(cam, render, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu").frame(
        pts, render.particle_counts, seed=5)
    proj = LightFieldProjector([cam], VolumeGrid.from_rig(tiny_rig), device="cpu")
    drt = reconstruct(proj, [frame], ReconSettings(iterations=8))
    mart = reconstruct(proj, [frame], ReconSettings(method="mart", iterations=3))
    return frame, drt, mart


def test_rendering_and_reconstruction_do_not_depend_on_the_cpu_threads(tiny_rig, monkeypatch):
    _threads(monkeypatch, 1)
    frame1, drt1, mart1 = _frame_and_reconstruction(tiny_rig)
    _threads(monkeypatch, 3)
    frame3, drt3, mart3 = _frame_and_reconstruction(tiny_rig)
    # rays land as integer quanta with per-thread random streams: bit for bit the same image
    assert np.array_equal(frame1, frame3) and frame1.sum() > 0
    # the same voxels and weights; projections summed in another order agree to float precision
    assert drt1.active_voxels == drt3.active_voxels and drt1.nnz == drt3.nnz and mart1.nnz == mart3.nnz
    scale = drt1.volume.max()
    assert scale > 0 and np.allclose(drt1.volume, drt3.volume, rtol=1e-4, atol=1e-5 * scale)
    assert np.allclose(mart1.volume, mart3.volume, rtol=1e-4, atol=1e-5 * mart1.volume.max())


def test_correlation_does_not_depend_on_the_cpu_threads(monkeypatch):
    from lfcore.correlate import CorrelationConfig, correlate
    from tests.blobs import blob_pair

    a, b = blob_pair((16, 32, 32), lambda p: np.broadcast_to([0.4, -1.1, 0.3], p.shape), seed=2)
    cfg = CorrelationConfig(windows=((16, 16, 8), (8, 8, 8)), overlap=0.5, deform_iterations=1)
    _threads(monkeypatch, 1)
    one = correlate(a, b, config=cfg, device="cpu")
    _threads(monkeypatch, 3)
    three = correlate(a, b, config=cfg, device="cpu")
    assert np.allclose(one.displacement, three.displacement, atol=1e-5, equal_nan=True)
    assert np.allclose(one.peak_ratio, three.peak_ratio, rtol=1e-5)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs os.fork")
def test_a_forked_child_can_still_split_launches(monkeypatch):
    import os

    monkeypatch.setattr(dev, "cpu_threads", lambda: 2)
    _run(8, "cpu", align=1)  # the parent's pool exists now
    pid = os.fork()
    if pid == 0:  # the child: a split launch must not wait for threads it does not have
        try:
            out, _ = _run(8, "cpu", align=1)
            os._exit(0 if out[7, 4] == 100704 else 1)
        except BaseException:
            os._exit(2)
    import signal
    import time

    end = time.monotonic() + 60
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0 and time.monotonic() < end:
        time.sleep(0.05)
    if done[0] == 0:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        pytest.fail("the split launch in the forked child never finished")
    assert os.waitstatus_to_exitcode(done[1]) == 0


def test_a_failed_allocation_becomes_a_budget_error():
    from lfcore.device import MemoryBudgetError, out_of_memory_is_budget_error

    with pytest.raises(MemoryBudgetError, match=r"^the test ran out of memory on cuda:0 \(1\.5 GiB more\); do less$"):
        with out_of_memory_is_budget_error("cuda:0", "the test", "do less"):
            raise RuntimeError("Failed to allocate 1610612736 bytes on device 'cuda:0'")
    with pytest.raises(RuntimeError, match="something else"):  # other errors pass through
        with out_of_memory_is_budget_error("cpu", "the test", "do less"):
            raise RuntimeError("something else")


def test_host_memory_counts_the_page_cache_the_kernel_gives_back(tmp_path):
    # a workstation that has just read a run store: little free, much in the page cache
    info = tmp_path / "meminfo"
    info.write_text("MemTotal:       131072000 kB\nMemFree:          2048000 kB\nMemAvailable:   120000000 kB\n")
    assert dev.host_available_bytes(meminfo=str(info)) == 120000000 * 1024
    # no MemAvailable (not Linux, or an old kernel): the free pages
    assert dev.host_available_bytes(meminfo=str(tmp_path / "none")) > 0
    assert 0 < dev.available_bytes("cpu") <= 2**50
