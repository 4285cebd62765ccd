"""What several test files share: the fast two-camera rig, the simulated lab of the recording
tests, running ``lfpiv`` in a child process and signalling it, the GenTL simulator, the hand
trigger of the simulated cameras and a hand-filled ring buffer."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from acquisition.ring import PairRing
from lfcore.runstore import RunStore
from sim.lab import SimLab
from sim.world import SimWorld

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: The ``lfpiv`` program in a child process.
LFPIV = [sys.executable, "-m", "lfpiv.cli"]


def fast_rig_text(rate_hz: float = 60.0, cameras: int = 2) -> str:
    """The tiny rig with a fast laser (pairs at ``rate_hz``) and a second camera at 90 degrees."""
    text = (EXAMPLES / "tiny.toml").read_text()
    text = text.replace("rate_hz = 10.0", f"rate_hz = {rate_hz}\nmax_rate_hz = {2 * rate_hz}")
    text = text.replace("dt_us = 2000.0", "dt_us = 1000.0\ncamera_max_fps = 500.0")
    if cameras == 2:
        cam = text[text.index("[[camera]]"):text.index("[laser]")]
        cam = cam.replace('"cam0"', '"cam1"').replace("[0.0, 0.0, 0.0]  # camera", "[0.0, 90.0, 0.0]  # camera")
        text += "\n" + cam
    return text


def sim_lab(rig, **faults) -> SimLab:
    """The simulated lab of the recording tests: sparse seeding, few rays, a quick emulator."""
    return SimLab(rig, world=SimWorld(rig, ppm=0.2), pool_pairs=3, rays_per_particle=300, reply_latency_s=0.0005,
                  camera_faults=faults)


def wait_store(path: Path, count: Callable[[RunStore], int], at_least: int, proc: subprocess.Popen,
               timeout_s: float = 60.0, what: str = "committed pairs") -> int:
    """Wait until ``count(store)`` of the run at ``path`` is ``at_least`` while ``proc`` runs."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        try:
            n = count(RunStore.open(path))
            if n >= at_least:
                return n
        except Exception:  # noqa: BLE001 - the store may not exist yet
            pass
        time.sleep(0.05)
    raise AssertionError(f"{path} did not reach {at_least} {what}")


def stop_when(proc: subprocess.Popen, path: Path, count: Callable[[RunStore], int], at_least: int, *,
              timeout_s: float = 120.0, what: str = "committed pairs") -> int:
    """Stop ``proc`` (SIGSTOP) once ``count(store)`` of the run at ``path`` is ``at_least``, and
    return the count. The store is read only while ``proc`` is stopped, which runs only during the
    waits between reads (SIGCONT): on a loaded machine, where opening a store is slow, ``proc``
    cannot go on far past the count, or finish and let go of the store, before it is stopped.
    ``proc`` is left stopped; SIGCONT or SIGKILL it."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        proc.send_signal(signal.SIGSTOP)
        try:
            n = count(RunStore.open(path))
        except Exception:  # noqa: BLE001 - the store may not exist yet, or be mid-write
            n = 0
        if n >= at_least:
            return n
        proc.send_signal(signal.SIGCONT)
        time.sleep(0.05)
    proc.send_signal(signal.SIGCONT)
    raise AssertionError(f"{path} did not reach {at_least} {what}")


def wait_committed(path: Path, at_least: int, proc: subprocess.Popen, timeout_s: float = 60.0) -> int:
    """Wait until the run at ``path`` has ``at_least`` committed pairs while ``proc`` runs."""
    return wait_store(path, lambda s: s.committed_pairs, at_least, proc, timeout_s)


def chunk_file(run: Path, array: str, first: int) -> Path:
    """The chunk file of ``array`` (e.g. "cam0/frames") whose first chunk index is ``first`` (pair)."""
    return next(p for p in sorted((run / array / "c").rglob("*")) if p.is_file()
                and p.relative_to(run / array / "c").parts[0] == str(first))


def damage_chunk(path: Path, how: str) -> None:
    """Damage a chunk file as disks and people do: "deleted", "random" bytes or "truncated" to half."""
    if how == "deleted":
        path.unlink()
    elif how == "random":
        path.write_bytes(os.urandom(path.stat().st_size))
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        raise ValueError(how)


def one_error(err: str) -> bool:
    """One line of error, last, no traceback (notes of what the command began may come before)."""
    lines = err.strip().splitlines()
    return bool(lines) and lines[-1].startswith("lfpiv: error: ") and sum("error" in x for x in lines) == 1 and \
        "Traceback" not in err


@contextmanager
def store_held(path: Path) -> Iterator[subprocess.Popen]:
    """A second process holding the run at ``path`` open for writing (the writer lock) until the
    block ends; it is killed then, which must leave nothing held."""
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from lfcore.runstore import RunStore; "
                               "s = RunStore.open(sys.argv[1], mode='r+'); print('held', flush=True); time.sleep(600)",
                               str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        holder.kill()
        holder.wait()


def no_space(real: Callable, after: int) -> Callable:
    """A store write that fills the disk: the first ``after`` calls are the ``real`` write, then
    every call raises ENOSPC as a full disk does (with no file name, as zarr's writes do)."""
    calls = [0]

    def write(*args, **kwargs):
        calls[0] += 1
        if calls[0] > after:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)
    return write


def signal_when_committed(proc: subprocess.Popen, path: Path, at_least: int, sig: int, *,
                          timeout_s: float = 60.0, exit_timeout_s: float = 60.0) -> tuple[str, str]:
    """Send ``sig`` to ``proc`` once the run at ``path`` has ``at_least`` committed pairs; its
    stdout and stderr when it has ended (it is killed if it has not)."""
    try:
        wait_committed(path, at_least, proc, timeout_s)
        proc.send_signal(sig)
        return proc.communicate(timeout=exit_timeout_s)
    finally:
        proc.kill()


def terminal_signals() -> None:
    """In a child before exec: SIGINT and SIGHUP as from a terminal. A test run started with
    ``nohup`` or as a background job ignores them, its children inherit that, and the program
    then keeps them ignored by design (``nohup`` means "keep recording")."""
    for sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def _viky() -> Path | None:
    try:
        import genicam
    except ImportError:
        return None
    path = Path(genicam.__file__).parent / "viky.cti"
    return path if path.is_file() else None


#: The GenTL simulator that ships with the genicam wheel, or None.
VIKY = _viky()

PERIOD_NS = 50_000_000  # 20 Hz T0
T0_NS = 7_000_000_000_000


class HandTrigger:
    """A trigger source fired by the test: ``fire(k)`` is T0 tick ``k`` with every output on."""

    def __init__(self, rig) -> None:
        self.listeners = []
        self.outputs = {ch: 0.0 for ch in rig.pulse_generator.channels.values()}
        self.outputs[rig.pulse_generator.channels["camera"]] = 100e-6

    def add_listener(self, callback) -> None:
        self.listeners.append(callback)

    def fire(self, tick: int) -> None:
        for cb in self.listeners:
            cb(tick, T0_NS + tick * PERIOD_NS, self.outputs)


#: The tiny rig's (rows, columns).
RING_SHAPE = (160, 192)


def ring_frames(seed: int) -> np.ndarray:
    """(2, rows, columns) uint16: noise and a few bright spots, shifted one pixel in frame B."""
    rng = np.random.default_rng(seed)
    img = rng.normal(100.0, 3.0, size=(2, *RING_SHAPE))
    for f in range(2):
        for r, c in rng.integers(20, 140, size=(30, 2)):
            img[f, r:r + 3, c + f:c + f + 3] += 400.0
    return np.clip(img, 0, 65535).astype(np.uint16)


def filled_ring(pairs: int, slots: int = 8) -> PairRing:
    """A ring of one camera ("cam0") with ``pairs`` pairs published."""
    ring = PairRing({"cam0": RING_SHAPE}, slots=slots)
    for p in range(pairs):
        fr = ring_frames(p)
        for f in range(2):
            assert ring.put("cam0", p, f, fr[f], 2 * p + f, time.time_ns())
        ring.publish(p)
    return ring


def smart_update(op, image, proj, e, relaxation: float, floor: float) -> None:
    """One SMART update of ``e`` through the operator ``op`` from the measured ``image`` and its
    projection ``proj`` ((n_pixels,) float32 each): the log ratios, then ``op.update``."""
    from lfcore.device import warp
    from lfcore.operator import log_ratio

    wp = warp()
    ratio = wp.empty(int(image.shape[0]), dtype=float, device=str(image.device))
    op.update(log_ratio(image, proj, floor, ratio), e, relaxation)


def tomo_arc_small():
    """The chapter's 4-camera arc of pinhole cameras on a 2 x 2 x 1.5 mm box (27 x 27 x 20 voxels at
    PVR 1), one camera with radial and tangential distortion and an off-centre principal point."""
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / "tomo_4_cameras.toml")
    cams = list(rig.camera)
    cams[2] = cams[2].model_copy(update={"k1": 0.8, "p1": 0.01, "principal_point_px": (3.0, -2.0)})
    return rig.model_copy(update={"camera": cams,
                                  "volume": rig.volume.model_copy(update={"size_mm": (2.0, 2.0, 1.5)})})


def lightfield_scene(rig, *, ppm: float = 0.3, rays_per_particle: int = 20_000):
    """``rig``'s box seeded at ``ppm`` and its first camera's image of it, rendered on the CPU with
    ``rays_per_particle``: (rig, grid, particles (n, 3) mm, image (rows, columns))."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer
    from lfcore.volume import VolumeGrid

    grid = VolumeGrid.from_rig(rig)
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(3))
    cfg = rig.render.model_copy(update={"rays_per_particle": rays_per_particle})
    img = LightFieldRenderer(rig.camera[0], cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu").frame(
        pts, 50_000.0, seed=1)
    return rig, grid, pts, img


def copy_run(run: Path, tmp_path: Path, name: str = "r.zarr") -> Path:
    """A copy of the run store ``run`` as ``tmp_path / name`` (a module fixture's run, changed by one test)."""
    import shutil

    shutil.copytree(run, tmp_path / name)
    return tmp_path / name


def velocity_rms(out: str) -> np.ndarray:
    """(3,) ``lfpiv evaluate``'s RMS velocity error u, v, w in voxels, read from its output ``out``."""
    import re

    m = re.search(r"velocity error: RMS u, v, w .* m/s \(([\d.]+), ([\d.]+), ([\d.]+) voxel\)", out)
    assert m, out
    return np.array([float(m.group(k)) for k in (1, 2, 3)])


def four_particles(grid) -> np.ndarray:
    """(4, 3) voxel index coordinates (z, y, x) of four particles of ``grid`` well apart, off the voxel
    centres (offsets 0.15 to 0.45 voxel), in the box's four quarters and at two depths away from a
    light-field camera focused on the box's middle plane."""
    shape = np.asarray(grid.shape, dtype=np.float64)
    frac = np.array([[0.15, 0.3, 0.28], [0.72, 0.7, 0.33], [0.77, 0.35, 0.71], [0.3, 0.72, 0.69]])
    return np.floor(frac * (shape - 1)) + np.array([[0.3, 0.25, 0.65], [0.6, 0.7, 0.2], [0.2, 0.4, 0.3],
                                                    [0.75, 0.15, 0.55]])


class Announced(Exception):
    """Raised by :func:`stop_at_announce`'s callback: the job said its line and stopped there."""


def stop_at_announce() -> tuple[list[str], Callable[[str], None]]:
    """A job's ``announce`` callback that records the line and stops the job (raises
    :class:`Announced`), so a test sees what was said before any long work began."""
    said: list[str] = []

    def announce(line: str) -> None:
        said.append(line)
        raise Announced

    return said, announce
