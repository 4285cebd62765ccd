"""A run's pairs on Dask workers (`--workers`, `--scheduler`) and resumed (`--skip-done`), end to end.

The workers are real processes; they must give what the command gives in one process, and the
run store's bookkeeping must list every pair they finished, and only those.
"""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.batch import worker_device
from lfpiv.cli import main
from lfpiv.errors import UsageError
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run

TINY = str(EXAMPLES / "tiny.toml")
RECON = ("--iterations", "10", "--device", "cpu", "--quiet")
CORR = ("--windows", "32x32x16,16x16x8", "--device", "cpu", "--quiet")



@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """A 3-pair synthetic run, reconstructed and correlated in one process: the reference."""
    path = tmp_path_factory.mktemp("batch") / "serial.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "3", "--ppm", "0.2", "--flow", "uniform",
                 "--quiet"]) == 0
    assert main(["reconstruct", str(path), *RECON]) == 0
    assert main(["correlate", str(path), *CORR]) == 0
    return path


def _copy_frames(serial, tmp_path, keep_volumes=False):
    """The serial run's recording without its vectors, and without its volumes unless kept."""
    import shutil

    path = tmp_path / "run.zarr"
    shutil.copytree(serial, path)
    s = RunStore.open(path, mode="r+")
    del s.group["vectors"]
    if not keep_volumes:
        del s.group["volumes"]
    return path


def test_local_workers_give_the_serial_volumes_and_vectors(serial, tmp_path, capsys):
    path = _copy_frames(serial, tmp_path)
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--workers", "2")
    assert rc == 0, err
    assert "reconstructed 6 volume(s)" in out and "by 2 local worker(s)" in out
    s, ref = RunStore.open(path), RunStore.open(serial)
    assert s.reconstructed_pairs() == [0, 1, 2]
    a, b = s.volumes()[...], ref.volumes()[...]
    assert b.max() > 0
    # the same kernels; only the CPU launches' split over threads differs
    assert np.abs(a - b).max() <= 1e-4 * b.max()
    assert s.group["volumes"].attrs["settings"] == ref.group["volumes"].attrs["settings"]

    # the serial volumes, so that the vectors can be compared one by one
    path = _copy_frames(serial, tmp_path / "c", keep_volumes=True)
    rc, out, err = _run(capsys, "correlate", path, *CORR, "--workers", "2")
    assert rc == 0, err
    assert "wrote" in out and "3 pair(s)" in out and "by 2 local worker(s) on cpu" in out
    s = RunStore.open(path)
    assert s.correlated_pairs() == [0, 1, 2]
    v, w = s.vectors(), ref.vectors()
    for c in "uvw":
        assert np.isfinite(v[c]).all()
        assert np.allclose(v[c], w[c], rtol=1e-4, atol=1e-5 * np.abs(w["u"]).max())
    assert np.array_equal(v["flags"], w["flags"])
    assert v["attrs"]["settings"]["device"] == "cpu"


def test_skip_done_resumes_where_a_run_stopped(serial, tmp_path, capsys, monkeypatch):
    import tempfile

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # $TMPDIR of this test
    path = _copy_frames(serial, tmp_path)
    assert _run(capsys, "reconstruct", path, *RECON, "--pairs", "1")[0] == 0
    first = RunStore.open(path).volumes()[1].copy()
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--skip-done")
    assert rc == 0, err
    assert "reconstructed 4 volume(s)" in out  # pairs 0 and 2 only
    s = RunStore.open(path)
    assert s.reconstructed_pairs() == [0, 1, 2]
    assert np.array_equal(s.volumes()[1], first)
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--skip-done", "--workers", "1")
    assert rc == 0 and "already reconstructed with these settings; nothing to do" in out
    assert list(scratch.iterdir()) == []  # the workers' scratch space (and its lock files) went with them
    # other settings are another set of volumes: nothing is skipped, volumes/ starts again
    rc, out, err = _run(capsys, "reconstruct", path, "--iterations", "3", "--device", "cpu", "--quiet",
                        "--skip-done", "--pairs", "0")
    assert rc == 0 and "reconstructed 2 volume(s)" in out
    assert RunStore.open(path).reconstructed_pairs() == [0]

    # correlation: the same settings keep the pairs correlated before, and --skip-done leaves them out
    path = _copy_frames(serial, tmp_path / "c", keep_volumes=True)
    assert _run(capsys, "correlate", path, *CORR, "--pairs", "2")[0] == 0
    rc, out, err = _run(capsys, "correlate", path, *CORR, "--skip-done")
    assert rc == 0 and "2 pair(s)" in out, out + err
    assert RunStore.open(path).correlated_pairs() == [0, 1, 2]
    rc, out, err = _run(capsys, "correlate", path, *CORR, "--skip-done")
    assert rc == 0 and "already correlated with these settings; nothing to do" in out
    # volumes made again replace the vectors of the old ones, even with the same correlation settings
    assert _run(capsys, "reconstruct", path, "--iterations", "3", "--device", "cpu", "--quiet", "--pairs", "0")[0] == 0
    rc, out, err = _run(capsys, "correlate", path, *CORR, "--skip-done")
    assert rc == 0 and "1 pair(s)" in out, out + err
    s = RunStore.open(path)
    assert s.correlated_pairs() == [0] and s.vectors()["attrs"]["volumes_id"] == s.volumes_id is not None


def test_the_workers_progress_line_shows_the_operator_memory_and_time_per_iteration(serial, tmp_path, capsys):
    path = _copy_frames(serial, tmp_path)
    rc, out, err = _run(capsys, "reconstruct", path, "--iterations", "10", "--device", "cpu", "--workers", "1",
                        "--pairs", "0:2", "--projector", "matrix-free")
    assert rc == 0, err
    op = RunStore.open(path).group["volumes"].attrs["operator"]
    # as the command's own line shows them (tests/functional/test_projector_wiring.py), for a pair a worker finished
    assert "projector=matrix-free" in err and re.search(r"ms_it=\d+\.\d", err), err
    mem = [float(m) for m in re.findall(r"mem=(\d+\.\d)MiB", err)]
    assert mem and max(mem) <= op["bytes"] / 2**20 + 0.1 and min(mem) > 0, err


def test_workers_of_a_running_scheduler(serial, tmp_path, capsys):
    from distributed import LocalCluster

    path = _copy_frames(serial, tmp_path)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as cluster:
        rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--pairs", "0:2", "--scheduler",
                            cluster.scheduler_address)
        assert rc == 0, err
        assert f"by the workers of {cluster.scheduler_address}" in out
        s = RunStore.open(path)
        assert s.reconstructed_pairs() == [0, 1]
        assert np.abs(s.volumes()[:2] - RunStore.open(serial).volumes()[:2]).max() <= 1e-4 * s.volumes()[0].max()
    # a worker of several threads would run two pairs on one operator at once: refused
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as cluster:
        rc, out, err = _run(capsys, "correlate", path, *CORR, "--scheduler", cluster.scheduler_address)
        assert rc == 2 and err.count("\n") == 1, err
        assert "runs 2 threads" in err and "--nthreads 1" in err


def test_cluster_errors_are_one_line(serial, tmp_path, capsys, monkeypatch):
    path = _copy_frames(serial, tmp_path)
    monkeypatch.setenv("LFPIV_DASK_TIMEOUT_S", "1")
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--scheduler", "tcp://127.0.0.1:9")
    assert rc == 2 and err.count("\n") == 1, err
    assert "--scheduler tcp://127.0.0.1:9: no Dask scheduler answered" in err and "--workers N" in err
    # a device a worker does not have: the worker's error, once, naming the worker
    rc, out, err = _run(capsys, "reconstruct", path, "--iterations", "2", "--device", "cuda:7", "--quiet",
                        "--workers", "1")
    assert rc == 2 and err.count("\n") == 1, err
    assert "Dask worker 0: device 'cuda:7' is not available here" in err
    rc, out, err = _run(capsys, "correlate", serial, *CORR, "--workers", "1", "--scheduler", "tcp://127.0.0.1:9")
    assert rc == 2 and "not allowed with argument" in err


def test_a_worker_that_cannot_see_the_run_store_says_so(tmp_path):
    """A cluster's worker without the shared file system: named, with what it needs."""
    from lfcore.correlate import CorrelationConfig
    from lfcore.runstore import RunStoreError
    from lfpiv.batch import dask_client, map_pairs, new_token
    from lfpiv.jobs.correlate import CorrelateJob, correlate_pair_task

    job = CorrelateJob(path=str(tmp_path / "elsewhere.zarr"), shape=(16, 32, 32),
                       config=CorrelationConfig(windows=((16, 16, 8),)), device="cpu", token=new_token())
    with dask_client(workers=1) as client, pytest.raises(RunStoreError) as err:
        map_pairs(client, correlate_pair_task, job, [0], on_done=lambda p, r: None, desc="correlating",
                  progress=False)
    assert str(err.value).startswith("Dask worker 0: ") and "elsewhere.zarr does not exist" in str(err.value)
    assert "same absolute path" in str(err.value)


def test_ctrl_c_keeps_the_pairs_the_workers_finished(serial, tmp_path, capsys, monkeypatch):
    """Ctrl-C while the workers run: the command stops with 130, the cluster is shut down, and
    the pairs recorded before are there to resume from."""
    path = _copy_frames(serial, tmp_path)
    record = RunStore.record_volumes
    calls = []

    def interrupted(self, written, **kw):
        calls.append(written)
        if len(calls) == 2:
            raise KeyboardInterrupt
        record(self, written, **kw)

    monkeypatch.setattr(RunStore, "record_volumes", interrupted)
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--workers", "1")
    assert rc == 130 and "interrupted" in err
    monkeypatch.undo()
    done = RunStore.open(path).reconstructed_pairs()
    assert len(done) == 1
    rc, out, err = _run(capsys, "reconstruct", path, *RECON, "--skip-done", "--workers", "1")
    assert rc == 0 and "reconstructed 4 volume(s)" in out
    assert RunStore.open(path).reconstructed_pairs() == [0, 1, 2]


@pytest.mark.parametrize(("asked", "name", "gpus", "expected"), [
    ("cpu", 3, ["cuda:0", "cuda:1"], "cpu"),
    ("cuda:1", 0, ["cuda:0", "cuda:1"], "cuda:1"),
    ("cuda", 3, ["cuda:0", "cuda:1"], "cuda:1"),
    (None, 2, ["cuda:0", "cuda:1"], "cuda:0"),
    ("cuda", "SLURMCluster-4", ["cuda:0", "cuda:1"], "cuda"),
    ("cuda", 1, [], "cuda"),
    (None, 1, [], None),
])
def test_worker_device(asked, name, gpus, expected):
    assert worker_device(asked, name, gpus) == expected


def _slow_unless_first(job, pair):
    """A task for map_pairs: pair 0 fails at once, the others finish a moment later."""
    import time

    if pair == 0:
        raise ValueError("pair 0 is bad")
    time.sleep(2.0)
    return pair * 10


def _dies(job, pair):
    import os

    os._exit(3)  # what the kernel's out-of-memory killer does to a worker


def test_after_a_failure_the_pairs_under_way_finish_and_are_recorded():
    from lfpiv.batch import dask_client, map_pairs

    done = {}
    with dask_client(workers=2) as client, pytest.raises(ValueError, match="pair 0 is bad"):
        map_pairs(client, _slow_unless_first, None, [0, 1, 2, 3], on_done=done.__setitem__, desc="t",
                  progress=False)
    # pair 1 was under way on the other worker when pair 0 failed, and is kept; the rest were not
    # given out (no more than the workers' two threads are out at a time)
    assert done.get(1) == 10 and len(done) < 3


def test_a_worker_that_dies_is_one_line():
    import dask

    from lfpiv.batch import dask_client, map_pairs

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), dask_client(workers=1) as client, \
            pytest.raises(UsageError) as err:
        map_pairs(client, _dies, None, [5], on_done=lambda p, r: None, desc="t", progress=False)
    assert str(err.value).startswith("pair 5: the Dask cluster lost its task (KilledWorker")
    assert "\n" not in str(err.value)
