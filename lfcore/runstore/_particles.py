"""Reconstructed particles: ``particles/`` ragged by frame.

Layout (docs/reference/run-store.md)::

    particles/table     float64 (n, 5): x, y, z (mm), intensity, residual of every frame's
                        particles, the frames' rows one after another in the order written
    particles/index     int64 (pairs, 2, 2): start and stop rows of frame A and B of each pair
                        in ``table``; -1 where not reconstructed
    attrs               origin_mm, voxel_mm (the grid the particles were fitted on), method,
                        settings, fields, particle_pairs (the pairs written so far)

``lfpiv track`` keeps its tracks with the vectors they make (``vectors/tracks``, ``track_index``
and, along a time-resolved series, ``series_tracks`` and ``series_index``).

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
#: The columns of ``vectors/tracks`` (written by ``lfpiv track``).
TRACK_COLUMNS = ("x_a_mm", "y_a_mm", "z_a_mm", "x_b_mm", "y_b_mm", "z_b_mm", "outlier")
#: The columns of ``vectors/series_tracks`` (written by ``lfpiv track --along-pairs``).
SERIES_COLUMNS = ("track", "frame", "x_mm", "y_mm", "z_mm", "x_fit_mm", "y_fit_mm", "z_fit_mm")


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

    # --- the tracks of lfpiv track, kept with the vectors they are binned into --------------------
    def create_tracks(self) -> None:
        """Add the track arrays to the ``vectors/`` being written (made by :meth:`create_vectors`):
        ``tracks`` float64 (m, 7): frame A's position, frame B's (x, y, z mm each) and 1 where the
        outlier test rejected the track, 0 where it is kept; ``track_index`` int64 (pairs, 2): each
        pair's start and stop row, -1 where not tracked. They follow ``vectors/`` wherever it goes
        (its pending replacement, or replaced by ``correlate``)."""
        g = self.writing("vectors")
        run_array(g, "tracks", "mm, mm, mm, mm, mm, mm, 1", ["track", "field"],
                  "frame A's x, y, z and frame B's x, y, z (mm) of each particle track, and 1 where rejected as an "
                  "outlier", shape=(0, 7), chunks=(TABLE_CHUNK, 7), dtype=np.float64, fill_value=np.nan)
        run_array(g, "track_index", "row", ["pair", "bound"], "start and stop row in tracks of each pair; -1 where "
                  "not tracked", shape=(self.n_pairs, 2), chunks=(self.n_pairs, 2), dtype=np.int64, fill_value=-1)

    def write_tracks(self, pair: int, tracks: np.ndarray) -> None:
        """Append one pair's (m, 7) tracks (see :meth:`create_tracks`) to the ``vectors/`` being written;
        the pair counts as done once its vectors are recorded (:meth:`write_vectors`)."""
        g = self.writing("vectors")
        rows = np.asarray(tracks, dtype=np.float64).reshape(-1, 7)
        table, index = g["tracks"], g["track_index"]
        start = int(table.shape[0])
        table.resize((start + len(rows), 7))
        if len(rows):
            table[start:] = rows
        bounds = index[...]
        bounds[pair] = (start, start + len(rows))
        index[...] = bounds

    def read_tracks(self, pair: int) -> np.ndarray:
        """The (m, 7) tracks of pair ``pair`` (:meth:`create_tracks`).

        Raises
        ------
        RunStoreError
            If the run's vectors hold no tracks of that pair (none tracked, or vectors from ``correlate``).
        """
        g = self.group["vectors"] if "vectors" in self.group else None
        if g is None or "tracks" not in g or pair not in g.attrs.get("correlated_pairs", []):
            raise RunStoreError(f"{self.path} holds no particle tracks of pair {pair}; run 'lfpiv track {self.path}'")
        start, stop = (int(v) for v in g["track_index"][pair])
        if start < 0 or stop < start or stop > g["tracks"].shape[0]:
            raise RunStoreError(f"{self.path}: vectors/track_index of pair {pair} is damaged ({start}, {stop}); run "
                                f"'lfpiv track {self.path}' again")
        try:
            rows = g["tracks"][start:stop]
        except Exception as exc:  # noqa: BLE001 - a damaged chunk: name it
            raise RunStoreError(f"{self.path}: vectors/tracks of pair {pair} cannot be read ({type(exc).__name__}: "
                                f"{exc}); 'lfpiv check {self.path}' lists what is damaged") from None
        return np.asarray(rows, dtype=np.float64).reshape(-1, 7)

    def write_series_tracks(self, rows: np.ndarray) -> None:
        """Write a time-resolved series' tracks through its frames (``lfpiv track --along-pairs``) to
        the ``vectors/`` being written, replacing any there: ``series_tracks`` float64 (k, 8), one
        row a point of a track (:data:`SERIES_COLUMNS`: the track, the frame in the series (frame A
        of pair p is 2 p, frame B 2 p + 1), the particle's x, y, z and the track's fitted x, y, z
        there, mm; NaN on tracks too short to fit), a track's points together in frame order;
        ``series_index`` int64 (tracks, 2): each track's start and stop row."""
        g = self.writing("vectors")
        t = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
        for name in ("series_tracks", "series_index"):
            if name in g:
                del g[name]
        run_array(g, "series_tracks", "1, 1, mm, mm, mm, mm, mm, mm", ["point", "field"],
                  "track, frame (2 pair + 0 for A, 1 for B), the particle's x, y, z and the track's fitted x, y, z "
                  "(mm; NaN where too short to fit) of every point of every track through the series",
                  shape=t.shape, chunks=(TABLE_CHUNK, 8), dtype=np.float64, fill_value=np.nan)[...] = t
        ids = t[:, 0].astype(np.int64)
        n = int(ids.max()) + 1 if len(ids) else 0
        start = np.searchsorted(ids, np.arange(n), side="left")
        stop = np.searchsorted(ids, np.arange(n), side="right")
        run_array(g, "series_index", "row", ["track", "bound"], "start and stop row in series_tracks of each track",
                  shape=(n, 2), chunks=(max(n, 1), 2), dtype=np.int64, fill_value=-1)[...] = np.column_stack(
                      [start, stop]).reshape(n, 2)
        g["series_tracks"].attrs["fields"] = list(SERIES_COLUMNS)

    def read_series_tracks(self) -> np.ndarray:
        """The (k, 8) points of the tracks through a time-resolved series (:meth:`write_series_tracks`).

        Raises
        ------
        RunStoreError
            If the run's vectors hold none (not tracked with ``--along-pairs``).
        """
        g = self.group["vectors"] if "vectors" in self.group else None
        if g is None or "series_tracks" not in g:
            raise RunStoreError(f"{self.path} holds no tracks through its series; run 'lfpiv track {self.path} "
                                "--along-pairs' (a time-resolved run)")
        try:
            rows = g["series_tracks"][...]
        except Exception as exc:  # noqa: BLE001 - a damaged chunk: name it
            raise RunStoreError(f"{self.path}: vectors/series_tracks cannot be read ({type(exc).__name__}: {exc}); "
                                f"'lfpiv check {self.path}' lists what is damaged") from None
        return np.asarray(rows, dtype=np.float64).reshape(-1, 8)

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

    def read_particles(self, pair: int, frame: int, *, writing: bool = False) -> np.ndarray:
        """The (n, 5) particles (x, y, z mm, intensity, residual) of frame ``frame`` (0: A, 1: B) of
        pair ``pair``.

        Parameters
        ----------
        pair, frame
            The pair, and its frame (0: A, 1: B).
        writing
            Read the set being written (``particles/``' pending replacement where one is resumed or
            made, :meth:`create_particles`) instead of ``particles/`` itself.

        Raises
        ------
        RunStoreError
            If the run has no particles, or none of that pair.
        """
        done = (self.done_pairs("particles", self._particles_writing()) if writing  # type: ignore[attr-defined]
                else self.particle_pairs())
        if pair not in done:
            raise RunStoreError(f"{self.path} holds no particles of pair {pair}; run 'lfpiv particles {self.path}' "
                                "for it")
        g = self._particles_writing() if writing else self.group["particles"]
        start, stop = (int(v) for v in g["index"][pair, frame])
        if start < 0 or stop < start or stop > g["table"].shape[0]:
            raise RunStoreError(f"{self.path}: {g.basename}/index of pair {pair} is damaged ({start}, {stop}); "
                                f"run 'lfpiv particles {self.path}' again")
        try:
            rows = g["table"][start:stop]
        except Exception as exc:  # noqa: BLE001 - a damaged chunk (checksum, codec, size): name it
            raise RunStoreError(f"{self.path}: {g.basename}/table rows {start} to {stop - 1} (pair {pair}) cannot be "
                                f"read ({type(exc).__name__}: {exc}); 'lfpiv check {self.path}' lists what is "
                                "damaged") from None
        return np.asarray(rows, dtype=np.float64).reshape(-1, 5)
