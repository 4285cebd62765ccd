"""An adversarial sweep: bad inputs and faults across the commands, as a new user (or a bad day
in the lab) would give them, each in a child process with a time limit.

Run from the repository root::

    .venv/bin/python benchmarks/adversarial.py                    # every case, 2 at a time
    .venv/bin/python benchmarks/adversarial.py --only rig,disk    # some groups
    .venv/bin/python benchmarks/adversarial.py --csv out.csv --jobs 1

Groups of cases:

rig
    rig files with bad keys and values (missing tables, unknown keys, zero, negative, NaN, huge
    numbers, wrong types, broken TOML, a directory, binary bytes).
path
    run stores, outputs, plots and logs at paths that are missing, files, directories, or not
    stores; an existing folder that is not a run store under ``--overwrite``.
option
    out-of-range, malformed and unbounded options of every command.
store
    damaged run stores: missing, random or cut-short chunks of frames, volumes and vectors, edited
    metadata (``data_type``, ``committed_pairs``, ``format_version``, ``state``, ...), fed to the
    commands that read them.
kill, interrupt
    SIGKILL, SIGINT and SIGTERM during ``acquire``, ``synth``, ``reconstruct`` and ``correlate``
    (and three Ctrl-Cs in a row).
writer
    a second writer on a store that one process is writing; readers beside a writer.
disk
    a full disk (a small tmpfs, mounted when this runs as root; the group is left out otherwise)
    under ``synth``, ``reconstruct``, ``correlate``, ``export`` and ``acquire``.
writes, streams, defaults, rig-range (issue 50, :func:`cases_writes_streams`)
    plots, screenshots, study outputs and imports on a full disk (the earlier file whole, the path
    named); ``--log-file`` inside a store or on a full disk (``/dev/full``); a broken pipe and
    closed stdout, stderr or all three; a stale ``vectors.replaced/``; a run with a recorded drop;
    rig values finite but meaningless (each naming its key); defaults that must not refuse.
schema
    edited or damaged store attributes (text for numbers, a zero, negative or moved voxel grid,
    ``timing`` not a table, lists as text) fed to ``info``, ``check``, ``correlate``, ``evaluate``
    and ``export`` (issue 50).
import
    import sets with entries that are not what they seem: dangling and looping links, pipes,
    a ``background.tif`` that sorts first, signed images with negative counts, LZW and corrupt
    compressed TIFFs, TIFFs appended page by page, 1-bit images (issue 50).

Each case is classified as

- ``clean error``: a non-zero exit and one line of error (``lfpiv: error: ...``), no traceback;
- ``accepted``: exit 0 where the input is valid (or is a fault the command rides out), the
  store's data checked where there is any;
- ``traceback``: a Python traceback, a fatal error or death by a signal it was not sent;
- ``hang``: still running at the time limit (killed);
- ``wrong result``: exit 0 on input that must be refused, or a result that is not what it must be;
- ``data lost``: a committed frame, or volumes and vectors made before, changed or gone after a
  command that failed or was refused;
- ``messy error``: a non-zero exit without a traceback but not one line.

The table of counts is printed and every case is written to a CSV (``--csv``, default
``adversarial.csv`` in the work folder). Record results in benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore.runstore import RunStore  # noqa: E402
from tests.helpers import fast_rig_text  # noqa: E402

TINY = ROOT / "examples" / "tiny.toml"
CLASSES = ("clean error", "accepted", "traceback", "hang", "wrong result", "data lost", "messy error")
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1", QT_QPA_PLATFORM="offscreen")


@dataclass
class Ctx:
    """The work folder and what every case may copy from it."""

    work: Path
    timeout_s: float
    made: Path = field(init=False)  # a tiny run with volumes and vectors (2 pairs)
    long: Path = field(init=False)  # a tiny run of 12 pairs, no volumes (for kills)
    fast_rig: Path = field(init=False)  # the tiny rig with a fast laser and two cameras
    tiny_text: str = field(init=False)

    def case_dir(self, name: str) -> Path:
        d = self.work / "cases" / name
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        return d


@dataclass
class Outcome:
    cls: str
    rc: int | None
    seconds: float
    detail: str


@dataclass
class Case:
    name: str
    group: str
    run: Callable[[Ctx, Path], Outcome]
    command: str = ""


# --- running lfpiv ---------------------------------------------------------------------------

def lfpiv(args: list[object], cwd: Path, timeout_s: float,
          env: dict | None = None) -> tuple[int | None, str, str, float]:
    """``lfpiv ARGS`` in a child process: exit code (None on a hang), stdout, stderr, seconds."""
    t = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "lfpiv", *map(str, args)], cwd=cwd, env=env or ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout_s)
        return proc.returncode, out, err, time.monotonic() - t
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        return None, out, err, time.monotonic() - t


def one_line_error(err: str) -> bool:
    """One line of error, last, no traceback (notes of what the command began may come before)."""
    lines = [x for x in err.strip().splitlines() if x.strip()]
    return bool(lines) and (lines[-1].startswith("lfpiv: error: ") or lines[-1].startswith("lfpiv: device error: ")) \
        and sum("error" in x for x in lines) == 1 and "Traceback" not in err


def crashed(rc: int | None, err: str, sent: int | None = None) -> bool:
    return "Traceback (most recent call last)" in err or "Fatal Python error" in err or \
        (rc is not None and rc < 0 and -rc != sent)


def last_line(out: str, err: str) -> str:
    lines = [x for x in (err.strip() or out.strip()).splitlines() if x.strip()]
    return lines[-1][:300] if lines else ""


def classify(rc: int | None, out: str, err: str, secs: float, expect: str) -> Outcome:
    """``expect``: "error" (must be refused), "accept" (must work), "either" (valid or refused),
    "report" (``check``: exit 1 listing the problems)."""
    detail = last_line(out, err)
    if rc is None:
        return Outcome("hang", rc, secs, detail)
    if crashed(rc, err):
        tb = [x for x in err.strip().splitlines() if x.strip()]
        return Outcome("traceback", rc, secs, tb[-1][:300] if tb else f"exit {rc}")
    if rc == 0:
        if expect in ("accept", "either"):
            return Outcome("accepted", rc, secs, detail)
        return Outcome("wrong result", rc, secs, "accepted: " + detail)
    if expect != "accept" and rc == 1 and "problem" in out:  # lfpiv check listing the problems
        return Outcome("clean error", rc, secs, detail)
    if one_line_error(err):
        if expect == "accept":
            return Outcome("wrong result", rc, secs, "refused: " + detail)
        return Outcome("clean error", rc, secs, detail)
    return Outcome("messy error", rc, secs, " | ".join(err.strip().splitlines()[-3:])[:300])


# --- store snapshots: what must never change --------------------------------------------------

def snapshot(store: Path) -> dict[str, str]:
    """Hash of every chunk file of frames, volumes and vectors (not replacements in progress)."""
    out = {}
    if not store.is_dir():
        return out
    for p in store.rglob("*"):
        rel = p.relative_to(store).as_posix()
        if p.is_file() and "/c/" in f"/{rel}" and ".pending" not in rel and not rel.endswith(".partial"):
            out[rel] = hashlib.sha1(p.read_bytes()).hexdigest()
    return out


def lost(before: dict[str, str], store: Path, *, keep: str = "all", damaged: str | None = None) -> list[str]:
    """Chunk files of ``before`` changed or gone: every one (``keep="all"``), or of frames only
    (``keep="frames"``, after a command that may replace volumes or vectors)."""
    now = snapshot(store)
    gone = []
    for rel, h in before.items():
        if rel == damaged or (keep == "frames" and not rel.split("/")[1:2] == ["frames"]):
            continue
        if now.get(rel) != h:
            gone.append(rel)
    return gone


def store_case(ctx: Ctx, d: Path, args: list[object], expect: str, *, src: str = "made",
               damage: Callable[[Path], str | None] | None = None, keep_if_ok: str = "frames") -> Outcome:
    """Run ``args`` (``RUN`` in them stands for a copy of a store) and classify, with the data check."""
    run = d / "run.zarr"
    shutil.copytree(getattr(ctx, src), run)
    damaged = damage(run) if damage else None
    before = snapshot(run)
    rc, out, err, secs = lfpiv([run if a == "RUN" else _sub(a, ctx, d) for a in args], d, ctx.timeout_s)
    o = classify(rc, out, err, secs, expect)
    if o.cls in ("hang", "traceback"):
        return o
    gone = lost(before, run, keep=keep_if_ok if rc == 0 else "all", damaged=damaged)
    if gone:
        return Outcome("data lost", rc, secs, f"{len(gone)} chunk(s) changed or gone, e.g. {gone[0]}; {o.detail}")
    if damage and rc == 0 and expect == "error":
        return Outcome("wrong result", rc, secs, "derived from damaged input: " + o.detail)
    return o


def simple(args: list[object], expect: str, *, prepare: Callable[[Ctx, Path], None] | None = None,
           after: Callable[[Ctx, Path, Outcome], Outcome] | None = None) -> Callable[[Ctx, Path], Outcome]:
    """A case: ``args`` (``RUN`` a copy of the made store, ``TINY`` the rig, ``D`` the case folder)."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        if prepare:
            prepare(ctx, d)
        if "RUN" in args:
            return store_case(ctx, d, args, expect)
        rc, out, err, secs = lfpiv([_sub(a, ctx, d) for a in args], d, ctx.timeout_s)
        o = classify(rc, out, err, secs, expect)
        return after(ctx, d, o) if after and o.cls not in ("hang", "traceback") else o
    return run


def _sub(a: object, ctx: Ctx, d: Path) -> object:
    if a == "TINY":
        return TINY
    if a == "FAST":
        return ctx.fast_rig
    if isinstance(a, str) and a.startswith("D/"):
        return d / a[2:]
    return a


# --- rig files ---------------------------------------------------------------------------------

def rig_variants(tiny: str) -> list[tuple[str, str, str]]:
    """(name, rig text or a special, expect)."""
    cam = tiny[tiny.index("[[camera]]"):tiny.index("[laser]")]

    def rep(old: str, new: str) -> str:
        assert old in tiny, old
        return tiny.replace(old, new, 1)

    v = [
        ("no-volume-table", tiny.replace(tiny[tiny.index("[volume]"):tiny.index("[[camera]]")], ""), "error"),
        ("no-camera", tiny.replace(cam, ""), "error"),
        ("no-sensor", rep("sensor_px = [192, 160]", ""), "error"),
        ("unknown-camera-key", rep("sensor_px = [192, 160]", "sensor_px = [192, 160]\nsensor_pxx = 3"), "error"),
        ("unknown-table", tiny + "\n[foo]\nbar = 1\n", "error"),
        ("unknown-top-key", "colour = 'red'\n" + tiny, "error"),
        ("sensor-zero", rep("sensor_px = [192, 160]", "sensor_px = [0, 0]"), "error"),
        ("sensor-negative", rep("sensor_px = [192, 160]", "sensor_px = [-192, 160]"), "error"),
        ("sensor-one-number", rep("sensor_px = [192, 160]", "sensor_px = [192]"), "error"),
        ("sensor-string", rep("sensor_px = [192, 160]", 'sensor_px = "192x160"'), "error"),
        ("sensor-float", rep("sensor_px = [192, 160]", "sensor_px = [192.5, 160]"), "error"),
        ("sensor-huge", rep("sensor_px = [192, 160]", "sensor_px = [1000000000, 1000000000]"), "error"),
        ("pitch-zero", rep("pixel_pitch_um = 5.5", "pixel_pitch_um = 0"), "error"),
        ("pitch-negative", rep("pixel_pitch_um = 5.5", "pixel_pitch_um = -5.5"), "error"),
        ("pitch-nan", rep("pixel_pitch_um = 5.5", "pixel_pitch_um = nan"), "error"),
        ("pitch-inf", rep("pixel_pitch_um = 5.5", "pixel_pitch_um = inf"), "error"),
        ("pitch-string", rep("pixel_pitch_um = 5.5", 'pixel_pitch_um = "5.5"'), "error"),
        ("pitch-bool", rep("pixel_pitch_um = 5.5", "pixel_pitch_um = true"), "error"),
        ("mla-grid-bad", rep('mla_grid = "hex"', 'mla_grid = "triangle"'), "error"),
        ("mla-pitch-zero", rep("mla_pitch_um = 55.0", "mla_pitch_um = 0.0"), "error"),
        ("mla-pitch-below-pixel", rep("mla_pitch_um = 55.0", "mla_pitch_um = 1.0"), "error"),
        ("mla-focal-negative", rep("mla_focal_length_um = 220.0", "mla_focal_length_um = -220.0"), "error"),
        ("main-focal-zero", rep("main_focal_length_mm = 50.0", "main_focal_length_mm = 0.0"), "error"),
        ("f-number-zero", rep("f_number = 2.0", "f_number = 0.0"), "error"),
        ("f-number-nan", rep("f_number = 2.0", "f_number = nan"), "error"),
        ("magnification-zero", rep("magnification = -1.0", "magnification = 0.0"), "error"),
        ("rotation-two", rep("rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [0.0, 0.0]"), "error"),
        ("rotation-nan", rep("rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [nan, 0.0, 0.0]"), "error"),
        ("focus-string", rep("focus_mm = [0.0, 0.0, 0.0]", 'focus_mm = "here"'), "error"),
        ("focus-far", rep("focus_mm = [0.0, 0.0, 0.0]", "focus_mm = [0.0, 0.0, 1e9]"), "error"),
        ("size-zero", rep("size_mm = [0.9, 0.75, 1.6]", "size_mm = [0.0, 0.75, 1.6]"), "error"),
        ("size-negative", rep("size_mm = [0.9, 0.75, 1.6]", "size_mm = [-0.9, 0.75, 1.6]"), "error"),
        ("size-huge", rep("size_mm = [0.9, 0.75, 1.6]", "size_mm = [1e6, 1e6, 1e6]"), "error"),
        ("size-inf", rep("size_mm = [0.9, 0.75, 1.6]", "size_mm = [inf, 0.75, 1.6]"), "error"),
        ("pvr-zero", rep("pvr = [2.0, 2.0, 10.0]", "pvr = [0.0, 2.0, 10.0]"), "error"),
        ("pvr-tiny", rep("pvr = [2.0, 2.0, 10.0]", "pvr = [1e-6, 1e-6, 1e-6]"), "either"),  # synth needs no voxels
        ("centre-nan", rep("centre_mm = [0.0, 0.0, 0.0]", "centre_mm = [nan, 0.0, 0.0]"), "error"),
        ("wavelength-zero", rep("wavelength_nm = 532.0", "wavelength_nm = 0.0"), "error"),
        ("rate-zero", rep("rate_hz = 10.0", "rate_hz = 0.0"), "error"),
        ("rate-negative", rep("rate_hz = 10.0", "rate_hz = -10.0"), "error"),
        ("sheet-bad", rep('sheet_profile = "uniform"', 'sheet_profile = "square"'), "error"),
        ("dt-zero", rep("dt_us = 2000.0", "dt_us = 0.0"), "error"),
        ("dt-negative", rep("dt_us = 2000.0", "dt_us = -2000.0"), "error"),
        ("dt-huge", rep("dt_us = 2000.0", "dt_us = 1e12"), "error"),
        ("rays-zero", rep("rays_per_particle = 4000", "rays_per_particle = 0"), "error"),
        ("rays-huge", rep("rays_per_particle = 4000", "rays_per_particle = 1000000000000"), "error"),
        ("rays-float", rep("rays_per_particle = 4000", "rays_per_particle = 4000.5"), "error"),
        ("particles-1e300", rep("particle_counts = 50000.0", "particle_counts = 1e300"), "error"),
        ("particles-negative", rep("particle_counts = 50000.0", "particle_counts = -1.0"), "error"),
        ("hardware-number", rep('hardware = "sim"', "hardware = 5"), "error"),
        ("hardware-bad", rep('hardware = "sim"', 'hardware = "magic"'), "error"),
        ("camera-twice", tiny + "\n" + cam, "error"),
        ("camera-name-empty", rep('name = "cam0"', 'name = ""'), "error"),
        ("camera-name-slash", rep('name = "cam0"', 'name = "cam/0"'), "error"),
        ("camera-name-dotdot", rep('name = "cam0"', 'name = ".."'), "error"),
        ("camera-kind-bad", rep('name = "cam0"', 'name = "cam0"\nkind = "fisheye"'), "error"),
        ("pinhole-no-focal", rep('name = "cam0"', 'name = "cam0"\nkind = "pinhole"'), "error"),
        ("toml-syntax", tiny.replace("[laser]", "[laser"), "error"),
        ("toml-duplicate-key", rep("f_number = 2.0", "f_number = 2.0\nf_number = 3.0"), "error"),
        ("empty-file", "", "error"),
        ("binary", "BINARY", "error"),
        ("directory", "DIR", "error"),
        ("missing", "MISSING", "error"),
        ("json-instead", json.dumps({"volume": {"size_mm": [1, 1, 1]}}), "error"),
    ]
    return v


def rig_case(text: str, expect: str, command: str) -> Callable[[Ctx, Path], Outcome]:
    def run(ctx: Ctx, d: Path) -> Outcome:
        rig = d / "rig.toml"
        if text == "DIR":
            rig.mkdir()
        elif text == "BINARY":
            rig.write_bytes(os.urandom(2000))
        elif text != "MISSING":
            rig.write_text(text)
        argv = {"synth": ["synth", "--rig", rig, "--out", d / "r.zarr", "--pairs", "1", "--ppm", "0.2", "--rays",
                          "100", "--quiet"],
                "devices": ["devices", "--rig", rig],
                "acquire": ["acquire", "--rig", rig, "--pairs", "2", "--out", d / "a.zarr", "--quiet", "--sim-rays",
                            "100", "--sim-pool", "1"]}[command]
        rc, out, err, secs = lfpiv(argv, d, ctx.timeout_s)
        return classify(rc, out, err, secs, expect)
    return run


# --- damaged stores ----------------------------------------------------------------------------

def _chunk(run: Path, array: str, first: int) -> Path:
    return next(p for p in sorted((run / array / "c").rglob("*")) if p.is_file()
                and p.relative_to(run / array / "c").parts[0] == str(first))


def chunk_damage(array: str, how: str, pair: int = 1) -> Callable[[Path], str]:
    def damage(run: Path) -> str:
        p = _chunk(run, array, pair)
        if how == "deleted":
            p.unlink()
        elif how == "random":
            p.write_bytes(os.urandom(p.stat().st_size))
        elif how == "truncated":
            p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
        elif how == "empty":
            p.write_bytes(b"")
        return p.relative_to(run).as_posix()
    return damage


def meta_damage(key: str, value: object, node: str = "") -> Callable[[Path], None]:
    """Set ``attributes[key]`` (or the array field ``key`` with ``node`` ending in '!') of a zarr.json."""
    def damage(run: Path) -> None:
        f = run / node.rstrip("!") / "zarr.json"
        meta = json.loads(f.read_text())
        if node.endswith("!"):
            meta[key] = value
        elif value is _DELETE:
            meta.get("attributes", {}).pop(key, None)
        else:
            meta.setdefault("attributes", {})[key] = value
        f.write_text(json.dumps(meta))
    return damage


_DELETE = object()


def file_damage(rel: str, how: str) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        f = run / rel
        if how == "deleted":
            f.unlink()
        elif how == "truncated":
            f.write_text(f.read_text()[:40])
        elif how == "garbage":
            f.write_bytes(os.urandom(200))
        elif how == "rmtree":
            shutil.rmtree(f)
    return damage


def damaged_case(damage: Callable[[Path], str | None], args: list[object],
                 expect: str) -> Callable[[Ctx, Path], Outcome]:
    def run(ctx: Ctx, d: Path) -> Outcome:
        return store_case(ctx, d, args, expect, damage=damage)
    return run


# --- signals and second writers ----------------------------------------------------------------

def _start(args: list[object], cwd: Path) -> subprocess.Popen:
    def terminal() -> None:
        for sig in (signal.SIGINT, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
    return subprocess.Popen([sys.executable, "-m", "lfpiv", *map(str, args)], cwd=cwd, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=terminal)


def _wait(cond: Callable[[], bool], proc: subprocess.Popen, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and proc.poll() is None:
        try:
            if cond():
                return True
        except Exception:  # noqa: BLE001 - the store may not exist yet, or be half written
            pass
        time.sleep(0.05)
    return False


def _committed(path: Path, n: int) -> Callable[[], bool]:
    return lambda: RunStore.open(path).committed_pairs >= n


def _volumes(path: Path, n: int, names: tuple[str, ...] = ("volumes.pending", "volumes")) -> Callable[[], bool]:
    def cond() -> bool:
        s = RunStore.open(path)
        for name in names:
            if name in s.group:
                if len(s.group[name].attrs.get("reconstructed_pairs", [])) >= n:
                    return True
        return False
    return cond


def _vectors(path: Path, n: int, names: tuple[str, ...] = ("vectors.pending", "vectors")) -> Callable[[], bool]:
    def cond() -> bool:
        s = RunStore.open(path)
        for name in names:
            if name in s.group and len(s.group[name].attrs.get("correlated_pairs", [])) >= n:
                return True
        return False
    return cond


def signal_case(command: str, sig: int, *, times: int = 1) -> Callable[[Ctx, Path], Outcome]:
    """Send ``sig`` to ``command`` once it has done some of its work; then the store is checked:
    what was committed (and volumes or vectors made before) unchanged, ``lfpiv check`` clean but
    for what the command left unfinished, and the same command again (``--skip-done``) finishes."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        t = time.monotonic()
        if command == "acquire":
            args = ["acquire", "--rig", ctx.fast_rig, "--pairs", "5000", "--out", run_, "--quiet", "--sim-rays",
                    "300", "--sim-ppm", "0.2", "--sim-pool", "2"]
            cond = _committed(run_, 20)
            again = None
        elif command == "synth":
            args = ["synth", "--rig", TINY, "--out", run_, "--pairs", "200", "--ppm", "0.2", "--rays", "300",
                    "--quiet"]
            cond = _committed(run_, 3)
            again = None
        elif command == "reconstruct":
            shutil.copytree(ctx.long, run_)
            args = ["reconstruct", run_, "--iterations", "3", "--quiet"]
            cond = _volumes(run_, 2)
            again = [*args, "--skip-done"]
        elif command == "reconstruct-replacement":
            shutil.copytree(ctx.made, run_)
            args = ["reconstruct", run_, "--iterations", "7", "--quiet"]
            cond = _volumes(run_, 1, ("volumes.pending",))  # made is reconstructed: wait for the replacement
            again = None
        else:  # correlate
            shutil.copytree(ctx.made, run_)
            args = ["correlate", run_, "--windows", "16x16x8", "--quiet"]
            cond = _vectors(run_, 1, ("vectors.pending",))  # made is correlated: wait for the replacement
            again = None
        before = snapshot(run_)
        proc = _start(args, d)
        try:
            reached = _wait(cond, proc, ctx.timeout_s)
            for k in range(times):
                if proc.poll() is None:
                    proc.send_signal(sig)
                if k + 1 < times:
                    time.sleep(0.2)
            out, err = proc.communicate(timeout=ctx.timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            return Outcome("hang", None, time.monotonic() - t, last_line(out, err))
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        secs = time.monotonic() - t
        rc = proc.returncode
        if crashed(rc, err, sent=sig):
            return Outcome("traceback", rc, secs, last_line(out, err))
        if sig != signal.SIGKILL and rc == -sig:
            return Outcome("wrong result", rc, secs, f"exit {rc} (ended by the signal), not 130, after: "
                           f"{last_line(out, err) or 'nothing said'}")
        if not reached and rc == 0:
            return Outcome("accepted", rc, secs, "finished before the signal: " + last_line(out, err))
        if sig != signal.SIGKILL and rc != 130:
            return Outcome("wrong result", rc, secs, f"exit {rc}, not 130: {last_line(out, err)}")
        gone = lost(before, run_)
        if gone:
            return Outcome("data lost", rc, secs, f"{len(gone)} chunk(s) changed or gone, e.g. {gone[0]}")
        s = RunStore.open(run_)
        if command == "acquire":
            n = s.committed_pairs
            want = "recording" if sig == signal.SIGKILL else "aborted"
            if n < 20 or s.state != want:
                return Outcome("wrong result", rc, secs, f"{n} pairs committed, state {s.state!r} (not {want!r})")
            if sig == signal.SIGINT and times > 1 and "the laser is disarmed" not in err:
                return Outcome("wrong result", rc, secs, "no line saying the laser is disarmed")
        problems = RunStore.check(run_)
        if problems:
            return Outcome("wrong result", rc, secs, f"check after the signal: {problems[0]}")
        if again:
            rc2, out2, err2, _ = lfpiv(again, d, ctx.timeout_s)
            if rc2 != 0:
                return Outcome("wrong result", rc, secs, f"resuming failed: {last_line(out2, err2)}")
            if RunStore.open(run_).reconstructed_pairs() != list(range(12)):
                return Outcome("wrong result", rc, secs, "resuming did not reconstruct every pair")
        return Outcome("accepted", rc, secs, f"exit {rc}; " + last_line(out, err))
    return run


def writer_case(first: str, second: list[object], *, reader: bool = False) -> Callable[[Ctx, Path], Outcome]:
    """While ``first`` writes the store, ``second`` (``RUN`` the store) must be refused in one line
    naming the first's process (or, ``reader``, work), and the first must finish unharmed."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        if first == "acquire":
            args = ["acquire", "--rig", ctx.fast_rig, "--pairs", "400", "--out", run_, "--quiet", "--sim-rays", "300",
                    "--sim-ppm", "0.2", "--sim-pool", "2"]
            cond = _committed(run_, 5)
        elif first == "reconstruct":
            shutil.copytree(ctx.long, run_)
            args = ["reconstruct", run_, "--iterations", "3", "--quiet"]
            cond = _volumes(run_, 1)
        else:  # correlate
            shutil.copytree(ctx.long, run_)
            assert lfpiv(["reconstruct", run_, "--iterations", "1", "--quiet"], d, ctx.timeout_s)[0] == 0
            args = ["correlate", run_, "--windows", "32x32x16", "--quiet"]
            cond = _vectors(run_, 1)
        if "import" in second:
            _tiffs(d, (160, 192))
        t = time.monotonic()
        proc = _start(args, d)
        try:
            if not _wait(cond, proc, ctx.timeout_s):
                out, err = proc.communicate(timeout=ctx.timeout_s)
                return Outcome("wrong result", proc.returncode, time.monotonic() - t,
                               "the first writer ended before the second came: " + last_line(out, err))
            rc, out, err, secs = lfpiv([run_ if a == "RUN" else _sub(a, ctx, d) for a in second], d, ctx.timeout_s)
            first_alive = proc.poll() is None
            out1, err1 = proc.communicate(timeout=ctx.timeout_s * 3)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            return Outcome("hang", None, time.monotonic() - t, "the first writer did not finish")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if rc is None:
            return Outcome("hang", None, secs, last_line(out, err))
        if crashed(rc, err) or crashed(proc.returncode, err1):
            return Outcome("traceback", rc, secs, last_line(out, err) + " / " + last_line(out1, err1))
        if proc.returncode != 0:
            return Outcome("data lost", rc, secs, "the first writer failed: " + last_line(out1, err1))
        s = RunStore.open(run_)
        whole = (s.committed_pairs == 400 and s.state == "complete") if first == "acquire" else \
            (s.reconstructed_pairs() == list(range(12)) and (first != "correlate" or s.correlated_pairs() ==
                                                              list(range(12))))
        if not whole:
            return Outcome("data lost", rc, secs, "the first writer's result is not whole")
        if reader:
            return Outcome("accepted" if rc == 0 else "wrong result", rc, secs, last_line(out, err))
        if rc == 0:
            return Outcome("wrong result", rc, secs, "a second writer was let in" + (
                "" if first_alive else " (after the first had finished)"))
        if not one_line_error(err):
            return Outcome("messy error", rc, secs, last_line(out, err))
        if f"pid {proc.pid}" not in err:
            return Outcome("wrong result", rc, secs, "refused without naming the writer: " + last_line(out, err))
        return Outcome("clean error", rc, secs, last_line(out, err))
    return run


# --- a full disk -------------------------------------------------------------------------------

def disk_case(command: str) -> Callable[[Ctx, Path], Outcome]:
    """``command`` on a tmpfs too small for its output: one line naming the path, nothing that was
    there before changed."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        mnt = d / "disk"
        mnt.mkdir()
        made_kib = sum(4 * (1 + p.stat().st_size // 4096) for p in ctx.made.rglob("*")) + 64  # tmpfs blocks
        size = {"synth": 200, "reconstruct": made_kib + 400, "correlate": made_kib + 40, "export": made_kib + 60,
                "acquire": 1500}[command]
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}k", "tmpfs", str(mnt)], capture_output=True)
        if r.returncode != 0:
            return Outcome("accepted", None, 0.0, "left out: cannot mount a tmpfs")
        try:
            run_ = mnt / "run.zarr"
            if command == "synth":
                args = ["synth", "--rig", TINY, "--out", run_, "--pairs", "40", "--ppm", "0.2", "--rays", "300",
                        "--quiet"]
            elif command == "acquire":
                args = ["acquire", "--rig", ctx.fast_rig, "--pairs", "3000", "--out", run_, "--quiet", "--sim-rays",
                        "300", "--sim-ppm", "0.2", "--sim-pool", "2"]
            else:
                shutil.copytree(ctx.made, run_, ignore=shutil.ignore_patterns("volumes", "vectors")
                                if command == "reconstruct" else None)
                args = {"reconstruct": ["reconstruct", run_, "--iterations", "2", "--quiet"],
                        "correlate": ["correlate", run_, "--windows", "8x8x4", "--overlap", "0.75", "--quiet"],
                        "export": ["export", run_, "--format", "vtk", "--out", mnt / "x"]}[command]
                # fill the rest of the disk but a little
                free = os.statvfs(mnt).f_bavail * os.statvfs(mnt).f_frsize
                (mnt / "filler").write_bytes(b"\0" * max(0, free - {"reconstruct": 150_000, "correlate": 8_000,
                                                                     "export": 4_000}[command]))
            before = snapshot(run_)
            rc, out, err, secs = lfpiv(args, d, ctx.timeout_s)
            o = classify(rc, out, err, secs, "error")
            if o.cls in ("hang", "traceback"):
                return o
            gone = lost(before, run_)
            if gone:
                return Outcome("data lost", rc, secs, f"{len(gone)} chunk(s) changed or gone, e.g. {gone[0]}")
            if o.cls == "clean error" and "No space left" in err and str(mnt) not in err:
                return Outcome("messy error", rc, secs, "the message does not name the path: " + o.detail)
            if command == "acquire" and run_.exists():
                s = RunStore.open(run_)
                if s.committed_pairs and RunStore.check(run_):
                    return Outcome("data lost", rc, secs, "committed pairs damaged: " + RunStore.check(run_)[0])
            return o
        finally:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
    return run


# --- the cases ---------------------------------------------------------------------------------

def cases(ctx: Ctx) -> list[Case]:
    out: list[Case] = []

    def add(name: str, group: str, fn: Callable[[Ctx, Path], Outcome], command: str = "") -> None:
        out.append(Case(name, group, fn, command))

    for name, text, expect in rig_variants(ctx.tiny_text):
        add(f"rig-{name}-synth", "rig", rig_case(text, expect, "synth"), "synth")
    for name, text, expect in rig_variants(ctx.tiny_text)[::6]:
        add(f"rig-{name}-devices", "rig", rig_case(text, expect, "devices"), "devices")
        add(f"rig-{name}-acquire", "rig", rig_case(text, expect, "acquire"), "acquire")

    # paths
    def mkfile(rel: str, text: str = "x") -> Callable[[Ctx, Path], None]:
        return lambda ctx, d: (d / rel).write_text(text)

    def mkdir(rel: str, inside: str | None = None) -> Callable[[Ctx, Path], None]:
        def f(ctx: Ctx, d: Path) -> None:
            (d / rel).mkdir()
            if inside:
                (d / rel / inside).write_text("keep me")
        return f

    def kept(rel: str) -> Callable[[Ctx, Path, Outcome], Outcome]:
        def f(ctx: Ctx, d: Path, o: Outcome) -> Outcome:
            if not (d / rel).is_file():
                return Outcome("data lost", o.rc, o.seconds, f"{rel} was deleted: {o.detail}")
            return o
        return f

    synth = ["synth", "--rig", "TINY", "--pairs", "1", "--ppm", "0.2", "--rays", "100", "--quiet", "--out"]
    paths = [
        ("reconstruct-missing", ["reconstruct", "D/none.zarr"], None, None),
        ("reconstruct-a-file", ["reconstruct", "D/f.zarr"], mkfile("f.zarr"), None),
        ("reconstruct-empty-dir", ["reconstruct", "D/e.zarr"], mkdir("e.zarr"), None),
        ("reconstruct-junk-zarr-json", ["reconstruct", "D/j.zarr"],
         lambda ctx, d: (mkdir("j.zarr")(ctx, d), (d / "j.zarr" / "zarr.json").write_text("{nope")), None),
        ("info-missing", ["info", "D/none.zarr"], None, None),
        ("check-a-file", ["check", "D/f.zarr"], mkfile("f.zarr"), None),
        ("correlate-missing", ["correlate", "D/none.zarr"], None, None),
        ("evaluate-a-dir", ["evaluate", "D/e"], mkdir("e"), None),
        ("export-missing", ["export", "D/none.zarr", "--format", "vtk", "--out", "D/x"], None, None),
        ("synth-out-missing-parent", [*synth, "D/no/such/dir/r.zarr"], None, None),
        ("synth-out-is-file", [*synth, "D/f.zarr"], mkfile("f.zarr"), kept("f.zarr")),
        ("synth-out-is-file-overwrite", [*synth, "D/f.zarr", "--overwrite"], mkfile("f.zarr"), kept("f.zarr")),
        ("synth-out-foreign-dir-overwrite", [*synth, "D/mine", "--overwrite"], mkdir("mine", "thesis.tex"),
         kept("mine/thesis.tex")),
        ("synth-out-foreign-dir", [*synth, "D/mine"], mkdir("mine", "thesis.tex"), kept("mine/thesis.tex")),
        ("synth-out-home", [*synth, "/"], None, None),
        ("acquire-out-foreign-dir-overwrite", ["acquire", "--rig", "FAST", "--pairs", "2", "--out", "D/mine",
                                               "--overwrite", "--quiet", "--sim-pool", "1", "--sim-rays", "100"],
         mkdir("mine", "thesis.tex"), kept("mine/thesis.tex")),
        ("evaluate-plot-missing-dir", ["evaluate", "RUN", "--plot", "/nonexistent/dir/q.png"], None, None),
        ("log-file-missing-dir", ["info", "TINY", "--log-file", "/nonexistent/dir/x.log"], None, None),
        ("log-file-a-dir", ["devices", "--rig", "TINY", "--log-file", "D/"], None, None),
        ("calibration-missing", ["reconstruct", "RUN", "--calibration", "/nonexistent/c.zarr"], None, None),
        ("calibration-is-run", ["reconstruct", "RUN", "--calibration", "RUN"], None, None),
        ("report-missing", ["calibrate", "report", "D/none.zarr"], None, None),
        ("report-of-a-run", ["calibrate", "report", "RUN"], None, None),
        ("import-no-match", ["import", "--rig", "TINY", "--out", "D/i.zarr", "--frames", "D/none/*.tif"], None, None),
        ("import-not-images", ["import", "--rig", "TINY", "--out", "D/i.zarr", "--frames", "D/*.tif"],
         lambda ctx, d: [(d / f"{k}.tif").write_text("not a tiff") for k in range(4)], None),
        ("import-wrong-size", ["import", "--rig", "TINY", "--out", "D/i.zarr", "--frames", "D/*.tif"],
         lambda ctx, d: _tiffs(d, (10, 10)), None),
        ("particles-missing", ["synth", "--rig", "TINY", "--out", "D/p.zarr", "--particles", "D/none.csv"], None,
         None),
        ("particles-bad-csv", ["synth", "--rig", "TINY", "--out", "D/p.zarr", "--particles", "D/p.csv"],
         mkfile("p.csv", "a,b\n1,2\n"), None),
        ("particles-nan-csv", ["synth", "--rig", "TINY", "--out", "D/p.zarr", "--particles", "D/p.csv"],
         mkfile("p.csv", "x_mm,y_mm,z_mm\nnan,0,0\n"), None),
        ("study-out-a-file", ["study", "iterations", "--out", "D/f", "--scale", "tiny"], mkfile("f"), kept("f")),
        ("demo-out-a-file", ["demo", "--out", "D/f", "--monitor", "no"], mkfile("f"), kept("f")),
        ("export-out-a-file", ["export", "RUN", "--format", "vtk", "--out", "D/f"], mkfile("f"), kept("f")),
    ]
    for name, args, prep, after in paths:
        if "RUN" in args and after is None:
            add(f"path-{name}", "path", simple(args, "error"), args[0])
        else:
            add(f"path-{name}", "path", simple(args, "error", prepare=prep, after=after), args[0])

    # options
    opts: list[tuple[list[object], str]] = []
    syn = ["synth", "--rig", "TINY", "--out", "D/s.zarr", "--quiet"]
    for o in (["--pairs", "0"], ["--pairs", "-1"], ["--pairs", "abc"], ["--pairs", "1000000000"], ["--ppm", "0"],
              ["--ppm", "-1"], ["--ppm", "nan"], ["--ppm", "1e9"], ["--ppp", "0.05"], ["--dt-ms", "0"],
              ["--dt-ms", "-1"], ["--dt-ms", "nan"], ["--seed", "abc"], ["--displacement-px", "1e7"],
              ["--displacement-px", "-5"], ["--displacement-px", "nan"], ["--displacement-px", "inf"],
              ["--flow", "nope"], ["--omega", "0"], ["--omega", "nan"], ["--rays", "0"], ["--rays", "1e12"],
              ["--device", "tpu"], ["--device", "cuda:9"], ["--flow", "A1", "--displacement-px", "1e7"],
              ["--flow", "jet", "--displacement-px", "1e7"]):
        opts.append((syn + o, "error"))
    rec = ["reconstruct", "RUN", "--quiet"]
    for o in (["--iterations", "0"], ["--iterations", "-1"], ["--iterations", "1000000000"], ["--relaxation", "0"],
              ["--relaxation", "-1"], ["--relaxation", "nan"], ["--relaxation", "inf"], ["--pvr", "a,b,c"],
              ["--pvr", "nan,nan,nan"], ["--pvr", "inf,2,2"], ["--margin-mm", "1e6,1e6,1e6"],
              ["--margin-mm", "-5,-5,-5"], ["--margin-mm", "nan,0,0"], ["--threshold-sigma", "nan"],
              ["--smooth", "-1"], ["--smooth", "nan"], ["--smooth", "1e9"], ["--sub-apertures", "0"],
              ["--sub-apertures", "-1"], ["--sub-apertures", "100000"], ["--background", "nan"],
              ["--background", "-1e30"], ["--cameras", ""], ["--pair-range", "abc"], ["--workers", "0"],
              ["--workers", "-1"], ["--scheduler", "tcp://127.0.0.1:1"], ["--device", "tpu"], ["--method", "foo"],
              ["--form", "foo"], ["--iterations", "1.5"]):
        opts.append((rec + o, "error"))
    cor = ["correlate", "RUN", "--quiet"]
    for o in (["--windows", "0x0x0"], ["--windows", "1x1x1"], ["--windows", "1000x1000x1000"],
              ["--windows", "abc"], ["--windows", "32x32"], ["--windows", "-8x8x8"], ["--overlap", "1"],
              ["--overlap", "-0.5"], ["--overlap", "nan"], ["--overlap", "2"], ["--deform-passes", "-1"],
              ["--deform-passes", "1000000"], ["--epsilon", "nan"], ["--threshold", "-1"], ["--threshold", "nan"],
              ["--search-radius", "-1"], ["--search-radius", "1e9"], ["--first-overlap", "1.5"],
              ["--interpolation", "quintic"], ["--pair-range", "9:"], ["--workers", "0"]):
        opts.append((cor + o, "error"))
    for o in (["--threshold", "-1"], ["--threshold", "nan"], ["--match-voxels", "0"], ["--match-voxels", "-1"],
              ["--pair-range", "5"]):
        opts.append((["evaluate", "RUN", *o], "error"))
    opts.append((["export", "RUN", "--format", "foo", "--out", "D/x"], "error"))
    mon = ["monitor", "--rig", "TINY", "--screenshot", "D/m.png", "--quiet"]
    for o in (["--iterations", "0"], ["--pairs", "0"], ["--after", "-1"], ["--slice", "w"], ["--passes", "3"],
              ["--ring", "0"], ["--sim-pool", "0"], ["--relaxation", "nan"], ["--pvr", "0,0,0"],
              ["--after", "1000000", "--pairs", "3"]):
        opts.append((mon + o, "error"))
    acq = ["acquire", "--rig", "FAST", "--out", "D/a.zarr", "--quiet"]
    for o in (["--pairs", "0"], ["--pairs", "-3"], ["--pairs", "3", "--ring", "0"],
              ["--pairs", "3", "--ring", "1000000000"], ["--pairs", "3", "--sim-pool", "0"],
              ["--pairs", "3", "--sim-pool", "100000"], ["--pairs", "3", "--sim-rays", "0"],
              ["--pairs", "3", "--sim-ppm", "-1"], ["--pairs", "3", "--sim-flow", "nope"],
              ["--pairs", "3", "--pairing", "timestamps"], ["--pairs", "1000000000000"]):
        opts.append((acq + o, "error"))
    for o in (["nope", "--out", "D/st"], ["iterations", "--out", "D/st", "--scale", "huge"],
              ["iterations", "--out", "D/st", "--workers", "0"]):
        opts.append((["study", *o], "error"))
    opts += [(["calibrate", "fit", "D/none.zarr"], "error"), (["calibrate", "mla"], "error"),
             (["calibrate", "volume", "--rig", "TINY"], "error"), (["nosuchcommand"], "error"), ([], "error"),
             (["demo", "--pairs", "0", "--out", "D/dm"], "error"), (["demo", "--rays", "-1", "--out", "D/dm"], "error")]
    # valid edge inputs, which must work
    opts += [(["reconstruct", "RUN", "--iterations", "1", "--pair-range", "1", "--quiet"], "accept"),
             (["reconstruct", "RUN", "--iterations", "1", "--relaxation", "2", "--smooth", "0", "--quiet"], "accept"),
             (["correlate", "RUN", "--windows", "16x16x8", "--overlap", "0", "--quiet"], "accept"),
             (["evaluate", "RUN"], "accept"), (["info", "RUN"], "accept"), (["check", "RUN"], "accept"),
             (["info", "RUN", "--check"], "accept"), (["export", "RUN", "--format", "mat", "--out", "D/x"], "accept"),
             (["synth", "--rig", "TINY", "--out", "D/s.zarr", "--pairs", "1", "--rays", "50", "--seed", "0",
               "--quiet"], "accept"), (["devices", "--rig", "TINY"], "accept")]
    for k, (args, expect) in enumerate(opts):
        tag = "-".join(str(a).strip("-") for a in args[args.index("--quiet") + 1:] if "--quiet" in args) \
            if "--quiet" in args else "-".join(str(a).strip("-").replace("/", "") for a in args[1:4])
        add(f"option-{k:03d}-{args[0] if args else 'none'}-{tag}"[:80], "option", simple(args, expect),
            args[0] if args else "")

    # damaged stores
    for array in ("cam0/frames",):
        for how in ("deleted", "random", "truncated", "empty"):
            dmg = chunk_damage(array, how)
            add(f"store-frame-{how}-reconstruct", "store", damaged_case(dmg, ["reconstruct", "RUN", "--iterations",
                                                                               "1", "--quiet"], "error"),
                "reconstruct")
            add(f"store-frame-{how}-check", "store", damaged_case(dmg, ["check", "RUN"], "report"), "check")
            add(f"store-frame-{how}-info-check", "store", damaged_case(dmg, ["info", "RUN", "--check"], "report"),
                "info")
    for how in ("deleted", "random", "truncated", "empty"):
        dmg = chunk_damage("volumes/data", how)
        for args in (["correlate", "RUN", "--windows", "16x16x8", "--quiet"], ["evaluate", "RUN"],
                     ["check", "RUN"]):
            add(f"store-volume-{how}-{args[0]}", "store", damaged_case(dmg, args, "report" if args[0] == "check"
                                                                        else "error"), args[0])
    for how in ("deleted", "random", "truncated"):
        dmg = chunk_damage("vectors/u", how)
        for args in (["export", "RUN", "--format", "vtk", "--out", "x"], ["evaluate", "RUN"], ["check", "RUN"]):
            add(f"store-vectors-{how}-{args[0]}", "store", damaged_case(dmg, args, "report" if args[0] == "check"
                                                                         else "error"), args[0])
    E, R, X, A = "error", "report", "either", "accept"
    metas = [  # name, damage, what info, check, reconstruct and evaluate must do
        ("root-json-truncated", file_damage("zarr.json", "truncated"), (E, R, E, E)),
        ("root-json-deleted", file_damage("zarr.json", "deleted"), (E, R, E, E)),
        ("root-json-garbage", file_damage("zarr.json", "garbage"), (E, R, E, E)),
        ("frames-json-deleted", file_damage("cam0/frames/zarr.json", "deleted"), (X, R, E, X)),
        ("frames-data-type", meta_damage("data_type", "float64", "cam0/frames!"), (X, R, E, X)),
        ("frames-shape", meta_damage("shape", [1, 2, 160, 192], "cam0/frames!"), (X, R, E, X)),
        ("committed-too-many", meta_damage("committed_pairs", 99), (X, R, E, X)),
        # evaluate reads derived data and the truth, not the commit record: either is right
        ("committed-negative", meta_damage("committed_pairs", -1), (E, R, E, X)),
        ("committed-string", meta_damage("committed_pairs", "two"), (E, R, E, X)),
        ("format-version-string", meta_damage("format_version", "1"), (E, R, E, E)),
        ("format-version-zero", meta_damage("format_version", 0), (E, R, E, E)),
        ("format-version-future", meta_damage("format_version", 999), (X, X, E, X)),
        ("state-unknown", meta_damage("state", "weird"), (X, R, X, X)),
        ("rig-deleted", meta_damage("rig", _DELETE), (E, R, E, E)),
        ("rig-garbage", meta_damage("rig", {"volume": 5}), (E, R, E, E)),
        ("timing-deleted", meta_damage("timing", _DELETE), (X, R, E, X)),
        ("volumes-pairs-garbage", meta_damage("reconstructed_pairs", "x", "volumes"), (X, R, X, E)),
        ("volumes-pairs-out-of-range", meta_damage("reconstructed_pairs", [0, 1, 50], "volumes"), (X, R, X, X)),
        ("volumes-json-deleted", file_damage("volumes/zarr.json", "deleted"), (X, R, X, E)),
        ("volumes-data-deleted", file_damage("volumes/data", "rmtree"), (X, R, X, E)),
        ("vectors-group-deleted", file_damage("vectors", "rmtree"), (X, X, X, X)),
        ("drops-deleted", file_damage("drops", "rmtree"), (X, X, X, X)),
        ("truth-deleted", file_damage("truth", "rmtree"), (X, X, X, X)),
        ("lock-garbage", lambda run: (run / ".lfpiv-writer.lock").write_bytes(os.urandom(100)), (A, A, A, A)),
    ]
    for name, dmg, expects in metas:
        commands = (["info", "RUN"], ["check", "RUN"], ["reconstruct", "RUN", "--iterations", "1", "--quiet"],
                    ["evaluate", "RUN"])
        for args, exp in zip(commands, expects, strict=True):
            add(f"store-{name}-{args[0]}", "store", damaged_case(dmg, args, exp), args[0])

    # signals
    for command in ("acquire", "synth", "reconstruct", "correlate"):
        for sig in (signal.SIGKILL, signal.SIGINT, signal.SIGTERM):
            grp = "kill" if sig == signal.SIGKILL else "interrupt"
            add(f"{grp}-{signal.Signals(sig).name}-{command}", grp, signal_case(command, sig), command)
    add("interrupt-ctrl-c-x3-acquire", "interrupt", signal_case("acquire", signal.SIGINT, times=3), "acquire")
    add("interrupt-ctrl-c-x3-reconstruct", "interrupt", signal_case("reconstruct", signal.SIGINT, times=3),
        "reconstruct")
    add("interrupt-SIGINT-reconstruct-replacement", "interrupt", signal_case("reconstruct-replacement",
                                                                             signal.SIGINT), "reconstruct")
    add("kill-SIGKILL-reconstruct-replacement", "kill", signal_case("reconstruct-replacement", signal.SIGKILL),
        "reconstruct")

    # second writers
    add("writer-acquire-acquire", "writer", writer_case("acquire", [
        "acquire", "--rig", "FAST", "--pairs", "3", "--out", "RUN", "--overwrite", "--quiet", "--sim-pool", "1",
        "--sim-rays", "100"]), "acquire")
    add("writer-acquire-synth", "writer", writer_case("acquire", [
        "synth", "--rig", "FAST", "--out", "RUN", "--overwrite", "--pairs", "1", "--rays", "50", "--quiet"]), "synth")
    add("writer-acquire-reconstruct", "writer", writer_case("acquire", [
        "reconstruct", "RUN", "--iterations", "1", "--pair-range", "0", "--quiet"]), "reconstruct")
    add("writer-reconstruct-reconstruct", "writer", writer_case("reconstruct", [
        "reconstruct", "RUN", "--iterations", "5", "--quiet"]), "reconstruct")
    add("writer-reconstruct-correlate", "writer", writer_case("reconstruct", [
        "correlate", "RUN", "--windows", "32x32x16", "--quiet"]), "correlate")
    add("writer-reconstruct-synth", "writer", writer_case("reconstruct", [
        "synth", "--rig", "TINY", "--out", "RUN", "--overwrite", "--pairs", "1", "--rays", "50", "--quiet"]), "synth")
    add("writer-reconstruct-import", "writer", writer_case("reconstruct", [
        "import", "--rig", "TINY", "--out", "RUN", "--overwrite", "--frames", "D/*.tif", "--dt-us", "1000"]), "import")
    add("writer-reconstruct-monitor", "writer", writer_case("reconstruct", [
        "monitor", "--rig", "TINY", "--pairs", "3", "--out", "RUN", "--overwrite", "--screenshot", "D/m.png",
        "--quiet"]), "monitor")
    add("writer-correlate-correlate", "writer", writer_case("correlate", [
        "correlate", "RUN", "--windows", "16x16x8", "--quiet"]), "correlate")
    add("writer-correlate-reconstruct", "writer", writer_case("correlate", [
        "reconstruct", "RUN", "--iterations", "2", "--quiet"]), "reconstruct")
    add("writer-reconstruct-info-reader", "writer", writer_case("reconstruct", ["info", "RUN"], reader=True), "info")
    add("writer-reconstruct-check-reader", "writer", writer_case("reconstruct", ["check", "RUN"], reader=True),
        "check")

    # a full disk
    for command in ("synth", "reconstruct", "correlate", "export", "acquire"):
        add(f"disk-full-{command}", "disk", disk_case(command), command)
    out += cases_writes_streams(ctx)
    out += cases_store_import(ctx)
    return out


# --- issue 50: writes, logs, streams, rig ranges and defaults -----------------------------------

def _tmpfs(mnt: Path, kib: int) -> bool:
    mnt.mkdir(exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(mnt)],
                          capture_output=True).returncode == 0


def _fill(mnt: Path, keep: int) -> None:
    st = os.statvfs(mnt)
    (mnt / "filler").write_bytes(b"\0" * max(0, st.f_bavail * st.f_frsize - keep))


def full_disk_file_case(command: str) -> Callable[[Ctx, Path], Outcome]:
    """A plot, a screenshot, a study's outputs or an import on a full disk (a tmpfs): one line
    naming the path, and an earlier file under the final name whole (never a stub or 0 bytes)."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        mnt = d / "disk"
        if not _tmpfs(mnt, 600):
            return Outcome("accepted", None, 0.0, "left out: cannot mount a tmpfs")
        try:
            old = b"\x89PNG earlier good picture" * 40
            target = mnt / "q.png"
            target.write_bytes(old)
            args = {"plot": ["evaluate", ctx.made, "--plot", target],
                    "screenshot": ["monitor", "--rig", TINY, "--pairs", "2", "--screenshot", target, "--device", "cpu",
                                   "--iterations", "1", "--sim-rays", "200", "--quiet"],
                    "study": ["study", "iterations", "--scale", "tiny", "--out", mnt / "st"],
                    "import": ["import", "--rig", TINY, "--out", mnt / "i.zarr", "--frames", d / "t" / "*.tif",
                               "--dt-us", "2000", "--quiet"]}[command]
            if command == "import":
                _frames_as_tiffs(ctx.made, d / "t")
            _fill(mnt, 2000)
            rc, out, err, secs = lfpiv(args, d, ctx.timeout_s)
            o = classify(rc, out, err, secs, "error")
            if o.cls in ("hang", "traceback"):
                return o
            if target.read_bytes() != old:
                size = target.stat().st_size
                return Outcome("data lost", rc, secs, f"the earlier {target.name} became {size} bytes: {o.detail}")
            if o.cls == "clean error" and str(mnt) not in err:
                return Outcome("messy error", rc, secs, "the message does not name the path: " + o.detail)
            return o
        finally:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
    return run


def _frames_as_tiffs(run: Path, folder: Path) -> None:
    import tifffile

    folder.mkdir(exist_ok=True)
    s = RunStore.open(run)
    for p in range(s.committed_pairs):
        for f in range(2):
            tifffile.imwrite(folder / f"{p:03d}{f}.tif", s.read_frame(s.cameras[0], p, f))


def log_into_store_case(rel: str) -> Callable[[Ctx, Path], Outcome]:
    """--log-file at a store's own file or inside it: refused, and the store byte for byte as it was."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        shutil.copytree(ctx.made, run_)
        before = {p: p.read_bytes() for p in run_.rglob("*") if p.is_file()}
        rc, out, err, secs = lfpiv(["--log-file", run_ / rel, "info", run_], d, ctx.timeout_s)
        o = classify(rc, out, err, secs, "error")
        if o.cls in ("hang", "traceback"):
            return o
        after = {p: p.read_bytes() for p in run_.rglob("*") if p.is_file()}
        if after != before:
            return Outcome("data lost", rc, secs, f"the store's files changed: {o.detail}")
        return o
    return run


def stream_case(how: str) -> Callable[[Ctx, Path], Outcome]:
    """A broken pipe on stdout (``check DAMAGED | head -c 1``: exit 1, as without the pipe), or
    stdout / stderr / all three closed (``reconstruct`` does its work and exits 0)."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        t = time.monotonic()
        if how == "broken-pipe":
            shutil.copytree(ctx.made, run_)
            chunk_damage("cam0/frames", "random")(run_)
            proc = subprocess.Popen([sys.executable, "-m", "lfpiv", "check", run_], cwd=d, env=ENV,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
            proc.stdout.read(1)
            proc.stdout.close()
            try:
                err = proc.stderr.read().decode(errors="replace")
                rc = proc.wait(timeout=ctx.timeout_s)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                return Outcome("hang", None, time.monotonic() - t, "")
            secs = time.monotonic() - t
            if crashed(rc, err) or "Exception ignored" in err:
                return Outcome("traceback", rc, secs, (err.strip().splitlines() or [""])[-1][:300])
            if rc != 1:
                return Outcome("wrong result", rc, secs, f"exit {rc} for a damaged run (1 without the pipe)")
            return Outcome("clean error", rc, secs, "exit 1 kept")
        shutil.copytree(ctx.made, run_, ignore=shutil.ignore_patterns("volumes", "vectors"))
        fds = {"closed-stdout": (1,), "closed-stderr": (2,), "closed-all": (0, 1, 2)}[how]

        def close() -> None:
            os.setsid()
            for fd in fds:
                os.close(fd)

        try:
            r = subprocess.run([sys.executable, "-m", "lfpiv", "reconstruct", run_, "--iterations", "1",
                                "--pair-range", "0"], cwd=d, env=ENV, stdin=subprocess.DEVNULL,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=close,
                               timeout=ctx.timeout_s)
        except subprocess.TimeoutExpired:
            return Outcome("hang", None, time.monotonic() - t, "")
        secs = time.monotonic() - t
        if r.returncode != 0:
            return Outcome("wrong result", r.returncode, secs, f"exit {r.returncode} with {how}")
        if RunStore.open(run_).reconstructed_pairs() != [0] or RunStore.check(run_):
            return Outcome("wrong result", r.returncode, secs, "the volume of pair 0 is not whole")
        return Outcome("accepted", 0, secs, f"reconstructed with {how}")
    return run


def stale_replaced_case() -> Callable[[Ctx, Path], Outcome]:
    """A ``vectors.replaced/`` an earlier replacement left: the next correlate with other settings
    settles it and puts its vectors in place."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        shutil.copytree(ctx.made, run_)
        shutil.copytree(run_ / "vectors", run_ / "vectors.replaced")
        rc, out, err, secs = lfpiv(["correlate", run_, "--windows", "16x16x8", "--quiet"], d, ctx.timeout_s)
        o = classify(rc, out, err, secs, "accept")
        if o.cls == "accepted" and (run_ / "vectors.replaced").exists():
            return Outcome("wrong result", rc, secs, "vectors.replaced/ is still there")
        return o
    return run


def drop_case() -> Callable[[Ctx, Path], Outcome]:
    """A run with a recorded drop: a plain reconstruct refused, naming --pair-range as the way on."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        run_ = d / "run.zarr"
        shutil.copytree(ctx.made, run_, ignore=shutil.ignore_patterns("volumes", "vectors"))
        s = RunStore.open(run_, mode="r+")
        s.add_drops([dict(camera="cam0", pair=1, frame=0, frame_id=-1, timestamp_ns=-1, reason="frame timeout")])
        del s
        _chunk(run_, "cam0/frames", 1).unlink()
        rc, out, err, secs = lfpiv(["reconstruct", run_, "--iterations", "1", "--quiet"], d, ctx.timeout_s)
        o = classify(rc, out, err, secs, "error")
        if o.cls == "clean error" and "--pair-range" not in err:
            return Outcome("messy error", rc, secs, "the way on (--pair-range) is not named: " + o.detail)
        return o
    return run


def rig_key_case(old: str, new: str, key: str) -> Callable[[Ctx, Path], Outcome]:
    """A rig value finite but meaningless: refused in one line naming its key."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        assert old in ctx.tiny_text, old
        rig = d / "rig.toml"
        rig.write_text(ctx.tiny_text.replace(old, new, 1))
        rc, out, err, secs = lfpiv(["synth", "--rig", rig, "--out", d / "r.zarr", "--pairs", "1", "--ppm", "0.2",
                                    "--rays", "100", "--quiet"], d, ctx.timeout_s)
        o = classify(rc, out, err, secs, "error")
        if o.cls == "clean error" and key not in err:
            return Outcome("messy error", rc, secs, f"the message does not name {key}: " + o.detail)
        return o
    return run


def cases_writes_streams(ctx: Ctx) -> list[Case]:
    """Issue 50's families: atomic writes of plots, screenshots, study outputs and imports on a
    full disk; --log-file into a store or on a full disk; broken pipes and closed streams; stale
    replacements; drops; rig values finite but meaningless; defaults that must not refuse."""
    out: list[Case] = []

    def add(name: str, group: str, fn: Callable[[Ctx, Path], Outcome], command: str = "") -> None:
        out.append(Case(name, group, fn, command))

    for command in ("plot", "screenshot", "study", "import"):
        add(f"writes-full-disk-{command}", "writes", full_disk_file_case(command),
            {"plot": "evaluate", "screenshot": "monitor"}.get(command, command))
    for rel in ("zarr.json", "cam0/frames/zarr.json", "run.log", "vectors/u/x.log"):
        add(f"writes-log-into-store-{rel.replace('/', '-')}", "writes", log_into_store_case(rel), "info")
    if Path("/dev/full").exists():
        add("writes-log-file-full-disk", "writes", simple(["--log-file", "/dev/full", "reconstruct", "RUN",
                                                            "--iterations", "1", "--quiet"], "error"), "reconstruct")
    for how in ("broken-pipe", "closed-stdout", "closed-stderr", "closed-all"):
        add(f"streams-{how}", "streams", stream_case(how), "check" if how == "broken-pipe" else "reconstruct")
    add("writes-stale-vectors-replaced", "writes", stale_replaced_case(), "correlate")
    add("defaults-drop-names-pair-range", "defaults", drop_case(), "reconstruct")
    for name, old, new, key in (
            ("dt-1e-300", "dt_us = 2000.0", "dt_us = 1e-300", "timing.dt_us"),
            ("dt-denormal", "dt_us = 2000.0", "dt_us = 5e-324", "timing.dt_us"),
            ("pvr-1e308", "pvr = [2.0, 2.0, 10.0]", "pvr = [1e308, 2.0, 10.0]", "volume.pvr"),
            ("pvr-one-voxel", "pvr = [2.0, 2.0, 10.0]", "pvr = [500.0, 2.0, 10.0]", "volume.pvr"),
            ("rotation-1e300", "rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [1e300, 0.0, 0.0]",
             "camera[0].rotation_deg"),
            ("magnification-tiny", "magnification = -1.0", "magnification = -1e-300", "camera[0].magnification"),
            ("size-1e300", "size_mm = [0.9, 0.75, 1.6]", "size_mm = [1e300, 0.75, 1.6]", "volume.size_mm"),
            ("centre-1e300", "centre_mm = [0.0, 0.0, 0.0]", "centre_mm = [0.0, 1e300, 0.0]", "volume.centre_mm"),
            ("rate-1e300", "rate_hz = 10.0", "rate_hz = 1e300", "laser.rate_hz")):
        add(f"rig-range-{name}", "rig-range", rig_key_case(old, new, key), "synth")
    mon = ["monitor", "--rig", "TINY", "--pairs", "2", "--device", "cpu", "--iterations", "1", "--sim-rays", "200",
           "--quiet"]
    add("defaults-monitor-pairs-2-screenshot", "defaults", simple([*mon, "--screenshot", "D/m.png"], "accept"),
        "monitor")
    add("defaults-monitor-offscreen-ends", "defaults", simple(mon, "accept"), "monitor")
    add("defaults-synth-dt-ms-denormal", "defaults", simple(["synth", "--rig", "TINY", "--out", "D/s.zarr", "--pairs",
                                                             "1", "--rays", "50", "--dt-ms", "1e-320", "--quiet"],
                                                            "error"), "synth")
    add("defaults-import-dt-us-denormal", "defaults", simple(
        ["import", "--rig", "TINY", "--out", "D/i.zarr", "--frames", "D/t/*.tif", "--dt-us", "5e-324", "--quiet"],
        "error", prepare=lambda ctx, d: _frames_as_tiffs(ctx.made, d / "t")), "import")


# --- issue 50: store attributes trusted on read, files that are not what they seem -------------

def _import_frames(n: int, seed: int = 0):
    import numpy as np

    return np.random.default_rng(seed).integers(100, 4000, (n, 160, 192)).astype(np.uint16)


def import_case(make: Callable[[Path], tuple[str, object]], expect: str) -> Callable[[Ctx, Path], Outcome]:
    """``lfpiv import`` of the files ``make(d)`` writes (it returns the pattern, and the frames the
    run must hold for an accepted case): refused in one line with nothing written, or imported
    with every frame in place."""
    def run(ctx: Ctx, d: Path) -> Outcome:
        import numpy as np

        pattern, want = make(d)
        out = d / "i.zarr"
        rc, o, err, secs = lfpiv(["import", "--rig", TINY, "--out", out, "--frames", pattern, "--dt-us", "1000",
                                  "--quiet"], d, ctx.timeout_s)
        res = classify(rc, o, err, secs, expect)
        if res.cls == "clean error" and out.exists():
            return Outcome("wrong result", rc, secs, "refused, but a store was left: " + res.detail)
        if res.cls == "accepted" and want is not None:
            held = RunStore.open(out).frames("cam0")[...].reshape(-1, 160, 192)
            if not np.array_equal(held, want):
                return Outcome("wrong result", rc, secs, "imported frames differ from the files: " + res.detail)
        return res
    return run


def cases_store_import(ctx: Ctx) -> list[Case]:
    """Issue 50's families: edited or damaged store attributes fed to every reader (group
    ``schema``), and import sets with entries that are not what they seem (group ``import``)."""
    import numpy as np
    import tifffile

    out: list[Case] = []
    E, R, X = "error", "report", "either"
    timing = {"dt_s": 0.002, "rate_hz": 10.0}
    attrs = [  # name, damage, what info, check, correlate, evaluate and export must do
        ("timing-dt-text", meta_damage("timing", {**timing, "dt_s": "0.002"}), (E, R, E, X, E)),
        ("timing-dt-negative", meta_damage("timing", {**timing, "dt_s": -0.002}), (E, R, E, X, E)),
        ("timing-dt-zero", meta_damage("timing", {**timing, "dt_s": 0}), (E, R, E, X, E)),
        ("timing-rate-text", meta_damage("timing", {**timing, "rate_hz": "ten"}), (E, R, E, X, E)),
        ("timing-a-list", meta_damage("timing", [1, 2]), (E, R, E, X, E)),
        ("timing-text", meta_damage("timing", "fast"), (E, R, E, X, E)),
        ("origin-two-values", meta_damage("origin_mm", [0.0, 0.0], "volumes"), (E, R, E, E, X)),
        ("origin-text", meta_damage("origin_mm", "0,0,0", "volumes"), (E, R, E, E, X)),
        ("origin-moved", meta_damage("origin_mm", [1.0, 0.0, 0.0], "volumes"), (E, R, E, E, X)),
        ("voxel-text", meta_damage("voxel_mm", "0.011", "volumes"), (E, R, E, E, X)),
        ("voxel-sign-flip", meta_damage("voxel_mm", [-0.011, 0.011, 0.055], "volumes"), (E, R, E, E, X)),
        ("voxel-zero", meta_damage("voxel_mm", [0.0, 0.011, 0.055], "volumes"), (E, R, E, E, X)),
        ("voxel-doubled", meta_damage("voxel_mm", [0.022, 0.011, 0.055], "volumes"), (E, R, E, E, X)),
        ("reconstructed-text", meta_damage("reconstructed_pairs", "0,1", "volumes"), (E, R, E, E, X)),
        ("correlated-text", meta_damage("correlated_pairs", "0,1", "vectors"), (E, R, E, E, E)),
        ("vectors-dt-negative", meta_damage("dt_s", -0.002, "vectors"), (E, R, E, E, E)),
        ("vectors-windows-text", meta_damage("windows", "32x32x16", "vectors"), (E, R, E, E, E)),
        ("vectors-overlap-two", meta_damage("overlap", [2.0, 2.0, 2.0], "vectors"), (E, R, E, E, E)),
        ("truth-flow-text", meta_damage("flow", "vortex-ring", "truth"), (E, R, X, E, X)),
        ("committed-true", meta_damage("committed_pairs", True), (E, R, X, X, X)),  # correlate reads no commits
    ]
    commands = (["info", "RUN"], ["check", "RUN"], ["correlate", "RUN", "--windows", "16x16x8", "--quiet"],
                ["evaluate", "RUN"], ["export", "RUN", "--format", "vtk", "--out", "D/x"])
    for name, dmg, expects in attrs:
        for args, exp in zip(commands, expects, strict=True):
            out.append(Case(f"schema-{name}-{args[0]}", "schema", damaged_case(dmg, args, exp), args[0]))

    def tiffs(d: Path, frames, **kw: object) -> Path:
        (d / "rec").mkdir(exist_ok=True)
        for i, f in enumerate(frames):
            tifffile.imwrite(d / "rec" / f"img_{i:04d}.tif", f, **kw)
        return d / "rec"

    def replaced(how: str) -> Callable[[Path], tuple[str, object]]:
        def make(d: Path) -> tuple[str, object]:
            rec = tiffs(d, _import_frames(6))
            entry = rec / "img_0002.tif"
            entry.unlink()
            if how == "dangling":
                os.symlink(rec / "gone.tif", entry)
            elif how == "loop":
                os.symlink(entry, entry)
            elif how == "pipe":
                os.mkfifo(entry)
            else:
                entry.mkdir()
            return str(rec / "*.tif"), None
        return make

    def background(d: Path) -> tuple[str, object]:
        rec = tiffs(d, _import_frames(4))
        tifffile.imwrite(rec / "background.tif", _import_frames(1, 9)[0])
        return str(rec / "*.tif"), None

    def signed(compression: str | None, offset: int) -> Callable[[Path], tuple[str, object]]:
        def make(d: Path) -> tuple[str, object]:
            frames = _import_frames(4)
            return str(tiffs(d, frames.astype(np.int16) - offset, compression=compression) / "*.tif"), frames
        return make

    def lzw(d: Path) -> tuple[str, object]:
        from PIL import Image

        frames = _import_frames(4)
        (d / "rec").mkdir()
        for i, f in enumerate(frames):
            Image.fromarray(f).save(d / "rec" / f"img_{i:04d}.tif", compression="tiff_lzw")
        return str(d / "rec" / "*.tif"), frames

    def corrupt_last(d: Path) -> tuple[str, object]:
        rec = tiffs(d, _import_frames(6), compression="zlib")
        last = rec / "img_0005.tif"
        with tifffile.TiffFile(last) as tf:
            offset, count = tf.pages[0].dataoffsets[0], tf.pages[0].databytecounts[0]
        raw = bytearray(last.read_bytes())
        raw[offset + 2:offset + count] = os.urandom(count - 2)
        last.write_bytes(bytes(raw))
        return str(rec / "*.tif"), None

    def appended(sizes: bool) -> Callable[[Path], tuple[str, object]]:
        def make(d: Path) -> tuple[str, object]:
            frames = _import_frames(4)
            for f in frames:
                tifffile.imwrite(d / "stack.tif", f, append=True)
            if sizes:
                tifffile.imwrite(d / "stack.tif", frames[0, :80], append=True)
            return str(d / "stack.tif"), None if sizes else frames
        return make

    def bilevel(d: Path) -> tuple[str, object]:
        return str(tiffs(d, _import_frames(4) > 2000) / "*.tif"), None

    def a_and_b(d: Path) -> tuple[str, object]:
        frames = _import_frames(4)
        (d / "rec").mkdir()
        for i, f in enumerate(frames):
            tifffile.imwrite(d / "rec" / f"B{i // 2 + 1:05d}_{'AB'[i % 2]}.tif", f)
        return str(d / "rec" / "*.tif"), frames

    imports = [("dangling-link", replaced("dangling"), E), ("looping-link", replaced("loop"), E),
               ("named-pipe", replaced("pipe"), E), ("folder-named-tif", replaced("folder"), E),
               ("background-sorts-first", background, E), ("signed-negative", signed(None, 200), E),
               ("signed-negative-zlib", signed("zlib", 200), E), ("signed-counts", signed(None, 0), "accept"),
               ("lzw-pillow", lzw, "accept"), ("zlib-last-page-corrupt", corrupt_last, E),
               ("appended-pages", appended(False), "accept"), ("appended-pages-two-sizes", appended(True), E),
               ("bilevel", bilevel, E), ("names-a-and-b", a_and_b, "accept")]
    for name, make, exp in imports:
        out.append(Case(f"import-{name}", "import", import_case(make, exp), "import"))
    return out


def _tiffs(d: Path, shape: tuple[int, int]) -> None:
    import numpy as np
    import tifffile

    for k in range(4):
        tifffile.imwrite(d / f"{k}.tif", np.zeros(shape, np.uint16))


def prepare(ctx: Ctx) -> None:
    """The stores every case copies."""
    ctx.tiny_text = TINY.read_text()
    ctx.fast_rig = ctx.work / "fast.toml"
    ctx.fast_rig.write_text(fast_rig_text())
    ctx.made = ctx.work / "made.zarr"
    ctx.long = ctx.work / "long.zarr"
    for args in (["synth", "--rig", TINY, "--out", ctx.made, "--pairs", "2", "--ppm", "0.2", "--quiet"],
                 ["reconstruct", ctx.made, "--iterations", "2", "--quiet"],
                 ["correlate", ctx.made, "--windows", "32x32x16", "--quiet"],
                 ["synth", "--rig", TINY, "--out", ctx.long, "--pairs", "12", "--ppm", "0.2", "--rays", "500",
                  "--quiet"]):
        rc, out, err, _ = lfpiv(args, ctx.work, 600)
        if rc != 0:
            raise SystemExit(f"preparing failed: {args}: {err}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, help="work folder (default: a new temporary one, removed at the end)")
    p.add_argument("--csv", type=Path, help="CSV of every case (default: adversarial.csv in the work folder)")
    p.add_argument("--only", help="comma-separated groups: rig, path, option, store, kill, interrupt, writer, disk, "
                   "writes, streams, defaults, rig-range, schema, import")
    p.add_argument("--match", help="only the cases whose name contains this")
    p.add_argument("--jobs", type=int, default=2, help="cases at a time (default: 2)")
    p.add_argument("--timeout", type=float, default=90.0, help="seconds a case may take before it is a hang")
    args = p.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="lfpiv-adversarial-"))
    work.mkdir(parents=True, exist_ok=True)
    ctx = Ctx(work, args.timeout)
    t0 = time.monotonic()
    prepare(ctx)
    todo = cases(ctx)
    if args.only:
        groups = set(args.only.split(","))
        todo = [c for c in todo if c.group in groups]
    if args.match:
        todo = [c for c in todo if args.match in c.name]
    rows: list[dict] = []

    def one(c: Case) -> dict:
        d = ctx.case_dir(c.name)
        try:
            o = c.run(ctx, d)
        except Exception as exc:  # noqa: BLE001 - a fault of the sweep itself, reported as such
            o = Outcome("messy error", None, 0.0, f"the sweep failed: {type(exc).__name__}: {exc}")
        shutil.rmtree(d, ignore_errors=True)
        row = {"case": c.name, "group": c.group, "command": c.command, "class": o.cls, "rc": o.rc,
               "seconds": round(o.seconds, 2), "detail": o.detail}
        print(f"{o.cls:13s} {c.name:60s} {o.detail[:150]}", flush=True)
        return row

    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(one, todo))
    csv_path = args.csv or work / "adversarial.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    counts = Counter(r["class"] for r in rows)
    by_group: dict[str, Counter] = {}
    for r in rows:
        by_group.setdefault(r["group"], Counter())[r["class"]] += 1
    print()
    print("| group | cases | " + " | ".join(CLASSES) + " |")
    print("| --- " * (len(CLASSES) + 2) + "|")
    for g, c in by_group.items():
        print(f"| {g} | {sum(c.values())} | " + " | ".join(str(c[k]) for k in CLASSES) + " |")
    print(f"| all | {len(rows)} | " + " | ".join(str(counts[k]) for k in CLASSES) + " |")
    print(f"\n{len(rows)} cases in {time.monotonic() - t0:.0f} s; CSV: {csv_path}")
    if not args.work:
        shutil.rmtree(work / "cases", ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
