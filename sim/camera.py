"""Simulated cameras (light-field or pinhole) that satisfy :class:`acquisition.protocols.Camera`.

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

GenICam. Each camera has a GenICam-style node map (:class:`SimNodeMap`, :attr:`SimCamera.node_map`)
with the SFNC features the GenICam driver sets: ``TriggerSelector`` (FrameStart,
FrameBurstStart) with ``TriggerMode``, ``TriggerSource`` and ``TriggerActivation`` per
selector, ``AcquisitionBurstFrameCount``, ``ExposureAuto``, ``ExposureMode``, ``ExposureTime``,
``AcquisitionMode``, ``PixelFormat`` (Mono12 / Mono16), ``Width``, ``Height``,
``ResultingFrameRate``, ``GevTimestampTickFrequency``, and one vendor feature,
``PIVDoubleExposure``, that the double-exposure hook registered for :data:`SIM_VENDOR`
switches on. :meth:`SimCamera.configure` runs the driver's own set-up
(:func:`acquisition.genicam.configure_node_map`) on it and then behaves as the nodes say: two
frames per trigger in PIV mode (or a burst of two), one frame per trigger otherwise (software
pairing, with ``allow_software_pairing``), triggered only from ``Line0`` (the generator's camera
output) on the edge ``TriggerActivation`` names.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from acquisition.genicam import configure_node_map, register_double_exposure
from acquisition.protocols import DeviceError, Frame
from lfcore.render import derive_seed, renderer_for
from lfcore.rig import Rig
from sim.world import SimWorld

__all__ = ["SIM_VENDOR", "SimCamera", "SimNode", "SimNodeMap", "TriggerSource"]

#: ``DeviceVendorName`` of the simulated cameras; a double-exposure hook is registered for it.
SIM_VENDOR = "lfpiv simulated cameras"


class SimNode:
    """One GenApi-style feature: ``value`` with its entries (``symbolics``) or ``min``/``max``."""

    def __init__(self, value: object, symbolics: tuple[str, ...] = (), lo: float | None = None,
                 hi: float | None = None, writable: bool = True) -> None:
        self._value, self.symbolics, self.min, self.max = value, symbolics, lo, hi
        self.writable, self.available = writable, True

    @property
    def value(self) -> object:
        return self._value

    @value.setter
    def value(self, v: object) -> None:
        if not self.writable:
            raise DeviceError("the feature is read-only")
        if self.symbolics and v not in self.symbolics:
            raise DeviceError(f"no entry {v!r}")
        if self.min is not None and not self.min <= float(v) <= self.max:  # type: ignore[arg-type]
            raise DeviceError(f"{v} is out of range")
        self._value = v


class SimNodeMap:
    """The simulated camera's node map; ``TriggerMode``, ``TriggerSource`` and
    ``TriggerActivation`` depend on ``TriggerSelector``, as in the SFNC."""

    SELECTORS = ("FrameStart", "FrameBurstStart")

    def __init__(self, sensor_px: tuple[int, int], max_fps: float) -> None:
        cols, rows = sensor_px
        self.DeviceVendorName = SimNode(SIM_VENDOR, writable=False)
        self.TriggerSelector = SimNode("FrameStart", self.SELECTORS)
        self._mode = {s: SimNode("Off", ("Off", "On")) for s in self.SELECTORS}
        self._source = {s: SimNode("Software", ("Software", "Line0", "Line1")) for s in self.SELECTORS}
        self._activation = {s: SimNode("RisingEdge", ("RisingEdge", "FallingEdge")) for s in self.SELECTORS}
        self.AcquisitionBurstFrameCount = SimNode(1, lo=1, hi=255)
        self.AcquisitionMode = SimNode("Continuous", ("Continuous", "SingleFrame", "MultiFrame"))
        self.ExposureAuto = SimNode("Continuous", ("Off", "Continuous"))
        self.ExposureMode = SimNode("TriggerWidth", ("Timed", "TriggerWidth"))
        self.ExposureTime = SimNode(1000.0, lo=1.0, hi=1e7)
        self.PixelFormat = SimNode("Mono16", ("Mono12", "Mono16"))
        self.Width = SimNode(cols, writable=False)
        self.Height = SimNode(rows, writable=False)
        self.ResultingFrameRate = SimNode(float(max_fps), writable=False)
        self.GevTimestampTickFrequency = SimNode(1_000_000_000, writable=False)
        #: The vendor's double-exposure (PIV) switch, set by the hook for :data:`SIM_VENDOR`.
        self.PIVDoubleExposure = SimNode("Off", ("Off", "On"))

    @property
    def TriggerMode(self) -> SimNode:  # noqa: N802 - GenICam feature name
        return self._mode[str(self.TriggerSelector.value)]

    @property
    def TriggerSource(self) -> SimNode:  # noqa: N802
        return self._source[str(self.TriggerSelector.value)]

    @property
    def TriggerActivation(self) -> SimNode:  # noqa: N802
        return self._activation[str(self.TriggerSelector.value)]

    def trigger(self, selector: str) -> tuple[bool, str, str]:
        """(mode on, source, activation) of one trigger selector."""
        return self._mode[selector].value == "On", str(self._source[selector].value), \
            str(self._activation[selector].value)


def _piv_double_exposure(nm: SimNodeMap) -> None:
    """The simulated vendor's double-exposure mode: frame B right after frame A."""
    nm.PIVDoubleExposure.value = "On"


register_double_exposure(SIM_VENDOR, _piv_double_exposure)

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
                 miss_triggers: set[int] | None = None, seed: int = 0, allow_software_pairing: bool = False,
                 pixel_format: str = "Mono16") -> None:
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
        self.allow_software_pairing = allow_software_pairing
        self.pixel_format = pixel_format
        #: The GenICam-style node map the driver's trigger set-up runs on (see the module docstring).
        self.node_map = SimNodeMap(self.camera.sensor_px, t.camera_max_fps)
        self.frames_per_trigger = 2
        self._selector = "FrameStart"
        self.mode = "not configured"

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
        r = renderer_for(self.camera, render, wavelength_nm=self.rig.laser.wavelength_nm, device=self.device)
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
        """Run the GenICam driver's trigger set-up on :attr:`node_map` and take frames as it left
        the nodes: a double-shutter PIV camera (frame B the rig's interframe time after frame A)
        when the vendor's ``PIVDoubleExposure`` or a ``FrameBurstStart`` burst of two is on, one
        frame per trigger otherwise. The exposure itself follows the rig's timing."""
        self._require_open()
        if not triggered:
            raise DeviceError(f"simulated camera '{self.name}' runs triggered only; configure it with triggered=True")
        if frames_per_trigger not in (1, 2):
            raise DeviceError(f"simulated camera '{self.name}': frames_per_trigger must be 1 or 2")
        nm = self.node_map
        nm.PIVDoubleExposure.value = "Off"
        nm.PixelFormat.value = self.pixel_format
        self.mode = configure_node_map(
            nm, where=f"simulated camera '{self.name}'", vendor=str(nm.DeviceVendorName.value), triggered=True,
            frames_per_trigger=frames_per_trigger, exposure_us=exposure_us, trigger_line="Line0",
            allow_software_pairing=self.allow_software_pairing, dt_us=dt_us)
        burst_on, source, _ = nm.trigger("FrameBurstStart")
        start_on, start_source, _ = nm.trigger("FrameStart")
        if burst_on and nm.AcquisitionBurstFrameCount.value == 2:
            self.frames_per_trigger, self._selector = 2, "FrameBurstStart"
        elif start_on:
            self.frames_per_trigger = 2 if nm.PIVDoubleExposure.value == "On" else 1
            source, self._selector = start_source, "FrameStart"
        else:
            raise DeviceError(f"simulated camera '{self.name}': no trigger is on after the set-up ({self.mode})")
        if source != "Line0":
            raise DeviceError(f"simulated camera '{self.name}': triggered from {source}, but only Line0 is wired "
                              "(to the pulse generator's camera output)")
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
        if self.node_map.trigger(self._selector)[2] == "FallingEdge":  # exposure starts as the pulse ends
            t_a += round(self.rig.timing.camera_exposure_us * 1e3)
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
                if self.node_map.PixelFormat.value == "Mono12":
                    image = np.minimum(image, 4095)
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
