"""The run store: one zarr v3 directory per run, recorded or synthetic (docs/reference/run-store.md).

This module is :mod:`lfcore`'s one exception to "never open a file": it owns the on-disk
format so that every writer (synthesis, the recorder, reconstruction) produces the same layout.

Layout::

    run.zarr/                 attrs: rig, timing, software_version, created, state,
                              committed_pairs, format, format_version
      <camera>/frames         uint16 (pairs, 2, rows, columns), one chunk per frame
      <camera>/frame_id       int64 (pairs, 2), -1 where never written
      <camera>/timestamp_ns   int64 (pairs, 2), -1 where never written
      drops/                  lost frames: camera, pair, frame, frame_id, timestamp_ns, reason
      truth/                  synthetic runs: particles (pairs, 2, n, 3) mm, brightness
                              (pairs, 2, n) counts; attrs: flow (name and parameters), seeding
      volumes/data            float32 (pairs, 2, z, y, x); attrs: origin_mm, voxel_mm, method,
                              settings, reconstructed_pairs, and (since the matrix-free projector)
                              operator: {projector ("stored" | "matrix-free" | both, comma-
                              separated), bytes (the largest frame's operator: weights, or
                              templates and voxel indices), ms_per_iteration (mean over the
                              frames), frames, and since the planner operators (names)};
                              plan {device, cameras, operator, cache, slabs, reasons}
                              (lfcore.plan.Plan); stores made before them have none
      volumes/x, y, z, time   coordinates: voxel centres (mm), time of each pair (s)
      vectors/                u, v, w, flags, peak_ratio (pairs, z, y, x); x_mm, y_mm, z_mm
      vectors/x, y, z, time   coordinates: window centres (mm, = x_mm ...), time of each pair (s)
      particles/              table float64 (n, 5): x, y, z mm, intensity, residual of every frame's
                              particles; index int64 (pairs, 2, 2): each frame's start and stop row;
                              attrs: origin_mm, voxel_mm, method, settings, fields, particle_pairs
      volumes.pending/,       a replacement of volumes/ or vectors/ (other settings) being made,
      vectors.pending/        same layout; it becomes volumes/ or vectors/ only once complete, so
                              an interrupted replacement leaves the old ones whole; readers
                              ignore it
      .lfpiv-writer.lock      the writer lock, naming the process that writes the run (not zarr)

Every array carries ``units`` and ``axes`` attributes, so plain zarr or xarray users can read a
run without lfpiv; ``xr.open_zarr(run, group="volumes")`` or ``group="vectors"`` labels the axes
with the coordinate arrays (:mod:`lfcore.runstore._coords`; stores made before them have none,
and read the same otherwise). Pairs ``0 .. committed_pairs - 1`` are complete; ``state`` says
whether the run is still ``recording``, ``complete`` or ``aborted``.

One process writes a run at a time (:mod:`lfcore.runstore._lock`: a POSIX lock the kernel
releases when its holder dies; readers take none). Every chunk carries a CRC-32C (zarr's
``crc32c`` codec) and every chunk written is stored, so a chunk of a recorded pair that is
missing, changed or cut short is damage: :meth:`RunStore.read_frame`, :meth:`~RunStore.read_volume`
and :meth:`~RunStore.read_vectors` raise naming it, and :meth:`RunStore.verify` lists every
problem of a run (:mod:`lfcore.runstore._integrity`). Stores made before both still open.

The store is split by what it holds: ``_frames`` (frames, ids, time stamps, state and commits,
and :class:`FrameWriter`), ``_drops``, ``_truth``, ``_volumes``, ``_vectors`` (with ``_coords``,
their coordinate arrays), ``_particles`` (ragged by frame), ``_replacement`` (the ``*.pending``
machinery), ``_integrity`` (checked reads and verification, with ``_chunks``), ``_lock`` and ``_schema`` (the
attributes as validated models: every reader checks what it reads, and a bad value is one line naming the
store, the attribute, what it holds and what it should), put together as :class:`RunStore` in ``_store``.
"""

from lfcore.runstore._common import FORMAT, FORMAT_VERSION, STATES, RunStoreError
from lfcore.runstore._coords import is_time_resolved
from lfcore.runstore._frames import FRAME_CODEC, FrameWriter
from lfcore.runstore._store import RunStore

__all__ = ["FORMAT", "FORMAT_VERSION", "FRAME_CODEC", "STATES", "FrameWriter", "RunStore", "RunStoreError",
           "is_time_resolved"]
