"""One writer per run store: a second writer process is refused, naming the first; a killed
writer leaves the store free; readers, the writer's own handles and the processes it shares its
lock with keep working."""

from __future__ import annotations

import gc
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lfcore.runstore import RunStore, RunStoreError

ROOT = Path(__file__).resolve().parents[3]

HOLDER = """
import json, os, sys
from lfcore.runstore import RunStore
s = RunStore.open(sys.argv[1], mode="r+")
print(json.dumps({"pid": os.getpid(), "token": s.writer_token}), flush=True)
sys.stdin.readline()  # hold the store until told to go, or killed
"""

WRITER = """
import sys
import numpy as np
from lfcore.runstore import RunStore
s = RunStore.open(sys.argv[1], mode="r+", shared_with=sys.argv[2] if len(sys.argv) > 2 else None)
s.write_frame("cam0", 0, 1, np.full((160, 192), 9, np.uint16), 1, 1)
print("wrote", flush=True)
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}


def _script(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture
def run(tiny_rig, tmp_path):
    path = tmp_path / "run.zarr"
    RunStore.create(path, tiny_rig, 2, timing={"dt_s": 0.002, "rate_hz": 10.0}, software_version="x").close()
    return path


@pytest.fixture
def holder(run, tmp_path):
    """Another process (a child, not an ancestor of this one) that holds the run's writer lock."""
    p = subprocess.Popen([sys.executable, str(_script(tmp_path, "holder.py", HOLDER)), str(run)], env=_env(),
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    assert line, p.stderr.read()
    info = json.loads(line)
    assert info["pid"] == p.pid
    yield p, info["token"]
    if p.poll() is None:
        p.kill()
    p.wait()
    for f in (p.stdin, p.stdout, p.stderr):
        f.close()


def test_a_second_writer_is_refused_naming_the_first_and_a_killed_one_leaves_it_free(run, holder):
    proc, _ = holder
    with pytest.raises(RunStoreError) as err:
        RunStore.open(run, mode="r+")
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{run} is being written by pid {proc.pid} on {socket.gethostname()} ('holder.py {run}', "
                          "since ")
    assert msg.endswith("wait for it to finish or stop it, then try again (reading it needs no lock: open it "
                        "read-only)")
    # replacing it is refused too, and leaves it whole
    with pytest.raises(RunStoreError, match=f"being written by pid {proc.pid}"):
        RunStore.create(run, RunStore.open(run).rig, 2, timing={}, software_version="x", overwrite=True)
    assert RunStore.open(run).n_pairs == 2 and (run / "cam0" / "frames" / "zarr.json").exists()
    # readers never wait for the lock, and can say who writes
    r = RunStore.open(run)
    assert r.writer["pid"] == proc.pid and r.writer["host"] == socket.gethostname() and r.writer_token is None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert r.writer is None  # the kernel released the lock of the killed process
    with RunStore.open(run, mode="r+") as w:
        assert w.writer["pid"] == os.getpid() and w.writer_token
        w.write_frame("cam0", 1, 0, np.full((160, 192), 3, np.uint16), 2, 2)
    assert RunStore.open(run).writer is None and RunStore.open(run).frames("cam0")[1, 0, 0, 0] == 3


def test_a_process_given_the_token_writes_under_the_writers_lock(run, holder, tmp_path):
    proc, token = holder
    w = RunStore.open(run, mode="r+", shared_with=token)  # a cluster's worker, given the token by the coordinator
    assert w.writer_token == token
    w.write_frame("cam0", 0, 0, np.full((160, 192), 5, np.uint16), 0, 0)
    with pytest.raises(RunStoreError, match=rf"being written by pid {proc.pid} .*, not by the process that shared its "
                                            r"lock \(token 0123abcd\)"):
        RunStore.open(run, mode="r+", shared_with="0123abcd" * 4)
    proc.stdin.write("go\n")
    proc.stdin.flush()
    proc.wait()
    with pytest.raises(RunStoreError, match=rf"has no writer any more: the process that shared its lock \(token "
                                            rf"{token[:8]}\) has ended; run the command again"):
        RunStore.open(run, mode="r+", shared_with=token)
    assert RunStore.open(run).frames("cam0")[0, 0, 0, 0] == 5


def test_processes_started_by_the_writer_share_its_lock(run, tmp_path):
    """A local Dask worker (``--workers N``) is a child of the command that holds the lock: it
    writes without taking it, with or without the token."""
    with RunStore.open(run, mode="r+") as s:
        script = str(_script(tmp_path, "writer.py", WRITER))
        for args in ([], [s.writer_token]):
            out = subprocess.run([sys.executable, script, str(run), *args], env=_env(), capture_output=True,
                                 text=True, timeout=120)
            assert out.returncode == 0 and out.stdout == "wrote\n", out.stderr
    assert RunStore.open(run).frames("cam0")[0, 1, 0, 0] == 9


def test_the_handles_of_one_process_share_the_lock_until_the_last_goes(run):
    a = RunStore.open(run, mode="r+")
    b = RunStore.open(run, mode="r+")  # the same process: one writer
    assert a.writer_token == b.writer_token
    a.close()
    a.close()  # idempotent
    assert RunStore.open(run).writer["pid"] == os.getpid()
    with pytest.raises(ValueError):  # a closed handle reads but no longer writes
        a.commit(1)
    b.commit(1)
    del b
    gc.collect()
    assert RunStore.open(run).writer is None  # a handle collected gives its share back
    c = RunStore.create(run, RunStore.open(run).rig, 3, timing={}, software_version="x", overwrite=True)
    assert c.n_pairs == 3 and c.writer["pid"] == os.getpid() and (run / ".lfpiv-writer.lock").exists()
    c.close()
    assert RunStore.open(run).writer is None


def test_readers_take_no_lock(run):
    os.remove(run / ".lfpiv-writer.lock")
    r = RunStore.open(run)
    assert r.writer is None and not (run / ".lfpiv-writer.lock").exists()
    r.close()  # nothing to give back
