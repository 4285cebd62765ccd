"""Camera images recorded by other software: TIFF, PNG, BMP and DaVis files, read as uint16 frames.

Formats
    TIFF (``.tif``, ``.tiff``) through ``tifffile``: one image or a stack of pages, 8 or 16 bits
    per sample (12-bit cameras write 16-bit containers); PNG and BMP through ``imageio`` (v3
    API); DaVis images (``.im7``, ``.imx``, and the ``.set`` of a recorded set with its folder
    of ``B00001.im7`` ...) through LaVision's ``lvpyio`` (:mod:`lfpiv.formats.davis`). Colour
    images, floating-point images and values that do not fit 16 bits are refused.
Frames
    A file holds one frame or several (TIFF pages, DaVis frames); each is an array (rows,
    columns) of uint16 counts, row 0 first as the file stores it. Sensor sizes are given as
    the rig gives them, ``sensor_px = (columns, rows)``.
Layouts (:func:`pair_frames`)
    ``interleaved``: the frames of the files, in order, alternate A, B, A, B (one frame a file,
    or the pages of stacks); ``double-frame``: each file holds the two frames of one pair (a
    two-page TIFF, a DaVis double-frame image, or one image twice the sensor's height whose
    top half is frame A); ``separate``: frames A from one list of files, frames B from another.
Provenance (:func:`source_file`)
    Each source file's absolute path, size and SHA-256 (read in 1 MiB blocks).

Source files are only ever opened for reading, and closed before a function returns: nothing
here modifies, moves or locks them. Every problem is a :class:`FormatError` with one line that
names the file and the fix. PNG, BMP and DaVis files are decoded whole by :func:`inspect_image`
(their libraries have no cheaper check), so that a damaged file is found before an import
writes anything; TIFF files are checked from their headers.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import io
import logging
import os
import re
import stat
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lfpiv.formats.errors import FormatError, one_line

__all__ = [
    "LAYOUTS",
    "CHECKSUMS",
    "SUFFIXES",
    "BitDepth",
    "FrameSource",
    "ImageInfo",
    "PairSource",
    "SourceFile",
    "bit_depth",
    "image_files",
    "inspect_image",
    "natural_sort",
    "odd_names",
    "pair_frames",
    "read_frame",
    "read_image",
    "read_pair",
    "read_sources",
    "source_file",
]

#: File suffixes read here (lower case) and the library family that reads them.
SUFFIXES = {".tif": "tiff", ".tiff": "tiff", ".png": "png", ".bmp": "bmp", ".im7": "davis", ".imx": "davis"}
#: How the frames of a recording are laid out over its files (see the module docstring).
LAYOUTS = ("interleaved", "double-frame", "separate")

_KNOWN = ", ".join(SUFFIXES)


# --- names ------------------------------------------------------------------------------
def _natural_key(path: Path) -> tuple:
    parts = re.split(r"(\d+)", str(path))
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.casefold()) for p in parts), str(path)


def natural_sort(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """The paths in natural order: runs of digits compare as numbers (``img2`` before ``img10``).

    Parameters
    ----------
    paths
        File names or paths.

    Returns
    -------
    list of pathlib.Path
        Sorted; text compares without regard to case.
    """
    return sorted((Path(p) for p in paths), key=_natural_key)


def image_files(pattern: str | os.PathLike[str]) -> list[Path]:
    """The image files a pattern names, in natural order (:func:`natural_sort`).

    Parameters
    ----------
    pattern
        A glob pattern (``rec/cam1_*.tif``; ``**`` descends into folders), a folder (its files
        with a suffix of :data:`SUFFIXES`), or a DaVis set: its ``.set`` file or its folder of
        ``.im7`` / ``.imx`` files.

    Returns
    -------
    list of pathlib.Path
        At least one file.

    Raises
    ------
    FormatError
        If nothing matches, or a DaVis set's folder is missing or holds no images.
    """
    p = Path(pattern)
    if p.suffix.lower() == ".set":
        folder = p.with_suffix("")
        if not folder.is_dir():
            raise FormatError(f"{p}: the DaVis set's folder {folder} is missing; copy the .set file together "
                              "with the folder of the same name")
        p = folder
    if p.is_dir():
        entries = [f for f in p.iterdir() if f.suffix.lower() in SUFFIXES]
        if not entries:
            vectors = any(f.suffix.lower() in (".vc7", ".vec") for f in p.iterdir())
            raise FormatError(f"{p} holds no image files ({_KNOWN})"
                              + ("; it holds DaVis vector fields: import the recorded images instead" if vectors
                                 else "; give the folder of the recording or a pattern such as 'rec/*.tif'"))
    else:
        entries = [Path(f) for f in glob.glob(str(pattern), recursive=True)]
        # a folder a pattern such as 'rec/*' matches is passed over; an entry named as an image is not
        entries = [f for f in entries if f.suffix.lower() in SUFFIXES or not f.is_dir()]
        if not entries:
            raise FormatError(f"no file matches {str(pattern)!r}; check the pattern (quote it, so that the shell "
                              "passes it on unexpanded)")
    entries = natural_sort(entries)
    unusable = [(f, why) for f in entries if (why := _not_a_file(f)) is not None]
    if unusable:
        more = (f" (and {len(unusable) - 1} more entr{'y' if len(unusable) == 2 else 'ies'} that cannot be read: "
                + ", ".join(str(f) for f, _ in unusable[1:4]) + (" ..." if len(unusable) > 4 else "") + ")"
                if len(unusable) > 1 else "")
        f, why = unusable[0]
        # skipping it would shift frames A and B of every later pair: it is named, never passed over
        raise FormatError(f"{f} {why}{more}; every file the pattern matches is a frame, so fix or remove it, or "
                          "narrow the pattern to the recording's files")
    found = entries
    odd = odd_names(found)
    if odd:
        common = re.sub(r"\d+", "*", next(f for f in found if f not in odd).name)
        them = "it" if len(odd) == 1 else "them"
        who = (f"{odd[0]}: its name does" if len(odd) == 1 else
               f"{len(odd)} files ({', '.join(f.name for f in odd[:3])}{' ...' if len(odd) > 3 else ''}) do")
        raise FormatError(f"{who} not follow the names of the other {len(found) - len(odd)} files ({common}), and "
                          f"taken as frames {them} would shift frames A and B of the pairs after {them}; move {them} "
                          f"out of the recording, or narrow the pattern (e.g. '{odd[0].parent / common}')")
    return found


def _not_a_file(path: Path) -> str | None:
    """Why a directory entry cannot be read as an image file (a dangling or looping symbolic
    link, a folder, a pipe, an entry that cannot be examined), or None for a regular file."""
    try:
        st = path.stat()
    except OSError as exc:
        if path.is_symlink():
            target = os.readlink(path)
            if exc.errno == errno.ELOOP:
                return f"is a symbolic link that loops (to {target})"
            return f"is a dangling symbolic link (to {target}, which does not exist)"
        return f"cannot be examined ({one_line(exc.strerror or exc)})"
    if stat.S_ISREG(st.st_mode):
        return None
    kind = "a folder" if stat.S_ISDIR(st.st_mode) else "a named pipe" if stat.S_ISFIFO(st.st_mode) else \
        "a device or socket"
    return f"is {kind}, not an image file"


def _name_pattern(name: str) -> str:
    """A file name with every run of digits as ``#`` (``img_0042.tif``: ``img_#.tif``)."""
    return re.sub(r"\d+", "#", name.casefold())


def odd_names(files: Sequence[Path]) -> list[Path]:
    """The files whose names break the pattern of the others (``background.tif`` among
    ``img_0001.tif`` ...), which taken as frames would shift frames A and B of every later pair.

    A file is odd when no other file's name has its pattern (digits aside) while the names of
    most files repeat a pattern: ``B00001_A.tif``, ``B00001_B.tif`` ... are two patterns, both
    kept. Sets of three files or fewer are not judged.

    Parameters
    ----------
    files
        The files of one camera's pattern, in order.

    Returns
    -------
    list of pathlib.Path
        The odd files, in order; [] if none.
    """
    if len(files) <= 3:
        return []
    patterns = [_name_pattern(f.name) for f in files]
    counts: dict[str, int] = {}
    for pat in patterns:
        counts[pat] = counts.get(pat, 0) + 1
    repeated = sum(n for n in counts.values() if n > 1)
    if repeated * 2 <= len(files):  # no pattern the names follow
        return []
    return [f for f, pat in zip(files, patterns, strict=True) if counts[pat] == 1]


# --- one file ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ImageInfo:
    """What a file holds, from its header (TIFF) or from decoding it (PNG, BMP, DaVis).

    Attributes
    ----------
    path
        The file.
    format
        ``"tiff"``, ``"png"``, ``"bmp"`` or ``"davis"``.
    frames
        Images in the file (TIFF pages, DaVis frames); 1 for PNG and BMP.
    rows, columns
        Size of each image in pixels.
    dtype
        NumPy name of the stored pixel type (``"uint16"``, ``"uint8"``, ...).
    bits_per_sample
        The bit depth the file declares (TIFF ``BitsPerSample``; PNG and BMP from the image
        mode), or None where the format declares none (DaVis).
    times_s
        Each frame's acquisition time in s where the file records one (DaVis
        ``AcqTimeSeries``), else None.
    """

    path: Path
    format: str
    frames: int
    rows: int
    columns: int
    dtype: str
    bits_per_sample: int | None
    times_s: tuple[float, ...] | None = None


def _family(path: Path) -> str:
    fam = SUFFIXES.get(path.suffix.lower())
    if fam is None:
        raise FormatError(f"{path} is not an image file lfpiv reads ({_KNOWN}); convert it, or narrow the file "
                          "pattern to the recording's images")
    return fam


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise FormatError(f"{path} does not exist; check the path")
    if path.is_dir():
        raise FormatError(f"{path} is a folder, not an image file; give the files in it (e.g. '{path}/*.tif')")
    if not os.access(path, os.R_OK):
        raise FormatError(f"{path} cannot be read (permission denied); make it readable for this user")
    if path.stat().st_size == 0:
        raise FormatError(f"{path} is empty (0 bytes): a copy that failed? copy it again from the recording")


@contextlib.contextmanager
def _tiff_errors() -> Iterator[list[str]]:
    """Collect what tifffile logs as errors (damaged tags, offsets past the end) instead of printing it."""
    log = logging.getLogger("tifffile")
    found: list[str] = []

    class _Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.ERROR:
                found.append(record.getMessage())

    handler, propagate = _Collect(), log.propagate
    log.addHandler(handler)
    log.propagate = False
    try:
        yield found
    finally:
        log.removeHandler(handler)
        log.propagate = propagate


def _damaged(path: Path, why: object) -> FormatError:
    return FormatError(f"{path} cannot be read ({one_line(why)}); the file is damaged or truncated: copy it "
                       "again from the recording")


def _tiff_frames(tf: Any, path: Path) -> list[tuple[int, int]]:
    """(series, page in it) of every frame of an open TIFF, in order: the pages of its one series,
    or of several series of one image size and type (a file appended page by page, which tifffile
    reads as one series per page).

    Raises
    ------
    FormatError
        Series of different sizes or types, or colour or multi-channel images.
    """
    series = tf.series
    shapes = {(tuple(s.shape[-2:]), np.dtype(s.dtype).name) for s in series}
    if len(series) > 1 and (len(shapes) > 1 or any(len(s.shape) > 3 for s in series)):
        sizes = ", ".join("x".join(map(str, s.shape)) + f" {np.dtype(s.dtype).name}" for s in series[:3])
        raise FormatError(f"{path} holds images of different sizes or types ({sizes}); export the frames of one "
                          "camera as pages of one size")
    for s in series:
        page = s.pages[0] if len(s.pages) else tf.pages[0]
        if page.samplesperpixel > 1 or len(s.shape) > 3:
            raise FormatError(f"{path} holds {'colour' if page.samplesperpixel > 1 else 'multi-channel'} "
                              f"images (shape {s.shape}); export the camera's greyscale frames")
        if page.bitspersample == 1:
            raise FormatError(f"{path} holds 1-bit (bilevel, black and white) images, not camera counts; export the "
                              "camera's 8- or 16-bit greyscale frames")
    if len(series) == 1:
        s = series[0]
        n = s.shape[0] if len(s.shape) == 3 else 1
        return [(0, k) for k in range(n)]
    return [(i, k) for i, s in enumerate(series) for k in range(s.shape[0] if len(s.shape) == 3 else 1)]


def _tiff_read(tf: Any, at: list[tuple[int, int]], keys: Sequence[int]) -> np.ndarray:
    """Frames ``keys`` (indices into ``at``, :func:`_tiff_frames`) of an open TIFF, decoded."""
    if len({i for i, _ in at}) == 1:  # one series: tifffile reads the pages asked at once
        return tf.asarray(key=list(keys), series=0) if len(at) > 1 else tf.asarray(series=0)
    return np.stack([tf.asarray(series=at[k][0], key=at[k][1]) for k in keys])


def _tiff_info(path: Path) -> ImageInfo:
    import tifffile

    size = path.stat().st_size
    try:
        with _tiff_errors() as errors, tifffile.TiffFile(path) as tf:
            if not len(tf.pages):
                raise _damaged(path, errors[0] if errors else "no image in the file")
            at = _tiff_frames(tf, path)
            s = tf.series[0]
            page = tf.pages[0]
            ends = [o + c for p in tf.pages for o, c in zip(p.dataoffsets, p.databytecounts, strict=False)]
            for ser in tf.series:
                if ser.dataoffset is not None:  # contiguous data (ImageJ stacks may hold one page header only)
                    ends.append(ser.dataoffset + ser.nbytes)
            if ends and max(ends) > size:
                raise _damaged(path, f"its image data end at byte {max(ends)}, the file at {size}")
            if errors:
                raise _damaged(path, errors[0])
            dtype = np.dtype(s.dtype)
            _uint16_dtype(dtype.name, path)
            if dtype.kind == "i" or any(p.compression != 1 for p in tf.pages):
                # compressed or signed pages are decoded now, each, so that a page that does not decode, or holds
                # negative counts, is found before an import writes anything (uncompressed unsigned pages were
                # checked above: their bytes are all in the file)
                for k in range(len(at)):
                    _as_uint16(np.asarray(_tiff_read(tf, at, [k])), path)
                if errors:
                    raise _damaged(path, errors[0])
            rows, columns = (int(n) for n in s.shape[-2:])
            return ImageInfo(path, "tiff", len(at), rows, columns, dtype.name, int(page.bitspersample))
    except FormatError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # tifffile raises TiffFileError, ValueError, struct.error, ... on bad files
        raise _damaged(path, exc) from None


_PIL_BITS = {"1": 1, "L": 8, "P": 8, "I;16": 16, "I;16B": 16, "I;16L": 16, "I;16N": 16, "I": 32}


def _pillow_read(path: Path, raw: bytes | None = None) -> tuple[np.ndarray, int]:
    """The pixels (rows, columns) and the declared bits of a PNG or BMP, through imageio (from
    the file's bytes ``raw`` when they were read already)."""
    import imageio.v3 as iio

    src: Any = path if raw is None else raw
    ext = path.suffix.lower()
    try:
        mode = iio.immeta(src, extension=ext).get("mode", "")
        data = iio.imread(src, extension=ext)
    except MemoryError:
        raise
    except Exception as exc:
        raise _damaged(path, exc) from None
    if mode not in _PIL_BITS or mode == "P" or data.ndim != 2:
        raise FormatError(f"{path} is a colour image (mode {mode or '?'}, shape {data.shape}); export the camera's "
                          "greyscale frames")
    return data, _PIL_BITS[mode]


def inspect_image(path: str | os.PathLike[str]) -> ImageInfo:
    """What an image file holds (see :class:`ImageInfo`), checked for damage.

    Parameters
    ----------
    path
        A file with a suffix of :data:`SUFFIXES`.

    Returns
    -------
    ImageInfo

    Raises
    ------
    FormatError
        If the file is missing, unreadable, of an unknown kind, damaged or truncated, colour, or
        of a pixel type that does not fit uint16.
    """
    path = Path(path)
    fam = _family(path)
    _check_readable(path)
    if fam == "tiff":
        info = _tiff_info(path)
        _uint16_dtype(info.dtype, path)
        return info
    if fam == "davis":
        from lfpiv.formats.davis import read_davis_image

        img = read_davis_image(path)
        frames = _as_uint16(img.frames, path)
        return ImageInfo(path, fam, frames.shape[0], frames.shape[1], frames.shape[2], img.frames.dtype.name, None,
                         img.times_s)
    data, bits = _pillow_read(path)
    _as_uint16(data, path)
    return ImageInfo(path, fam, 1, data.shape[0], data.shape[1], data.dtype.name, bits)


def _uint16_dtype(dtype: str, path: Path) -> None:
    d = np.dtype(dtype)
    if d.kind == "f" or d.kind == "c":
        raise FormatError(f"{path} holds floating-point pixels ({d.name}), not camera counts; import the raw "
                          "recording, not processed images")
    if d.kind == "b":
        raise FormatError(f"{path} holds 1-bit (bilevel, black and white) images, not camera counts; export the "
                          "camera's 8- or 16-bit greyscale frames")
    if d.kind not in "ui":
        raise FormatError(f"{path} holds pixels of type {d.name}; export 8- or 16-bit greyscale images")


def _as_uint16(data: np.ndarray, path: Path) -> np.ndarray:
    """The pixels as uint16, refusing what would change a value."""
    _uint16_dtype(data.dtype.name, path)
    if data.dtype == np.uint16:
        return data
    if data.dtype.itemsize > 1 or data.dtype.kind == "i":
        lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
        if lo < 0:  # refused, not offset: an offset would change every count the reconstruction sees
            raise FormatError(f"{path} holds signed {data.dtype.name} values down to {lo}, and camera counts are never "
                              "negative (a background-subtracted image?); import the raw recording, or add an offset "
                              f"of at least {-lo} and save the frames as unsigned 16-bit")
        if hi > 65535:
            raise FormatError(f"{path} holds {data.dtype.name} values from {lo} to {hi}, outside 0..65535 of 16-bit "
                              "camera counts; export the raw 16-bit frames")
    return data.astype(np.uint16)


def _read(path: Path, frames: Sequence[int] | None = None, raw: bytes | None = None) -> np.ndarray:
    """Frames ``frames`` (all: None) of a file as uint16 (n, rows, columns); from the file's bytes
    ``raw`` when they were read already (TIFF, PNG, BMP; DaVis files are read by path)."""
    fam = _family(path)
    if raw is None:
        _check_readable(path)
    if fam == "tiff":
        import tifffile

        try:
            with _tiff_errors() as errors, tifffile.TiffFile(path if raw is None else io.BytesIO(raw)) as tf:
                at = _tiff_frames(tf, path) if tf.series else []
                n = len(at)
                keys = list(range(n)) if frames is None else list(frames)
                if any(k >= n for k in keys):
                    raise FormatError(f"{path} holds {n} page(s), not page {max(keys)}; was it changed since it was "
                                      "inspected?")
                views = None if raw is None else [_raw_view(raw, tf.series[at[k][0]].pages[at[k][1]], tf.byteorder)
                                                  for k in keys]
                if views is not None and all(v is not None for v in views):
                    data = np.stack(views)  # uncompressed pages of a file read already: no decoding
                else:
                    data = _tiff_read(tf, at, keys)
                if errors:
                    raise _damaged(path, errors[0])
        except FormatError:
            raise
        except MemoryError:
            raise
        except Exception as exc:
            raise _damaged(path, exc) from None
        data = np.asarray(data)
        return _as_uint16(data.reshape(len(keys), *data.shape[-2:]), path)
    if fam == "davis":
        from lfpiv.formats.davis import read_davis_image

        all_frames = _as_uint16(read_davis_image(path).frames, path)
    else:
        all_frames = _as_uint16(_pillow_read(path, raw)[0], path)[None]
    if frames is None:
        return all_frames
    if any(k >= len(all_frames) for k in frames):
        raise FormatError(f"{path} holds {len(all_frames)} frame(s), not frame {max(frames)}; was it changed since "
                          "it was inspected?")
    return all_frames[list(frames)]


def _raw_view(raw: bytes, page: Any, byteorder: str) -> np.ndarray | None:
    """An uncompressed, contiguous 16-bit TIFF page as a view of the file's bytes (None for any
    other page: tifffile decodes those)."""
    try:
        if (page is None or page.compression != 1 or page.predictor != 1 or page.fillorder != 1
                or page.sampleformat != 1 or page.bitspersample != 16 or page.samplesperpixel != 1
                or not page.is_contiguous or len(page.shape) != 2):
            return None
        offset, count = page.dataoffsets[0], int(np.prod(page.shape)) * 2
    except (AttributeError, IndexError, TypeError):
        return None
    if offset + count > len(raw):
        return None  # truncated: tifffile's own read says how
    return np.frombuffer(raw, dtype=np.dtype("u2").newbyteorder(byteorder), count=count // 2,
                         offset=offset).reshape(page.shape)


def read_image(path: str | os.PathLike[str], *, frame: int | None = None) -> np.ndarray:
    """The pixels of an image file as uint16 counts.

    Parameters
    ----------
    path
        A file with a suffix of :data:`SUFFIXES`.
    frame
        One frame (TIFF page, DaVis frame) to read; None: all.

    Returns
    -------
    numpy.ndarray
        uint16 (rows, columns) for ``frame``, else (frames, rows, columns).

    Raises
    ------
    FormatError
        As :func:`inspect_image`, or if the file holds no frame ``frame``.
    """
    path = Path(path)
    if frame is None:
        return _read(path)
    return _read(path, [int(frame)])[0]


@dataclass(frozen=True)
class BitDepth:
    """The bit depth a file declares and the bits its values need.

    Attributes
    ----------
    declared
        Bits per sample the file declares (TIFF ``BitsPerSample``, PNG/BMP mode), or None.
    largest
        The largest value in the file, counts.
    needed
        Bits that value needs (4095 needs 12; 0 needs 0).
    """

    declared: int | None
    largest: int
    needed: int


def bit_depth(path: str | os.PathLike[str]) -> BitDepth:
    """The declared bit depth of an image file and the largest value it holds (it reads all frames).

    Parameters
    ----------
    path
        A file with a suffix of :data:`SUFFIXES`.

    Returns
    -------
    BitDepth

    Raises
    ------
    FormatError
        As :func:`inspect_image`.
    """
    info = inspect_image(path)
    data = _read(Path(path))
    top = int(data.max()) if data.size else 0
    return BitDepth(info.bits_per_sample, top, top.bit_length())


# --- frames, pairs and the checks against the camera ------------------------------------
@dataclass(frozen=True)
class FrameSource:
    """Where one frame of a recording lies.

    Attributes
    ----------
    path
        The file.
    frame
        Page (TIFF) or frame (DaVis) in the file, from 0.
    half
        None: the whole image; 0: its top half; 1: its bottom half (a double-frame image twice
        the sensor's height holds frame A on top).
    """

    path: Path
    frame: int = 0
    half: int | None = None

    def __str__(self) -> str:
        where = f" frame {self.frame}" if self.frame else ""
        return f"{self.path}{where}{'' if self.half is None else (' (top half)', ' (bottom half)')[self.half]}"


@dataclass(frozen=True)
class PairSource:
    """The two frames of one pair: ``a`` (first pulse) and ``b`` (second pulse)."""

    a: FrameSource
    b: FrameSource


def _frames_in_order(infos: Sequence[ImageInfo]) -> list[FrameSource]:
    return [FrameSource(i.path, k) for i in infos for k in range(i.frames)]


def _double_frame(info: ImageInfo, camera: int) -> PairSource:
    if info.frames == 1:
        if info.rows % 2:
            raise FormatError(f"{info.path} holds one image of {info.rows} rows, an odd number, so not two frames "
                              "one above the other; choose the interleaved or separate layout")
        return PairSource(FrameSource(info.path, 0, 0), FrameSource(info.path, 0, 1))
    if info.frames == 2 and camera == 0:
        return PairSource(FrameSource(info.path, 0), FrameSource(info.path, 1))
    if info.format == "davis" and info.frames % 2 == 0:  # DaVis: frames A, B of camera 1, then of camera 2, ...
        if camera >= info.frames // 2:
            raise FormatError(f"{info.path} holds the frames of {info.frames // 2} camera(s), not of camera "
                              f"{camera + 1}; choose a camera from 1 to {info.frames // 2}")
        return PairSource(FrameSource(info.path, 2 * camera), FrameSource(info.path, 2 * camera + 1))
    if camera:
        raise FormatError(f"{info.path} holds {info.frames} frame(s), and only DaVis files hold the frames of more "
                          "than one camera; leave the camera at 1")
    raise FormatError(f"{info.path} holds {info.frames} frames, and a double-frame file holds two (or one image "
                      "twice the sensor's height); for a stack of pairs choose the interleaved layout")


def _frame_shape(src: FrameSource, info: ImageInfo) -> tuple[int, int]:
    return (info.rows // 2 if src.half is not None else info.rows), info.columns


def pair_frames(files: Sequence[str | os.PathLike[str]], *, layout: str,
                files_b: Sequence[str | os.PathLike[str]] | None = None, camera: int = 0,
                sensor_px: tuple[int, int] | None = None,
                unpaired: list[FrameSource] | None = None) -> list[PairSource]:
    """Where the frames A and B of each pair lie, for one of the :data:`LAYOUTS`.

    Every file is inspected (:func:`inspect_image`) and every frame must have the same size
    (and the sensor's, where given), so a set that cannot be imported is refused before
    anything is read for good.

    Parameters
    ----------
    files
        The recording's files in order (:func:`image_files`); frames A for ``separate``.
    layout
        ``"interleaved"``, ``"double-frame"`` or ``"separate"`` (see the module docstring).
    files_b
        Frames B, for ``separate`` only, in the order of ``files``.
    camera
        For DaVis files that hold the frames of several cameras: which one, from 0.
    sensor_px
        (columns, rows) of the camera's sensor, as the rig gives it; None: not checked.
    unpaired
        Where a last frame A without its frame B (an odd number of frames, interleaved) goes,
        for the caller to record as lost; None: such a set is refused.

    Returns
    -------
    list of PairSource
        One per pair, in order.

    Raises
    ------
    FormatError
        For an unknown layout, a file that cannot be inspected, a frame count that does not fit
        the layout, frames of mixed sizes, or frames that are not the sensor's size.
    """
    if layout not in LAYOUTS:
        raise FormatError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    if (layout == "separate") != (files_b is not None):
        raise FormatError("the separate layout needs the files of frames B as well, and only it takes them"
                          if layout == "separate" else f"the {layout} layout takes one list of files, not frames B")
    if not files:
        raise FormatError("no image files given; check the file pattern")
    infos: dict[Path, ImageInfo] = {}
    bad: list[tuple[Path, FormatError]] = []
    for p in [*files, *(files_b or [])]:
        try:
            infos[Path(p)] = inspect_image(p)
        except FormatError as exc:  # every file that cannot be used is named, not only the first
            bad.append((Path(p), exc))
    if bad:
        more = "" if len(bad) == 1 else (f" (and {len(bad) - 1} more file(s) that cannot be used: "
                                         + ", ".join(str(p) for p, _ in bad[1:4]) + (" ..." if len(bad) > 4 else "")
                                         + ")")
        raise FormatError(f"{bad[0][1]}{more}")
    seq = [infos[Path(p)] for p in files]
    if layout == "interleaved":
        frames = _frames_in_order(seq)
        if len(frames) % 2 and unpaired is not None:
            unpaired.append(frames.pop())
        if len(frames) % 2:
            raise FormatError(f"the files hold {len(frames)} frames, an odd number, so the last ({frames[-1]}) has no "
                              "partner in the interleaved layout; remove it, or check the layout")
        pairs = [PairSource(a, b) for a, b in zip(frames[0::2], frames[1::2], strict=True)]
    elif layout == "double-frame":
        pairs = [_double_frame(i, camera) for i in seq]
    else:
        frames_a, frames_b = _frames_in_order(seq), _frames_in_order([infos[Path(p)] for p in files_b or []])
        if len(frames_a) != len(frames_b):
            raise FormatError(f"the files of frames A hold {len(frames_a)} frames and those of frames B "
                              f"{len(frames_b)}; each frame A needs its frame B: check both patterns")
        pairs = [PairSource(a, b) for a, b in zip(frames_a, frames_b, strict=True)]
    if not pairs:
        raise FormatError(f"the files hold a single frame ({unpaired[-1] if unpaired else files[0]}), no pair; a "
                          "double-frame recording needs frames A and B")
    first = pairs[0].a
    shape0 = _frame_shape(first, infos[first.path])
    for p in pairs:
        for src in (p.a, p.b):
            shape = _frame_shape(src, infos[src.path])
            if sensor_px is not None:
                _check_sensor(shape, src, sensor_px, whole=infos[src.path].rows if src.half is None else None)
            elif shape != shape0:
                raise FormatError(f"{src} is {shape[1]} x {shape[0]} px but {first} is {shape0[1]} x {shape0[0]} px: "
                                  "a set of mixed sizes; import the files of one camera and one setting at a time")
    return pairs


def _check_sensor(shape: tuple[int, int], src: FrameSource, sensor_px: tuple[int, int], *,
                  whole: int | None = None) -> None:
    cols, rows = (int(n) for n in sensor_px)
    if shape == (rows, cols):
        return
    hint = ""
    if whole == 2 * rows and shape[1] == cols:
        hint = " (two frames one above the other: choose the double-frame layout)"
    raise FormatError(f"{src} is {shape[1]} x {shape[0]} px (columns x rows){hint}, but the camera's sensor_px is "
                      f"[{cols}, {rows}]; check sensor_px in the rig, or that these are this camera's files")


def _check_bits(image: np.ndarray, src: FrameSource, bit_depth: int) -> None:
    top = int(image.max()) if image.size else 0
    if top < (1 << bit_depth):
        return
    shift = 16 - bit_depth
    aligned = shift > 0 and not np.any(image & np.uint16((1 << shift) - 1))
    hint = (f"; all its values are multiples of {1 << shift}: {bit_depth}-bit data shifted left by {shift} bits, "
            f"to be shifted back (value >> {shift})" if aligned else
            "; check bit_depth in the rig, or that these are this camera's files")
    raise FormatError(f"{src} holds values up to {top} ({top.bit_length()} bits), more than the camera's bit_depth "
                      f"of {bit_depth} allows (at most {(1 << bit_depth) - 1}){hint}")


def _checked(image: np.ndarray, src: FrameSource, sensor_px: tuple[int, int] | None,
             bit_depth: int | None) -> np.ndarray:
    if src.half is not None:
        if image.shape[0] % 2:
            raise FormatError(f"{src.path} holds an image of {image.shape[0]} rows, an odd number, so not two frames "
                              "one above the other; choose the interleaved or separate layout")
        h = image.shape[0] // 2
        image = image[h:] if src.half else image[:h]
    if sensor_px is not None:
        _check_sensor(image.shape, src, sensor_px)
    if bit_depth is not None:
        _check_bits(image, src, bit_depth)
    return np.ascontiguousarray(image)


def read_frame(source: FrameSource, *, sensor_px: tuple[int, int] | None = None,
               bit_depth: int | None = None) -> np.ndarray:
    """One frame as uint16 (rows, columns), checked against the camera.

    Parameters
    ----------
    source
        Where the frame lies (:func:`pair_frames`).
    sensor_px
        (columns, rows) of the sensor; None: not checked.
    bit_depth
        The camera's bits per pixel (the rig's ``bit_depth``); a larger value is refused.

    Returns
    -------
    numpy.ndarray
        uint16 (rows, columns).

    Raises
    ------
    FormatError
        As :func:`inspect_image`, or for a frame of another size than the sensor's, or a value
        that needs more bits than ``bit_depth``.
    """
    return _checked(_read(Path(source.path), [source.frame])[0], source, sensor_px, bit_depth)


def read_pair(pair: PairSource, *, sensor_px: tuple[int, int] | None = None,
              bit_depth: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frames A and B of a pair as uint16 (rows, columns) each, a file that holds both read once.

    Parameters and errors as :func:`read_frame`.
    """
    a, b = pair.a, pair.b
    if Path(a.path) == Path(b.path):
        keys = sorted({a.frame, b.frame})
        data = _read(Path(a.path), keys)
        img_a, img_b = data[keys.index(a.frame)], data[keys.index(b.frame)]
    else:
        img_a, img_b = _read(Path(a.path), [a.frame])[0], _read(Path(b.path), [b.frame])[0]
    return _checked(img_a, a, sensor_px, bit_depth), _checked(img_b, b, sensor_px, bit_depth)


# --- provenance -------------------------------------------------------------------------
#: Checksums a source file's provenance may carry: SHA-256 (what ``sha256sum`` prints) and CRC32C
#: (the Castagnoli CRC that zarr's and cloud storage's checksums are, hardware-accelerated: about
#: six times faster, which matters when a recording is read at disk speed).
CHECKSUMS = ("sha256", "crc32c")


class _Crc32c:
    """CRC32C with hashlib's update / hexdigest (``google-crc32c``, which zarr brings)."""

    def __init__(self) -> None:
        import google_crc32c

        self._c = google_crc32c.Checksum()

    def update(self, data: bytes) -> None:
        self._c.update(data)

    def hexdigest(self) -> str:
        return self._c.digest().hex()


def _digest(checksum: str) -> Any:
    if checksum not in CHECKSUMS:
        raise FormatError(f"unknown checksum {checksum!r}; choose one of {', '.join(CHECKSUMS)}")
    return hashlib.sha256() if checksum == "sha256" else _Crc32c()


@dataclass(frozen=True)
class SourceFile:
    """A source file as an imported run records it: absolute path, size in bytes, and its SHA-256
    or CRC32C (hex), whichever was asked for (the other is None)."""

    path: str
    size: int
    sha256: str | None = None
    crc32c: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """``{"path": ..., "size": ..., "sha256": ...}`` or ``{..., "crc32c": ...}`` (JSON-ready)."""
        return {k: v for k, v in asdict(self).items() if v is not None}


def _source(path: Path, size: int, checksum: str, digest: Any) -> SourceFile:
    return SourceFile(str(path.resolve()), size, **{checksum: digest.hexdigest()})


def read_sources(path: str | os.PathLike[str], sources: Sequence[FrameSource], *,
                 sensor_px: tuple[int, int] | None = None, bit_depth: int | None = None,
                 checksum: str = "sha256") -> tuple[list[np.ndarray], SourceFile]:
    """The frames ``sources`` of one file, checked as :func:`read_frame` checks them, and the
    file's provenance (:func:`source_file`), from ONE read of the file: an import reads every
    byte of a recording once, for its pixels and its checksum alike.

    Parameters
    ----------
    path
        The file.
    sources
        Frames of that file (:func:`pair_frames`), in any order.
    sensor_px, bit_depth
        As :func:`read_frame`.
    checksum
        One of :data:`CHECKSUMS`.

    Returns
    -------
    frames : list of numpy.ndarray
        uint16 (rows, columns), one per source, in the order given.
    source : SourceFile
        The file's absolute path, size and checksum.

    Raises
    ------
    FormatError
        As :func:`read_frame` and :func:`source_file`.
    """
    p = Path(path)
    _check_readable(p)
    if _family(p) == "davis":  # lvpyio reads by path: the checksum is a second (cached) read
        images = _read(p, sorted({s.frame for s in sources}))
        prov = source_file(p, checksum=checksum)
    else:
        try:
            raw = p.read_bytes()
        except OSError as exc:
            raise FormatError(f"{p} cannot be read ({one_line(exc.strerror or exc)}); check the file and its "
                              "permissions") from None
        digest = _digest(checksum)
        digest.update(raw)
        prov = _source(p, len(raw), checksum, digest)
        images = _read(p, sorted({s.frame for s in sources}), raw)
    at = {k: i for i, k in enumerate(sorted({s.frame for s in sources}))}
    return [_checked(images[at[s.frame]], s, sensor_px, bit_depth) for s in sources], prov


def source_file(path: str | os.PathLike[str], *, block: int = 1 << 20, checksum: str = "sha256") -> SourceFile:
    """Path, size and checksum (:data:`CHECKSUMS`) of a source file, read in blocks of ``block`` bytes.

    Raises
    ------
    FormatError
        If the file is missing or cannot be read.
    """
    p = Path(path)
    _check_readable(p)
    digest = _digest(checksum)
    size = 0
    try:
        with open(p, "rb") as fh:
            while chunk := fh.read(block):
                digest.update(chunk)
                size += len(chunk)
    except OSError as exc:
        raise FormatError(f"{p} cannot be read ({one_line(exc.strerror or exc)}); check the file and its "
                          "permissions") from None
    return _source(p, size, checksum, digest)
