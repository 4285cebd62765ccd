"""The chunks of a run's arrays: which hold a slab, whether they are stored, whether they decode,
and how a message names one that is damaged."""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec

#: What every message about damage says to do.
RESTORE = "restore it from a copy of the run"


def checksummed(array: zarr.Array) -> bool:
    """Whether the chunks of ``array`` carry a CRC-32C (zarr's ``crc32c`` codec). Those of a
    run store that has them are all stored when written, so a missing one is damage; stores
    made before checksums did not store chunks equal to the fill value."""
    return any(isinstance(c, Crc32cCodec) for c in getattr(array.metadata, "codecs", ()))


def chunk_coords(array: zarr.Array, lead: tuple[int | slice, ...]) -> list[tuple[int, ...]]:
    """Chunk-grid coordinates of the chunks that hold ``array[lead]`` (``lead``: along the first
    axes, indices or ranges ``slice(start, stop)`` of step 1, such as a volume's planes), in C
    order."""
    axes = []
    for i, c, n in zip(lead, array.chunks, array.shape, strict=False):
        if isinstance(i, slice):
            lo, hi, _ = i.indices(n)
            axes.append(range(lo // c, (hi - 1) // c + 1))
        else:
            axes.append((int(i) // int(c),))
    rest = array.cdata_shape[len(lead):]
    return list(itertools.product(*axes, *(range(n) for n in rest)))


def chunk_key(array: zarr.Array, coords: tuple[int, ...]) -> str:
    """The chunk's key inside its array (e.g. ``c/3/1/0/0``)."""
    return array.metadata.encode_chunk_key(coords)


def chunk_stored(array: zarr.Array, coords: tuple[int, ...]) -> bool:
    """Whether the chunk is stored (run stores are local directories)."""
    root = Path(array.store_path.store.root)
    return os.path.exists(root / array.path / chunk_key(array, coords))


def decode_problem(exc: Exception) -> str:
    """What a failed read of a stored chunk says about it."""
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    if "checksum" in msg:
        return "is damaged (its checksum does not match its bytes)"
    if "reshape" in msg:
        return f"decodes to the wrong size ({msg})"
    if isinstance(exc, OSError):
        return f"cannot be read ({exc.strerror or msg})"
    return f"cannot be decoded ({type(exc).__name__}: {msg})"


def chunk_problem(array: zarr.Array, coords: tuple[int, ...], *, required: bool) -> str | None:
    """What is wrong with one chunk, or None: ``"is missing"`` (only if ``required``), or
    damaged, undecodable or the wrong size (read through zarr, which checks the checksum)."""
    if not chunk_stored(array, coords):
        return "is missing" if required else None
    try:
        array.get_block_selection(coords)
    except Exception as exc:  # noqa: BLE001 - every codec fails in its own way
        return decode_problem(exc)
    return None


def damage(array: zarr.Array, where: str, coords: tuple[int, ...], problem: str) -> str:
    """One line naming a damaged chunk: the array, what it holds (``where``) and the chunk."""
    hint = ""
    if problem == "is missing" and not checksummed(array):
        hint = " (or, in a store written before lfpiv kept checksums, one that held only its fill value)"
    return f"{array.path} {where}: chunk {chunk_key(array, coords)} {problem}{hint}; {RESTORE}"


def read_slab(array: zarr.Array, lead: tuple[int | slice, ...], where: str) -> tuple[np.ndarray | None, str | None]:
    """``array[lead]``, or None and the line naming the first of its chunks that fails to decode."""
    try:
        return array[lead], None
    except Exception as exc:  # noqa: BLE001 - find the chunk and say what is wrong with it
        for c in chunk_coords(array, lead):
            problem = chunk_problem(array, c, required=False)
            if problem is not None:
                return None, damage(array, where, c, problem)
        return None, f"{array.path} {where}: {decode_problem(exc)}; {RESTORE}"


def dtype_problem(array: zarr.Array, expected: type | str) -> str | None:
    """A line if ``array`` does not hold the data type the layout gives it (``"str"``: text)."""
    if expected == "str":
        ok = np.dtype(array.dtype).kind in "OTU"
    else:
        ok = np.dtype(array.dtype) == np.dtype(expected)
    if ok:
        return None
    want = "text" if expected == "str" else np.dtype(expected).name
    return (f"{array.path} holds {array.dtype}, but the layout says {want} (its zarr.json was edited or damaged); "
            f"{RESTORE}")
