"""Simulated light-field cameras that satisfy :class:`acquisition.protocols.Camera`.

A :class:`SimCamera` is wired to the trigger output of the emulated pulse generator: each T0
tick in which the generator's camera output is enabled triggers one double-frame burst. Frame A
shows the particles of the world at the first laser pulse if both of cavity 1's outputs
(flashlamp and Q-switch) fired, frame B those at the second pulse if cavity 2 fired; an unlit
frame shows only background and noise. So the laser being armed or not is visible in the
images, exactly as in the lab. While the world shows a continuously lit scene
(:meth:`sim.world.SimWorld.show`: a white diffuser or the calibration target), every frame shows
that scene instead, rendered on the trigger's thread and cached while the scene is unchanged.

Rendering a light field takes longer than a trigger period on a CPU, so the camera renders a
pool of ``pool_pairs`` pairs of the world when it opens and serves trigger ``k`` from pool entry
``k % pool_pairs`` (:meth:`SimCamera.pool_index`); the truth of every recorded pair is therefore
known exactly. Frames wait in a bounded set of ``buffers`` like a real camera's buffer pool: a
frame produced while every buffer is full is lost, and the frame counter still advances, so
the loss shows up as a ``frame_id`` gap downstream.

Faults to inject (all by frame id, counted from the first frame after ``start``):
``lose_frames`` never delivers those frames (a gap), ``incomplete_frames`` delivers them marked
incomplete, ``lose_rate`` loses frames at random, and ``fail_after_frames`` makes ``fetch`` raise
:class:`~acquisition.protocols.DeviceError` once that many frames were produced (a pulled
cable). ``miss_triggers`` (by trigger, counted from 0 at the first trigger after ``start``)
ignores those triggers: no frames, and the frame counter does not advance, as when a real
camera misses a trigger pulse; only the time stamps show it.

Time stamps are the camera's clock (``Frame.device_clock``): the emulated generator's T0 edge
plus the camera output's delay for frame A, and frame B the exposure and interframe time later.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from acquisition.protocols import DeviceError, Frame
from lfcore.render import LightFieldRenderer, derive_seed
from lfcore.rig import Rig
from sim.world import SimWorld

__all__ = ["SimCamera", "TriggerSource"]

TriggerCallback = Callable[[int, int, dict[int, float]], None]


class TriggerSource:
    """What a simulated camera needs from the emulated pulse generator: tick listeners.

    The emulator calls each listener as ``callback(tick, t0_ns, outputs)`` where ``outputs``
    maps every enabled output channel to its delay in seconds.
    """

    def add_listener(self, callback: TriggerCallback) -> None:  # pragma: no cover - protocol
        raise NotImplementedError


class SimCamera:
    """A simulated light-field camera of ``rig``, triggered by an emulated pulse generator.

    Parameters
    ----------
    name
        The camera's name in the rig.
    rig
        The rig (camera optics, render settings, pulse-generator channel roles, timing).
    world
        What the camera looks at.
    trigger
        The emulated pulse generator (anything with ``add_listener``).
    pool_pairs
        Distinct pairs rendered at :meth:`open` and cycled through.
    buffers
        Frames the camera holds before it loses new ones.
    lose_frames, incomplete_frames, lose_rate, fail_after_frames, miss_triggers
        Faults to inject (see the module docstring).
    rays_per_particle
        Overrides the rig's ``render.rays_per_particle`` (fewer rays, faster start).
    device
        Warp device for rendering.
    """

    def __init__(self, name: str, rig: Rig, world: SimWorld, trigger: TriggerSource, *, pool_pairs: int = 4,
                 buffers: int = 16, rays_per_particle: int | None = None, device: str | None = None,
                 lose_frames: set[int] | None = None, incomplete_frames: set[int] | None = None,
                 lose_rate: float = 0.0, fail_after_frames: int | None = None,
                 miss_triggers: set[int] | None = None, seed: int = 0) -> None:
        self.name = name
        self.rig = rig
        self.camera = rig.camera_named(name)
        self.world = world
        self.pool_pairs = int(pool_pairs)
        self.buffers = int(buffers)
        self.rays_per_particle = rays_per_particle
        self.device = device
        self.lose_frames = set(lose_frames or ())
        # not named incomplete_frames: a session reads an int of that name as a driver's count
        # of discarded incomplete images
        self.incomplete_ids = set(incomplete_frames or ())
        self.miss_triggers = set(miss_triggers or ())
        self.lose_rate = float(lose_rate)
        self.fail_after_frames = fail_after_frames
        self._rng = np.random.default_rng(derive_seed(seed, 7919, rig.camera.index(self.camera)))
        self._trigger = trigger
        self._listening = False
        self._queue: deque[Frame] = deque()
        self._cond = threading.Condition()
        self._running = False
        self._open = False
        self._configured = False
        self._counter = 0
        self._triggers = 0
        self._failed = False
        self.frames_produced = 0
        self.frames_lost = 0
        self.triggers_missed = 0
        self._lit: list[np.ndarray] = []  # per pool pair: (2, rows, cols) lit frames
        self._dark: np.ndarray | None = None
        self._scene_cache: tuple[object, np.ndarray] | None = None
        roles = rig.pulse_generator.channels
        self._ch = {role: roles[role] for role in roles}
        t = rig.timing
        self._frame_b_delay_ns = round((t.camera_exposure_us + t.camera_interframe_us) * 1e3)

    # --- Camera protocol ------------------------------------------------------------------
    @property
    def sensor_px(self) -> tuple[int, int]:
        return self.camera.sensor_px

    @property
    def first_frame_id(self) -> int:
        return 0

    def open(self) -> None:
        """Render the pool of pairs and the unlit frame."""
        if self._open:
            return
        render = self.rig.render
        if self.rays_per_particle is not None:
            render = render.model_copy(update={"rays_per_particle": int(self.rays_per_particle)})
        r = LightFieldRenderer(self.camera, render, self.rig.laser.wavelength_nm, self.device)
        ci = self.rig.camera.index(self.camera)
        self._lit = []
        for j in range(self.pool_pairs):
            particles, brightness = self.world.pair(j)
            frames = np.stack([r.frame(particles[f], brightness[f], seed=derive_seed(self.world.seed, j, f, ci))
                               for f in range(2)])
            frames.flags.writeable = False
            self._lit.append(frames)
        self._dark = r.frame(np.zeros((0, 3)), np.zeros(0), seed=derive_seed(self.world.seed, 104729, ci))
        self._dark.flags.writeable = False
        self._open = True

    def configure(self, *, triggered: bool, frames_per_trigger: int, exposure_us: float,
                  dt_us: float | None = None) -> None:
        """Check the set-up; the simulated camera is a double-shutter PIV camera whose frame B
        opens the rig's interframe time after frame A, so ``exposure_us`` and ``dt_us`` change
        nothing (the rig's timing decides)."""
        self._require_open()
        if not triggered:
            raise DeviceError(f"simulated camera '{self.name}' runs triggered only; configure it with triggered=True")
        if frames_per_trigger not in (1, 2):
            raise DeviceError(f"simulated camera '{self.name}': frames_per_trigger must be 1 or 2")
        self.frames_per_trigger = frames_per_trigger
        self._configured = True

    def start(self) -> None:
        self._require_open()
        if not self._configured:
            raise DeviceError(f"simulated camera '{self.name}' is not configured; call configure() before start()")
        with self._cond:
            self._queue.clear()
            self._counter = 0
            self._triggers = 0
            self.frames_produced = 0
            self.frames_lost = 0
            self.triggers_missed = 0
            self._failed = False
            self._running = True
        if not self._listening:
            self._trigger.add_listener(self._on_trigger)
            self._listening = True

    def fetch(self, timeout_s: float) -> Frame | None:
        end = time.monotonic() + timeout_s
        with self._cond:
            while not self._queue:
                if self._failed:
                    raise DeviceError(f"simulated camera '{self.name}' stopped answering (injected cable fault); "
                                      "check the camera's cable and power")
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._queue.popleft()

    def stop(self) -> None:
        with self._cond:
            self._running = False

    def close(self) -> None:
        self.stop()
        self._open = False

    # --- the simulated sensor ---------------------------------------------------------------
    def pool_index(self, tick: int) -> int:
        """Which pair of :attr:`world` trigger ``tick`` shows."""
        return tick % self.pool_pairs

    def _require_open(self) -> None:
        if not self._open:
            raise DeviceError(f"simulated camera '{self.name}' is not open; call open() first")

    def _on_trigger(self, tick: int, t0_ns: int, outputs: dict[int, float]) -> None:
        # Called on the emulator's tick thread: only copy references, never render here.
        ch = self._ch
        if not self._running or ch["camera"] not in outputs:
            return
        with self._cond:
            n, self._triggers = self._triggers, self._triggers + 1
            if n in self.miss_triggers:
                self.triggers_missed += 1
                return
        fired = [ch[f"flashlamp{c}"] in outputs and ch[f"qswitch{c}"] in outputs for c in (1, 2)]
        t_a = t0_ns + round(outputs[ch["camera"]] * 1e9)
        if self.world.scene is not None:
            # A continuously lit scene (calibration) shows in every frame, laser or not.
            image = self._scene_image()
            images = [image] * self.frames_per_trigger
        else:
            lit = self._lit[self.pool_index(tick)]
            images = [lit[f] if fired[f] else self._dark for f in range(self.frames_per_trigger)]
        with self._cond:
            if not self._running:
                return
            for f, image in enumerate(images):
                self._emit(image, t_a + f * self._frame_b_delay_ns)
            self._cond.notify_all()

    def prepare_scene(self) -> None:
        """Render the world's current scene now, so that a trigger serves it from the cache."""
        if self.world.scene is not None:
            self._scene_image()

    def _scene_image(self) -> np.ndarray:
        key = self.world.scene_key
        if self._scene_cache is None or self._scene_cache[0] != key or key is None:
            image = np.asarray(self.world.scene(self.rig.camera.index(self.camera)), dtype=np.uint16)
            image.flags.writeable = False
            self._scene_cache = (key, image)
        return self._scene_cache[1]

    def _emit(self, image: np.ndarray, timestamp_ns: int) -> None:
        # Caller holds self._cond.
        fid = self._counter
        self._counter += 1
        self.frames_produced += 1
        if self.fail_after_frames is not None and fid >= self.fail_after_frames:
            self._failed = True
            return
        lost = (fid in self.lose_frames or len(self._queue) >= self.buffers
                or (self.lose_rate > 0 and self._rng.random() < self.lose_rate))
        if lost:
            self.frames_lost += 1
            return
        self._queue.append(Frame(image, self.name, fid, timestamp_ns, complete=fid not in self.incomplete_ids,
                                 device_clock=True))
