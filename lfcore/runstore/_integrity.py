"""Damage named as damage: reads that check every chunk they use, and a walk over the whole run.

Every chunk a run store writes carries a CRC-32C (zarr's ``crc32c`` codec), and every chunk
written is stored, even one equal to the fill value, so in a store made with checksums:

- a frame of a committed pair has an image (its ``frame_id`` is not -1) or a row in ``drops/``
  saying why not; its chunk missing is damage;
- a volume of a reconstructed pair, and the vectors of a correlated pair, have all their chunks;
- a chunk whose bytes changed fails its checksum; one cut short, or of the wrong size, fails too.

Stores made before checksums did not store chunks equal to the fill value and cannot tell a
changed chunk that still decodes: for them a missing frame of a recorded frame id is still
reported (frames are never all zero in practice), missing chunks of volumes and vectors read as
their fill value as before, and only chunks that fail to decode are damage.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import zarr

from lfcore.runstore._chunks import (
    RESTORE,
    checksummed,
    chunk_coords,
    chunk_problem,
    chunk_stored,
    damage,
    dtype_problem,
    read_slab,
)
from lfcore.runstore._common import STATES, Part, RunStoreError
from lfcore.runstore._coords import COORDINATE_ARRAYS
from lfcore.runstore._drops import DROP_FIELDS
from lfcore.runstore._frames import CAMERA_ARRAYS
from lfcore.runstore._schema import problems
from lfcore.runstore._truth import TRUTH_ARRAYS
from lfcore.runstore._vectors import GRID_ARRAYS, VECTOR_FIELDS
from lfcore.runstore._volumes import VOLUME_DTYPE, grid_problem
from lfcore.volume import VolumeGrid
from lfcore.zarrstore import damaged_metadata

_FRAME = "AB"


def _pairs(first: int, last: int) -> str:
    return f"pair {first}" if first == last else f"pairs {first}-{last}"


class Integrity(Part):
    """Reads that tell damage from data (:meth:`read_frame`, :meth:`read_volume`,
    :meth:`read_vectors`) and :meth:`verify`, which lists every problem of the run."""

    def _line(self, text: str) -> str:
        return f"{self.path}: {text}"

    def _array(self, key: str, *, missing_ok: bool = False) -> tuple[zarr.Array | None, str | None]:
        """The array ``key`` of the run, or None and the line saying why it cannot be opened
        (None and None: it is missing, and ``missing_ok``)."""
        try:
            node = self.group[key]
        except KeyError:
            return None, None if missing_ok else self._line(f"{key} is missing; {RESTORE}")
        except json.JSONDecodeError as exc:
            return None, self._line(f"{damaged_metadata(key, exc)}; restore that file from a copy of the run")
        except Exception as exc:  # noqa: BLE001 - metadata zarr cannot make sense of
            return None, self._line(f"{key}/zarr.json cannot be read ({type(exc).__name__}: {exc}); restore that "
                                    "file from a copy of the run")
        if not isinstance(node, zarr.Array):
            return None, self._line(f"{key} is a group, not an array; {RESTORE}")
        return node, None

    def _checked(self, key: str, dtype: type | str, *, missing: str | None = None) -> zarr.Array:
        """The array ``key``, of the data type the layout gives it, or a :class:`RunStoreError`
        (``missing``: its message when there is no such array)."""
        a, problem = self._typed(key, dtype, missing_ok=missing is not None)
        if problem is not None:
            raise RunStoreError(problem)
        if a is None:
            raise RunStoreError(missing)
        return a

    def _typed(self, key: str, dtype: type | str, *, missing_ok: bool = False) -> tuple[zarr.Array | None, str | None]:
        """:meth:`_array`, and the line saying so if it does not hold the data type of the layout."""
        a, problem = self._array(key, missing_ok=missing_ok)
        if a is not None and (wrong := dtype_problem(a, dtype)):
            return None, self._line(wrong)
        return a, problem

    def _read(self, a: zarr.Array, lead: tuple[int | slice, ...], where: str, *, strict: bool = False) -> np.ndarray:
        """``a[lead]`` of a recorded item, every chunk of it intact, and stored (in a store with
        checksums, or ``strict``: stores before them did not store chunks of fill values)."""
        if strict or checksummed(a):
            for c in chunk_coords(a, lead):
                if not chunk_stored(a, c):
                    raise RunStoreError(self._line(damage(a, where, c, "is missing")))
        data, problem = read_slab(a, lead, where)
        if problem is not None:
            raise RunStoreError(self._line(problem))
        return data

    # --- checked reads --------------------------------------------------------------------
    def read_frame(self, camera: str, pair: int, frame: int) -> np.ndarray:
        """One recorded frame (rows, columns) uint16 of a committed pair, 0: frame A, 1: frame B.

        Unlike indexing :meth:`frames`, which gives zeros for a chunk that is not there, this
        reads a frame only from its chunk, stored and intact.

        Raises
        ------
        RunStoreError
            One line: the pair is not committed, the frame was lost while recording (with the
            reason from ``drops/``), or its chunk is missing or damaged (naming the array, pair,
            frame and chunk), or the array's metadata is.
        """
        a = self._checked(f"{camera}/frames", CAMERA_ARRAYS["frames"])
        n = a.shape[0]
        if not (0 <= pair < n and frame in (0, 1)):
            raise RunStoreError(self._line(f"{camera} has pairs 0-{n - 1}, frames 0 (A) and 1 (B): pair {pair} "
                                           f"frame {frame} is none of them"))
        where = f"pair {pair} frame {_FRAME[frame]}"
        committed = self.committed_pairs
        if pair >= committed:
            held = f"pairs 0-{committed - 1}" if committed else "no pairs yet"
            still = ", and is still recording" if self.state == "recording" else ""
            raise RunStoreError(self._line(f"{camera} {where} is not recorded: the run holds {held}{still}"))
        (c,) = chunk_coords(a, (pair, frame))
        if not chunk_stored(a, c):
            lost = next((d["reason"] for d in self.drops()
                         if (d["camera"], d["pair"], d["frame"]) == (camera, pair, frame)), None)
            if lost is not None:
                raise RunStoreError(self._line(f"{camera} {where} was lost while recording ({lost}); it has no image"))
        return self._read(a, (pair, frame), where, strict=True)

    def read_volume(self, pair: int, frame: int, *, planes: tuple[int, int] | None = None) -> np.ndarray:
        """One reconstructed volume (z, y, x) float32 of ``volumes/``, every chunk stored and intact.

        ``planes`` (z0, z1) reads only planes z0 .. z1 - 1 (depth slabs), and checks only the
        chunks that hold them.

        Raises
        ------
        RunStoreError
            One line: the run has no volumes, the volume is not reconstructed, or one of its
            chunks is missing or damaged (naming the array, pair, frame and chunk).
        """
        a = self._checked("volumes/data", VOLUME_DTYPE, missing=self._NO_VOLUMES.format(path=self.path))
        n = a.shape[0]
        if not (0 <= pair < n and frame in (0, 1)):
            raise RunStoreError(self._line(f"volumes/data has pairs 0-{n - 1}, frames 0 (A) and 1 (B): pair {pair} "
                                           f"frame {frame} is none of them"))
        where = f"pair {pair} frame {_FRAME[frame]}"
        written = {tuple(x) for x in self._volume_attr("_frames_written")}  # type: ignore[attr-defined]
        if pair not in self.reconstructed_pairs() and (pair, frame) not in written:
            raise RunStoreError(self._line(f"volumes/ has no volume of {where}: it is not reconstructed; run 'lfpiv "
                                           f"reconstruct {self.path} --pairs {pair}:{pair + 1}'"))
        if planes is None:
            return self._read(a, (pair, frame), where)
        z0, z1 = (int(v) for v in planes)
        nz = a.shape[2]
        if not 0 <= z0 < z1 <= nz:
            raise RunStoreError(self._line(f"volumes/data is {nz} planes deep: planes {z0}-{z1 - 1} are not all in it"))
        return self._read(a, (pair, frame, slice(z0, z1)), where)

    def read_vectors(self, pair: int) -> dict[str, np.ndarray]:
        """The vectors of one correlated pair: u, v, w (m/s), flags and peak_ratio, each (z, y, x),
        every chunk stored and intact.

        Raises
        ------
        RunStoreError
            One line: the run has no vectors, the pair is not correlated, or a chunk of it is
            missing or damaged (naming the array, pair and chunk).
        """
        self._vectors_group()  # says so when there are none
        if pair not in self.correlated_pairs():
            raise RunStoreError(self._line(f"vectors/ has no vectors of pair {pair}: it is not correlated; run "
                                           f"'lfpiv correlate {self.path}'"))
        out = {}
        for name, dtype in VECTOR_FIELDS.items():
            a = self._checked(f"vectors/{name}", dtype)
            if not 0 <= pair < a.shape[0]:
                raise RunStoreError(self._line(f"vectors/ lists pair {pair} as correlated, but vectors/{name} holds "
                                               f"{a.shape[0]} pairs (its zarr.json was edited or damaged); {RESTORE}"))
            out[name] = self._read(a, (pair,), f"pair {pair}")
        return out

    # --- the whole run ----------------------------------------------------------------------
    @classmethod
    def check(cls, path: str | Path) -> list[str]:
        """:meth:`verify` of the run at ``path``, opened read-only; a run that cannot be opened
        gives the one line saying why. Never raises for damage."""
        try:
            store = cls.open(path)  # type: ignore[attr-defined]
        except RunStoreError as exc:
            return [str(exc)]
        return store.verify()

    def verify(self) -> list[str]:
        """Every problem of the run, one line each (naming the array, the pair and frame, and
        the chunk, and what to do), or [] for a whole run. Never raises for damage.

        It reads every chunk of the committed pairs' frames, ids and time stamps, of drops and
        truth, and of the volumes and vectors of the pairs they list as done (checksums checked
        by zarr as it decodes them), and checks that each recorded item has its chunks, each
        array the data type and shape the layout gives it, and the root attributes
        (``committed_pairs`` within the arrays, ``state``) make sense. Pending replacements
        (``*.pending/``) are work in progress and not checked.
        """
        out: list[str] = []
        committed = self._verify_root(out)
        lost = self._verify_drops(out)
        for cam in self.cameras:
            self._verify_camera(cam, committed, lost, out)
        self._verify_truth(out)
        self._verify_derived("volumes", out)
        self._verify_derived("vectors", out)
        self._verify_particles(out)
        return out

    def _verify_particles(self, out: list[str]) -> None:
        """``particles/``: its table and index, every chunk, and each recorded pair's rows within the table."""
        if "particles" not in self.group:
            return
        table = self._layout("particles/table", np.float64, out)
        index = self._layout("particles/index", np.int64, out)
        if table is not None:
            step = int(table.chunks[0])
            for c in chunk_coords(table, ()):
                first = c[0] * step
                where = f"rows {first} to {min(table.shape[0], first + step) - 1}"
                self._verify_chunks(table, [c], where, required=checksummed(table), out=out)
        if index is None or table is None:
            return
        if not self._verify_chunks(index, list(chunk_coords(index, ())), "(all)", required=checksummed(index),
                                   out=out):
            return
        bounds = index[...]
        for p in self.group["particles"].attrs.get("particle_pairs", []):
            if not (isinstance(p, int) and 0 <= p < bounds.shape[0]) or np.any(bounds[p] < 0) or np.any(
                    bounds[p, :, 1] < bounds[p, :, 0]) or np.any(bounds[p] > table.shape[0]):
                out.append(self._line(f"particles/ lists pair {p} in particle_pairs, but particles/index does not "
                                      f"hold its rows (its zarr.json was edited or damaged); {RESTORE}"))

    def _verify_root(self, out: list[str]) -> int:
        # the number of pairs to walk: committed_pairs as recorded, if it is one
        a = self.group.attrs
        # every root attribute as the layout gives it (state and committed_pairs: their own lines below)
        out.extend(problems(self.path, "", a, skip=("state", "committed_pairs")))
        try:
            _ = self.rig  # type: ignore[attr-defined] - validated like a rig file
        except RunStoreError as exc:
            out.append(str(exc))
        c = a.get("committed_pairs")
        if a.get("state") not in STATES:
            out.append(self._line(f"state is {a.get('state')!r}, not one of {STATES} (the root zarr.json was edited "
                                  f"or damaged); {RESTORE}"))
        if isinstance(c, bool) or not isinstance(c, int | float) or c != int(c) or c < 0:
            out.append(self._line(f"committed_pairs is {c!r}, not a number of pairs (the root zarr.json was edited "
                                  f"or damaged); {RESTORE}"))
            return 0
        return int(c)

    def _verify_chunks(self, a: zarr.Array, coords: list[tuple[int, ...]], where: str, *, required: bool,
                       out: list[str]) -> bool:
        """Append the problems of the chunks ``coords`` of ``a``; True if there were none."""
        ok = True
        for c in coords:
            problem = chunk_problem(a, c, required=required)
            if problem is not None:
                out.append(self._line(damage(a, where, c, problem)))
                ok = False
        return ok

    def _verify_whole(self, a: zarr.Array, out: list[str], *, required: bool) -> None:
        """Every chunk of ``a``, each named by the pairs (first axis) it holds."""
        step = int(a.chunks[0]) if a.ndim else 1
        for c in chunk_coords(a, ()):
            first = c[0] * step if a.ndim else 0
            where = _pairs(first, min(a.shape[0], first + step) - 1) if a.ndim and a.shape[0] else "(all)"
            self._verify_chunks(a, [c], where, required=required, out=out)

    def _layout(self, key: str, dtype: type | str, out: list[str]) -> zarr.Array | None:
        """:meth:`_typed` for :meth:`verify`: the array, or None and its problem appended to ``out``."""
        a, problem = self._typed(key, dtype)
        if problem is not None:
            out.append(problem)
        return a

    def _holds_the_pairs(self, a: zarr.Array, out: list[str]) -> bool:
        """Whether ``a`` has one entry per pair of the run along its first axis; if not, says so."""
        if a.shape[0] == self.n_pairs:
            return True
        out.append(self._line(f"{a.path} holds {a.shape[0]} pairs, but the run has {self.n_pairs} (its zarr.json was "
                              f"edited or damaged); {RESTORE}"))
        return False

    def _verify_drops(self, out: list[str]) -> set[tuple[str, int, int]] | None:
        """Check ``drops/``; the (camera, pair, frame) of every lost frame, or None if unreadable."""
        cols = {}
        for name, (dtype, _, _) in DROP_FIELDS.items():
            a = self._layout(f"drops/{name}", "str" if dtype is str else dtype, out)
            if a is not None and self._verify_chunks(a, chunk_coords(a, ()), "rows", required=False, out=out):
                cols[name] = a[...]
        if len(cols) < len(DROP_FIELDS):
            return None
        n = min(len(v) for v in cols.values())  # a kill between two resizes leaves some longer: not damage
        return {(str(cols["camera"][i]), int(cols["pair"][i]), int(cols["frame"][i]))
                for i in range(n) if cols["reason"][i]}

    def _verify_camera(self, cam: str, committed: int, lost: set[tuple[str, int, int]] | None,
                       out: list[str]) -> None:
        arrays = {name: self._layout(f"{cam}/{name}", dtype, out) for name, dtype in CAMERA_ARRAYS.items()}
        frames = arrays["frames"]
        rig_cam = next((c for c in self.group.attrs["rig"]["camera"] if c.get("name") == cam), {})
        cols, rows = rig_cam.get("sensor_px", (None, None))
        if frames is not None and (frames.ndim != 4 or frames.shape[1] != 2 or frames.shape[2:] != (rows, cols)):
            out.append(self._line(f"{cam}/frames is {frames.shape}, but the layout says (pairs, 2, {rows}, {cols}) "
                                  f"for camera {cam} of the rig (its zarr.json was edited or damaged); {RESTORE}"))
            frames = None
        present = {name: a for name, a in arrays.items() if a is not None}
        walk = min([committed, *(a.shape[0] for a in present.values())])
        if walk < committed:
            name, a = min(present.items(), key=lambda kv: kv[1].shape[0])
            out.append(self._line(f"committed_pairs is {committed}, more than the {a.shape[0]} pairs {cam}/{name} "
                                  f"holds (the root zarr.json was edited or damaged); {RESTORE}"))
        # frame ids and time stamps, chunk by chunk; ids of a damaged chunk are unknown
        ids: np.ndarray | None = None
        for name in ("frame_id", "timestamp_ns"):
            a = arrays[name]
            if a is None:
                continue
            step = int(a.chunks[0])
            values = np.full((walk, 2), -2, dtype=np.int64)  # -2: unknown
            for ci in range(-(-walk // step)):
                where = _pairs(ci * step, min(a.shape[0], (ci + 1) * step) - 1)
                if self._verify_chunks(a, [(ci, 0)], where, required=checksummed(a), out=out):
                    block = a.get_block_selection((ci, 0))
                    values[ci * step:min(walk, (ci + 1) * step)] = block[:min(walk, (ci + 1) * step) - ci * step]
            if name == "frame_id":
                ids = values
        if frames is None:
            return
        for p in range(walk):
            for k in (0, 1):
                where = f"pair {p} frame {_FRAME[k]}"
                (c,) = chunk_coords(frames, (p, k))
                fid = int(ids[p, k]) if ids is not None else -2
                dropped = lost is not None and (cam, p, k) in lost
                if fid == -1 and not dropped and lost is not None:
                    out.append(self._line(f"{cam} {where} is neither recorded (frame_id -1) nor listed in drops/ as "
                                          f"lost: {cam}/frame_id or drops/ is damaged; {RESTORE}"))
                required = fid >= 0 or (fid == -2 and not dropped and checksummed(frames))
                self._verify_chunks(frames, [c], where, required=required, out=out)

    def _verify_truth(self, out: list[str]) -> None:
        if "truth" not in self.group:
            return
        g = self.group["truth"]
        for name, dtype in TRUTH_ARRAYS.items():
            if name == "t0_s" and name not in g:  # written before the times were kept
                continue
            a = self._layout(f"truth/{name}", dtype, out)
            if a is not None and self._holds_the_pairs(a, out):
                self._verify_whole(a, out, required=checksummed(a))
        out.extend(problems(self.path, "truth", g.attrs))

    def _verify_derived(self, name: str, out: list[str]) -> None:
        """``volumes/`` or ``vectors/``: their arrays, the pairs they list as done, and every
        chunk of those pairs."""
        try:
            if name not in self.group:
                if any((Path(self.path) / name).glob("*/zarr.json")):  # its arrays, without the group's record
                    out.append(self._line(f"{name}/zarr.json is missing, the record of which pairs {name}/ holds; "
                                          f"{RESTORE}"))
                return
            g = self.group[name]
        except json.JSONDecodeError as exc:
            out.append(self._line(f"{damaged_metadata(name, exc)}; restore that file from a copy of the run"))
            return
        fields: dict[str, type | str] = {"data": VOLUME_DTYPE} if name == "volumes" else dict(VECTOR_FIELDS)
        if name == "volumes":
            a, problem = self._array("volumes/data", missing_ok=True)
            if a is None and problem is None:  # a reconstruction killed as it began: none
                if g.attrs.get(self.DONE[name]):  # type: ignore[attr-defined]
                    out.append(self._line(f"volumes/data is missing, though volumes/ records reconstructed pairs; "
                                          f"{RESTORE}"))
                return
        arrays = {n: self._layout(f"{name}/{n}", t, out) for n, t in fields.items()}
        done_key = self.DONE[name]  # type: ignore[attr-defined]
        wrong = problems(self.path, name, g.attrs)
        out.extend(wrong)
        done = g.attrs.get(done_key, [])
        if any(f" attribute {done_key} " in line for line in wrong):
            done = []
        elif name == "volumes" and not wrong and arrays["data"] is not None:
            grid = VolumeGrid(shape=tuple(int(n) for n in arrays["data"].shape[2:]),
                              voxel_mm=tuple(g.attrs["voxel_mm"]), origin_mm=tuple(g.attrs["origin_mm"]))
            mismatch = grid_problem(g, grid)
            if mismatch is not None:
                out.append(self._line(f"{mismatch}; {RESTORE}"))
        for n, a in arrays.items():
            if a is None or not self._holds_the_pairs(a, out):
                continue
            for p in done:
                if not 0 <= p < a.shape[0]:
                    out.append(self._line(f"{name}/ lists pair {p} in {done_key}, but {name}/{n} holds {a.shape[0]} "
                                          f"pairs (its zarr.json was edited or damaged); {RESTORE}"))
                    continue
                for k in ((0, 1) if name == "volumes" else (None,)):
                    lead = (p,) if k is None else (p, k)
                    where = f"pair {p}" if k is None else f"pair {p} frame {_FRAME[k]}"
                    self._verify_chunks(a, chunk_coords(a, lead), where, required=checksummed(a), out=out)
        grid = GRID_ARRAYS if name == "vectors" else ()
        for n in (*grid, *(c for c in COORDINATE_ARRAYS if c in g)):  # older stores have no coordinate arrays
            a = self._layout(f"{name}/{n}", np.float64, out)
            if a is not None:
                self._verify_whole(a, out, required=checksummed(a))
