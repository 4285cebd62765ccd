"""Reconstructed volumes: ``volumes/data`` and the voxel grid in its attributes."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import zarr

from lfcore.runstore._chunks import RESTORE
from lfcore.runstore._common import Part, RunStoreError, run_array
from lfcore.runstore._coords import COORDINATES, add_coordinates
from lfcore.runstore._schema import validated
from lfcore.volume import VolumeGrid

#: The data type of ``volumes/data``.
VOLUME_DTYPE = np.float32


class Volumes(Part):
    """The particle volumes reconstructed from the frames, two per pair."""

    def create_volumes(self, grid: VolumeGrid, *, method: str, settings: dict[str, Any]) -> zarr.Array:
        """Create (or replace) ``volumes/`` for every pair of the run, all zero.

        Volumes already reconstructed are not deleted: the new ones are made in
        ``volumes.pending/``, which :meth:`finish` makes ``volumes/`` once they are all written
        (see :meth:`writing`).

        ``volumes/data`` is float32 (pairs, 2, z, y, x) in chunks of at most 16 x 256 x 256
        voxels; the group's attributes hold the grid (``origin_mm``, ``voxel_mm``), the method
        and its settings, ``reconstructed_pairs``, the pairs written so far, and ``volumes_id``, a
        name new with every ``volumes/`` made, which the vectors correlated from it record. The
        coordinate arrays ``x``, ``y``, ``z`` (mm, voxel centres) and ``time`` (s, per pair) label
        the axes for xarray (:mod:`lfcore.runstore._coords`). The reconstruction adds
        ``operator`` as frames are written (what applied the operator, its memory and the mean
        milliseconds per iteration; see the layout in :mod:`lfcore.runstore`); volumes made before
        it have none.
        """
        g = self._begin("volumes", staged=bool(self.reconstructed_pairs()))
        g.attrs.update({"origin_mm": list(grid.origin_mm), "voxel_mm": list(grid.voxel_mm), "method": method,
                        "settings": settings, "reconstructed_pairs": [], "volumes_id": uuid.uuid4().hex,
                        "description": "reconstructed particle volumes; origin_mm is the world (x, y, z) "
                                       "of the centre of voxel [0, 0, 0]"})
        add_coordinates(g, {a: grid.axis_mm(a) for a in "xyz"}, n_pairs=self.n_pairs, timing=self.timing,
                        of="the voxel centres")
        nz, ny, nx = grid.shape
        data = run_array(g, "data", "intensity", ["pair", "frame", "z", "y", "x"], "voxel intensity",
                         shape=(self.n_pairs, 2, nz, ny, nx), dtype=VOLUME_DTYPE, fill_value=0.0,
                         chunks=(1, 1, min(nz, 16), min(ny, 256), min(nx, 256)))
        data.attrs["coordinates"] = COORDINATES
        return data

    def write_volume(self, pair: int, frame: int, volume: np.ndarray, *, record: bool = True) -> None:
        """Store one reconstructed volume (z, y, x) float32 of pair ``pair``, frame 0 (A) or 1 (B).

        A pair counts as reconstructed once both of its frames are written. With ``record``
        False only the voxels are written, not the bookkeeping: for worker processes that write
        distinct volumes at once, while one coordinator records them (:meth:`record_volumes`),
        since attributes are rewritten whole and concurrent writers would lose each other's.
        """
        self.writing("volumes")["data"][pair, frame] = volume
        if record:
            self.record_volumes([(pair, frame)])

    def record_volumes(self, written: list[tuple[int, int]], *,
                       attrs: Callable[[Mapping[str, Any]], dict[str, Any]] | None = None) -> None:
        """Add (pair, frame) volumes, already written, to ``reconstructed_pairs``.

        ``attrs(current)`` gives further attributes of ``volumes/`` to record in the same write
        (from its current ones), e.g. the operator figures of the frames written.
        """
        g = self.writing("volumes")
        key = "_frames_written"
        before = validated(self.path, g.basename, g.attrs, key)
        done = {tuple(x) for x in before} | {(int(p), int(f)) for p, f in written}
        pairs = sorted({p for p, _ in done if (p, 0) in done and (p, 1) in done})
        more = {} if attrs is None else attrs(g.attrs)
        g.attrs.update({**more, key: sorted(done), "reconstructed_pairs": pairs})

    @property
    def has_volumes(self) -> bool:
        """True when the run holds ``volumes/``.

        Raises
        ------
        RunStoreError
            If ``volumes/`` is damaged: its data without its zarr.json (the record of which pairs
            it holds), or pairs recorded as reconstructed whose data is gone.
        """
        if "volumes/data" in self.group:
            if "volumes" not in self.group:
                raise RunStoreError(f"{self.path}: volumes/zarr.json is missing, the record of which pairs "
                                    f"volumes/data holds; {RESTORE}, or remove {self.path}/volumes to make the "
                                    "volumes again")
            return True
        # a group without its array is a reconstruction killed as it began: none, to make again
        if "volumes" in self.group and self.group["volumes"].attrs.get("reconstructed_pairs"):
            raise RunStoreError(f"{self.path}: volumes/data is missing, though volumes/ records reconstructed pairs; "
                                f"{RESTORE}, or remove {self.path}/volumes to make the volumes again")
        return False

    @property
    def volumes_id(self) -> str | None:
        """The name of the current ``volumes/`` (new each time it is made), None if there is none
        (or it was made before lfpiv recorded one)."""
        return self._volume_attr("volumes_id") if self.has_volumes else None

    def _volume_attr(self, key: str) -> Any:
        # one attribute of volumes/, checked (a reader of the vectors need not trust the whole grid)
        return validated(self.path, "volumes", self.group["volumes"].attrs, key)

    def volume_attrs(self, *, group: zarr.Group | None = None) -> dict[str, Any]:
        """The attributes of ``volumes/`` (or of ``group``, its pending replacement), checked
        (:class:`~lfcore.runstore._schema.VolumesAttrs`: the grid, the method, its settings and the
        pairs reconstructed), a copy.

        Raises
        ------
        RunStoreError
            The run has no volumes, or one of them is not what the layout gives it (one line
            naming it).
        """
        if group is None:
            if "volumes" not in self.group:
                raise RunStoreError(self._NO_VOLUMES.format(path=self.path))
            group = self.group["volumes"]
        return dict(validated(self.path, group.basename, group.attrs))

    # what a run without volumes says (formatted with path)
    _NO_VOLUMES = "{path} has no reconstructed volumes; run 'lfpiv reconstruct {path}' first"

    def volumes(self) -> zarr.Array:
        """The (pairs, 2, z, y, x) float32 ``volumes/data`` array (:meth:`read_volume` reads one
        volume checking its chunks)."""
        if not self.has_volumes:
            raise RunStoreError(self._NO_VOLUMES.format(path=self.path))
        return self.group["volumes/data"]

    def volume_grid(self) -> VolumeGrid:
        """The voxel grid of ``volumes/``."""
        return self.grid_of(self.group["volumes"] if "volumes" in self.group else None)

    def grid_of(self, group: zarr.Group | None) -> VolumeGrid:
        """The voxel grid of a volumes group (``volumes/`` or its pending replacement)."""
        if group is None or "data" not in group:
            raise RunStoreError(self._NO_VOLUMES.format(path=self.path))
        a = self.volume_attrs(group=group)
        shape = tuple(int(n) for n in group["data"].shape[2:])
        grid = VolumeGrid(shape=shape, voxel_mm=tuple(a["voxel_mm"]), origin_mm=tuple(a["origin_mm"]))
        problem = grid_problem(group, grid)
        if problem is not None:
            raise RunStoreError(f"{self.path}: {problem}; restore it from a copy of the run, or remove "
                                f"{self.path}/{group.basename} to reconstruct again")
        return grid

    def reconstructed_pairs(self) -> list[int]:
        """The pairs of ``volumes/`` whose two volumes are written."""
        return list(self._volume_attr("reconstructed_pairs")) if self.has_volumes else []


def grid_problem(group: zarr.Group, grid: VolumeGrid) -> str | None:
    """How the voxel grid of a volumes group's attributes (``origin_mm``, ``voxel_mm``) disagrees
    with its coordinate arrays ``x``, ``y``, ``z`` (written with them: an edited attribute), or
    None where they agree or the group has none (made before them)."""
    for k, axis in enumerate("xyz"):
        if axis not in group:
            return None
        try:
            stored = np.asarray(group[axis][...], dtype=np.float64)
        except Exception:  # noqa: BLE001 - a damaged coordinate chunk: RunStore.verify names it
            return None
        want = grid.axis_mm(axis)
        where = f"{group.basename}/ attribute"
        if stored.shape != want.shape:
            return (f"{group.basename}/{axis} holds {stored.size} voxel centres, but {group.basename}/data "
                    f"{want.size} voxels along {axis} (a zarr.json was edited or damaged)")
        # the attributes and the coordinates come from the same floats: only an edit moves them apart
        if np.allclose(stored, want, rtol=1e-9, atol=1e-9 * abs(grid.voxel_mm[k])):
            continue
        step = float(np.diff(stored).mean()) if stored.size > 1 else grid.voxel_mm[k]
        if not np.isclose(step, grid.voxel_mm[k], rtol=1e-9):
            return (f"{where} voxel_mm is {list(grid.voxel_mm)}, but the voxel centres of {group.basename}/{axis} "
                    f"are {step:.6g} mm apart (its zarr.json was edited or damaged)")
        return (f"{where} origin_mm is {list(grid.origin_mm)}, but the first voxel centre of "
                f"{group.basename}/{axis} is at {stored[0]:.6g} mm (its zarr.json was edited or damaged)")
    return None
