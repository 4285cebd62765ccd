"""Vector fields: ``vectors/`` u, v, w, flags and peak_ratio per pair, on the grid of x_mm, y_mm, z_mm."""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr

from lfcore.runstore._common import Part, RunStoreError, run_array
from lfcore.runstore._coords import COORDINATES, add_coordinates
from lfcore.runstore._schema import validated

#: The (pairs, z, y, x) arrays of ``vectors/``, with their data types.
VECTOR_FIELDS = {"u": np.float32, "v": np.float32, "w": np.float32, "flags": np.uint8, "peak_ratio": np.float32}
#: The grid's 1-D world coordinates (mm) as lfpiv has always kept them.
GRID_ARRAYS = ("x_mm", "y_mm", "z_mm")


class Vectors(Part):
    """The velocity fields correlated from the volumes, one per pair."""

    def create_vectors(self, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray, *, dt_s: float,
                       windows: list[list[int]], overlap: list[float], settings: dict[str, Any]) -> None:
        """Create (or replace) ``vectors/`` for every pair of the run, all NaN.

        Vectors already correlated are kept until the new ones are complete, as
        :meth:`create_volumes` keeps volumes.

        Parameters
        ----------
        x_mm, y_mm, z_mm
            1-D world coordinates (mm) of the vector grid along x, y and z.
        dt_s
            Time between the frames of a pair, s.
        windows
            The window size (x, y, z) in voxels of every pass, largest first.
        overlap
            Overlap (x, y, z) of neighbouring windows, fractions.
        settings
            Everything else that made the vectors (JSON-compatible).

        ``u``, ``v``, ``w`` are float32 (pairs, z, y, x) in m/s, ``flags`` uint8 (bit 1: outlier,
        bit 2: replaced), ``peak_ratio`` float32; the group's ``correlated_pairs`` attribute lists
        the pairs written so far, and ``volumes_id`` the :attr:`volumes_id` of the volumes they are
        correlated from. The coordinate arrays ``x``, ``y``, ``z`` (mm, the same as ``x_mm``,
        ``y_mm``, ``z_mm``) and ``time`` (s, per pair) label the axes for xarray
        (:mod:`lfcore.runstore._coords`).
        """
        g = self._begin("vectors", staged=bool(self.correlated_pairs()))
        g.attrs.update({"dt_s": float(dt_s), "windows": [[int(n) for n in w] for w in windows],
                        "overlap": [float(o) for o in overlap], "settings": settings, "correlated_pairs": [],
                        "volumes_id": self.volumes_id,
                        "description": "3D velocity from multi-grid cross-correlation of volumes/data; windows "
                                       "are (x, y, z) voxels per pass"})
        axes = {"x": np.asarray(x_mm, dtype=np.float64), "y": np.asarray(y_mm, dtype=np.float64),
                "z": np.asarray(z_mm, dtype=np.float64)}
        for name, c in axes.items():  # the grid as lfpiv has always kept it
            run_array(g, f"{name}_mm", "mm", [name], f"world {name} of the window centres", shape=c.shape,
                      dtype=np.float64)[...] = c
        add_coordinates(g, axes, n_pairs=self.n_pairs, timing=self.timing, of="the window centres")
        shape = (self.n_pairs, len(axes["z"]), len(axes["y"]), len(axes["x"]))
        chunks = (1, *shape[1:])
        dims = ["pair", "z", "y", "x"]
        fields = [run_array(g, name, "m/s", dims, f"velocity along world {what}; NaN where not measured",
                            shape=shape, chunks=chunks, dtype=np.float32, fill_value=np.nan)
                  for name, what in (("u", "x"), ("v", "y"), ("w", "z"))]
        fields.append(run_array(g, "flags", "1", dims, "vector quality flags (bits)", shape=shape,
                                chunks=chunks, dtype=np.uint8, fill_value=0))
        fields[-1].attrs.update({"flag_masks": [1, 2], "flag_meanings": "outlier replaced"})
        fields.append(run_array(g, "peak_ratio", "1", dims, "highest over second-highest correlation peak "
                                "of the last pass", shape=shape, chunks=chunks, dtype=np.float32,
                                fill_value=np.nan))
        for a in fields:
            a.attrs["coordinates"] = COORDINATES

    def vector_arrays(self) -> dict[str, zarr.Array]:
        """The ``u``, ``v``, ``w``, ``flags`` and ``peak_ratio`` arrays being written (``vectors/``
        or its pending replacement, :meth:`writing`), opened now.

        For a worker that writes many pairs while another process records them: writing through
        arrays opened once never reads the group's attributes again, which the recording process
        rewrites as pairs finish (see :meth:`write_vectors`).
        """
        key = self._target["vectors"]
        if key not in self.group:
            raise RunStoreError(f"{self.path} has no {key}/ group; create it first")
        g = self.group[key]
        return {n: g[n] for n in VECTOR_FIELDS}

    def write_vectors(self, pair: int, velocity_m_s: np.ndarray, flags: np.ndarray, peak_ratio: np.ndarray, *,
                      record: bool = True, arrays: dict[str, zarr.Array] | None = None) -> None:
        """Store the vector field of one pair; with ``record`` False, without adding it to
        ``correlated_pairs`` (for concurrent writers: see :meth:`write_volume`).

        Parameters
        ----------
        pair
            Pair index.
        velocity_m_s
            (z, y, x, 3) velocity (u, v, w) in m/s.
        flags
            (z, y, x) uint8 flags (1 outlier, 2 replaced).
        peak_ratio
            (z, y, x) peak ratio.
        arrays
            :meth:`vector_arrays` opened before, to write through; by default they are opened now.
        """
        g = self.vector_arrays() if arrays is None else arrays
        shape = g["u"].shape[1:]
        vel = np.asarray(velocity_m_s)
        if vel.shape != (*shape, 3) or np.shape(flags) != shape or np.shape(peak_ratio) != shape:
            raise RunStoreError(f"vectors of this run are (z, y, x) = {shape}, got velocity {vel.shape}, "
                                f"flags {np.shape(flags)}, peak_ratio {np.shape(peak_ratio)}")
        for c, name in enumerate("uvw"):
            g[name][pair] = vel[..., c].astype(np.float32)
        g["flags"][pair] = np.asarray(flags, dtype=np.uint8)
        g["peak_ratio"][pair] = np.asarray(peak_ratio, dtype=np.float32)
        if record:
            self.record_vectors([pair])

    def record_vectors(self, pairs: list[int]) -> None:
        """Add pairs whose vectors are already written to ``correlated_pairs``."""
        g = self.writing("vectors")
        done = sorted(set(self.done_pairs("vectors", g)) | {int(p) for p in pairs})
        g.attrs.update({"correlated_pairs": done})

    @property
    def has_vectors(self) -> bool:
        return "vectors" in self.group

    @property
    def vectors_outdated(self) -> bool:
        """True when ``vectors/`` was correlated from volumes since replaced (or removed)."""
        if not self.has_vectors:
            return False
        made_from = self.vector_attrs().get("volumes_id")
        return made_from is not None and made_from != self.volumes_id

    def correlated_pairs(self) -> list[int]:
        """The pairs of ``vectors/`` whose vectors are written ([] if the run has no vectors)."""
        return list(self.vector_attrs()["correlated_pairs"]) if self.has_vectors else []

    def vector_attrs(self, *, group: zarr.Group | None = None) -> dict[str, Any]:
        """The attributes of ``vectors/`` (or of ``group``, its pending replacement), checked
        (:class:`~lfcore.runstore._schema.VectorsAttrs`: ``dt_s``, windows, overlap, settings and
        the pairs correlated), a copy.

        Raises
        ------
        RunStoreError
            The run has no vectors, or one of them is not what the layout gives it (one line
            naming it).
        """
        g = self._vectors_group() if group is None else group
        return dict(validated(self.path, g.basename, g.attrs))

    def _vectors_group(self) -> zarr.Group:
        """The ``vectors/`` group.

        Raises
        ------
        RunStoreError
            If the run has no vectors.
        """
        if not self.has_vectors:
            raise RunStoreError(f"{self.path} has no vectors; run 'lfpiv correlate {self.path}' first")
        return self.group["vectors"]

    def vectors(self) -> dict[str, Any]:
        """``vectors/`` as NumPy arrays: u, v, w, flags, peak_ratio (pairs, z, y, x); x_mm, y_mm, z_mm; attrs
        (:meth:`read_vectors` reads one pair checking its chunks).

        Raises
        ------
        RunStoreError
            If the run has no vectors.
        """
        g = self._vectors_group()
        self.vector_attrs()  # damaged attributes are said before any array is read
        out: dict[str, Any] = {}
        for n in (*VECTOR_FIELDS, *GRID_ARRAYS):
            try:
                out[n] = g[n][...]
            except Exception as exc:  # noqa: BLE001 - a damaged chunk (checksum, codec, size): name it
                for pair in self.correlated_pairs():
                    self.read_vectors(pair)  # type: ignore[attr-defined] - raises naming the pair and chunk
                raise RunStoreError(f"{self.path}: vectors/{n} cannot be read ({type(exc).__name__}: {exc}); "
                                    f"'lfpiv check {self.path}' lists what is damaged") from None
        out["attrs"] = self.vector_attrs()
        return out
