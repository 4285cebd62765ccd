"""Lost frames: the ``drops/`` table, one row per frame that was not recorded, with the reason."""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr

from lfcore.runstore._common import Part, RunStoreError, run_array

#: The columns of ``drops/``: (type, fill value, what it holds).
DROP_FIELDS = {
    "camera": (str, "", "camera name"),
    "pair": (np.int64, -1, "pair index, -1 if unknown"),
    "frame": (np.int64, -1, "0 for frame A, 1 for frame B, -1 if unknown"),
    "frame_id": (np.int64, -1, "camera frame counter"),
    "timestamp_ns": (np.int64, -1, "when the loss was detected, ns since the epoch"),
    "reason": (str, "", "why the frame was lost"),
}


def create_drops(root: zarr.Group) -> None:
    """Create the empty ``drops/`` table in a new run's ``root``."""
    drops = root.create_group("drops")
    drops.attrs.update({"description": "every frame that was not recorded, with the reason; a row with an "
                                       "empty reason was never written (a recorder killed while adding it)"})
    for name, (dtype, fill, what) in DROP_FIELDS.items():
        run_array(drops, name, "ns" if name == "timestamp_ns" else "1", ["drop"], what, shape=(0,),
                  chunks=(4096,), dtype=dtype, fill_value=fill)


class Drops(Part):
    """The frames a recording lost, each with its reason."""

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
        cols = [self.group[f"drops/{name}"] for name in DROP_FIELDS]
        n = min(a.shape[0] for a in cols)
        for a in cols:
            a.resize((n + len(rows),))
        for a, (name, (dtype, _, _)) in zip(cols, DROP_FIELDS.items(), strict=True):
            a[n:] = np.asarray([r[name] for r in rows], dtype=object if dtype is str else dtype)

    def drops(self) -> list[dict[str, Any]]:
        """Every lost frame, as dicts with the fields of ``drops/``.

        Of a run killed while recording (``state`` still "recording"), only the drops of
        committed pairs: rows of a pair the kill left uncommitted, or half-appended, are left out.
        """
        cols = {name: self.group[f"drops/{name}"][...] for name in DROP_FIELDS}
        n = min(len(v) for v in cols.values())  # a kill between two resizes leaves some columns longer
        rows = [{k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in cols.items()} for i in range(n)]
        if self.state == "recording":
            rows = [r for r in rows if r["pair"] < self.committed_pairs]
        return [r for r in rows if r["reason"]]  # an empty reason: a row grown but never written
