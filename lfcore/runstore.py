"""The run store: one zarr v3 directory per run, recorded or synthetic (DESIGN.md, "Files").

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
                              settings, reconstructed_pairs
      vectors/                u, v, w, flags, peak_ratio (pairs, z, y, x); x_mm, y_mm, z_mm
      volumes.pending/,       a replacement of volumes/ or vectors/ (other settings) being made,
      vectors.pending/        same layout; it becomes volumes/ or vectors/ only once complete, so
                              an interrupted replacement leaves the old ones whole; readers
                              ignore it

Every array carries ``units`` and ``axes`` attributes, so plain zarr or xarray users can read a
run without lfpiv. Pairs ``0 .. committed_pairs - 1`` are complete; ``state`` says whether the
run is still ``recording``, ``complete`` or ``aborted``.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import numcodecs
import numpy as np
import zarr
from zarr.codecs import BloscCodec, BytesCodec
from zarr.storage import LocalStore

from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfcore.zarrstore import RigStore, described_array

__all__ = ["RunStore", "RunStoreError", "STATES"]

FORMAT = "lfpiv-run"
FORMAT_VERSION = 1
STATES = ("recording", "complete", "aborted")
_DROP_FIELDS = {
    "camera": (str, "", "camera name"),
    "pair": (np.int64, -1, "pair index, -1 if unknown"),
    "frame": (np.int64, -1, "0 for frame A, 1 for frame B, -1 if unknown"),
    "frame_id": (np.int64, -1, "camera frame counter"),
    "timestamp_ns": (np.int64, -1, "when the loss was detected, ns since the epoch"),
    "reason": (str, "", "why the frame was lost"),
}


#: Raw frames are compressed with LZ4 after bit shuffling (Blosc). Camera counts of 12 bits or
#: fewer leave the top bits of every uint16 zero, which bit shuffling turns into long zero runs:
#: on rendered 2048 x 2048 light-field frames it encodes at about 1.2 GB/s per core with a ratio
#: of 1.66, against 1.0 GB/s and 1.42 with byte shuffling and 0.4 GB/s with Zstandard, so the
#: recorder keeps up with the cameras. Any zarr reader decodes it.
FRAME_CODEC = BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle")


class FrameWriter:
    """Writes raw frames into one camera's ``frames`` array, one encoded chunk per frame.

    For a run store in a local directory with the frames' own codecs (little-endian bytes, then
    Blosc), each frame is compressed with Blosc and written as its chunk file directly: the
    same bytes zarr itself writes, at about twice the rate of ``zarr.Array.__setitem__`` (whose
    codec pipeline, not the disk, bounds a recording). Any other store or codec is written
    through zarr. Callers may write from several threads, distinct frames each.

    Parameters
    ----------
    array
        A (pairs, 2, rows, columns) uint16 frames array (:meth:`RunStore.frames`).
    """

    def __init__(self, array: zarr.Array) -> None:
        self.array = array
        self._root: Path | None = None
        self._blosc: numcodecs.Blosc | None = None
        meta = array.metadata
        codecs = getattr(meta, "codecs", ())
        store = array.store_path.store
        direct = (isinstance(store, LocalStore) and array.dtype == np.uint16 and len(codecs) == 2
                  and isinstance(codecs[0], BytesCodec) and getattr(codecs[0].endian, "value", None) == "little"
                  and isinstance(codecs[1], BloscCodec)
                  and tuple(array.chunks) == (1, 1, *array.shape[2:]))
        if direct:
            b = codecs[1]
            shuffle = {"noshuffle": numcodecs.Blosc.NOSHUFFLE, "shuffle": numcodecs.Blosc.SHUFFLE,
                       "bitshuffle": numcodecs.Blosc.BITSHUFFLE}[b.shuffle.value]
            self._blosc = numcodecs.Blosc(cname=b.cname.value, clevel=b.clevel, shuffle=shuffle, blocksize=b.blocksize)
            self._root = Path(store.root) / array.store_path.path

    @property
    def direct(self) -> bool:
        """True when frames are encoded and written as chunk files directly."""
        return self._blosc is not None

    def write(self, pair: int, frame: int, image: np.ndarray) -> None:
        """Store one (rows, columns) uint16 frame of ``pair`` (0: frame A, 1: frame B)."""
        if self._blosc is None:
            self.array[pair, frame] = image
            return
        assert self._root is not None
        path = self._root / self.array.metadata.encode_chunk_key((pair, frame, 0, 0))
        data = self._blosc.encode(np.ascontiguousarray(image, dtype="<u2"))
        try:
            path.write_bytes(data)
        except FileNotFoundError:  # the chunk's folder is made on first use
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)

    def write_pairs(self, first: int, frames: np.ndarray) -> None:
        """Store (n, 2, rows, columns) uint16 frames of pairs ``first`` .. ``first + n - 1``."""
        if self._blosc is None:
            self.array[first:first + len(frames)] = frames
            return
        for i, pair in enumerate(frames):
            for k in range(2):
                self.write(first + i, k, pair[k])


class RunStoreError(ValueError):
    """A run store that cannot be created or read; the message says what to do."""


class RunStore(RigStore):
    """Read and write access to one run.

    Use :meth:`create` for a new run and :meth:`open` for an existing one.
    """

    FORMAT = FORMAT
    FORMAT_VERSION = FORMAT_VERSION
    KIND = "lfpiv run store"
    HINT = "give the path of a run store (a .zarr directory)"
    Error = RunStoreError
    #: Suffix of the group where a replacement of ``volumes/`` or ``vectors/`` is made.
    PENDING = ".pending"

    def __init__(self, group: zarr.Group, path: Path) -> None:
        super().__init__(group, path)
        # where volumes/ and vectors/ are written: themselves, or their pending replacement
        self._target = {"volumes": "volumes", "vectors": "vectors"}

    # --- creation and opening -----------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, rig: Rig, n_pairs: int, *, timing: dict[str, Any],
               software_version: str, overwrite: bool = False) -> RunStore:
        """Create an empty run of ``n_pairs`` pairs for every camera of ``rig``.

        Raises
        ------
        RunStoreError
            If ``path`` exists and ``overwrite`` is false (nothing recorded is ever replaced
            silently), or if ``n_pairs`` is not positive.
        """
        path = Path(path)
        if n_pairs < 1:
            raise RunStoreError(f"a run needs at least one pair, got {n_pairs}")
        cls.check_new(path, overwrite)
        root = zarr.open_group(str(path), mode="w", zarr_format=3)
        root.attrs.update({
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "rig": rig.to_dict(),
            "timing": timing,
            "software_version": software_version,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "state": "recording",
            "committed_pairs": 0,
        })
        for cam in rig.camera:
            cols, rows = cam.sensor_px
            g = root.create_group(cam.name)
            g.attrs.update({"sensor_px": [cols, rows]})
            described_array(g, "frames", "counts", ["pair", "frame", "row", "column"],
                            "raw light-field images; frame 0 is A, 1 is B", shape=(n_pairs, 2, rows, cols),
                            chunks=(1, 1, rows, cols), dtype=np.uint16, fill_value=0, compressors=FRAME_CODEC)
            for name, units, what in (("frame_id", "1", "camera frame counter"),
                                      ("timestamp_ns", "ns", "the camera's clock where it has one, else the host's "
                                       "time of fetch (ns since the epoch); synthetic runs: from the first pulse")):
                described_array(g, name, units, ["pair", "frame"], what + "; -1 where never written",
                                shape=(n_pairs, 2), chunks=(min(n_pairs, 1024), 2), dtype=np.int64, fill_value=-1)
        drops = root.create_group("drops")
        drops.attrs.update({"description": "every frame that was not recorded, with the reason; a row with an "
                                           "empty reason was never written (a recorder killed while adding it)"})
        for name, (dtype, fill, what) in _DROP_FIELDS.items():
            described_array(drops, name, "ns" if name == "timestamp_ns" else "1", ["drop"], what, shape=(0,),
                            chunks=(4096,), dtype=dtype, fill_value=fill)
        return cls(root, path)

    @classmethod
    def check_new(cls, path: str | Path, overwrite: bool = False) -> None:
        """Raise :class:`RunStoreError` unless a new run may be created at ``path``.

        ``overwrite`` replaces only an lfpiv run store, never another file or folder. Call it
        before long work whose result goes to ``path``, so that the user hears at once.
        """
        path = Path(path)
        if path.is_symlink():
            # replacing a run through a link would delete the folder it points to, or write
            # beside a dangling one: say so rather than guess
            raise RunStoreError(f"{path} is a symbolic link (to {os.readlink(path)}); give the real path, or another "
                                "output path")
        if not path.exists():
            return
        if not overwrite:
            raise RunStoreError(f"{path} already exists; choose another output path or pass --overwrite")
        try:
            cls._open_root(path, "r")
        except RunStoreError as exc:
            raise RunStoreError(f"{exc}, and --overwrite replaces only run stores; choose another output path") \
                from None

    @classmethod
    def open(cls, path: str | Path, mode: str = "r") -> RunStore:
        """Open an existing run (``mode`` ``"r"`` or ``"r+"``); ``"r+"`` settles a replacement
        of volumes or vectors killed as it was put in place (:meth:`recover`).

        Raises
        ------
        RunStoreError
            If ``path`` does not exist or is not an lfpiv run store.
        """
        path = Path(path)
        root = cls._open_root(path, mode)
        missing = cls._missing(root)
        if missing:
            raise RunStoreError(f"{path} is incomplete: {missing} is missing (a store still being created, or a "
                                "damaged one), so it cannot be read as a run; if it is not being created, copy what "
                                "you need from it with zarr, or record it again")
        store = cls(root, path)
        if mode != "r":
            store.recover()
        return store

    @staticmethod
    def _missing(root: zarr.Group) -> str | None:
        """The first attribute or array of the layout that ``root`` lacks (a run store damaged
        by hand or cut off while being created), or None."""
        for key in ("rig", "timing", "state", "committed_pairs"):
            if key not in root.attrs:
                return f"the root attribute {key!r}"
        try:
            names = [c["name"] for c in root.attrs["rig"]["camera"]]
        except (KeyError, TypeError):
            return "the rig's cameras"
        needed = [f"{n}/{a}" for n in names for a in ("frames", "frame_id", "timestamp_ns")]
        needed += [f"drops/{f}" for f in _DROP_FIELDS]
        return next((n for n in needed if n not in root), None)

    # --- metadata -----------------------------------------------------------------------
    @property
    def n_pairs(self) -> int:
        return int(self.frames(self.cameras[0]).shape[0])

    @property
    def state(self) -> str:
        return str(self.group.attrs["state"])

    @property
    def committed_pairs(self) -> int:
        return int(self.group.attrs["committed_pairs"])

    @property
    def timing(self) -> dict[str, Any]:
        return dict(self.group.attrs["timing"])

    def frames(self, camera: str) -> zarr.Array:
        """The (pairs, 2, rows, columns) uint16 frames array of one camera."""
        return self.group[f"{camera}/frames"]

    def frame_ids(self, camera: str) -> np.ndarray:
        return self.group[f"{camera}/frame_id"][...]

    def timestamps_ns(self, camera: str) -> np.ndarray:
        return self.group[f"{camera}/timestamp_ns"][...]

    # --- writing ------------------------------------------------------------------------
    def write_frame(self, camera: str, pair: int, frame: int, image: np.ndarray, frame_id: int,
                    timestamp_ns: int) -> None:
        """Store one raw frame (rows, columns) uint16 with its id and timestamp."""
        arr = self.frames(camera)
        if image.shape != arr.shape[2:] or image.dtype != np.uint16:
            raise RunStoreError(f"camera '{camera}' frames are uint16 {arr.shape[2:]}, "
                                f"got {image.dtype} {image.shape}")
        arr[pair, frame] = image
        self.group[f"{camera}/frame_id"][pair, frame] = frame_id
        self.group[f"{camera}/timestamp_ns"][pair, frame] = timestamp_ns

    def commit(self, pairs: int) -> None:
        """Declare pairs ``0 .. pairs - 1`` complete (call after their frames are written)."""
        self.group.attrs["committed_pairs"] = int(pairs)

    def set_state(self, state: str) -> None:
        if state not in STATES:
            raise RunStoreError(f"state must be one of {STATES}, got '{state}'")
        self.group.attrs["state"] = state

    def add_drop(self, camera: str, pair: int, frame: int, frame_id: int, timestamp_ns: int,
                 reason: str) -> None:
        """Append one lost frame to ``drops``."""
        self.add_drops([{"camera": camera, "pair": pair, "frame": frame, "frame_id": frame_id,
                         "timestamp_ns": timestamp_ns, "reason": reason}])

    def add_drops(self, rows: list[dict[str, Any]]) -> None:
        """Append lost frames to ``drops``; each row has the fields camera, pair, frame,
        frame_id, timestamp_ns and reason.

        Every column first grows by the new rows (their fill values: ``reason`` empty), and only
        then are the rows written, ``reason`` last: a row counts once its reason is written (see
        :meth:`drops`). A process killed half-way so leaves no broken row, and the columns keep
        one length (plain zarr and xarray readers need it) unless the kill falls between two
        resizes, a few metadata writes.
        """
        if not rows:
            return
        if not all(r["reason"] for r in rows):
            raise RunStoreError("every drop needs a reason: a row with an empty one reads as never written")
        cols = [self.group[f"drops/{name}"] for name in _DROP_FIELDS]
        n = min(a.shape[0] for a in cols)
        for a in cols:
            a.resize((n + len(rows),))
        for a, (name, (dtype, _, _)) in zip(cols, _DROP_FIELDS.items(), strict=True):
            a[n:] = np.asarray([r[name] for r in rows], dtype=object if dtype is str else dtype)

    def drops(self) -> list[dict[str, Any]]:
        """Every lost frame, as dicts with the fields of ``drops/``.

        Of a run killed while recording (``state`` still "recording"), only the drops of
        committed pairs: rows of a pair the kill left uncommitted, or half-appended, are left out.
        """
        cols = {name: self.group[f"drops/{name}"][...] for name in _DROP_FIELDS}
        n = min(len(v) for v in cols.values())  # a kill between two resizes leaves some columns longer
        rows = [{k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in cols.items()} for i in range(n)]
        if self.state == "recording":
            rows = [r for r in rows if r["pair"] < self.committed_pairs]
        return [r for r in rows if r["reason"]]  # an empty reason: a row grown but never written

    def write_truth(self, particles_mm: np.ndarray, brightness: np.ndarray, flow: dict[str, Any],
                    t0_s: np.ndarray | None = None, **attrs: Any) -> None:
        """Store the ground truth of a synthetic run.

        Parameters
        ----------
        particles_mm
            (pairs, 2, n, 3) float world positions (x, y, z) in mm of every particle in
            frames A and B of every pair.
        brightness
            (pairs, 2, n) signal of each particle in counts (laser sheet included).
        flow
            The flow's name and parameters (:meth:`lfcore.flows.Flow.params`).
        t0_s
            (pairs,) time of each pair's first pulse on the flow's clock, s, kept as
            ``truth/t0_s``; None: pair / ``timing.rate_hz`` (a simulated lab that shows a pool
            of pairs over and over passes the times of the pairs it showed).
        **attrs
            More JSON-compatible attributes (seeding density, seed, render settings).
        """
        if "truth" in self.group:
            del self.group["truth"]
        g = self.group.create_group("truth")
        g.attrs.update({"flow": flow, **attrs})
        p = np.asarray(particles_mm, dtype=np.float64)
        described_array(g, "particles", "mm", ["pair", "frame", "particle", "xyz"], "true particle positions",
                        shape=p.shape, chunks=(1, 2, *p.shape[2:]), dtype=np.float64)[...] = p
        b = np.asarray(brightness, dtype=np.float32)
        described_array(g, "brightness", "counts", ["pair", "frame", "particle"], "signal of each particle",
                        shape=b.shape, chunks=(1, 2, b.shape[2]), dtype=np.float32)[...] = b
        t0 = self._pair_times_s() if t0_s is None else np.asarray(t0_s, dtype=np.float64)
        if t0.shape != (p.shape[0],):
            raise ValueError(f"t0_s must hold one time per pair ({p.shape[0]}), got shape {t0.shape}")
        described_array(g, "t0_s", "s", ["pair"], "time of each pair's first pulse on the flow's clock",
                        shape=t0.shape, chunks=t0.shape, dtype=np.float64)[...] = t0

    def _pair_times_s(self) -> np.ndarray:
        rate = self.timing.get("rate_hz")
        return np.arange(self.n_pairs) / float(rate) if rate else np.zeros(self.n_pairs)

    # --- reconstructed volumes ----------------------------------------------------------
    def create_volumes(self, grid: VolumeGrid, *, method: str, settings: dict[str, Any]) -> zarr.Array:
        """Create (or replace) ``volumes/`` for every pair of the run, all zero.

        Volumes already reconstructed are not deleted: the new ones are made in
        ``volumes.pending/``, which :meth:`finish` makes ``volumes/`` once they are all written
        (see :meth:`writing`).

        ``volumes/data`` is float32 (pairs, 2, z, y, x) in chunks of at most 16 x 256 x 256
        voxels; the group's attributes hold the grid (``origin_mm``, ``voxel_mm``), the method
        and its settings, ``reconstructed_pairs``, the pairs written so far, and ``volumes_id``, a
        name new with every ``volumes/`` made, which the vectors correlated from it record.
        """
        g = self._begin("volumes", staged=bool(self.reconstructed_pairs()))
        g.attrs.update({"origin_mm": list(grid.origin_mm), "voxel_mm": list(grid.voxel_mm), "method": method,
                        "settings": settings, "reconstructed_pairs": [], "volumes_id": uuid.uuid4().hex,
                        "description": "reconstructed particle volumes; origin_mm is the world (x, y, z) "
                                       "of the centre of voxel [0, 0, 0]"})
        nz, ny, nx = grid.shape
        return described_array(g, "data", "intensity", ["pair", "frame", "z", "y", "x"], "voxel intensity",
                               shape=(self.n_pairs, 2, nz, ny, nx), dtype=np.float32, fill_value=0.0,
                               chunks=(1, 1, min(nz, 16), min(ny, 256), min(nx, 256)))

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

    def record_volumes(self, written: list[tuple[int, int]]) -> None:
        """Add (pair, frame) volumes, already written, to ``reconstructed_pairs``."""
        g = self.writing("volumes")
        key = "_frames_written"
        done = {tuple(x) for x in g.attrs.get(key, [])} | {(int(p), int(f)) for p, f in written}
        pairs = sorted({p for p, _ in done if (p, 0) in done and (p, 1) in done})
        g.attrs.update({key: sorted(done), "reconstructed_pairs": pairs})

    @property
    def has_volumes(self) -> bool:
        # a group without its array is a reconstruction killed as it began: none, to make again
        return "volumes/data" in self.group

    @property
    def volumes_id(self) -> str | None:
        """The name of the current ``volumes/`` (new each time it is made), None if there is none
        (or it was made before lfpiv recorded one)."""
        return self.group["volumes"].attrs.get("volumes_id") if self.has_volumes else None

    def volumes(self) -> zarr.Array:
        """The (pairs, 2, z, y, x) float32 ``volumes/data`` array."""
        if not self.has_volumes:
            raise RunStoreError(f"{self.path} has no reconstructed volumes; run 'lfpiv reconstruct {self.path}' first")
        return self.group["volumes/data"]

    def volume_grid(self) -> VolumeGrid:
        """The voxel grid of ``volumes/``."""
        return self.grid_of(self.group["volumes"] if "volumes" in self.group else None)

    def grid_of(self, group: zarr.Group | None) -> VolumeGrid:
        """The voxel grid of a volumes group (``volumes/`` or its pending replacement)."""
        if group is None or "data" not in group:
            raise RunStoreError(f"{self.path} has no reconstructed volumes; run 'lfpiv reconstruct {self.path}' "
                                "first")
        a = group.attrs
        shape = tuple(int(n) for n in group["data"].shape[2:])
        return VolumeGrid(shape=shape, voxel_mm=tuple(a["voxel_mm"]), origin_mm=tuple(a["origin_mm"]))

    def reconstructed_pairs(self) -> list[int]:
        return list(self.group["volumes"].attrs["reconstructed_pairs"]) if self.has_volumes else []

    def truth(self) -> dict[str, Any] | None:
        """``{"particles", "brightness", "t0_s", "attrs"}`` of a synthetic run, or None if recorded.

        ``t0_s`` (pairs,): when each pair's first pulse fired on the flow's clock, s, the time
        to evaluate the truth flow at (pair / ``timing.rate_hz`` for stores written before it
        was kept).
        """
        if "truth" not in self.group:
            return None
        g = self.group["truth"]
        missing = [n for n in ("particles", "brightness") if n not in g]
        if missing:
            raise RunStoreError(f"{self.path}: truth/ has no {missing[0]} (the run was interrupted while its "
                                "truth was written); render it again with --overwrite")
        t0 = g["t0_s"][...] if "t0_s" in g else self._pair_times_s()
        return {"particles": g["particles"][...], "brightness": g["brightness"][...], "t0_s": t0,
                "attrs": dict(g.attrs)}

    # --- vector fields --------------------------------
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
        correlated from.
        """
        g = self._begin("vectors", staged=bool(self.correlated_pairs()))
        g.attrs.update({"dt_s": float(dt_s), "windows": [[int(n) for n in w] for w in windows],
                        "overlap": [float(o) for o in overlap], "settings": settings, "correlated_pairs": [],
                        "volumes_id": self.volumes_id,
                        "description": "3D velocity from multi-grid cross-correlation of volumes/data; windows "
                                       "are (x, y, z) voxels per pass"})
        coords = {"x_mm": x_mm, "y_mm": y_mm, "z_mm": z_mm}
        for name, c in coords.items():
            c = np.asarray(c, dtype=np.float64)
            described_array(g, name, "mm", [name[0]], f"world {name[0]} of the window centres", shape=c.shape,
                            dtype=np.float64)[...] = c
        shape = (self.n_pairs, len(coords["z_mm"]), len(coords["y_mm"]), len(coords["x_mm"]))
        chunks = (1, *shape[1:])
        axes = ["pair", "z", "y", "x"]
        for name, what in (("u", "x"), ("v", "y"), ("w", "z")):
            described_array(g, name, "m/s", axes, f"velocity along world {what}; NaN where not measured",
                            shape=shape, chunks=chunks, dtype=np.float32, fill_value=np.nan)
        a = described_array(g, "flags", "1", axes, "vector quality flags (bits)", shape=shape, chunks=chunks,
                            dtype=np.uint8, fill_value=0)
        a.attrs.update({"flag_masks": [1, 2], "flag_meanings": "outlier replaced"})
        described_array(g, "peak_ratio", "1", axes, "highest over second-highest correlation peak of the last pass",
                        shape=shape, chunks=chunks, dtype=np.float32, fill_value=np.nan)

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
        return {n: g[n] for n in ("u", "v", "w", "flags", "peak_ratio")}

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
        done = sorted(set(g.attrs.get("correlated_pairs", [])) | {int(p) for p in pairs})
        g.attrs.update({"correlated_pairs": done})

    @property
    def has_vectors(self) -> bool:
        return "vectors" in self.group

    @property
    def vectors_outdated(self) -> bool:
        """True when ``vectors/`` was correlated from volumes since replaced (or removed)."""
        if not self.has_vectors:
            return False
        made_from = self.group["vectors"].attrs.get("volumes_id")
        return made_from is not None and made_from != self.volumes_id

    def correlated_pairs(self) -> list[int]:
        return list(self.group["vectors"].attrs["correlated_pairs"]) if self.has_vectors else []

    def vectors(self) -> dict[str, Any]:
        """``vectors/`` as NumPy arrays: u, v, w, flags, peak_ratio (pairs, z, y, x); x_mm, y_mm, z_mm; attrs.

        Raises
        ------
        RunStoreError
            If the run has no vectors.
        """
        if not self.has_vectors:
            raise RunStoreError(f"{self.path} has no vectors; run 'lfpiv correlate {self.path}' first")
        g = self.group["vectors"]
        out: dict[str, Any] = {n: g[n][...] for n in ("u", "v", "w", "flags", "peak_ratio", "x_mm", "y_mm", "z_mm")}
        out["attrs"] = dict(g.attrs)
        return out

    # --- replacing derived data whole ---------------------------------------------------
    #: The attribute of ``volumes/`` and ``vectors/`` that lists the pairs written so far.
    DONE = {"volumes": "reconstructed_pairs", "vectors": "correlated_pairs"}

    def _begin(self, name: str, *, staged: bool) -> zarr.Group:
        """A new, empty group where ``name`` (``volumes`` or ``vectors``) is made from now on:
        ``name`` itself, or with ``staged`` its pending replacement, which leaves ``name`` whole
        until :meth:`finish`."""
        pending = name + self.PENDING
        if pending in self.group:  # an earlier replacement, interrupted, and now superseded
            del self.group[pending]
        key = pending if staged else name
        if key in self.group:
            del self.group[key]
        self._target[name] = key
        return self.group.create_group(key)

    def pending(self, name: str) -> zarr.Group | None:
        """The unfinished replacement of ``name`` (``volumes`` or ``vectors``) that an interrupted
        run left, or None."""
        key = name + self.PENDING
        return self.group[key] if key in self.group else None

    def resume(self, name: str) -> zarr.Group:
        """Write ``name`` into its pending replacement again (a replacement resumed), and return it."""
        g = self.pending(name)
        if g is None:
            raise RunStoreError(f"{self.path} has no {name}{self.PENDING}/ to resume")
        self._target[name] = g.basename
        return g

    def writing(self, name: str) -> zarr.Group:
        """The group that writes of ``name`` (``volumes`` or ``vectors``) go to: ``name`` itself,
        or the pending replacement that :meth:`create_volumes`, :meth:`create_vectors` or
        :meth:`resume` chose."""
        key = self._target[name]
        if key not in self.group:
            raise RunStoreError(f"{self.path} has no {key}/ group; create it first")
        return self.group[key]

    def plan(self, name: str, pairs: list[int]) -> None:
        """Add ``pairs`` to those the pending replacement of ``name`` being written must hold
        before :meth:`finish` puts it in place (nothing to do when ``name`` itself is written):
        a replacement resumed for a few pairs does not drop the old set's others unasked."""
        g = self.writing(name)
        if g.basename != name:
            g.attrs["planned_pairs"] = sorted(set(g.attrs.get("planned_pairs", [])) | {int(p) for p in pairs})

    def unfinished(self, name: str) -> list[int]:
        """The planned pairs (:meth:`plan`) that the pending replacement of ``name`` being
        written still lacks; [] when it is complete or ``name`` itself is written."""
        g = self.writing(name)
        if g.basename == name:
            return []
        return sorted(set(g.attrs.get("planned_pairs", [])) - set(g.attrs.get(self.DONE[name], [])))

    def finish(self, name: str) -> bool:
        """Put the pending replacement of ``name`` being written in place of ``name`` once it
        holds every planned pair (:meth:`plan`): two directory renames, then the old set is
        deleted. Returns True when it replaced ``name``.

        Until then readers see the old ``name`` whole. A kill between the renames, or while the
        old set is deleted, leaves ``<name>.replaced/``, which :meth:`recover` settles.
        """
        key = self._target[name]
        if key == name or self.unfinished(name):
            return False
        root = Path(self.path)
        old = root / f"{name}.replaced"
        shutil.rmtree(old, ignore_errors=True)
        if (root / name).exists():
            os.replace(root / name, old)
        os.replace(root / key, root / name)
        self._target[name] = name
        shutil.rmtree(old, ignore_errors=True)
        return True

    def replaced_left(self, name: str) -> bool:
        """Whether ``<name>.replaced/`` is left by a replacement killed in :meth:`finish`."""
        return (Path(self.path) / f"{name}.replaced").exists()

    def recover(self) -> list[str]:
        """Settle replacements killed in :meth:`finish`: one killed between its renames is
        completed (its pending set was complete), and the old set's folder left by one killed
        while deleting it is deleted. Returns what was done, one line each."""
        root, done = Path(self.path), []
        for name in self._target:
            cur, pending, old = root / name, root / (name + self.PENDING), root / f"{name}.replaced"
            if not old.exists():
                continue
            if not cur.exists():
                os.replace(pending if pending.exists() else old, cur)
                done.append(f"completed the replacement of {name}/ that was interrupted as it was put in place")
            shutil.rmtree(old, ignore_errors=True)
        return done
