"""What every part of the run store shares: its error, format name and version, the zarr group
it is written through, and the attributes each part of :class:`lfcore.runstore.RunStore` uses."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import zarr

from lfcore.zarrstore import described_array

FORMAT = "lfpiv-run"
FORMAT_VERSION = 1
STATES = ("recording", "complete", "aborted")

#: zarr's runtime setting for every array of a run: store each chunk written, even one that
#: equals the fill value (a black frame, an empty volume, a pair without vectors), so that a
#: chunk missing from a recorded pair is damage, never "all fill" (and zarr need not compare
#: each chunk with the fill value before writing it).
WRITE_ALL_CHUNKS = {"write_empty_chunks": True}


class RunStoreError(ValueError):
    """A run store that cannot be created or read; the message says what to do."""


class StoreGroup(zarr.Group):
    """A group of a run store: its arrays, and those of its groups, are opened with
    :data:`WRITE_ALL_CHUNKS`, whoever writes through them (the recorder's id arrays, a Dask
    worker's volumes)."""

    def __getitem__(self, path: str) -> Any:
        node = super().__getitem__(path)
        if isinstance(node, zarr.Array):
            return node.with_config(WRITE_ALL_CHUNKS)
        return StoreGroup(node._async_group)

    def create_group(self, name: str, **kwargs: Any) -> StoreGroup:
        return StoreGroup(super().create_group(name, **kwargs)._async_group)

    def create_array(self, name: str, **kwargs: Any) -> Any:
        kwargs.setdefault("config", WRITE_ALL_CHUNKS)
        return super().create_array(name, **kwargs)


def run_array(group: zarr.Group, name: str, units: str, axes: list[str], description: str,
              **create: Any) -> zarr.Array:
    """:func:`lfcore.zarrstore.described_array` for a run store: every chunk checksummed (zarr's
    ``crc32c`` codec) and stored when written (:data:`WRITE_ALL_CHUNKS`)."""
    create.setdefault("config", WRITE_ALL_CHUNKS)
    return described_array(group, name, units, axes, description, checksum=True, **create)


class Part:
    """Base of the parts :class:`lfcore.runstore.RunStore` is made of (frames, drops, truth,
    volumes, vectors, replacement, integrity): each holds one kind of data of the run, all of
    them in :attr:`group`, the run's root group, at :attr:`path`; a part may use the others'
    members, which :class:`~lfcore.runstore.RunStore` puts together."""

    group: zarr.Group
    path: Path
    # where volumes/ and vectors/ are written: themselves, or their pending replacement
    _target: dict[str, str]
    # what the parts use of each other (and of lfcore.zarrstore.RigStore), for readers and checkers
    cameras: list[str]
    n_pairs: int
    state: str
    committed_pairs: int
    timing: dict[str, Any]
    dt_s: float
    volumes_id: str | None
