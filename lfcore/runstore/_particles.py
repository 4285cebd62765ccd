"""Reconstructed particles: ``particles/`` ragged by frame.

Layout (docs/reference/run-store.md)::

    particles/table     float64 (n, 5): x, y, z (mm), intensity, residual of every frame's
                        particles, the frames' rows one after another in the order written
    particles/index     int64 (pairs, 2, 2): start and stop rows of frame A and B of each pair
                        in ``table``; -1 where not reconstructed
    attrs               origin_mm, voxel_mm (the grid the particles were fitted on), method,
                        settings, fields, particle_pairs (the pairs written so far)

A pair is written by appending its two frames' rows to ``table`` and then setting its ``index``;
only the pairs in ``particle_pairs`` are whole (rows of a frame killed half-way are never indexed).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr

from lfcore.runstore._common import Part, RunStoreError, run_array
from lfcore.volume import VolumeGrid

#: The columns of ``particles/table``.
PARTICLE_COLUMNS = ("x_mm", "y_mm", "z_mm", "intensity", "residual")
#: Rows of ``particles/table`` per chunk.
TABLE_CHUNK = 65536


class Particles(Part):
    """The particles reconstructed from the frames, ragged by frame."""

    def create_particles(self, grid: VolumeGrid, *, method: str, settings: dict[str, Any]) -> None:
        """Create (or replace) ``particles/`` for every pair of the run, empty.

        Particles already reconstructed are kept until the new ones are complete, in
        ``particles.pending/``, as :meth:`create_volumes` keeps volumes.

        ``table`` is float64 (n, 5) rows of x, y, z (mm), intensity and fit residual; ``index``
        int64 (pairs, 2, 2) the start and stop row of each frame (A, B) of each pair, -1 where not
        reconstructed. The attributes hold the grid (``origin_mm``, ``voxel_mm``), ``method``,
        ``settings`` and ``particle_pairs``, the pairs written so far.
        """
        g = self._begin("particles", staged=bool(self.particle_pairs()))
        g.attrs.update({"origin_mm": list(grid.origin_mm), "voxel_mm": list(grid.voxel_mm), "method": method,
                        "settings": settings, "fields": list(PARTICLE_COLUMNS), "particle_pairs": [],
                        "description": "particles by iterative particle reconstruction: rows of table are x, y, z "
                                       "(mm), intensity, residual; index gives each frame's start and stop row"})
        run_array(g, "table", "mm, mm, mm, intensity, 1", ["particle", "field"],
                  "x, y, z (mm), intensity and fit residual of every frame's particles", shape=(0, 5),
                  chunks=(TABLE_CHUNK, 5), dtype=np.float64, fill_value=np.nan)
        run_array(g, "index", "row", ["pair", "frame", "bound"], "start and stop row in table of each frame "
                  "(A, B); -1 where not reconstructed", shape=(self.n_pairs, 2, 2), chunks=(self.n_pairs, 2, 2),
                  dtype=np.int64, fill_value=-1)

    def _particles_writing(self) -> zarr.Group:
        key = self._target["particles"]
        if key not in self.group:
            raise RunStoreError(f"{self.path} has no {key}/ group; create it first")
        return self.group[key]

    def write_particles(self, pair: int, frames: list[np.ndarray], *, record: bool = True) -> None:
        """Store the particles of both frames of one pair.

        Parameters
        ----------
        pair
            Pair index.
        frames
            Two (n, 5) arrays (frame A, frame B): x, y, z (mm), intensity, residual.
        record
            Add the pair to ``particle_pairs`` (False: a writer that records later).
        """
        g = self._particles_writing()
        if len(frames) != 2:
            raise RunStoreError(f"a pair has two frames of particles, got {len(frames)}")
        rows = [np.asarray(f, dtype=np.float64).reshape(-1, 5) for f in frames]
        table, index = g["table"], g["index"]
        start = int(table.shape[0])
        stop = start + sum(len(r) for r in rows)
        table.resize((stop, 5))
        if stop > start:
            table[start:stop] = np.concatenate(rows)
        bounds = index[...]
        at = start
        for k, r in enumerate(rows):
            bounds[pair, k] = (at, at + len(r))
            at += len(r)
        index[...] = bounds
        if record:
            self.record_particles([pair])

    def record_particles(self, pairs: list[int]) -> None:
        """Add pairs whose particles are written to ``particle_pairs``."""
        g = self._particles_writing()
        done = sorted(set(g.attrs.get("particle_pairs", [])) | {int(p) for p in pairs})
        g.attrs.update({"particle_pairs": done})

    @property
    def has_particles(self) -> bool:
        return "particles" in self.group

    def particle_pairs(self) -> list[int]:
        """The pairs ``particles/`` holds."""
        return list(self.group["particles"].attrs["particle_pairs"]) if self.has_particles else []

    def particle_attrs(self) -> dict[str, Any]:
        """The attributes of ``particles/`` (grid, method, settings, pairs).

        Raises
        ------
        RunStoreError
            If the run has no particles.
        """
        if not self.has_particles:
            raise RunStoreError(f"{self.path} has no particles; run 'lfpiv particles {self.path}' first")
        return dict(self.group["particles"].attrs)

    def read_particles(self, pair: int, frame: int) -> np.ndarray:
        """The (n, 5) particles (x, y, z mm, intensity, residual) of frame ``frame`` (0: A, 1: B) of
        pair ``pair``.

        Raises
        ------
        RunStoreError
            If the run has no particles, or none of that pair.
        """
        if pair not in self.particle_pairs():
            raise RunStoreError(f"{self.path} holds no particles of pair {pair}; run 'lfpiv particles {self.path}' "
                                "for it")
        g = self.group["particles"]
        start, stop = (int(v) for v in g["index"][pair, frame])
        if start < 0 or stop < start or stop > g["table"].shape[0]:
            raise RunStoreError(f"{self.path}: particles/index of pair {pair} is damaged ({start}, {stop}); "
                                f"run 'lfpiv particles {self.path}' again")
        try:
            rows = g["table"][start:stop]
        except Exception as exc:  # noqa: BLE001 - a damaged chunk (checksum, codec, size): name it
            raise RunStoreError(f"{self.path}: particles/table rows {start} to {stop - 1} (pair {pair}) cannot be "
                                f"read ({type(exc).__name__}: {exc}); 'lfpiv check {self.path}' lists what is "
                                "damaged") from None
        return np.asarray(rows, dtype=np.float64).reshape(-1, 5)
