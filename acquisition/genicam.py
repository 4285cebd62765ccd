"""GenICam cameras through ``harvesters`` (GenTL producers, ``.cti`` files).

One process talks to every GenICam camera through a single shared :class:`harvesters.core.Harvester`
(a second Harvester on the same producer sees no devices, and ``Harvester.update`` destroys
the image acquirers already created). The shared object is created lazily, under a lock, the
first time a device is listed or opened; :func:`reset_system` releases it (tests).

``harvesters`` is imported lazily, so ``import acquisition.genicam`` works without it; any call
that needs it raises a one-line :class:`~acquisition.protocols.DeviceError` saying how to
install it.

Behaviour worth knowing, checked against harvesters 1.4.3 and the GenTL simulator ``viky.cti``
that ships with the ``genicam`` wheel:

* Acquisition runs without harvesters' background thread (its hand-off queue holds one buffer
  and silently drops the rest). :meth:`GenICamCamera.fetch` polls the producer's output queue
  in the calling thread. The producer's buffer handling mode is ``OldestFirst``: when every
  buffer is full the producer discards *new* frames, so a lost frame shows as a gap in
  ``frame_id`` and never reorders the stream.
* GenTL's EventGetData holds the GIL while it waits, so :meth:`GenICamCamera.fetch` polls
  without waiting (``timeout_period_on_update_event_data_call = 0``) and sleeps
  :data:`POLL_INTERVAL_S` in Python between polls: other threads keep running, at the cost of
  up to a millisecond (a GIL switch interval under load) of latency.
* harvesters 1.4 requeues incomplete buffers itself and never hands them out; they show as
  ``frame_id`` gaps, and :attr:`GenICamCamera.incomplete_frames` counts them (in the thread
  that fetches, before the next complete frame is returned) so that a session can tell
  "incomplete" from "not delivered".
* Creating an ``ImageAcquirer`` in the main thread replaces the SIGINT handler with one that
  silently destroys the acquirer; :meth:`GenICamCamera.open` puts the previous handler back,
  so Ctrl-C still raises :class:`KeyboardInterrupt`.

viky (``viky.cti``): three devices ``VikyTL_DEV_red``/``green``/``blue`` with serial numbers
``"0"``, ``"1"``, ``"2"`` (vendor "Machine Vision Games Ltd.", model "Viky", TL type
"Custom"); 400 x 400 pixels, ``RGBa8`` (default) or ``Mono8``; free run at 20 frames/s
(``AcquisitionFrameRate``); no trigger, exposure or time-stamp support (host time is used);
the first frame after every start has ``frame_id`` 1.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from acquisition.protocols import DeviceError, Frame

if TYPE_CHECKING:
    from types import ModuleType

    from lfcore.rig import Rig

__all__ = [
    "DEFAULT_NUM_BUFFERS",
    "ENV_VAR",
    "POLL_INTERVAL_S",
    "DeviceInfo",
    "GenICamCamera",
    "configure_node_map",
    "frames_per_trigger_of",
    "image_to_uint16",
    "list_devices",
    "producer_paths",
    "register_double_exposure",
    "reset_system",
    "unregister_double_exposure",
]

_log = logging.getLogger(__name__)

#: Environment variable that lists directories holding GenTL producers (64-bit).
ENV_VAR = "GENICAM_GENTL64_PATH"
#: Buffers announced to the producer per camera unless the constructor says otherwise.
DEFAULT_NUM_BUFFERS = 16
#: Sleep between two non-blocking polls of the producer's output queue, seconds.
POLL_INTERVAL_S = 0.001
#: How long :meth:`GenICamCamera.stop` waits for frames still in flight after AcquisitionStop.
_DRAIN_S = 0.05

_INSTALL_HINT = "GenICam camera support is not installed: pip install 'lfpiv[genicam]'"

#: GenTL DEVICE_ACCESS_STATUS values, as words.
_ACCESS = {
    0: "unknown",
    1: "available",
    2: "read-only",
    3: "no access",
    4: "busy",
    5: "open",
    6: "open read-only",
}


# --------------------------------------------------------------------------------------------
# harvesters, imported lazily
# --------------------------------------------------------------------------------------------
def _harvesters() -> ModuleType:
    """``harvesters.core``, or a one-line DeviceError saying how to install it."""
    try:
        import harvesters.core as core
    except ImportError:
        raise DeviceError(_INSTALL_HINT) from None
    return core


def _genicam_errors() -> tuple[type[BaseException], ...]:
    """The base exception classes of genicam's GenApi and GenTL bindings."""
    try:
        from genicam.genapi import GenericException as GenApiError
        from genicam.gentl import GenericException as GenTLError
    except ImportError:  # pragma: no cover - genicam comes with harvesters
        return ()
    return (GenApiError, GenTLError)


# --------------------------------------------------------------------------------------------
# producers
# --------------------------------------------------------------------------------------------
def producer_paths(producers: Rig | Iterable[str | os.PathLike[str]] | None = None) -> list[str]:
    """The GenTL producer files (``.cti``) to load.

    Parameters
    ----------
    producers
        A rig (its ``gentl_producers`` are used) or an explicit list of ``.cti`` files.
        Relative paths are taken from the current directory; ``~`` and ``$VARS`` are expanded.
        When the list is empty (or None), every ``*.cti`` file in the directories listed in
        the ``GENICAM_GENTL64_PATH`` environment variable is used (an entry may also name a
        ``.cti`` file directly).

    Returns
    -------
    list of str
        Absolute paths, in the order given, without duplicates.

    Raises
    ------
    DeviceError
        An explicit file does not exist, or no producer was found at all.
    """
    given = getattr(producers, "gentl_producers", producers)
    if isinstance(given, (str, os.PathLike)):
        given = [given]
    explicit = list(given or ())
    found: list[str] = []
    if explicit:
        for p in explicit:
            path = Path(os.path.expandvars(os.path.expanduser(os.fspath(p))))
            if not path.is_file():
                raise DeviceError(f"GenTL producer '{p}' not found; check gentl_producers in the rig file")
            found.append(str(path.resolve()))
    else:
        env = os.environ.get(ENV_VAR, "")
        for entry in filter(None, env.split(os.pathsep)):
            path = Path(os.path.expanduser(entry))
            if path.is_file() and path.suffix.lower() == ".cti":
                found.append(str(path.resolve()))
            elif path.is_dir():
                found.extend(str(f.resolve()) for f in sorted(path.glob("*.cti")) if f.is_file())
        if not found:
            raise DeviceError(
                f"no GenTL producer (.cti) found: set gentl_producers in the rig file or {ENV_VAR} "
                f"(now {env!r}) to the camera vendor's producer"
            )
    return list(dict.fromkeys(found))


# --------------------------------------------------------------------------------------------
# the one Harvester of the process
# --------------------------------------------------------------------------------------------
class _System:
    """The process-wide Harvester, the producers it loaded and the cameras open on it."""

    lock = threading.RLock()
    harvester: Any = None
    files: list[str] = []  # guarded by lock
    updated: bool = False
    open_cameras: set[int] = set()

    @classmethod
    def get(cls, producers: Sequence[str], *, refresh: bool = False) -> Any:
        """The shared Harvester with ``producers`` loaded and its device list current.

        ``Harvester.update`` destroys every image acquirer, so it runs only while no camera is
        open: the first time, when a new producer is needed, or on ``refresh`` (device listing).
        """
        with cls.lock:
            core = _harvesters()
            if cls.harvester is None:
                cls.harvester = core.Harvester()
                cls.files = []
                cls.updated = False
            new = [p for p in producers if p not in cls.files]
            if new and cls.open_cameras:
                raise DeviceError(
                    f"cannot load GenTL producer '{new[0]}' while cameras are open on "
                    f"{', '.join(map(repr, cls.files))}; give every camera the same producers"
                )
            if new or not cls.updated or (refresh and not cls.open_cameras):
                for p in new:
                    cls.harvester.add_file(p)
                    cls.files.append(p)
                cls.harvester.update()
                cls.updated = True
            return cls.harvester

    @classmethod
    def reset(cls) -> None:
        with cls.lock:
            if cls.harvester is not None:
                try:
                    cls.harvester.reset()
                finally:
                    cls.harvester = None
            cls.files = []
            cls.updated = False
            cls.open_cameras = set()


def reset_system() -> None:
    """Release the shared Harvester, every camera opened on it and every producer.

    Cameras still open become unusable (:meth:`GenICamCamera.close` stays safe). The next
    listing or ``open`` creates a fresh Harvester. Meant for tests.
    """
    _System.reset()


# --------------------------------------------------------------------------------------------
# device listing
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """One device a GenTL producer reports (what ``lfpiv devices`` prints).

    Attributes
    ----------
    vendor, model, serial_number
        As the producer reports them; ``serial_number`` is what a rig file's ``serial`` matches.
    id
        The producer's device id (unique within the producer).
    tl_type
        Transport layer: "GEV" (GigE Vision), "U3V" (USB3 Vision), "CL", "Custom", ...
    display_name, user_defined_name, version
        Empty where the producer does not report them.
    access
        "available", "busy" (open elsewhere), "open" (by this process), "read-only", ...
    producer
        Path of the ``.cti`` file that reported the device.
    """

    vendor: str
    model: str
    serial_number: str
    id: str
    tl_type: str
    display_name: str = ""
    user_defined_name: str = ""
    version: str = ""
    access: str = "unknown"
    producer: str = ""


def _info_attr(info: Any, name: str) -> Any:
    try:
        return getattr(info, name)
    except Exception:  # producers raise NotAvailable & co. for missing info
        return None


def _producer_of(info: Any) -> str:
    try:
        return str(Path(info.parent.parent.parent.module.path_name).resolve())
    except Exception:
        return ""


def _describe(info: Any) -> DeviceInfo:
    def s(name: str) -> str:
        v = _info_attr(info, name)
        return "" if v is None else str(v)

    status = _info_attr(info, "access_status")
    return DeviceInfo(
        vendor=s("vendor"),
        model=s("model"),
        serial_number=s("serial_number"),
        id=s("id_"),
        tl_type=s("tl_type"),
        display_name=s("display_name"),
        user_defined_name=s("user_defined_name"),
        version=s("version"),
        access=_ACCESS.get(status, "unknown") if isinstance(status, int) else "unknown",
        producer=_producer_of(info),
    )


def _raw_devices(producers: Sequence[str], *, refresh: bool) -> list[Any]:
    """harvesters' DeviceInfo objects of the devices the given producers report."""
    h = _System.get(producers, refresh=refresh)
    wanted = set(producers)
    return [d for d in h.device_info_list if _producer_of(d) in wanted or not _producer_of(d)]


def list_devices(producers: Rig | Iterable[str | os.PathLike[str]] | None = None) -> list[DeviceInfo]:
    """Every GenICam device the producers see.

    Parameters
    ----------
    producers
        See :func:`producer_paths`.

    Returns
    -------
    list of DeviceInfo
        In producer order. The list is enumerated afresh unless cameras are open in this
        process (enumerating would close them); then it is the list from when they were opened.

    Raises
    ------
    DeviceError
        harvesters is missing or no producer was found.
    """
    paths = producer_paths(producers)
    with _System.lock:
        return [_describe(d) for d in _raw_devices(paths, refresh=True)]


# --------------------------------------------------------------------------------------------
# vendor double-exposure hooks
# --------------------------------------------------------------------------------------------
_DOUBLE_EXPOSURE: dict[str, Callable[[Any], None]] = {}


def register_double_exposure(vendor_prefix: str, fn: Callable[[Any], None]) -> None:
    """Register how cameras of one vendor are put into double-exposure (PIV) mode.

    Parameters
    ----------
    vendor_prefix
        Matched, case-insensitively, against the start of the device's vendor name; the longest
        matching prefix wins.
    fn
        ``fn(node_map) -> None``, called by :meth:`GenICamCamera.configure` with the remote
        device's GenApi node map when ``triggered=True`` and ``frames_per_trigger=2``, after the
        standard SFNC set-up (all trigger modes off, then ``TriggerSelector=FrameStart``,
        ``TriggerSource``, ``TriggerActivation``, ``TriggerMode=On``, ``ExposureMode=Timed``,
        ``ExposureTime``). It must leave the camera delivering two frames per trigger (frame A
        with the set exposure, frame B straight after the interframe time).
    """
    if not vendor_prefix:
        raise ValueError("vendor_prefix must not be empty")
    _DOUBLE_EXPOSURE[vendor_prefix.casefold()] = fn


def unregister_double_exposure(vendor_prefix: str) -> None:
    """Remove a hook added by :func:`register_double_exposure` (no error if absent)."""
    _DOUBLE_EXPOSURE.pop(vendor_prefix.casefold(), None)


def _double_exposure_hook(vendor: str) -> Callable[[Any], None] | None:
    v = vendor.casefold()
    matches = [p for p in _DOUBLE_EXPOSURE if v.startswith(p)]
    return _DOUBLE_EXPOSURE[max(matches, key=len)] if matches else None


# --------------------------------------------------------------------------------------------
# GenApi feature access (works on genicam NodeMaps and on simple stand-ins in tests)
# --------------------------------------------------------------------------------------------
def _feature(nm: Any, name: str) -> Any | None:
    """The node ``name`` when it is implemented and available, else None."""
    try:
        node = getattr(nm, name)
    except Exception:  # AttributeError or a GenApi error for a missing node
        return None
    try:
        from genicam.genapi import is_available

        return node if is_available(node) else None
    except (ImportError, TypeError):  # a stand-in node map
        return node if getattr(node, "available", True) else None


def _writable(node: Any) -> bool:
    try:
        from genicam.genapi import is_writable

        return bool(is_writable(node))
    except (ImportError, TypeError):
        return bool(getattr(node, "writable", True))


def _symbolics(node: Any) -> tuple[str, ...]:
    try:
        return tuple(node.symbolics)
    except Exception:
        return ()


def _set(nm: Any, name: str, value: Any, where: str, *, required: bool = True) -> bool:
    """Write a feature; False when it is missing and not required.

    Raises
    ------
    DeviceError
        The feature is required but missing, not writable, or refuses the value (one line,
        naming the feature, the camera and what it accepts).
    """
    node = _feature(nm, name)
    if node is None:
        if required:
            raise DeviceError(f"{where} has no {name} feature")
        return False
    if not _writable(node):
        if not required:
            _log.debug("%s: %s is not writable; left as it is", where, name)
            return False
        raise DeviceError(f"{where}: {name} is not writable (is acquisition running?)")
    options = _symbolics(node)
    if options and value not in options:
        if not required:
            _log.debug("%s: %s has no entry %r (%s); left as it is", where, name, value, options)
            return False
        raise DeviceError(f"{where}: {name} cannot be {value!r}; it accepts {', '.join(options)}")
    try:
        node.value = value
    except Exception as exc:  # GenApi OutOfRange/Access/Logical errors
        limits = ""
        lo, hi = getattr(node, "min", None), getattr(node, "max", None)
        if lo is not None and hi is not None:
            limits = f" (allowed {lo} to {hi})"
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DeviceError(f"{where}: cannot set {name} = {value!r}{limits}: {first}") from None
    return True


def _frame_period_us(nm: Any) -> float | None:
    """The camera's frame period, microseconds, as its node map states it; None if it does not.

    ``ResultingFrameRate`` (what the camera will really do with the current exposure and
    settings) first; then ``AcquisitionFrameRate`` where it is enabled (or has no enable
    switch), else its maximum, the rate a camera runs at when its frame rate is not limited.
    """
    for name in ("ResultingFrameRate", "ResultingFrameRateAbs"):
        node = _feature(nm, name)
        try:
            rate = float(node.value) if node is not None else 0.0
        except Exception:
            rate = 0.0
        if math.isfinite(rate) and rate > 0:
            return 1e6 / rate
    for name in ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"):
        node = _feature(nm, name)
        if node is None:
            continue
        enable = _feature(nm, "AcquisitionFrameRateEnable")
        try:
            rate = float(node.value) if enable is None or bool(enable.value) else float(node.max)
        except Exception:
            continue
        if math.isfinite(rate) and rate > 0:
            return 1e6 / rate
    return None


def _burst_misses_pulse_2(nm: Any, exposure_us: float, dt_us: float | None) -> str | None:
    """Why a FrameBurstStart burst of two frames cannot catch laser pulse 2; None if it can.

    In a burst, frame B starts one camera frame period ``T`` after frame A and is exposed for
    the same ``exposure_us`` (it is not a double-shutter frame that opens right after frame A).
    The timing plan puts pulse 1 one straddle margin ``m`` before frame A closes and pulse 2
    ``dt`` later, so pulse 2 is inside frame B only when ``dt <= T <= dt + exposure - 2 m``.
    """
    from acquisition.timing import STRADDLE_MARGIN_US as m

    if dt_us is None:
        return ("FrameBurstStart starts frame B one frame period after frame A, and configure() was not "
                "given dt_us to check that frame B catches laser pulse 2")
    period = _frame_period_us(nm)
    if period is None:
        return ("FrameBurstStart starts frame B one frame period after frame A, and the camera states no "
                "frame rate (ResultingFrameRate, AcquisitionFrameRate) to check that frame B catches laser pulse 2")
    lo, hi = dt_us, dt_us + exposure_us - 2 * m
    if lo <= period <= hi:
        return None
    where_b = "opens after" if period > hi else "closes before"
    return (f"FrameBurstStart starts frame B one frame period ({period:.1f} us) after frame A, so frame B "
            f"{where_b} laser pulse 2 (dt = {dt_us:g} us, exposure {exposure_us:g} us; the period would have "
            f"to be {lo:.1f}-{hi:.1f} us)")


def configure_node_map(
    nm: Any,
    *,
    where: str,
    vendor: str,
    triggered: bool,
    frames_per_trigger: int,
    exposure_us: float,
    trigger_line: str,
    allow_software_pairing: bool,
    dt_us: float | None = None,
) -> str:
    """Apply the SFNC trigger and exposure set-up to a GenApi node map; return a short
    description of the mode (what :meth:`GenICamCamera.configure` does, and what simulated
    cameras run on their own node map).

    The description ends in "one frame per trigger (paired in software...)" when a double frame
    was asked for and the camera is left taking one frame per trigger.

    For ``frames_per_trigger=2`` without a vendor hook, ``FrameBurstStart`` is used only when
    :func:`_burst_misses_pulse_2` finds that frame B catches laser pulse 2; otherwise the camera
    is set to one frame per trigger where ``allow_software_pairing`` allows it, or refused.
    """
    _set(nm, "AcquisitionMode", "Continuous", where, required=False)
    _set(nm, "ExposureAuto", "Off", where, required=False)
    _set(nm, "ExposureMode", "Timed", where, required=False)
    exposure_name = next((n for n in ("ExposureTime", "ExposureTimeAbs") if _feature(nm, n) is not None), None)
    if exposure_name is not None:
        _set(nm, exposure_name, float(exposure_us), where)
    else:
        _log.info("%s has no ExposureTime feature; exposure left as it is", where)

    selector = _feature(nm, "TriggerSelector")
    selectors = _symbolics(selector) if selector is not None else ()

    def all_triggers_off() -> None:
        for sel in selectors:
            if _set(nm, "TriggerSelector", sel, where, required=False):
                _set(nm, "TriggerMode", "Off", where, required=False)
        if not selectors:
            _set(nm, "TriggerMode", "Off", where, required=False)

    if not triggered:
        all_triggers_off()
        return "free run" + (" (consecutive frames paired)" if frames_per_trigger == 2 else "")

    for required in ("TriggerMode", "TriggerSource"):
        if _feature(nm, required) is None:
            raise DeviceError(
                f"{where} has no {required} feature, so it cannot be triggered externally; "
                "configure it with triggered=False (free run)"
            )
    all_triggers_off()

    hook = _double_exposure_hook(vendor) if frames_per_trigger == 2 else None
    burst = (frames_per_trigger == 2 and hook is None and "FrameBurstStart" in selectors
             and _feature(nm, "AcquisitionBurstFrameCount") is not None)
    fix = (f"register the camera's double-exposure (PIV) mode for vendor {vendor!r} with "
           "acquisition.genicam.register_double_exposure, or pass allow_software_pairing=True and trigger the "
           "camera once per frame")
    if frames_per_trigger == 2 and hook is None and not burst and not allow_software_pairing:
        raise DeviceError(f"{where} has no double-exposure mode known to lfpiv (no FrameBurstStart trigger, "
                          f"no hook for vendor {vendor!r}): {fix}")

    def trigger_on(start: str) -> None:
        if selectors:
            _set(nm, "TriggerSelector", start, where)
        _set(nm, "AcquisitionBurstFrameCount", 2 if start == "FrameBurstStart" else 1, where,
             required=start == "FrameBurstStart")
        _set(nm, "TriggerSource", trigger_line, where)
        _set(nm, "TriggerActivation", "RisingEdge", where, required=False)
        _set(nm, "TriggerMode", "On", where)

    start = "FrameBurstStart" if burst else "FrameStart"
    trigger_on(start)
    unfit = None
    if burst:
        # checked once set up: the frame rate the camera reports depends on exposure and burst
        unfit = _burst_misses_pulse_2(nm, exposure_us, dt_us)
        if unfit is not None:
            if not allow_software_pairing:
                raise DeviceError(f"{where}: {unfit}; {fix}")
            _log.warning("%s: %s; using one frame per trigger, paired in software", where, unfit)
            all_triggers_off()
            start, burst = "FrameStart", False
            trigger_on(start)
    mode = f"{start} trigger on {trigger_line}"
    if hook is not None:
        try:
            hook(nm)
        except DeviceError:
            raise
        except Exception as exc:
            raise DeviceError(f"{where}: double-exposure hook for {vendor!r} failed: {exc}") from None
        mode += f", double exposure ({vendor})"
    elif burst:
        mode += ", bursts of 2 frames"
    elif frames_per_trigger == 2:
        mode += ", one frame per trigger (paired in software" + ("; no usable burst)" if unfit else ")")
    return mode


_configure_node_map = configure_node_map  # the name the tests of the set-up use


def frames_per_trigger_of(mode: str, asked: int) -> int:
    """Frames one trigger makes, from :func:`configure_node_map`'s description of the mode."""
    return 1 if asked == 1 or "one frame per trigger" in mode else 2


# --------------------------------------------------------------------------------------------
# pixel formats
# --------------------------------------------------------------------------------------------
def _is_rgb(fmt: str) -> bool:
    return fmt.startswith(("RGB", "BGR")) and not fmt.endswith(("Planar", "p", "Packed"))


def _supported(fmt: str) -> bool:
    return fmt.startswith(("Mono", "Bayer")) or _is_rgb(fmt)


def image_to_uint16(data: np.ndarray, pixel_format: str, width: int, height: int) -> np.ndarray:
    """Copy a delivered image into a new uint16 array of shape (rows, columns).

    Parameters
    ----------
    data
        The 1-D pixel data of the buffer as harvesters expands it (uint8 for 8-bit formats,
        uint16 for 10- to 16-bit ones, packed formats already unpacked), possibly with padding
        at the end of each line.
    pixel_format
        PFNC name, e.g. "Mono8", "Mono12", "RGBa8".
    width, height
        Image size in pixels.

    Returns
    -------
    numpy.ndarray
        uint16 (height, width). Mono and Bayer formats keep their values (Bayer images stay raw
        mosaics). RGB formats (``RGB8``, ``RGBa8``, ``BGR8``, ``BGRa8``, ``RGB16``...) become
        luminance, Y = (77 R + 150 G + 29 B + 128) >> 8 (ITU-R BT.601 weights), in the source
        bit depth.

    Raises
    ------
    DeviceError
        Unsupported pixel format (YUV, 3-D coordinates, floating point...).
    ValueError
        ``data`` is too small for the image.
    """
    if not _supported(pixel_format) or data.dtype.kind not in "ui":
        raise DeviceError(f"pixel format {pixel_format} is not supported; choose a Mono format (e.g. Mono12)")
    channels = 1
    if _is_rgb(pixel_format):
        channels = 4 if pixel_format[3:4].lower() == "a" else 3
    flat = np.asarray(data).reshape(-1)
    line = flat.size // height if height else 0
    if height <= 0 or width <= 0 or line < width * channels:
        raise ValueError(f"{flat.size} values cannot hold a {width} x {height} {pixel_format} image")
    img = flat[: height * line].reshape(height, line)[:, : width * channels]
    if channels == 1:
        return img.astype(np.uint16)
    px = img.reshape(height, width, channels).astype(np.uint32)
    r, g, b = (0, 1, 2) if pixel_format.startswith("RGB") else (2, 1, 0)
    y = (77 * px[..., r] + 150 * px[..., g] + 29 * px[..., b] + 128) >> 8
    return y.astype(np.uint16)


# --------------------------------------------------------------------------------------------
# the camera
# --------------------------------------------------------------------------------------------
class GenICamCamera:
    """A GenICam camera driven through harvesters; implements :class:`acquisition.protocols.Camera`.

    Parameters
    ----------
    name
        The camera's name in the rig file (goes into every :class:`Frame`).
    serial
        GenICam serial number (``DeviceInfo.serial_number``) of the device to open. When
        None, the device at ``index`` in the producers' device list is opened.
    producers
        GenTL producers, see :func:`producer_paths`. Every camera of a process should be given
        the same producers (they share one Harvester, loaded once).
    index
        Position in :func:`list_devices` when ``serial`` is None (default 0).
    trigger_line
        ``TriggerSource`` for external triggering, e.g. "Line0".
    pixel_format
        PFNC name written to ``PixelFormat`` by :meth:`configure` (e.g. "Mono12"); None keeps
        the camera's current format.
    num_buffers
        Buffers announced to the producer. Each holds one frame; with ``OldestFirst`` handling
        the producer drops new frames once all are waiting to be fetched.
    allow_software_pairing
        With ``triggered=True, frames_per_trigger=2`` on a camera without a double-exposure
        mode (no vendor hook, and no ``FrameBurstStart`` burst whose frame B catches laser
        pulse 2, see :meth:`configure`): accept a plain one-frame-per-trigger set-up and let
        consecutive frames form the pairs, instead of raising.
    first_frame_id
        ``frame_id`` of the first frame after :meth:`start`. Default: 0 for USB3 Vision
        ("U3V", block ids start at 0), 1 otherwise (GigE Vision block ids start at 1; viky
        also starts at 1).

    Notes
    -----
    ``frame_id`` is the producer's frame (block) id, unwrapped where 16-bit GigE Vision ids wrap,
    so a frame lost anywhere leaves a gap. ``timestamp_ns`` is the buffer's time stamp from the
    camera clock where the producer reports one (``timestamp_ns``, or ticks over the device's
    tick frequency; then ``Frame.device_clock`` is True), otherwise the host's
    ``time.time_ns()`` when the frame was fetched.
    """

    def __init__(
        self,
        name: str,
        serial: str | None = None,
        producers: Rig | Iterable[str | os.PathLike[str]] | None = None,
        index: int | None = None,
        *,
        trigger_line: str = "Line0",
        pixel_format: str | None = None,
        num_buffers: int = DEFAULT_NUM_BUFFERS,
        allow_software_pairing: bool = False,
        first_frame_id: int | None = None,
    ) -> None:
        if num_buffers < 1:
            raise ValueError("num_buffers must be at least 1")
        self.name = name
        self.serial = None if serial is None else str(serial)
        self.index = index
        self.trigger_line = trigger_line
        self.pixel_format = pixel_format
        self.num_buffers = int(num_buffers)
        self.allow_software_pairing = allow_software_pairing
        self._producers_arg = producers
        self._first_frame_id_arg = first_frame_id
        self._lock = threading.RLock()
        self._ia: Any = None
        self._info: DeviceInfo | None = None
        self._sensor_px: tuple[int, int] | None = None
        self._acquiring = False
        self._pending: deque[Frame] = deque()
        self._incomplete = 0
        self._last_raw_id: int | None = None  # the producer's last frame (block) id
        self._id_base = 0  # added to it for the 16-bit GigE Vision ids that wrapped
        self._tick_hz: float | None = None
        self._mode = "not configured"
        self._frames_per_trigger = 2

    # --- description -----------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"GenICamCamera({self.name!r}, serial={self.serial!r}, {'open' if self._ia else 'closed'})"

    @property
    def _where(self) -> str:
        if self._info is None:
            return f"camera '{self.name}'"
        i = self._info
        return f"camera '{self.name}' ({i.vendor} {i.model}, serial {i.serial_number})"

    @property
    def device_info(self) -> DeviceInfo | None:
        """What the producer reported for the opened device; None before :meth:`open`."""
        return self._info

    @property
    def mode(self) -> str:
        """How :meth:`configure` set the camera up, in words (for logs)."""
        return self._mode

    @property
    def frames_per_trigger(self) -> int:
        """Frames one trigger makes as configured: 1 when the camera was left taking one frame per
        trigger (``allow_software_pairing``), so that the recording session pairs consecutive
        triggers by the camera's time stamps; 2 otherwise (and in free run)."""
        return self._frames_per_trigger

    @property
    def node_map(self) -> Any:
        """The remote device's GenApi node map, for features lfpiv does not set itself.

        Raises
        ------
        DeviceError
            The camera is not open.
        """
        with self._lock:
            return self._node_map()

    @property
    def is_open(self) -> bool:
        """True between :meth:`open` and :meth:`close`."""
        return self._ia is not None

    @property
    def sensor_px(self) -> tuple[int, int]:
        """(columns, rows) of the delivered image, from the camera's Width and Height.

        (0, 0) until :meth:`open` (raising here would break ``isinstance(cam, Camera)``).
        """
        return self._sensor_px or (0, 0)

    @property
    def first_frame_id(self) -> int:
        """``frame_id`` of the first frame after :meth:`start` (see the class notes)."""
        if self._first_frame_id_arg is not None:
            return self._first_frame_id_arg
        tl = self._info.tl_type if self._info is not None else ""
        return 0 if tl.upper() == "U3V" else 1

    @property
    def incomplete_frames(self) -> int:
        """Incomplete buffers the producer delivered and harvesters discarded since :meth:`open`."""
        return self._incomplete

    # --- life cycle ------------------------------------------------------------------------
    def __enter__(self) -> GenICamCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Find the device by serial number (or index) and take exclusive control of it.

        Raises
        ------
        DeviceError
            harvesters missing, no producer, no such device (the message lists the serial
            numbers seen), or the device is in use by another program.
        """
        if self._ia is not None:
            return
        paths = producer_paths(self._producers_arg)
        core = _harvesters()
        with _System.lock:
            h = _System.get(paths)
            devices = _raw_devices(paths, refresh=False)
            chosen = self._choose(devices, paths)
            info = _describe(chosen)
            self._info = info
            on_main = threading.current_thread() is threading.main_thread()
            previous = signal.getsignal(signal.SIGINT) if on_main else None
            try:
                ia = h.create(chosen)
            except _genicam_errors() as exc:
                first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise DeviceError(f"{self._where} cannot be opened (in use by another program?): {first}") from None
            finally:
                if on_main and previous is not None:
                    signal.signal(signal.SIGINT, previous)
            _System.open_cameras.add(id(self))
        self._ia = ia
        try:
            ia.timeout_period_on_update_event_data_call = 0  # poll; GenTL waits hold the GIL
            camera = self

            class _CountIncomplete(core.Callback):
                def emit(self, context: object = None) -> None:
                    camera._incomplete += 1

            ia.add_callback(core.ImageAcquirer.Events.INCOMPLETE_BUFFER, _CountIncomplete())
            self._tick_hz = self._tick_frequency()
            self._read_size()
        except BaseException:
            self.close()
            raise
        _log.info("opened %s via %s", self._where, info.producer)

    def _choose(self, devices: list[Any], paths: Sequence[str]) -> Any:
        if self.serial is not None:
            for d in devices:
                if str(_info_attr(d, "serial_number")).strip() == self.serial.strip():
                    return d
            seen = ", ".join(repr(str(_info_attr(d, "serial_number"))) for d in devices) or "none"
            raise DeviceError(
                f"camera '{self.name}': no GenICam device with serial {self.serial!r} "
                f"(seen: {seen}; producers: {', '.join(Path(p).name for p in paths)}); "
                "check the serial in the rig file and the camera's connection"
            )
        index = 0 if self.index is None else self.index
        if not 0 <= index < len(devices):
            raise DeviceError(
                f"camera '{self.name}': no GenICam device at index {index} "
                f"({len(devices)} found via {', '.join(Path(p).name for p in paths)})"
            )
        return devices[index]

    def _node_map(self) -> Any:
        if self._ia is None:
            raise DeviceError(f"{self._where} is not open")
        if not self._ia.is_valid():
            raise DeviceError(f"{self._where} was released (reset_system); open it again")
        return self._ia.remote_device.node_map

    def _read_size(self) -> None:
        nm = self._node_map()
        try:
            self._sensor_px = (int(nm.Width.value), int(nm.Height.value))
        except Exception as exc:
            raise DeviceError(f"{self._where}: cannot read Width/Height: {exc}") from None

    def _tick_frequency(self) -> float | None:
        try:
            return float(self._ia.device.module.timestamp_frequency)
        except Exception:
            pass
        node = _feature(self._ia.remote_device.node_map, "GevTimestampTickFrequency")
        try:
            return float(node.value) if node is not None else None
        except Exception:
            return None

    def configure(self, *, triggered: bool, frames_per_trigger: int, exposure_us: float,
                  dt_us: float | None = None) -> None:
        """Set up external triggering (SFNC) or free run, and the exposure.

        Triggered: every trigger selector off, then ``TriggerSelector=FrameStart`` (or
        ``FrameBurstStart`` with ``AcquisitionBurstFrameCount=2``, see below),
        ``TriggerSource`` = ``trigger_line``, ``TriggerActivation=RisingEdge`` (where present),
        ``TriggerMode=On``; ``ExposureAuto=Off``, ``ExposureMode=Timed`` (where present),
        ``ExposureTime`` = ``exposure_us``; then the vendor's double-exposure hook for
        ``frames_per_trigger=2`` (see :func:`register_double_exposure`). Free run: every
        trigger mode off, exposure as above; consecutive frames form the pairs.
        ``pixel_format`` (constructor) is written first.

        Double frames without a vendor hook. A PIV double-shutter camera opens frame B right
        after frame A (the interframe time); a ``FrameBurstStart`` burst of two frames opens it
        one whole frame period ``T`` later, with the same exposure. Pulse 2, ``dt_us`` after
        pulse 1 (which the timing plan puts just before frame A closes), is then inside frame B
        only when ``dt_us <= T <= dt_us + exposure_us - 2 x`` the straddle margin; at a camera's
        usual rate (e.g. 16.7 ms at 60 frames/s against a dt of 2 ms) frame B would record no
        particles. So the burst is used only when the frame period the camera reports
        (``ResultingFrameRate``, else ``AcquisitionFrameRate``) fits; a frame rate set through
        :attr:`node_map` before ``configure`` can make it fit. Otherwise, with
        ``allow_software_pairing``, the camera takes one frame per trigger; without it
        ``configure`` raises.

        Parameters
        ----------
        triggered, frames_per_trigger, exposure_us
            See :meth:`acquisition.protocols.Camera.configure`.
        dt_us
            Time between the two laser pulses of a pair, microseconds (the rig's
            ``timing.dt_us``); needed to accept a ``FrameBurstStart`` burst.

        Raises
        ------
        DeviceError
            One line naming the camera and the missing or refused feature, e.g. a camera
            without ``TriggerMode`` asked for ``triggered=True``, or a burst whose frame B
            misses pulse 2; or acquisition is running.
        ValueError
            ``frames_per_trigger`` not 1 or 2, or a non-positive exposure or dt.
        """
        if frames_per_trigger not in (1, 2):
            raise ValueError(f"frames_per_trigger must be 1 or 2, got {frames_per_trigger}")
        if not (math.isfinite(exposure_us) and exposure_us > 0):
            raise ValueError(f"exposure_us must be positive, got {exposure_us}")
        if dt_us is not None and not (math.isfinite(dt_us) and dt_us > 0):
            raise ValueError(f"dt_us must be positive, got {dt_us}")
        with self._lock:
            nm = self._node_map()
            if self._acquiring:
                raise DeviceError(f"{self._where} is acquiring; stop it before configure")
            if self.pixel_format is not None:
                _set(nm, "PixelFormat", self.pixel_format, self._where)
            self._mode = configure_node_map(
                nm,
                where=self._where,
                vendor=self._info.vendor if self._info else "",
                triggered=triggered,
                frames_per_trigger=frames_per_trigger,
                exposure_us=exposure_us,
                trigger_line=self.trigger_line,
                allow_software_pairing=self.allow_software_pairing,
                dt_us=dt_us,
            )
            self._frames_per_trigger = frames_per_trigger_of(self._mode, frames_per_trigger) if triggered else 2
            self._read_size()
        _log.info("%s: %s", self._where, self._mode)

    def start(self) -> None:
        """Start acquisition: ``OldestFirst`` buffer handling, ``num_buffers`` buffers, no
        background thread. Frames left over from a previous run are discarded.

        Raises
        ------
        DeviceError
            Not open, an unsupported pixel format, or the producer refused to start.
        """
        with self._lock:
            nm = self._node_map()
            if self._acquiring:
                return
            fmt_node = _feature(nm, "PixelFormat")
            fmt = str(fmt_node.value) if fmt_node is not None else "Mono8"
            if not _supported(fmt):
                raise DeviceError(
                    f"{self._where}: pixel format {fmt} is not supported; pass pixel_format='Mono8' (or Mono12...)"
                )
            self._read_size()
            self._pending.clear()
            self._last_raw_id, self._id_base = None, 0
            ia = self._ia
            stream = ia.data_streams[0] if ia.data_streams else None
            if stream is None:
                raise DeviceError(f"{self._where} has no data stream")
            if not _set(stream.node_map, "StreamBufferHandlingMode", "OldestFirst", self._where, required=False):
                _log.warning(
                    "%s: cannot select OldestFirst buffer handling; the producer's default applies", self._where
                )
            ia.num_buffers = max(self.num_buffers, ia.min_num_buffers)
            try:
                ia.start(run_as_thread=False)
            except _genicam_errors() as exc:
                raise DeviceError(f"{self._where}: acquisition did not start: {exc}") from None
            self._acquiring = True
        _log.debug("%s: started", self._where)

    def fetch(self, timeout_s: float) -> Frame | None:
        """The oldest delivered frame not yet fetched, or None.

        Waits up to ``timeout_s`` while acquiring. After :meth:`stop`, returns the frames
        that were delivered before it, then None at once.

        Raises
        ------
        DeviceError
            Not open, or the frame cannot be read (unsupported pixel format).
        """
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            with self._lock:
                if self._pending:
                    return self._pending.popleft()
                if not self._acquiring:
                    self._node_map()  # raises when not open
                    return None
                frame = self._poll()
                if frame is not None:
                    return frame
            if time.monotonic() >= deadline:
                return None
            time.sleep(POLL_INTERVAL_S)

    def _poll(self) -> Frame | None:
        """One non-blocking look at the producer's output queue (lock held)."""
        try:
            got = self._ia.try_fetch(timeout=1e-4)  # try_fetch never returns at timeout=0
        except _genicam_errors() as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DeviceError(f"{self._where}: fetching a frame failed: {first}") from None
        if isinstance(got, list):  # a device with several data streams: use the first
            for extra in got[1:]:
                if extra is not None:
                    extra.queue()
            got = got[0]
        if got is None:
            return None
        host_ns = time.time_ns()
        with got as buffer:
            return self._to_frame(buffer, host_ns)

    def _to_frame(self, buffer: Any, host_ns: int) -> Frame:
        raw = buffer.module
        try:
            frame_id = self._unwrap(int(raw.frame_id))
        except Exception:
            frame_id = -1
        try:
            complete = bool(raw.is_complete())
        except Exception:
            complete = False
        cols, rows = self.sensor_px
        data = None
        try:
            comp = buffer.payload.components[0]
            data = image_to_uint16(comp.data, str(comp.data_format), int(comp.width), int(comp.height))
        except DeviceError as exc:
            raise DeviceError(f"{self._where}: {exc}") from None
        except Exception as exc:  # a payload harvesters cannot parse
            _log.warning("%s: frame %d unreadable (%s); recorded as incomplete", self._where, frame_id, exc)
        if data is None:
            data, complete = np.zeros((rows, cols), np.uint16), False
        stamp = self._timestamp(raw)
        return Frame(
            data=data,
            camera=self.name,
            frame_id=frame_id,
            timestamp_ns=stamp or host_ns,
            complete=complete,
            device_clock=bool(stamp),
        )

    def _unwrap(self, raw_id: int) -> int:
        """The frame count since :meth:`start` from the producer's frame (block) id.

        GigE Vision 1.x block ids are 16 bits and wrap from 65535 to 1 (0 is never used): after
        55 minutes of double frames at 10 Hz. A jump back of more than half that range from
        a 16-bit id is a wrap, and the count goes on from 65536. 64-bit ids (USB3 Vision, GigE
        Vision 2 extended ids) never wrap in practice and pass unchanged.
        """
        if raw_id < 0:
            return -1
        last = self._last_raw_id
        if last is not None and last <= 0xFFFF and last - raw_id > 0x8000:
            self._id_base += 0xFFFF
        self._last_raw_id = raw_id
        return raw_id + self._id_base

    def _timestamp(self, raw: Any) -> int:
        try:
            return int(raw.timestamp_ns)
        except Exception:  # NotAvailable on producers without time stamps
            pass
        if self._tick_hz:
            try:
                return int(round(int(raw.timestamp) * 1e9 / self._tick_hz))
            except Exception:
                pass
        return 0

    def stop(self) -> None:
        """Stop acquisition. Frames delivered before the stop stay available to :meth:`fetch`."""
        with self._lock:
            if not self._acquiring:
                return
            self._acquiring = False
            ia = self._ia
            if ia is None or not ia.is_valid():
                return
            try:
                ia.remote_device.node_map.AcquisitionStop.execute()
            except Exception as exc:
                _log.debug("%s: AcquisitionStop: %s", self._where, exc)
            deadline = time.monotonic() + _DRAIN_S
            while time.monotonic() < deadline:  # frames in flight or waiting in the queue
                try:
                    frame = self._poll()
                except Exception as exc:
                    _log.warning("%s: while draining: %s", self._where, exc)
                    break
                if frame is not None:
                    self._pending.append(frame)
                    deadline = time.monotonic() + _DRAIN_S
                else:
                    time.sleep(POLL_INTERVAL_S)
            try:
                ia.stop()
            except Exception as exc:
                raise DeviceError(f"{self._where}: acquisition did not stop cleanly: {exc}") from None
        _log.debug("%s: stopped, %d frames left to fetch", self._where, len(self._pending))

    def close(self) -> None:
        """Stop (best effort) and release the device. Safe in any state, more than once."""
        with self._lock:
            ia = self._ia
            if ia is None:
                return
            try:
                if ia.is_valid():
                    try:
                        self.stop()
                    except DeviceError as exc:
                        _log.warning("%s", exc)
                    ia.destroy()
            finally:
                self._ia = None
                self._acquiring = False
                self._sensor_px = None
                with _System.lock:
                    _System.open_cameras.discard(id(self))
                    if _System.harvester is not None and ia in _System.harvester.image_acquirers:
                        _System.harvester.image_acquirers.remove(ia)
        _log.info("closed %s", self._where)
