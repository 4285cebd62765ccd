"""Coordinate arrays of ``volumes/`` and ``vectors/``, so that plain xarray labels their axes.

Each group gets ``x``, ``y`` and ``z`` (float64, mm, world coordinates of the voxel or window
centres), whose names equal their zarr v3 ``dimension_names``, so xarray makes them index
coordinates, and ``time`` (float64, s) along ``pair``: the time of each pair's first pulse since
the first pair's, ``pair / timing.rate_hz`` (NaN where the run's timing has no rate). ``time``
is not a dimension, so every (pair, ...) array names it in its CF ``coordinates`` attribute,
which xarray's ``decode_coords`` (on by default) reads to attach it. Its units are plain ``"s"``
(not ``"seconds since ..."``), so xarray leaves it float seconds rather than decoding dates.

The run clock, not the truth's: ``truth/t0_s`` of a synthetic run is the flow's clock, which
repeats when a simulated lab shows a pool of pairs again; ``time`` is when the pairs were taken.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import zarr

from lfcore.runstore._common import run_array

#: The coordinate arrays (float64) of ``volumes/`` and ``vectors/``.
COORDINATE_ARRAYS = ("x", "y", "z", "time")
#: The CF ``coordinates`` attribute of every (pair, ...) array of ``volumes/`` and ``vectors/``.
COORDINATES = "time"


def pair_times_s(n_pairs: int, timing: Mapping[str, Any]) -> np.ndarray | None:
    """(n_pairs,) time of each pair's first pulse since the first pair's, s: pair / ``rate_hz``
    of the run's ``timing``; None if it has no rate."""
    rate = timing.get("rate_hz")
    return np.arange(n_pairs) / float(rate) if rate else None


def is_time_resolved(timing: Mapping[str, Any]) -> bool:
    """Whether a run's ``timing`` is a time-resolved series: frames evenly spaced in time (A0, B0,
    A1, B1, ... each ``dt_s`` apart), i.e. one pair every two ``dt_s`` (``1 / rate_hz = 2 dt_s``
    within 1%). Frame B of pair i and frame A of pair i + 1 are then ``dt_s`` apart too, and a
    particle can be followed through every frame (``lfpiv track --along-pairs``).

    Parameters
    ----------
    timing
        A run's timing: ``dt_s`` (s between frames A and B) and ``rate_hz`` (pairs per second);
        either missing, not a number or not positive makes it not time-resolved.

    Returns
    -------
    bool
        Whether ``1 / rate_hz`` is ``2 dt_s`` within 1%.
    """
    rate, dt = timing.get("rate_hz"), timing.get("dt_s")
    try:
        rate, dt = float(rate), float(dt)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False
    if not (np.isfinite(rate) and np.isfinite(dt) and rate > 0 and dt > 0):
        return False
    return abs(1.0 / rate - 2.0 * dt) <= 0.01 * 2.0 * dt


def add_coordinates(group: zarr.Group, axes_mm: Mapping[str, np.ndarray], *, n_pairs: int,
                    timing: Mapping[str, Any], of: str) -> None:
    """Create the ``x``, ``y``, ``z`` and ``time`` coordinate arrays in ``group``.

    Parameters
    ----------
    group
        ``volumes/``, ``vectors/`` or their pending replacement, being made.
    axes_mm
        1-D world coordinates (mm) along ``"x"``, ``"y"`` and ``"z"``.
    n_pairs
        Pairs of the run (the length of ``time``).
    timing
        The run's timing attributes (``rate_hz``).
    of
        What the coordinates are of, for their descriptions ("the voxel centres").
    """
    for name in ("x", "y", "z"):
        c = np.asarray(axes_mm[name], dtype=np.float64)
        a = run_array(group, name, "mm", [name], f"world {name} of {of}", shape=c.shape, dtype=np.float64)
        a[...] = c
        a.attrs["axis"] = name.upper()
    t = pair_times_s(n_pairs, timing)
    a = run_array(group, "time", "s", ["pair"], "time of each pair's first pulse since the first pair's "
                  "(pair / timing.rate_hz; NaN: the run's timing has no rate)", shape=(n_pairs,),
                  dtype=np.float64, fill_value=np.nan)
    a[...] = np.full(n_pairs, np.nan) if t is None else t  # stored either way: a missing chunk is damage
    a.attrs["axis"] = "T"
