"""A run's vector fields with their derived quantities, as every writer of :mod:`lfpiv.formats` takes them.

:class:`Fields` holds the grid as the run store does (world coordinates in mm) and the
quantities in SI (m/s, 1/s, 1/s^2); the writers give positions in metres, so that a tool's own
derivatives of the exported velocity (ParaView's Gradient filter, Tecplot's, DaVis's) equal the
exported vorticity. :data:`QUANTITIES` names each scalar the writers write, with its units and
description, once for all formats.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED, divergence, q_criterion, vorticity
from lfpiv.formats.errors import FormatError

__all__ = ["FLAG_MEANINGS", "QUANTITIES", "Fields", "Quantity", "fields_of", "global_attributes", "uniform_spacing"]

#: The bits of ``Fields.flags`` and their names (CF ``flag_masks`` / ``flag_meanings``).
FLAG_MEANINGS = ((FLAG_OUTLIER, "outlier"), (FLAG_REPLACED, "replaced"))


@dataclass(frozen=True)
class Fields:
    """The vector fields of the correlated pairs of a run and their derived quantities.

    Attributes
    ----------
    pairs
        Index in the run of each pair held, in order.
    time_s
        (pairs,) time of each pair's frame A since the run's start, s.
    x_mm, y_mm, z_mm
        1-D world coordinates of the vector grid (window centres), mm, as the store holds them.
    velocity
        (pairs, z, y, x, 3) velocity (u, v, w), m/s.
    vorticity
        (pairs, z, y, x, 3) vorticity (x, y, z components), 1/s.
    divergence
        (pairs, z, y, x) du/dx + dv/dy + dw/dz, 1/s.
    q_criterion
        (pairs, z, y, x) Q = (|Omega|^2 - |S|^2) / 2, 1/s^2.
    flags
        (pairs, z, y, x) uint8 bits (:data:`FLAG_MEANINGS`).
    peak_ratio
        (pairs, z, y, x) highest over second-highest correlation peak.
    attrs
        The attributes of the store's ``vectors/`` (``dt_s``, ``windows``, ``overlap``, ...).
    start
        When the run started (ISO 8601, UTC; the store's ``created``); times count from it.
        None: unknown (the netCDF file then counts from the Unix epoch and says so).
    """

    pairs: list[int]
    time_s: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    velocity: np.ndarray
    vorticity: np.ndarray
    divergence: np.ndarray
    q_criterion: np.ndarray
    flags: np.ndarray
    peak_ratio: np.ndarray
    attrs: dict = field(default_factory=dict)
    start: str | None = None

    def __post_init__(self) -> None:
        n, coords = len(self.pairs), (np.shape(self.z_mm), np.shape(self.y_mm), np.shape(self.x_mm))
        if any(len(c) != 1 or c[0] < 1 for c in coords):
            raise FormatError(f"the grid's coordinates must be 1-D and not empty, got shapes x {coords[2]}, "
                              f"y {coords[1]}, z {coords[0]}")
        grid = (n, coords[0][0], coords[1][0], coords[2][0])
        expected = {"time_s": (n,), "velocity": (*grid, 3), "vorticity": (*grid, 3), "divergence": grid,
                    "q_criterion": grid, "flags": grid, "peak_ratio": grid}
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise FormatError(f"Fields.{name} has shape {np.shape(getattr(self, name))}, but {n} pair(s) on a "
                                  f"{grid[3]} x {grid[2]} x {grid[1]} grid need {shape} (pairs, z, y, x[, 3])")

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx) of the vector grid."""
        return len(self.z_mm), len(self.y_mm), len(self.x_mm)

    def coords_m(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grid's 1-D coordinates (x, y, z) in metres (float64)."""
        return tuple(np.asarray(c, dtype=np.float64) * 1e-3 for c in (self.x_mm, self.y_mm, self.z_mm))  # type: ignore[return-value]


def fields_of(vectors: dict, pairs: list[int], rate_hz: float | None, *, start: str | None = None,
              rows: list[int] | None = None) -> Fields:
    """The fields of the pairs ``pairs`` of ``RunStore.vectors()``, with vorticity, divergence and Q.

    Parameters
    ----------
    vectors
        The store's vectors: u, v, w, flags, peak_ratio (pairs, z, y, x) in m/s; x_mm, y_mm,
        z_mm; attrs.
    pairs
        Indices of the pairs to take.
    rate_hz
        Pairs per second, for each pair's time (pair / rate); None: the pair index.
    start
        When the run started (ISO 8601), see :class:`Fields`.
    rows
        Where the pairs lie along the arrays' first axis, when the arrays hold only them (the
        pairs read one by one); None: at their indices.

    Returns
    -------
    Fields
    """
    x, y, z = vectors["x_mm"], vectors["y_mm"], vectors["z_mm"]
    at = pairs if rows is None else rows
    vel = np.stack([vectors[c][at] for c in "uvw"], axis=-1).astype(np.float64)
    vort = np.stack([vorticity(v, x, y, z) for v in vel]) if pairs else np.zeros_like(vel)
    div = np.stack([divergence(v, x, y, z) for v in vel]) if pairs else vel[..., 0]
    q = np.stack([q_criterion(v, x, y, z) for v in vel]) if pairs else vel[..., 0]
    t = np.asarray(pairs, dtype=np.float64) / rate_hz if rate_hz else np.asarray(pairs, dtype=np.float64)
    return Fields(pairs=list(pairs), time_s=t, x_mm=x, y_mm=y, z_mm=z, velocity=vel, vorticity=vort, divergence=div,
                  q_criterion=q, flags=np.asarray(vectors["flags"][at], dtype=np.uint8),
                  peak_ratio=vectors["peak_ratio"][at], attrs=dict(vectors["attrs"]), start=start)


@dataclass(frozen=True)
class Quantity:
    """A scalar the writers write: its name, units (UDUNITS, and as people write them), description, and
    where it lies in :class:`Fields`."""

    name: str
    units: str
    symbol: str
    long_name: str
    get: Callable[[Fields], np.ndarray]


#: Every scalar of a :class:`Fields`, each (pairs, z, y, x), in the order the writers write them.
QUANTITIES: tuple[Quantity, ...] = (
    Quantity("u", "m s-1", "m/s", "velocity along x", lambda f: f.velocity[..., 0]),
    Quantity("v", "m s-1", "m/s", "velocity along y", lambda f: f.velocity[..., 1]),
    Quantity("w", "m s-1", "m/s", "velocity along z", lambda f: f.velocity[..., 2]),
    Quantity("vorticity_x", "s-1", "1/s", "vorticity along x (dw/dy - dv/dz)", lambda f: f.vorticity[..., 0]),
    Quantity("vorticity_y", "s-1", "1/s", "vorticity along y (du/dz - dw/dx)", lambda f: f.vorticity[..., 1]),
    Quantity("vorticity_z", "s-1", "1/s", "vorticity along z (dv/dx - du/dy)", lambda f: f.vorticity[..., 2]),
    Quantity("divergence", "s-1", "1/s", "divergence du/dx + dv/dy + dw/dz", lambda f: f.divergence),
    Quantity("q_criterion", "s-2", "1/s^2", "Q-criterion (|Omega|^2 - |S|^2) / 2", lambda f: f.q_criterion),
    Quantity("peak_ratio", "1", "1", "highest over second-highest correlation peak", lambda f: f.peak_ratio),
    Quantity("flags", "1", "1", "vector quality flags (1 outlier, 2 replaced)", lambda f: f.flags),
)


def uniform_spacing(coords: np.ndarray, *, axis: str, rtol: float = 1e-6) -> float:
    """The spacing of evenly spaced 1-D coordinates (1.0 for a single point).

    Raises
    ------
    FormatError
        If the coordinates are not evenly spaced and increasing.
    """
    c = np.asarray(coords, dtype=np.float64)
    if len(c) < 2:
        return 1.0
    d = np.diff(c)
    if not (d[0] > 0 and np.allclose(d, d[0], rtol=rtol, atol=0.0)):
        raise FormatError(f"the vector grid's {axis} coordinates are not evenly spaced and increasing (steps "
                          f"{d.min():.6g} to {d.max():.6g}); this format needs a uniform grid: export netcdf, which "
                          "keeps each coordinate")
    return float((c[-1] - c[0]) / (len(c) - 1))


def global_attributes(f: Fields) -> dict[str, Any]:
    """The attributes every writer records with the fields: the correlation settings and the frame.

    Returns
    -------
    dict
        ``dt_s`` (time between frames, s), ``windows_xyz_voxels`` (text), ``overlap_xyz``
        (list of float) and ``frame`` (text).
    """
    a = f.attrs
    return {
        "dt_s": float(a.get("dt_s", np.nan)),
        "windows_xyz_voxels": "; ".join("x".join(str(n) for n in w) for w in a.get("windows", [])),
        "overlap_xyz": [float(o) for o in a.get("overlap", [])],
        "frame": "the rig's right-handed world frame, origin at the centre of the measurement volume",
    }
