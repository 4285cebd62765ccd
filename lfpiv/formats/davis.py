"""DaVis files through LaVision's ``lvpyio``: recorded images in, vector fields out.

Images
    ``.im7`` (and the older ``.imx``) files hold one buffer of frames: a double-frame PIV
    recording holds frames A and B of each camera in turn (A, B of camera 1, then of camera 2).
    A recorded set is a ``.set`` file beside a folder of ``B00001.im7`` ... files
    (:func:`lfpiv.formats.images.image_files` lists them). DaVis records each frame's time as
    the attribute ``AcqTimeSeries`` (e.g. ``"100250 µs"``; older files as ``AcqTimeSeries0``,
    ``AcqTimeSeries1`` ... on the buffer): :func:`davis_timing` turns it into the time between
    frames A and B and the pair rate.
Vector fields
    :func:`write_davis_set` writes a DaVis vector set: ``<name>.set`` and the folder ``<name>/``
    with one ``B00001.vc7`` ... per pair, each a 3D3C field: one plane per z of the grid, the
    components U0, V0, W0 in m/s (float32), the positions from the frame's scales in metres.
    lvpyio places vector ``i`` of an axis at ``offset + slope * grid * (i + 0.5)`` (the centre
    of its interrogation window), so the scales are written as slope = spacing, offset = first
    centre - spacing / 2, grid = 1. Outliers that were not replaced are disabled vectors
    (``ENABLED`` 0), missing ones are masked (``MASK`` 0); vorticity, divergence, Q-criterion,
    peak ratio and the flags are typed scalars (``TS:...``), so replaced vectors are told by
    ``TS:flags`` (DaVis's own "filled" mark, ``ACTIVE_CHOICE`` 4, exists only in fields of
    four choices: a single-choice field, as written here, drops it). Each frame's
    ``AcqTimeSeries`` is the pair's time.

What lvpyio 1.5 can do (tried): read and write ``.im7`` images (single and multi-frame, uint16,
with frame attributes), image and vector sets (``write_set`` / ``read_set``), and 2D or 3D,
2C or 3C vector fields (``.vc7``) with typed scalars. What it cannot: write a valid ``.imx``
(the files it writes read back with twice the rows and a broken second frame), so ``.imx`` is
read here but was never tested with a file from DaVis itself. Note that ``lvpyio.write_set``
empties the folder it writes into; :func:`write_davis_set` writes into a new folder and
moves it into place.

lvpyio is LaVision's package (free to use, not to redistribute); DaVis files need it, and
everything else here works without it.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.formats.errors import FormatError, one_line

if TYPE_CHECKING:
    from lfpiv.formats.fields import Fields
    from lfpiv.formats.images import ImageInfo

__all__ = ["DavisImage", "DavisTiming", "davis_timing", "read_davis_image", "write_davis_set"]

_INSTALL = "install it with: pip install 'lfpiv[davis]' (or pip install lvpyio)"


def _lvpyio() -> Any:
    try:
        import lvpyio
    except ImportError as exc:
        raise FormatError(f"DaVis files need LaVision's lvpyio, which cannot be imported ({one_line(exc)}); "
                          f"{_INSTALL}") from None
    return lvpyio


# --- images -----------------------------------------------------------------------------
@dataclass(frozen=True)
class DavisImage:
    """The frames of one DaVis image file.

    Attributes
    ----------
    frames
        (frames, rows, columns) raw pixel values as stored (uint16 for camera images).
    times_s
        Each frame's acquisition time in s (``AcqTimeSeries``), or None where the file has none.
    """

    frames: np.ndarray
    times_s: tuple[float, ...] | None


_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6, "ns": 1e-9}


def _seconds(text: object) -> float | None:
    """``"100250 µs"`` -> 0.10025; None for anything else (``"no acquisition time series value"``)."""
    m = re.fullmatch(r"\s*([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(\S+)\s*", str(text))
    if not m or m.group(2) not in _TIME_UNITS:
        return None
    return float(m.group(1)) * _TIME_UNITS[m.group(2)]


def read_davis_image(path: str | Path) -> DavisImage:
    """The frames and frame times of a DaVis image file (``.im7``, ``.imx``).

    Parameters
    ----------
    path
        The file.

    Returns
    -------
    DavisImage

    Raises
    ------
    FormatError
        If lvpyio is missing, the file cannot be read (missing, damaged, truncated, not an image),
        or holds colour (Bayer) images or volumes.
    """
    lv = _lvpyio()
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the Bayer-pattern warning; refused below
            buf = lv.read_buffer(str(path))
    except MemoryError:
        raise
    except Exception as exc:  # lvpyio raises RuntimeError("Invalid header.", "File not of type IM7.", ...)
        raise FormatError(f"{path} cannot be read as a DaVis image ({one_line(exc)}); the file is damaged or "
                          "truncated: copy it again from the recording") from None
    frames = list(buf.frames)
    if not frames or any(type(f).__name__ != "ImageFrame" for f in frames):
        raise FormatError(f"{path} holds no camera images (a DaVis vector or scalar field?); import the recorded "
                          "images")
    if any(str(f.attributes.get("RGBFrame", "0")) != "0" for f in frames):
        raise FormatError(f"{path} holds colour (Bayer pattern) images; record with the camera in greyscale mode")
    planes = [f.images for f in frames]
    if any(len(p) != 1 for p in planes):
        raise FormatError(f"{path} holds frames of {max(len(p) for p in planes)} planes (volumes), not camera "
                          "images; import the recorded images")
    data = np.stack([np.asarray(p[0]) for p in planes])
    times = [_seconds(f.attributes.get("AcqTimeSeries")) for f in frames]
    if any(t is None for t in times):  # older files: AcqTimeSeries0, 1, ... on the buffer
        times = [_seconds(buf.attributes.get(f"AcqTimeSeries{k}")) for k in range(len(frames))]
    return DavisImage(data, None if any(t is None for t in times) else tuple(float(t) for t in times))  # type: ignore[arg-type]


@dataclass(frozen=True)
class DavisTiming:
    """The timing DaVis recorded with a set of double-frame images.

    Attributes
    ----------
    dt_s
        Time between frames A and B of a pair, s; None where the files do not say.
    rate_hz
        Pairs per second (from the times of the first two files' frames A); None where unknown.
    """

    dt_s: float | None
    rate_hz: float | None


def davis_timing(infos: Sequence[ImageInfo], *, camera: int = 0) -> DavisTiming:
    """The time between frames and the pair rate of double-frame DaVis files.

    Parameters
    ----------
    infos
        The files in order, as :func:`lfpiv.formats.images.inspect_image` describes them.
    camera
        Which camera's frames (0: frames 0 and 1 of each file, 1: frames 2 and 3, ...).

    Returns
    -------
    DavisTiming
        Fields are None where the files carry no times (or the times make no sense).
    """
    a, b = 2 * camera, 2 * camera + 1
    times = [i.times_s for i in infos]
    dt = None
    if times and times[0] is not None and len(times[0]) > b and times[0][b] > times[0][a]:
        dt = times[0][b] - times[0][a]
    rate = None
    if len(times) > 1 and times[0] is not None and times[1] is not None and len(times[0]) > a and len(times[1]) > a:
        step = times[1][a] - times[0][a]
        rate = 1.0 / step if step > 0 else None
    return DavisTiming(dt, rate)


# --- vector fields ----------------------------------------------------------------------
_EXPORTED = re.compile(r"B\d{5}\.vc7")


def _vector_buffer(lv: Any, fields: Fields, i: int) -> Any:
    """Pair ``i`` of the fields as an lvpyio buffer of one 3D3C vector frame (see the module docstring)."""
    from lvpyio.types.buffer import Buffer
    from lvpyio.types.component import Component, Components
    from lvpyio.types.frame import VectorFrame
    from lvpyio.types.scale import Scale, Scales

    from lfpiv import __version__
    from lfpiv.formats.fields import QUANTITIES, global_attributes, uniform_spacing

    x, y, z = fields.coords_m()
    scales = []
    for c, axis in ((x, "x"), (y, "y"), (z, "z")):
        step = uniform_spacing(c, axis=axis)
        scales.append(Scale(step, float(c[0]) - 0.5 * step, "m", axis))  # lvpyio: offset + slope * (i + 0.5)
    vel = np.asarray(fields.velocity[i], dtype=np.float64)
    finite = np.isfinite(vel).all(axis=-1)
    flags = np.asarray(fields.flags[i], dtype=np.uint8)
    disabled = ((flags & FLAG_OUTLIER) > 0) & ((flags & FLAG_REPLACED) == 0)

    def planes(a: np.ndarray, dtype: Any) -> list[np.ndarray]:
        return [np.ascontiguousarray(p, dtype=dtype) for p in a]

    comps = Components()
    speed = Scale(1.0, 0.0, "m/s", "velocity")
    for k, name in enumerate(("U0", "V0", "W0")):
        comps[name] = Component(speed, planes(np.where(finite, vel[..., k], 0.0), np.float32))
    comps["ENABLED"] = Component(Scale(), planes(~disabled, np.uint8))
    comps["MASK"] = Component(Scale(), planes(finite, np.uint8))
    for q in QUANTITIES[3:]:  # the derived scalars, peak ratio and flags
        data = np.nan_to_num(np.asarray(q.get(fields)[i], dtype=np.float64), nan=0.0)
        dtype = np.int32 if q.name == "flags" else np.float32
        comps[f"TS:{q.name}"] = Component(Scale(1.0, 0.0, q.symbol if q.units != "1" else "", q.long_name),
                                          planes(data, dtype))
    when = {"AcqTimeSeries": f"{float(fields.time_s[i]) * 1e6:.3f} \u00b5s"}  # as DaVis writes it
    frame = VectorFrame(comps, Scales(*scales, speed), when, lv.Grid(1, 1, 1), 1)
    g = global_attributes(fields)
    attrs = {"lfpiv_version": __version__, "lfpiv_pair": str(fields.pairs[i]), "lfpiv_dt_s": f"{g['dt_s']:.9g}",
             "lfpiv_windows_xyz_voxels": g["windows_xyz_voxels"], "lfpiv_frame": g["frame"]}
    return Buffer([frame], attrs)


def write_davis_set(out_dir: str | Path, fields: Fields, *, name: str = "vectors") -> list[Path]:
    """Write the fields as a DaVis vector set: ``<name>.set`` and ``<name>/B00001.vc7`` ... (one per pair).

    The set is written into a new folder beside the target and then moved into place, so an
    earlier export stays whole until the new one is complete (lvpyio empties the folder it
    writes into, so it never writes into the target itself).

    Parameters
    ----------
    out_dir
        An existing folder.
    fields
        The fields; the grid must be evenly spaced.
    name
        Name of the set (its ``.set`` file and its folder).

    Returns
    -------
    list of pathlib.Path
        The ``.set`` file and the set's folder.

    Raises
    ------
    FormatError
        If lvpyio is missing, the grid is not evenly spaced, or ``<name>/`` holds files that are
        not an earlier export's ``B00001.vc7`` ... (they would be lost).
    """
    import shutil
    import tempfile

    lv = _lvpyio()
    out = Path(out_dir)
    folder, set_file = out / name, out / f"{name}.set"
    if folder.is_symlink() or set_file.is_symlink():
        raise FormatError(f"{folder if folder.is_symlink() else set_file} is a symbolic link, and export does not "
                          "write through links; remove it or choose another folder")
    if folder.exists():
        other = sorted(p.name for p in folder.iterdir() if not (p.is_file() and _EXPORTED.fullmatch(p.name)))
        if other:
            raise FormatError(f"{folder} holds {other[0]}{f' and {len(other) - 1} more' if len(other) > 1 else ''}, "
                              "which is not part of an earlier DaVis export and would be lost; move it, or choose "
                              "another folder")
    buffers = [_vector_buffer(lv, fields, i) for i in range(len(fields.pairs))]
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.partial-", dir=out))
    try:
        lv.write_set(buffers, str(tmp / name))
        earlier = tmp / "earlier"
        if folder.exists():
            folder.rename(earlier)
        try:
            (tmp / name).rename(folder)
        except BaseException:
            if earlier.exists():
                earlier.rename(folder)
            raise
        os.replace(tmp / f"{name}.set", set_file)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [set_file, folder]
