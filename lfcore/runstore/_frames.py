"""Raw frames and the recording's progress: ``<camera>/frames``, ``frame_id``, ``timestamp_ns``,
and the root attributes ``state``, ``committed_pairs`` and ``timing``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import google_crc32c
import numcodecs
import numpy as np
import zarr
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec
from zarr.storage import LocalStore

from lfcore.rig import Rig
from lfcore.runstore._common import STATES, Part, RunStoreError, run_array
from lfcore.runstore._schema import validated

#: Raw frames are compressed with LZ4 after bit shuffling (Blosc). Camera counts of 12 bits or
#: fewer leave the top bits of every uint16 zero, which bit shuffling turns into long zero runs:
#: on rendered 2048 x 2048 light-field frames it encodes at about 1.2 GB/s per core with a ratio
#: of 1.66, against 1.0 GB/s and 1.42 with byte shuffling and 0.4 GB/s with Zstandard, so the
#: recorder keeps up with the cameras. Any zarr reader decodes it.
FRAME_CODEC = BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle")


class FrameWriter:
    """Writes raw frames into one camera's ``frames`` array, one encoded chunk per frame.

    For a run store in a local directory with the frames' own codecs (little-endian bytes, then
    Blosc, then the CRC-32C checksum, which stores made before checksums lack), each frame is
    compressed with Blosc and written as its chunk file directly: the same bytes zarr itself
    writes, at about twice the rate of ``zarr.Array.__setitem__`` (whose codec pipeline, not the
    disk, bounds a recording). The checksum is computed over the compressed bytes as they are
    written (about 5 GB/s, with the interpreter lock released), with no read back. Any other
    store or codec is written through zarr. Callers may write from several threads, distinct
    frames each.

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
        self._crc = len(codecs) == 3 and isinstance(codecs[2], Crc32cCodec)
        direct = (isinstance(store, LocalStore) and array.dtype == np.uint16 and len(codecs) == 2 + self._crc
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
        # zarr's crc32c codec: the CRC-32C of the encoded bytes, 4 bytes little-endian, after them
        crc = google_crc32c.value(data).to_bytes(4, "little") if self._crc else b""
        try:
            f = open(path, "wb")  # noqa: SIM115 - two writes, so the frame's bytes are not copied
        except FileNotFoundError:  # the chunk's folder is made on first use
            path.parent.mkdir(parents=True, exist_ok=True)
            f = open(path, "wb")  # noqa: SIM115
        with f:
            f.write(data)
            f.write(crc)

    def write_pairs(self, first: int, frames: np.ndarray) -> None:
        """Store (n, 2, rows, columns) uint16 frames of pairs ``first`` .. ``first + n - 1``."""
        if self._blosc is None:
            self.array[first:first + len(frames)] = frames
            return
        for i, pair in enumerate(frames):
            for k in range(2):
                self.write(first + i, k, pair[k])


def create_frames(root: zarr.Group, rig: Rig, n_pairs: int) -> None:
    """Create the empty ``<camera>/`` groups of every camera of ``rig`` in a new run's ``root``."""
    for cam in rig.camera:
        cols, rows = cam.sensor_px
        g = root.create_group(cam.name)
        g.attrs.update({"sensor_px": [cols, rows]})
        run_array(g, "frames", "counts", ["pair", "frame", "row", "column"], "raw light-field images; frame 0 is A, "
                  "1 is B", shape=(n_pairs, 2, rows, cols), chunks=(1, 1, rows, cols), dtype=np.uint16, fill_value=0,
                  compressors=FRAME_CODEC)
        for name, units, what in (("frame_id", "1", "camera frame counter"),
                                  ("timestamp_ns", "ns", "the camera's clock where it has one, else the host's "
                                   "time of fetch (ns since the epoch); synthetic runs: from the first pulse")):
            run_array(g, name, units, ["pair", "frame"], what + "; -1 where never written", shape=(n_pairs, 2),
                      chunks=(min(n_pairs, 1024), 2), dtype=np.int64, fill_value=-1)


#: The arrays of every camera's group, with their data types.
CAMERA_ARRAYS = {"frames": np.uint16, "frame_id": np.int64, "timestamp_ns": np.int64}


class Frames(Part):
    """The recording: raw frames of every camera, their ids and time stamps, and how far it got."""

    @property
    def n_pairs(self) -> int:
        """The number of pairs the run holds room for."""
        return int(self.frames(self.cameras[0]).shape[0])

    @property
    def state(self) -> str:
        """``"recording"``, ``"complete"`` or ``"aborted"``.

        Raises
        ------
        RunStoreError
            If it is none of these (the root zarr.json was edited or damaged).
        """
        state = self.group.attrs["state"]
        if state not in STATES:
            raise RunStoreError(f"{self.path}: state is {state!r}, not one of {', '.join(STATES)} (the root zarr.json "
                                "was edited or damaged); restore it from a copy of the run")
        return str(state)

    @property
    def committed_pairs(self) -> int:
        """Pairs ``0 .. committed_pairs - 1`` are complete.

        Raises
        ------
        RunStoreError
            If the attribute is not a number of pairs the run's arrays hold (edited or damaged).
        """
        c = self.group.attrs["committed_pairs"]
        if isinstance(c, bool) or not isinstance(c, int | float) or c != int(c) or c < 0:
            raise RunStoreError(f"{self.path}: committed_pairs is {c!r}, not a number of pairs (the root zarr.json "
                                "was edited or damaged); restore it from a copy of the run")
        if c > self.n_pairs:
            raise RunStoreError(f"{self.path}: committed_pairs is {c}, more than the {self.n_pairs} pairs the run's "
                                "arrays hold (the root zarr.json was edited or damaged); restore it from a copy of "
                                "the run")
        return int(c)

    @property
    def timing(self) -> dict[str, Any]:
        """The run's timing (``dt_s``, ``rate_hz``, ...), a copy.

        Raises
        ------
        RunStoreError
            If it is not what the layout gives it (:class:`~lfcore.runstore._schema.TimingAttrs`:
            a table, ``dt_s`` a positive time, ``rate_hz`` a positive rate or null), one line.
        """
        return dict(validated(self.path, "", self.group.attrs, "timing"))

    @property
    def dt_s(self) -> float:
        """Time between frames A and B of a pair, s (the root attribute ``timing.dt_s``).

        Raises
        ------
        RunStoreError
            If the run's timing holds none, or not a positive time.
        """
        dt = self.timing.get("dt_s")
        if dt is None:
            raise RunStoreError(f"{self.path}: the run's timing holds no dt_s (the time between frames A and B), so "
                                "velocities cannot be computed; record or import the run with its dt")
        return float(dt)

    def frames(self, camera: str) -> zarr.Array:
        """The (pairs, 2, rows, columns) uint16 frames array of one camera.

        Indexing it reads a chunk that is not there as zeros, as zarr does; :meth:`read_frame`
        reads a recorded frame and raises where its chunk is missing or damaged.
        """
        return self.group[f"{camera}/frames"]

    def frame_ids(self, camera: str) -> np.ndarray:
        """(pairs, 2) int64 camera frame counters of one camera, -1 where never written."""
        return self.group[f"{camera}/frame_id"][...]

    def timestamps_ns(self, camera: str) -> np.ndarray:
        """(pairs, 2) int64 time stamps of one camera's frames, ns, -1 where never written."""
        return self.group[f"{camera}/timestamp_ns"][...]

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
        """Set the run's ``state``, one of :data:`STATES`."""
        if state not in STATES:
            raise RunStoreError(f"state must be one of {STATES}, got '{state}'")
        self.group.attrs["state"] = state
