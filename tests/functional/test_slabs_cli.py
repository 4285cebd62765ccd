"""`lfpiv reconstruct --slabs`: a box too big for the memory proceeds in depth slabs, with the
in-memory volume."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.cli import main
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run

TINY = str(EXAMPLES / "tiny.toml")
#: Below the 2.6 MB the tiny rig's box (82 x 68 x 29 voxels, 16 bytes each) needs in memory.
SMALL_BUDGET = 2_400_000


@pytest.fixture(scope="module")
def one_pair(tmp_path_factory):
    path = tmp_path_factory.mktemp("slabs") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "1", "--ppm", "0.2", "--quiet"]) == 0
    return path


def _small_memory(monkeypatch):
    import lfcore.plan as job

    monkeypatch.setattr(job, "available_bytes", lambda device: SMALL_BUDGET)


def test_a_box_too_big_for_the_memory_proceeds_in_slabs_with_the_in_memory_volume(capsys, one_pair, tmp_path,
                                                                                  monkeypatch):
    here, sliced = tmp_path / "memory.zarr", tmp_path / "slabs.zarr"
    shutil.copytree(one_pair, here)
    shutil.copytree(one_pair, sliced)
    rc, out, err = _run(capsys, "reconstruct", here, "--iterations", "10", "--quiet", "--slabs", "auto")
    assert rc == 0 and "depth slabs" not in out, err  # the box fits: in memory
    _small_memory(monkeypatch)
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet")  # as before: refused
    assert rc == 2 and err.count("\n") == 1 and "more than it has free; use a coarser --pvr, or --slabs auto" in err
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet", "--slabs", "auto")
    assert rc == 0, err
    assert "reconstructed 2 volume(s) of 82 x 68 x 29 voxels (x, y, z) with drt-mart" in out
    # half the budget for one slab's buffers: 10 planes of 20 bytes a voxel, less the halo of 2 + 2: 6 planes
    assert "each volume was reconstructed in 5 depth slabs, written into the store slab by slab; peak memory" in out
    a, b = RunStore.open(here), RunStore.open(sliced)
    assert b.reconstructed_pairs() == [0]
    want, got = a.volumes()[0], b.volumes()[0]
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))
    # the slabs do not change the volumes' settings: the same volumes, nothing to do again in memory
    monkeypatch.undo()
    rc, out, _ = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet", "--skip-done")
    assert rc == 0 and "already reconstructed with these settings" in out


def test_a_box_past_the_index_limit_proceeds_in_slabs_whatever_the_memory(capsys, one_pair, tmp_path, monkeypatch):
    """The chapter's dual-camera box (1939 x 1455 x 1939 voxels) has more voxels than int32 indices
    number; here the limit is lowered to 12 of the tiny box's 29 planes. In memory it is refused in
    one line; --slabs auto splits it into slabs that each number their own voxels, with the volume
    the box gives below the limit."""
    import lfcore.operator as projector_module

    here, sliced = tmp_path / "memory.zarr", tmp_path / "slabs.zarr"
    shutil.copytree(one_pair, here)
    shutil.copytree(one_pair, sliced)
    assert _run(capsys, "reconstruct", here, "--iterations", "10", "--quiet")[0] == 0
    monkeypatch.setattr(projector_module, "INDEX_LIMIT", 12 * 68 * 82 + 1)
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "is more than int32 voxel indices number in one piece; use --slabs auto" in err
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet", "--slabs", "2")
    assert rc == 2 and err.count("\n") == 1 and "have more voxels than int32 indices number" in err, err
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--quiet", "--slabs", "auto")
    assert rc == 0, err
    # the memory is plenty: slabs of at most 12 planes less the halo of 2 + 2
    assert "each volume was reconstructed in 4 depth slabs" in out, out
    want, got = RunStore.open(here).volumes()[0], RunStore.open(sliced).volumes()[0]
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))


@pytest.mark.parametrize(("value", "expected"), [
    ("0", "--slabs: expected a whole number of slabs (1 or more) or auto, got '0'"),
    ("many", "got 'many'"),
    ("30", "--slabs 30: the box is 29 voxels deep; give from 1 to 29 slabs, or auto"),
])
def test_bad_slabs_are_one_line(capsys, one_pair, tmp_path, value, expected):
    run = tmp_path / "run.zarr"
    shutil.copytree(one_pair, run)
    rc, out, err = _run(capsys, "reconstruct", run, "--iterations", "2", "--quiet", "--slabs", value)
    assert rc == 2 and out == "" and err.count("\n") == 1 and expected in err, err


def test_the_sequential_form_is_not_split(capsys, one_pair, tmp_path):
    run = tmp_path / "run.zarr"
    shutil.copytree(one_pair, run)
    rc, _, err = _run(capsys, "reconstruct", run, "--iterations", "2", "--quiet", "--slabs", "3", "--form",
                      "sequential", "--relaxation", "1")
    assert rc == 2 and err.count("\n") == 1 and "depth slabs need the simultaneous form" in err, err


def test_slabs_on_a_dask_worker_give_the_in_memory_volume(capsys, one_pair, tmp_path):
    here, there = tmp_path / "memory.zarr", tmp_path / "worker.zarr"
    shutil.copytree(one_pair, here)
    shutil.copytree(one_pair, there)
    assert _run(capsys, "reconstruct", here, "--iterations", "5", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "reconstruct", there, "--iterations", "5", "--quiet", "--slabs", "3", "--workers", "1")
    assert rc == 0 and "in 3 depth slabs" in out, err
    want, got = RunStore.open(here).volumes()[0], RunStore.open(there).volumes()[0]
    assert RunStore.open(there).reconstructed_pairs() == [0] and want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(want.max()))
    # the fast protocol's warm start, left out in the workers' depth slabs, is recorded as left out
    rc, out, err = _run(capsys, "reconstruct", there, "--protocol", "fast", "--quiet", "--slabs", "3", "--workers",
                        "1")
    assert rc == 0 and "in 3 depth slabs" in out, err
    assert RunStore.open(there).group["volumes"].attrs["settings"]["warm_start"] is False


def test_the_python_api_takes_slabs(one_pair, tmp_path):
    import lfpiv
    from lfpiv.errors import UsageError

    run = tmp_path / "run.zarr"
    shutil.copytree(one_pair, run)
    with pytest.raises(UsageError, match="expected a whole number of slabs or auto, got 'some'"):
        lfpiv.reconstruct(run, iterations=2, progress=False, slabs="some")
    (a, b) = lfpiv.reconstruct(run, iterations=2, progress=False, slabs=2)
    assert a.slabs == b.slabs == 2 and RunStore.open(run).reconstructed_pairs() == [0]


def test_the_fast_protocol_in_slabs_gives_its_in_memory_volume(capsys, one_pair, tmp_path, monkeypatch):
    """`--protocol fast --slabs 2` runs the protocol's whole plan (coarse-to-fine elimination, here on the
    tiny box with the size rule lowered; DRT-MART's first 20 iterations on line-of-sight weights; 4
    ordered subsets; the stopping rule): the in-memory `--protocol fast` volumes to float round-off, and
    the settings recorded say so. The warm start alone is left out (in memory too, here: the protocol's
    own-pair warm start would start the pair's frame B from its frame A)."""
    import lfcore.coarse as coarse_grids

    monkeypatch.setattr(coarse_grids, "COARSE_MIN_VOXELS", 100_000)  # the tiny box: 161,704 voxels
    here, sliced = tmp_path / "memory.zarr", tmp_path / "slabs.zarr"
    shutil.copytree(one_pair, here)
    shutil.copytree(one_pair, sliced)
    rc, out, err = _run(capsys, "reconstruct", here, "--protocol", "fast", "--no-warm-start", "--quiet")
    assert rc == 0 and "depth slabs" not in out, err
    rc, out, err = _run(capsys, "reconstruct", sliced, "--protocol", "fast", "--slabs", "2", "--quiet")
    assert rc == 0 and "in 2 depth slabs" in out, err
    settings = RunStore.open(sliced).group["volumes"].attrs["settings"]
    assert (settings["subsets"], settings["los_iterations"], settings["coarse"]) == (6, 20, 3)
    assert settings["warm_start"] is False and settings["stop_tolerance"] > 0
    want, got = RunStore.open(here).volumes()[0], RunStore.open(sliced).volumes()[0]
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * float(want.max()))
    # --subsets given in slabs runs them too, as in memory
    rc, out, err = _run(capsys, "reconstruct", sliced, "--iterations", "10", "--subsets", "4", "--slabs", "2",
                        "--quiet")
    assert rc == 0 and "in 2 depth slabs" in out, err
    assert RunStore.open(sliced).group["volumes"].attrs["settings"]["subsets"] == 4


def test_workers_slabs_auto_record_the_warm_start_that_ran(capsys, one_pair, tmp_path):
    """`--workers 1 --slabs auto` under the fast protocol: the worker's memory holds the tiny box, so it
    reconstructs in memory and warm-starts frame B, as volumes/ records: the volumes of the same command
    run in this process."""
    here, there = tmp_path / "memory.zarr", tmp_path / "worker.zarr"
    shutil.copytree(one_pair, here)
    shutil.copytree(one_pair, there)
    assert _run(capsys, "reconstruct", here, "--protocol", "fast", "--quiet")[0] == 0
    rc, out, err = _run(capsys, "reconstruct", there, "--protocol", "fast", "--quiet", "--slabs", "auto", "--workers",
                        "1")
    assert rc == 0 and "depth slabs" not in out, err
    assert "1 frame(s) B started from their frame A" in out, out
    assert RunStore.open(there).group["volumes"].attrs["settings"]["warm_start"] is True
    rc, info, _ = _run(capsys, "info", there)
    assert rc == 0 and "frames B warm-started by their own pair" in info, info
    want, got = RunStore.open(here).volumes()[0], RunStore.open(there).volumes()[0]
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * float(want.max()))


def test_workers_that_plan_slabs_auto_in_slabs_record_no_warm_start(one_pair, tmp_path, monkeypatch):
    """A worker whose memory takes the box in depth slabs only (`--slabs auto`) runs no warm start: the
    job finds so before the workers start, and volumes/ records every frame started uniform, as the
    frames ran (here a worker thread of this process, whose memory is lowered)."""
    from distributed import Client, LocalCluster

    from lfcore.reconstruct import ReconSettings
    from lfpiv.jobs.reconstruct import reconstruct_run

    run = tmp_path / "run.zarr"
    shutil.copytree(one_pair, run)
    _small_memory(monkeypatch)
    store = RunStore.open(run, mode="r+")
    settings = ReconSettings.protocol("fast")
    assert settings.warm_start
    with (LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
          Client(cluster) as client):
        results = reconstruct_run(store, settings, progress=False, client=client, slabs="auto", protocol="fast")
    assert [r.slabs > 1 for r in results] == [True, True] and not any(r.warm for r in results)
    recorded = RunStore.open(run).group["volumes"].attrs["settings"]
    assert recorded["warm_start"] is False and recorded["protocol"] == "fast"
