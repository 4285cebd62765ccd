"""Particle tracks (``lfpiv track``) as files: a VTK PolyData time series (``.vtp`` + ``.pvd``) for
ParaView and a CSV table.

The tracks come as (m, 11) rows: pair, frame A's x, y, z and frame B's (mm), u, v, w (m/s) and
outlier (1 rejected by the outlier test, 0 kept).

VTK: one XML PolyData file ``tracks_pairNNNN.vtp`` per pair (NNNN the pair's index in the run) and
a ParaView collection ``tracks.pvd`` listing them with their times in seconds. Each track is a line
from its particle in frame A to its particle in frame B; points in metres (SI, like the vector
exports), ``2 k`` and ``2 k + 1`` the ends of track ``k``. Point data: ``velocity`` (Float32, 3
components, m/s: the track's, at both ends) and ``frame`` (UInt8, 0 at A, 1 at B); cell data:
``velocity`` and ``outlier`` (UInt8); field data ``TimeValue`` (s). ASCII, so any VTK reader opens
it and a person can read it.

The tracks through a time-resolved series (``lfpiv track --along-pairs``) as CSV, one row a point
of a track: ``track,frame,time_s,x_mm,y_mm,z_mm,x_fit_mm,y_fit_mm,z_fit_mm`` (the fitted position
``nan`` on tracks too short to fit).

CSV: one row per track with the header ``pair,x_a_mm,y_a_mm,z_a_mm,x_b_mm,y_b_mm,z_b_mm,u_m_s,v_m_s,
w_m_s,outlier``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from lfpiv.formats._files import replacing

__all__ = ["CSV_HEADER", "PVD_NAME", "SERIES_CSV_HEADER", "vtp_name", "write_series_csv", "write_tracks_csv",
           "write_tracks_vtp", "write_tracks_vtp_series"]

#: The collection file of a series.
PVD_NAME = "tracks.pvd"
#: The CSV file's header.
CSV_HEADER = "pair,x_a_mm,y_a_mm,z_a_mm,x_b_mm,y_b_mm,z_b_mm,u_m_s,v_m_s,w_m_s,outlier"
#: The header of the tracks through a time-resolved series (``--format series-csv``).
SERIES_CSV_HEADER = "track,frame,time_s,x_mm,y_mm,z_mm,x_fit_mm,y_fit_mm,z_fit_mm"
_VTP = re.compile(r"tracks_pair\d{4,}\.vtp")


def vtp_name(pair: int) -> str:
    """``tracks_pair0007.vtp``: the file of pair ``pair`` in a series."""
    return f"tracks_pair{pair:04d}.vtp"


def _table(rows: np.ndarray) -> np.ndarray:
    t = np.asarray(rows, dtype=np.float64).reshape(-1, 11)
    return t


def write_tracks_csv(path: str | os.PathLike[str], rows: np.ndarray) -> Path:
    """Write (m, 11) track rows (see the module docstring) as CSV, whole or not at all; returns ``path``."""
    path = Path(path)
    t = _table(rows)
    with replacing(path) as tmp:
        np.savetxt(tmp, t, delimiter=",", header=CSV_HEADER, comments="",
                   fmt=["%d", *["%.6f"] * 6, *["%.6g"] * 3, "%d"])
    return path


def write_series_csv(path: str | os.PathLike[str], rows: np.ndarray, *, dt_s: float) -> Path:
    """Write the (k, 8) points of the tracks through a time-resolved series as CSV, one point a line
    with its time, whole or not at all.

    Parameters
    ----------
    path
        The CSV file (:data:`SERIES_CSV_HEADER`'s columns).
    rows
        (k, 8) :meth:`lfcore.runstore.RunStore.read_series_tracks`' points: track, frame (``2 p`` for
        pair p's A, ``2 p + 1`` for its B), the particle's x, y, z and the track's fitted x, y, z, mm.
    dt_s
        The time between frames, s: a point's ``time_s`` is its frame times ``dt_s``, the time since
        frame A of pair 0.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    t = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    table = np.column_stack([t[:, :2], t[:, 1] * float(dt_s), t[:, 2:]])
    with replacing(path) as tmp:
        np.savetxt(tmp, table, delimiter=",", header=SERIES_CSV_HEADER, comments="",
                   fmt=["%d", "%d", "%.9g", *["%.6f"] * 6])
    return path


def _ascii(a: np.ndarray, fmt: str) -> str:
    return " ".join(fmt % v for v in np.asarray(a).ravel())


def write_tracks_vtp(path: str | os.PathLike[str], rows: np.ndarray, *, time_s: float) -> Path:
    """Write one pair's (m, 11) track rows as VTK XML PolyData lines (see the module docstring).

    Parameters
    ----------
    path
        The ``.vtp`` file; written under a temporary name, then renamed.
    rows
        The pair's tracks.
    time_s
        The pair's time, s (the field data ``TimeValue``).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    t = _table(rows)
    m = len(t)
    points = np.empty((2 * m, 3))
    points[0::2], points[1::2] = t[:, 1:4] * 1e-3, t[:, 4:7] * 1e-3  # mm to m
    vel = t[:, 7:10].astype(np.float32)
    outlier = t[:, 10].astype(np.uint8)
    xml = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian">',
        "  <PolyData>",
        "    <FieldData>",
        f'      <DataArray type="Float64" Name="TimeValue" NumberOfTuples="1" format="ascii">{float(time_s)!r}'
        "</DataArray>",
        "    </FieldData>",
        f'    <Piece NumberOfPoints="{2 * m}" NumberOfVerts="0" NumberOfLines="{m}" NumberOfStrips="0" '
        'NumberOfPolys="0">',
        "      <Points>",
        f'        <DataArray type="Float64" NumberOfComponents="3" format="ascii">{_ascii(points, "%.9g")}'
        "</DataArray>",
        "      </Points>",
        '      <PointData Vectors="velocity">',
        f'        <DataArray type="Float32" Name="velocity" NumberOfComponents="3" format="ascii">'
        f"{_ascii(np.repeat(vel, 2, axis=0), '%.7g')}</DataArray>",
        f'        <DataArray type="UInt8" Name="frame" format="ascii">{_ascii(np.tile([0, 1], m), "%d")}</DataArray>',
        "      </PointData>",
        '      <CellData Vectors="velocity" Scalars="outlier">',
        f'        <DataArray type="Float32" Name="velocity" NumberOfComponents="3" format="ascii">'
        f"{_ascii(vel, '%.7g')}</DataArray>",
        f'        <DataArray type="UInt8" Name="outlier" format="ascii">{_ascii(outlier, "%d")}</DataArray>',
        "      </CellData>",
        "      <Lines>",
        f'        <DataArray type="Int64" Name="connectivity" format="ascii">{_ascii(np.arange(2 * m), "%d")}'
        "</DataArray>",
        f'        <DataArray type="Int64" Name="offsets" format="ascii">{_ascii(2 * np.arange(1, m + 1), "%d")}'
        "</DataArray>",
        "      </Lines>",
        "    </Piece>",
        "  </PolyData>",
        "</VTKFile>",
        "",
    ])
    with replacing(path) as tmp:
        Path(tmp).write_text(xml)
    return path


def write_tracks_vtp_series(out_dir: str | os.PathLike[str], rows: np.ndarray, *, rate_hz: float | None,
                            pairs: list[int] | None = None) -> list[Path]:
    """One ``tracks_pairNNNN.vtp`` per pair of ``rows`` and ``tracks.pvd`` listing them by time.

    A series exported into ``out_dir`` before is replaced whole: the files of pairs this one lacks
    are removed once the new ones are written. Other files are left alone.

    Parameters
    ----------
    out_dir
        An existing folder.
    rows
        (m, 11) track rows of every pair (see the module docstring).
    rate_hz
        Pairs per second, for each pair's time (pair / rate); None: the pair index.
    pairs
        The pairs to write, a file each (a pair without tracks: a file without lines); None: those
        in ``rows``.

    Returns
    -------
    list of pathlib.Path
        The ``.vtp`` files in pair order, then the ``.pvd``.
    """
    out = Path(out_dir)
    t = _table(rows)
    pairs = sorted({int(p) for p in t[:, 0]} if pairs is None else {int(p) for p in pairs})
    times = [p / rate_hz if rate_hz else float(p) for p in pairs]
    files = [write_tracks_vtp(out / vtp_name(p), t[t[:, 0] == p], time_s=s) for p, s in zip(pairs, times, strict=True)]
    keep = {f.name for f in files}
    for old in out.iterdir():
        if _VTP.fullmatch(old.name) and old.name not in keep:
            old.unlink()
    entries = [f'    <DataSet timestep="{s!r}" part="0" file="{f.name}"/>' for s, f in zip(times, files, strict=True)]
    pvd = out / PVD_NAME
    with replacing(pvd) as tmp:
        Path(tmp).write_text("\n".join(['<?xml version="1.0"?>', '<VTKFile type="Collection" version="1.0">',
                                        "  <Collection>", *entries, "  </Collection>", "</VTKFile>", ""]))
    return [*files, pvd]
