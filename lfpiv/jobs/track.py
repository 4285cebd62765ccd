"""Tracking a run's particles into ``vectors/`` (``lfpiv track``): each pair's frame A particles
paired with frame B's (:mod:`lfcore.track`), binned on a grid in the layout ``correlate`` writes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.runstore import RunStore
from lfcore.track import TrackSettings, track_pair
from lfcore.volume import VolumeGrid
from lfpiv.errors import UsageError
from lfpiv.pair_runner import particle_pairs, run_pairs

__all__ = ["TrackSettings", "TracksDone", "track_run", "track_settings", "tracks_csv"]


def track_settings(**options: Any) -> TrackSettings:
    """:class:`lfcore.track.TrackSettings` of the given options, or a one-line :class:`UsageError`."""
    try:
        return TrackSettings(**options)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


@dataclass
class TracksDone:
    """What :func:`track_run` did: the pairs tracked now, their tracks, outliers and vectors."""

    pairs: list[int] = field(default_factory=list)
    tracks: int = 0
    outliers: int = 0
    vectors: int = 0
    bins: int = 0
    shape: tuple[int, int, int] = (0, 0, 0)


def _create(store: RunStore, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray, dt_s: float,
            windows: list[list[int]], meta: dict[str, Any]) -> None:
    store.create_vectors(x_mm, y_mm, z_mm, dt_s=dt_s, windows=windows, overlap=[0.0] * 3, settings=meta)
    store.create_tracks()


def tracks_csv(store: RunStore, path: str, pairs: list[int] | None = None) -> int:
    """Write the stored tracks of ``pairs`` (None: every tracked pair) to a CSV file: pair, frame A's
    x, y, z and frame B's (mm), u, v, w (m/s) and outlier (1 rejected, 0 kept); returns the rows."""
    dt_s = float(store.timing["dt_s"])
    chosen = store.correlated_pairs() if pairs is None else pairs
    rows = []
    for p in chosen:
        t = store.read_tracks(p)
        vel = (t[:, 3:6] - t[:, 0:3]) * 1e-3 / dt_s
        rows.append(np.column_stack([np.full(len(t), p), t[:, :6], vel, t[:, 6]]))
    table = np.concatenate(rows) if rows else np.zeros((0, 11))
    header = "pair,x_a_mm,y_a_mm,z_a_mm,x_b_mm,y_b_mm,z_b_mm,u_m_s,v_m_s,w_m_s,outlier"
    np.savetxt(path, table, delimiter=",", header=header, comments="",
               fmt=["%d", *["%.6f"] * 6, *["%.6g"] * 3, "%d"])
    return len(table)


def track_run(store: RunStore, settings: TrackSettings, pairs: slice | None = None, *, progress: bool = True,
              skip_done: bool = False, option: str = "--pair-range") -> TracksDone:
    """Track the particles of ``pairs`` (None: every pair with particles) into ``vectors/``.

    The field is the mean displacement of the tracks in each bin over the pair's time, in m/s,
    on the grid of the bins' centres; bins with too few tracks are NaN. Vectors of other settings
    (or of ``correlate``) are replaced once the new ones are complete.

    Raises
    ------
    UsageError
        A run without particles, or none of the selected pairs with particles.
    """
    attrs, chosen = particle_pairs(store, pairs, option=option)
    grid = VolumeGrid.from_rig(store.rig)
    if (not np.allclose(grid.origin_mm, attrs["origin_mm"]) or not np.allclose(grid.voxel_mm, attrs["voxel_mm"])):
        raise UsageError(f"{store.path}: particles/ was made on another grid than the run's rig gives; run "
                         f"'lfpiv particles {store.path}' again")
    dt_s = float(store.timing["dt_s"])
    # the bins' grid, from a pair's result on no particles
    empty = track_pair(np.zeros((0, 3)), np.zeros((0, 3)), grid, settings=settings)
    x_mm, y_mm, z_mm = empty.x_mm, empty.y_mm, empty.z_mm
    windows = [[int(v) for v in settings.bin_voxels]]
    meta = {"source": "particle tracks", **settings.as_dict(), "particles": attrs.get("settings", {})}
    out = TracksDone(shape=(len(x_mm), len(y_mm), len(z_mm)))

    def matches(g: Any) -> bool:
        return (g is not None and g.attrs.get("settings") == meta and g.attrs.get("windows") == windows
                and float(g.attrs.get("dt_s", -1)) == dt_s and g.attrs.get("volumes_id") == store.volumes_id)

    def differences(g: Any) -> list[str]:
        old = dict(g.attrs.get("settings", {})) if g is not None else {}
        return [k for k in meta if old.get(k) != meta[k]] or ["source"]

    def here(todo: list[int]) -> None:
        with tqdm(total=len(todo), unit="pair", disable=not progress, desc="tracking", leave=False) as bar:
            for p in todo:
                a_all, b_all = store.read_particles(p, 0)[:, :3], store.read_particles(p, 1)[:, :3]
                res = track_pair(a_all, b_all, grid, settings=settings)
                vel = res.field_mm * 1e-3 / dt_s  # mm over dt to m/s
                flags = np.zeros(vel.shape[:3], np.uint8)
                store.write_tracks(p, np.column_stack([a_all[res.a_index], b_all[res.b_index],
                                                       res.outlier.astype(np.float64)]))
                store.write_vectors(p, vel, flags, np.full(vel.shape[:3], np.nan, np.float32))  # records the pair
                out.pairs.append(p)
                out.tracks += len(res.a_index)
                out.outliers += int(res.outlier.sum())
                out.vectors += int(np.isfinite(res.field_mm[..., 0]).sum())
                out.bins += res.counts.size
                bar.update(1)

    run_pairs(store, "vectors", chosen, matches=matches, differences=differences,
              create=lambda: _create(store, x_mm, y_mm, z_mm, dt_s, windows, meta),
              skip_done=skip_done, here=here, remote=None, client=None, on_done=lambda p, r: None, desc="tracking",
              progress=progress)
    return out
