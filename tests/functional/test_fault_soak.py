"""A soak of faults: kills, a full disk, damaged chunks and second writers, one after another
over a few hundred pairs, each followed by a check of everything recorded and derived against a
clean run of the same pairs.

A synthetic run is made twice from the same seed: once cleanly (synth, reconstruct, correlate:
the reference) and once through the faults, in rounds of a slice of its pairs each. After every
fault each committed frame must equal the reference bit for bit, every volume and vector field
there must equal the reference's (the reconstruction and correlation are deterministic on one
device, so bit for bit too), nothing there before the fault may be gone, and damaged input must
have been named in one line (exit 2) and nothing derived from it. Recordings (``acquire`` on the
simulated lab) are killed, refused to a second writer and cut short by a full disk between the
rounds; their committed frames must equal the frames the simulated cameras made.

The frames are tiny (64 x 48 pixels) so that the default soak (132 synthetic pairs, about 400
with the recordings, every fault kind at least once) stays well within CI's time on 2 cores.
``LFPIV_LONG_SOAK=1`` runs the long version: 720 synthetic pairs, every fault kind three times.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lfcore.errors import DeviceError
from lfcore.runstore import FrameWriter, RunStore
from lfpiv.cli import main
from lfpiv.jobs.acquire import record
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import (
    LFPIV,
    chunk_file,
    damage_chunk,
    fast_rig_text,
    no_space,
    one_error,
    sim_lab,
    stop_when,
    store_held,
    terminal_signals,
    wait_committed,
)

LONG = os.environ.get("LFPIV_LONG_SOAK", "") not in ("", "0")
#: Rounds of faults on the synthetic run, in the order they come; the recordings' faults
#: (``acquire-*``) come between them.
SCHEDULE = ("kill-reconstruct", "frame-deleted", "full-disk-reconstruct", "acquire-kill", "second-writer",
            "volume-random", "kill-correlate", "acquire-second-writer", "frame-random", "full-disk-correlate",
            "frame-truncated", "acquire-full-disk", "volume-truncated", "frame-damaged-replacement")
SYNTH_ROUNDS = [f for f in SCHEDULE if not f.startswith("acquire-")] * (3 if LONG else 1)
ACQUIRE_ROUNDS = [f for f in SCHEDULE if f.startswith("acquire-")] * (3 if LONG else 1)
SLICE = 60 if LONG else 12  # pairs per round
PAIRS = SLICE * len(SYNTH_ROUNDS)
ITER = ["--iterations", "2"]
WINDOWS = ["--windows", "16x16x8"]


def _small(text: str) -> str:
    """A rig of the tiny rig's optics on a 64 x 48 pixel crop of its sensor and a volume to match."""
    return (text.replace("sensor_px = [192, 160]", "sensor_px = [64, 48]")
            .replace("size_mm = [0.9, 0.75, 1.6]", "size_mm = [0.3, 0.22, 0.8]")
            .replace("rays_per_particle = 4000", "rays_per_particle = 500"))


@pytest.fixture(scope="module")
def soak_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("soak")


@pytest.fixture(scope="module")
def clean(soak_dir: Path) -> dict:
    """The reference: the synthetic run made, reconstructed and correlated without a fault, and a
    copy of it as recorded (frames only) for the faults."""
    rig = soak_dir / "small.toml"
    rig.write_text(_small((EXAMPLES / "tiny.toml").read_text()))
    ref = soak_dir / "clean.zarr"
    assert main(["synth", "--rig", str(rig), "--out", str(ref), "--pairs", str(PAIRS), "--ppm", "0.3",
                 "--quiet"]) == 0
    shutil.copytree(ref, soak_dir / "faulted.zarr")
    assert main(["reconstruct", str(ref), *ITER, "--quiet"]) == 0
    assert main(["correlate", str(ref), *WINDOWS, "--quiet"]) == 0
    s = RunStore.open(ref)
    vec = s.vectors()
    return {"rig": rig, "path": ref, "frames": s.frames("cam0")[...], "volumes": s.volumes()[...],
            "vectors": {k: vec[k][...] for k in ("u", "v", "w", "flags")}}


class Ledger:
    """What the faulted run holds, checked against the reference after every fault: every frame,
    every volume and vector field there, and that nothing there before is gone."""

    def __init__(self, path: Path, clean: dict) -> None:
        self.path = path
        self.clean = clean
        self.volumes: set[int] = set()
        self.vectors: set[int] = set()

    def check(self, fault: str, *, damaged: Path | None = None, skip: int | None = None) -> None:
        """``damaged``: a chunk file left damaged for now, of pair ``skip``, which is not read."""
        s = RunStore.open(self.path)
        assert s.committed_pairs == PAIRS and s.state == "complete", fault
        idx = sorted(set(range(PAIRS)) - {skip})
        frames = s.frames("cam0").get_orthogonal_selection((idx,))
        assert np.array_equal(frames, self.clean["frames"][idx]), f"{fault}: a recorded frame changed"
        vols, vecs = set(s.reconstructed_pairs()), set(s.correlated_pairs()) if s.has_vectors else set()
        assert vols >= self.volumes, f"{fault}: volumes of pairs {sorted(self.volumes - vols)} are gone"
        assert vecs >= self.vectors, f"{fault}: vectors of pairs {sorted(self.vectors - vecs)} are gone"
        if vols:
            idx = sorted(vols - {skip})
            assert s.group["volumes"].attrs["settings"]["iterations"] == 2, fault
            now = s.volumes().get_orthogonal_selection((idx,))
            assert np.array_equal(now, self.clean["volumes"][idx]), f"{fault}: volumes differ"
        if vecs:
            idx = sorted(vecs)
            now = s.vectors()
            for k, ref in self.clean["vectors"].items():
                assert np.array_equal(now[k][...][idx], ref[idx], equal_nan=True), f"{fault}: vectors {k} differ"
        self.volumes, self.vectors = vols, vecs
        if damaged is None:
            assert RunStore.check(self.path) == [], fault


def _pairs(r: int) -> list[str]:
    return ["--pair-range", f"{r * SLICE}:{(r + 1) * SLICE}"]


def _start(*argv: object) -> subprocess.Popen:
    return subprocess.Popen([*LFPIV, *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=terminal_signals)


def _kill_when(proc: subprocess.Popen, path: Path, count, at_least: int, what: str, capsys, second) -> None:
    """SIGKILL ``proc`` once ``count(store)`` reaches ``at_least``; just before, ``second`` (a
    command line) must be refused in one line naming it. The store is read only while ``proc`` is
    stopped (SIGSTOP), and ``proc`` stays stopped once the count is reached: it runs only during the
    waits between reads, so even on a loaded machine, where opening the store is slow, it cannot
    finish its slice, and let go of the store, while it is read or while the second writer starts."""
    try:
        n = stop_when(proc, path, count, at_least, what=what)  # holds the store, alive, mid-way
        assert n < SLICE, f"the process finished its slice ({n} {what}) before it could be stopped"
        rc, _, err = _run(capsys, *second)
        assert rc == 2 and one_error(err) and f"pid {proc.pid}" in err, err
        proc.kill()
        proc.wait(30)
    finally:
        proc.kill()
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL


def _recover(capsys, path: Path, r: int) -> None:
    """The pairs of round ``r`` reconstructed and correlated, going on from where a fault left off."""
    for argv in (["reconstruct", path, *ITER, *_pairs(r), "--skip-done", "--quiet"],
                 ["correlate", path, *WINDOWS, *_pairs(r), "--skip-done", "--quiet"]):
        rc, _, err = _run(capsys, *argv)
        assert rc == 0, err


def _synth_round(fault: str, r: int, ledger: Ledger, capsys, monkeypatch, tmp: Path) -> None:
    path = ledger.path
    first = r * SLICE
    damaged: Path | None = None
    if fault == "kill-reconstruct":  # mid-way through the slice, after a second writer is refused
        proc = _start("reconstruct", path, *ITER, *_pairs(r), "--quiet")
        _kill_when(proc, path, lambda s: len([p for p in s.reconstructed_pairs() if p >= first]), 1, "volumes",
                   capsys, ["correlate", path, *WINDOWS, "--quiet"])
    elif fault == "kill-correlate":
        assert _run(capsys, "reconstruct", path, *ITER, *_pairs(r), "--quiet")[0] == 0
        ledger.check(fault + " (before)")
        proc = _start("correlate", path, *WINDOWS, *_pairs(r), "--quiet")
        _kill_when(proc, path, lambda s: len([p for p in s.correlated_pairs() if p >= first]), 1, "vectors",
                   capsys, ["reconstruct", path, *ITER, *_pairs(r), "--quiet"])
    elif fault.startswith("full-disk-"):  # the disk fills after a third of the slice
        import lfcore.runstore as runstore

        name = "write_volume" if fault.endswith("reconstruct") else "write_vectors"
        if name == "write_vectors":
            assert _run(capsys, "reconstruct", path, *ITER, *_pairs(r), "--quiet")[0] == 0
            ledger.check(fault + " (before)")
        with monkeypatch.context() as m:
            m.setattr(runstore.RunStore, name, no_space(getattr(runstore.RunStore, name), SLICE // 3))
            argv = ["reconstruct", path, *ITER] if name == "write_volume" else ["correlate", path, *WINDOWS]
            rc, _, err = _run(capsys, *argv, *_pairs(r), "--quiet")
        assert rc == 2 and one_error(err) and f"cannot use {path}/" in err and "No space left" in err, err
    elif fault == "second-writer":  # a writer holds the run: every other writer refused, readers work
        with store_held(path) as holder:
            for argv in (["reconstruct", path, *ITER, *_pairs(r), "--quiet"],
                         ["correlate", path, *WINDOWS, "--quiet"],
                         ["synth", "--rig", ledger.clean["rig"], "--out", path, "--overwrite", "--pairs", "1",
                          "--quiet"]):
                rc, _, err = _run(capsys, *argv)
                assert rc == 2 and one_error(err) and f"pid {holder.pid}" in err, (argv, err)
            rc, out, _ = _run(capsys, "info", path)
            assert rc == 0 and f"being written by pid {holder.pid}" in out
            ledger.check(fault + " (held)")
    elif fault.startswith(("frame-", "volume-")):  # a chunk of a pair not yet derived is damaged
        how = fault.split("-")[1]
        pair = first + SLICE // 2
        if fault.startswith("volume-"):
            assert _run(capsys, "reconstruct", path, *ITER, *_pairs(r), "--quiet")[0] == 0
            ledger.check(fault + " (before)")
        if how == "damaged":  # frame-damaged-replacement: frames of derived pairs, other settings
            _recover(capsys, path, r)
            ledger.check(fault + " (before)")
            how = "random"
        array = "cam0/frames" if fault.startswith("frame-") else "volumes/data"
        damaged = chunk_file(path, array, pair)
        backup = damaged.read_bytes()
        damage_chunk(damaged, how)
        if fault == "frame-damaged-replacement":
            argv = ["reconstruct", path, "--iterations", "3", *_pairs(r), "--quiet"]
        elif array == "cam0/frames":
            argv = ["reconstruct", path, *ITER, *_pairs(r), "--quiet"]
        else:
            argv = ["correlate", path, *WINDOWS, *_pairs(r), "--quiet"]
        rc, _, err = _run(capsys, *argv)
        assert rc == 2 and one_error(err) and f"{array} pair {pair}" in err, err
        assert RunStore.check(path), "lfpiv check finds no damage"
        ledger.check(fault, damaged=damaged, skip=pair)
        derived = ledger.volumes if array == "cam0/frames" else ledger.vectors
        assert fault == "frame-damaged-replacement" or pair not in derived, f"{fault}: derived from damaged input"
        damaged.write_bytes(backup)  # the lab's backup copy put back
    ledger.check(fault)
    _recover(capsys, path, r)
    ledger.check(fault + " (recovered)")
    assert set(range(first, first + SLICE)) <= ledger.volumes & ledger.vectors


@pytest.fixture(scope="module")
def fast_rig_file(soak_dir: Path) -> Path:
    """The fast two-camera rig of the recording tests on the small sensor."""
    path = soak_dir / "fast.toml"
    path.write_text(_small(fast_rig_text()).replace("sensor_px = [192, 160]", "sensor_px = [64, 48]"))
    return path


def _acquire(rig: Path, out: Path, pairs: int) -> subprocess.Popen:
    return _start("acquire", "--rig", rig, "--pairs", pairs, "--out", out, "--quiet", "--sim-rays", "300",
                  "--sim-ppm", "0.3", "--sim-pool", "2")


def _recorded_as_made(path: Path, pool: dict[str, np.ndarray], *, at_least: int) -> int:
    """Every committed frame is the one its camera made for that trigger (pool pair ``p % len``),
    or dropped; the run is whole. The number of committed pairs."""
    s = RunStore.open(path)
    n = s.committed_pairs
    assert n >= at_least
    for cam, made in pool.items():
        frames, ids = s.frames(cam)[:n], s.frame_ids(cam)[:n]
        p, f = np.nonzero(ids >= 0)
        assert len(p) >= 2 * n - 4  # the simulated lab drops none but by a fault
        assert np.array_equal(frames[p, f], made[p % len(made), f]), f"{path}: {cam} frames differ"
    assert RunStore.check(path) == [], RunStore.check(path)
    return n


def _acquire_round(fault: str, k: int, rig: Path, pool: dict, capsys, monkeypatch, tmp: Path) -> int:
    out = tmp / f"{fault}-{k}.zarr"
    if fault == "acquire-kill":
        proc = _acquire(rig, out, 5000)
        try:
            wait_committed(out, 60, proc, timeout_s=120)
        finally:
            proc.kill()
            proc.communicate()
        assert RunStore.open(out).state == "recording"  # nobody could say otherwise
        return _recorded_as_made(out, pool, at_least=60)
    if fault == "acquire-second-writer":
        proc = _acquire(rig, out, 150)
        try:
            wait_committed(out, 5, proc, timeout_s=120)
            rc, _, err = _run(capsys, "acquire", "--rig", rig, "--pairs", "3", "--out", out, "--overwrite",
                              "--quiet", "--sim-pool", "1")
            assert rc == 2 and one_error(err) and f"pid {proc.pid}" in err, err
            _, err = proc.communicate(timeout=120)
        finally:
            proc.kill()
        assert proc.returncode == 0, err
        assert RunStore.open(out).state == "complete"
        return _recorded_as_made(out, pool, at_least=150)
    # acquire-full-disk: the disk fills while frames are written; the laser is disarmed, what was
    # committed is kept whole
    fast = load_rig(rig)
    with sim_lab(fast) as lab, monkeypatch.context() as m:
        m.setattr(FrameWriter, "write", no_space(FrameWriter.write, 4 * 50))
        with pytest.raises(DeviceError) as exc:
            record(fast, out, 500, sim_options={"lab": lab})
        assert not lab.pulse_generator.outputs_enabled()
        made = {c.name: np.asarray(c._lit) for c in lab.cameras}
    assert "No space left" in str(exc.value) and str(out) in str(exc.value), exc.value
    assert "the laser was disarmed" in str(exc.value)
    assert RunStore.open(out).state == "aborted"
    return _recorded_as_made(out, made, at_least=20)


def test_faults_one_after_another_lose_nothing_and_derive_nothing_from_damage(
        clean, soak_dir, fast_rig_file, tmp_path, capsys, monkeypatch):
    ledger = Ledger(soak_dir / "faulted.zarr", clean)
    # what the simulated cameras make for each trigger (pool pair p % 2), from a clean recording
    ref = tmp_path / "ref.zarr"
    proc = _acquire(fast_rig_file, ref, 2)
    assert proc.wait(120) == 0, proc.communicate()[1]
    s = RunStore.open(ref)
    pool = {cam: s.frames(cam)[...] for cam in s.cameras}
    recorded = 0
    acquire_rounds = iter(enumerate(ACQUIRE_ROUNDS))
    for r, fault in enumerate(SYNTH_ROUNDS):
        _synth_round(fault, r, ledger, capsys, monkeypatch, tmp_path)
        if r % 3 == 2:  # a recording's fault every third round
            k, afault = next(acquire_rounds, (None, None))
            if afault:
                recorded += _acquire_round(afault, k, fast_rig_file, pool, capsys, monkeypatch, tmp_path)
    for k, afault in acquire_rounds:
        recorded += _acquire_round(afault, k, fast_rig_file, pool, capsys, monkeypatch, tmp_path)
    assert ledger.volumes == ledger.vectors == set(range(PAIRS))
    print(f"soak: {PAIRS} synthetic pairs through {len(SYNTH_ROUNDS)} faults, {recorded} recorded pairs through "
          f"{len(ACQUIRE_ROUNDS)}")
