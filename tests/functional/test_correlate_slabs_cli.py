"""`lfpiv correlate --slabs`: each pair correlated in depth slabs read from the store slab by slab,
with the vectors of the in-memory correlation."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from lfcore.correlate import CorrelationConfig
from lfcore.flows import Uniform
from lfcore.runstore import RunStore
from lfcore.slab_correlate import correlation_bytes, slabs_for_budget
from lfcore.volume import VolumeGrid
from lfpiv.cli import main
from tests.blobs import blob_pair
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run

TINY = str(EXAMPLES / "tiny.toml")
WINDOWS = "32x32x16,16x16x8"
CORR = ("--windows", WINDOWS, "--device", "cpu", "--quiet")
#: The tiny rig at PVR (4, 4, 1.25): 41 x 34 x 232 voxels (x, y, z), deep enough for slabs that
#: read less than the box.
DEEP_PVR = (4.0, 4.0, 1.25)
DEEP_WINDOWS = "16x16x16,16x16x8"


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    """A synthetic run of the tiny rig, reconstructed."""
    path = tmp_path_factory.mktemp("corrslabs") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--ppm", "0.2", "--quiet"]) == 0
    assert main(["reconstruct", str(path), "--iterations", "5", "--quiet"]) == 0
    return path


@pytest.fixture(scope="module")
def deep(tmp_path_factory, tiny_rig):
    """A run whose volumes are blobs moved by a flow that changes along z, 232 planes deep."""
    path = tmp_path_factory.mktemp("corrdeep") / "run.zarr"
    grid = VolumeGrid.from_rig(tiny_rig, pvr=DEEP_PVR)
    s = RunStore.create(path, tiny_rig, 1, timing={"dt_s": 2e-3, "rate_hz": 10.0}, software_version="test")
    s.write_truth(np.zeros((1, 2, 1, 3)), np.zeros((1, 2, 1)), Uniform(velocity_m_s=(0.0, 0.0, 0.0)).params())
    s.create_volumes(grid, method="gaussian blobs", settings={})
    nz = grid.shape[0]

    def flow(q):
        return np.stack([0.4 + 0.01 * (q[:, 2] - nz / 2), -0.3 + 0 * q[:, 0], 0.6 - 0.01 * (q[:, 1] - 17)], axis=1)

    a, b = blob_pair(grid.shape, flow, seed=1, density=0.025)
    s.write_volume(0, 0, a)
    s.write_volume(0, 1, b)
    s.commit(1)
    s.set_state("complete")
    return path, grid


def _vectors(path):
    return RunStore.open(path).read_vectors(0)


def _assert_same_vectors(got, want):
    for name in ("u", "v", "w"):
        scale = float(np.abs(want[name]).max())
        assert scale > 0
        np.testing.assert_allclose(got[name], want[name], rtol=0, atol=1e-5 * scale)  # measured 2e-7 of it
    assert np.array_equal(got["flags"], want["flags"])
    np.testing.assert_allclose(got["peak_ratio"], want["peak_ratio"], rtol=1e-4)


def test_three_slabs_of_a_reconstructed_run_give_the_in_memory_vectors(capsys, reconstructed, tmp_path):
    here, sliced = tmp_path / "memory.zarr", tmp_path / "slabs.zarr"
    shutil.copytree(reconstructed, here)
    shutil.copytree(reconstructed, sliced)
    rc, out, err = _run(capsys, "correlate", here, *CORR)
    assert rc == 0 and "depth slabs" not in out, err
    rc, out, err = _run(capsys, "correlate", sliced, *CORR, "--slabs", "3")
    assert rc == 0, err
    assert "each pair was correlated in 3 depth slabs, read from the store slab by slab" in out
    assert "peak memory of the volumes and buffers" in out
    _assert_same_vectors(_vectors(sliced), _vectors(here))
    # the slabs do not change the vectors' settings: nothing to do again in memory
    rc, out, _ = _run(capsys, "correlate", sliced, *CORR, "--skip-done")
    assert rc == 0 and "already correlated with these settings" in out


def test_slabs_read_only_their_planes_and_give_the_in_memory_vectors(capsys, deep, tmp_path, monkeypatch):
    path, grid = deep
    here, sliced = tmp_path / "memory.zarr", tmp_path / "slabs.zarr"
    shutil.copytree(path, here)
    shutil.copytree(path, sliced)
    deep_corr = ("--windows", DEEP_WINDOWS, "--device", "cpu", "--quiet")
    assert _run(capsys, "correlate", here, *deep_corr)[0] == 0
    reads = []
    original = RunStore.read_volume

    def spy(self, pair, frame, *, planes=None):
        reads.append(planes)
        return original(self, pair, frame, planes=planes)

    monkeypatch.setattr(RunStore, "read_volume", spy)
    rc, out, err = _run(capsys, "correlate", sliced, *deep_corr, "--slabs", "3")
    assert rc == 0 and "in 3 depth slabs" in out, err
    nz = grid.shape[0]
    assert None not in reads and len(reads) == 6  # A and B of each slab, never a whole volume
    assert all(hi - lo < nz for lo, hi in reads), reads
    assert reads[0][0] == 0 and reads[-1][1] == nz
    _assert_same_vectors(_vectors(sliced), _vectors(here))


def test_slabs_auto_correlates_in_memory_where_the_pair_fits_and_in_slabs_where_not(capsys, deep, tmp_path,
                                                                                  monkeypatch):
    import lfpiv.jobs.correlate as job

    path, grid = deep
    cfg = CorrelationConfig(windows=((16, 16, 16), (16, 16, 8)), overlap=0.75)
    need = correlation_bytes(grid.shape[0], grid.shape, cfg, "cpu")
    deep_corr = ("--windows", DEEP_WINDOWS, "--device", "cpu", "--quiet")
    run = tmp_path / "run.zarr"
    shutil.copytree(path, run)
    monkeypatch.setattr(job, "available_bytes", lambda device: need)
    rc, out, err = _run(capsys, "correlate", run, *deep_corr, "--slabs", "auto")
    assert rc == 0 and "depth slabs" not in out, err  # it fits: in memory
    free = need - 1
    monkeypatch.setattr(job, "available_bytes", lambda device: free)
    expected = slabs_for_budget(grid.shape, cfg, int(job.SLAB_SHARE * free), device="cpu")
    assert expected > 1
    rc, out, err = _run(capsys, "correlate", run, *deep_corr, "--slabs", "auto")
    assert rc == 0 and f"in {expected} depth slabs" in out, err
    # the halo alone does not fit: one line
    monkeypatch.setattr(job, "available_bytes", lambda device: need // 8)
    rc, out, err = _run(capsys, "correlate", run, *deep_corr, "--slabs", "auto")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--slabs auto: even" in err, err


@pytest.mark.parametrize(("value", "expected"), [
    ("0", "--slabs: expected a whole number of slabs (1 or more) or auto, got '0'"),
    ("many", "got 'many'"),
    ("30", "--slabs 30: the box is 29 voxels deep; give from 1 to 29 slabs, or auto"),
])
def test_bad_slabs_are_one_line(capsys, reconstructed, tmp_path, value, expected):
    run = tmp_path / "run.zarr"
    shutil.copytree(reconstructed, run)
    rc, out, err = _run(capsys, "correlate", run, *CORR, "--slabs", value)
    assert rc == 2 and out == "" and err.count("\n") == 1 and expected in err, err


def test_slabs_on_a_dask_worker_give_the_in_memory_vectors(capsys, deep, tmp_path):
    path, _ = deep
    here, there = tmp_path / "memory.zarr", tmp_path / "worker.zarr"
    shutil.copytree(path, here)
    shutil.copytree(path, there)
    deep_corr = ("--windows", DEEP_WINDOWS, "--device", "cpu", "--quiet")
    assert _run(capsys, "correlate", here, *deep_corr)[0] == 0
    rc, out, err = _run(capsys, "correlate", there, *deep_corr, "--slabs", "3", "--workers", "1")
    assert rc == 0 and "in 3 depth slabs" in out, err
    assert RunStore.open(there).correlated_pairs() == [0]
    _assert_same_vectors(_vectors(there), _vectors(here))


def test_the_python_api_takes_slabs(deep, tmp_path):
    import lfpiv
    from lfpiv.errors import UsageError

    path, _ = deep
    run = tmp_path / "run.zarr"
    shutil.copytree(path, run)
    with pytest.raises(UsageError, match="expected a whole number of slabs or auto, got 'some'"):
        lfpiv.correlate(run, windows=((16, 16, 16), (16, 16, 8)), device="cpu", progress=False, slabs="some")
    done = lfpiv.correlate(run, windows=((16, 16, 16), (16, 16, 8)), device="cpu", progress=False, slabs=2)
    assert done.slabs == 2 and done.peak_bytes > 0 and RunStore.open(run).correlated_pairs() == [0]
