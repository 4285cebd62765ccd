"""What every part of the run store shares: its error, format name and version, and the
attributes each part of :class:`lfcore.runstore.RunStore` works on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import zarr

FORMAT = "lfpiv-run"
FORMAT_VERSION = 1
STATES = ("recording", "complete", "aborted")


class RunStoreError(ValueError):
    """A run store that cannot be created or read; the message says what to do."""


class Part:
    """Base of the parts :class:`lfcore.runstore.RunStore` is made of (frames, drops, truth,
    volumes, vectors, replacement): each holds one kind of data of the run, all of them in
    :attr:`group`, the run's root group, at :attr:`path`."""

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
    volumes_id: str | None
