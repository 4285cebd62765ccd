"""A run's vector fields as files for the tools labs open them with (``lfpiv export``).

Every format is in SI units (positions in metres, velocity in m/s, vorticity and divergence in
1/s), so a tool's own derivative of the exported velocity (ParaView's Gradient filter, Tecplot's,
DaVis's) equals the exported vorticity; the writers are :mod:`lfpiv.formats`'.

==========  ===========================================  ==============================================
``--format``  files in ``--out``                          opened by
==========  ===========================================  ==============================================
netcdf      ``vectors.nc`` (netCDF-4, CF-1.8, time,      ParaView / VTK's netCDF CF reader, xarray,
            z, y, x)                                     VisIt, MATLAB's ``ncread``
vtk         ``vectors.pvd`` + ``vectors_pairNNNN.vti``   ParaView, VTK
tecplot     ``vectors.dat`` (ASCII, one ordered zone     Tecplot, ParaView's Tecplot reader
            per pair)
davis       ``vectors.set`` + ``vectors/B00001.vc7`` ... DaVis, lvpyio
mat         ``vectors.mat`` (meshgrid order)             MATLAB, ``scipy.io.loadmat``
tracks-vtk  ``tracks.pvd`` + ``tracks_pairNNNN.vtp``     ParaView, VTK (particle tracks as lines)
tracks-csv  ``tracks.csv``                               spreadsheets, pandas, MATLAB
series-csv  ``series_tracks.csv`` (the tracks through a     spreadsheets, pandas, MATLAB
            time-resolved series, one row a point)
==========  ===========================================  ==============================================

The ``tracks-*`` formats write the particle tracks ``lfpiv track`` kept with its vectors
(:mod:`lfpiv.formats.tracks`), ``series-csv`` those ``lfpiv track --along-pairs`` followed through a
time-resolved series; the others, the vector fields.

Pairs that were not correlated are left out. Files of an earlier export are replaced only with
``overwrite``, each whole or not at all, and never through a symbolic link.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lfcore.runstore import RunStore, RunStoreError
from lfpiv.errors import UsageError
from lfpiv.formats import FormatError
from lfpiv.formats.fields import Fields, fields_of

__all__ = ["FORMATS", "TRACK_FORMATS", "Fields", "export_run", "fields_of"]

#: Export formats (``lfpiv export --format``) and the names they write in the folder.
FORMATS = {"netcdf": ("vectors.nc",), "vtk": ("vectors.pvd",), "tecplot": ("vectors.dat",),
           "davis": ("vectors.set", "vectors"), "mat": ("vectors.mat",), "tracks-vtk": ("tracks.pvd",),
           "tracks-csv": ("tracks.csv",), "series-csv": ("series_tracks.csv",)}
#: The formats of the particle tracks rather than the vector fields.
TRACK_FORMATS = ("tracks-vtk", "tracks-csv", "series-csv")


def _targets(fmt: str, out: Path, pairs: list[int]) -> list[Path]:
    """What this export writes in ``out``, and what an earlier one left (a VTK series is replaced whole)."""
    from lfpiv.formats.vti import vti_name

    names = list(FORMATS[fmt])
    if fmt == "vtk":
        names += [vti_name(p) for p in pairs] + [f.name for f in out.glob("vectors_pair[0-9][0-9][0-9][0-9].vti")]
    if fmt == "tracks-vtk":
        from lfpiv.formats.tracks import vtp_name

        names += [vtp_name(p) for p in pairs] + [f.name for f in out.glob("tracks_pair[0-9][0-9][0-9][0-9].vtp")]
    return sorted({out / n for n in names})


def _write(fmt: str, out: Path, fields: Fields, source: str) -> list[Path]:
    if fmt == "netcdf":
        from lfpiv.formats.netcdf import write_netcdf

        return [write_netcdf(out / "vectors.nc", fields, source=source)]
    if fmt == "vtk":
        from lfpiv.formats.vti import write_vti_series

        return write_vti_series(out, fields)
    if fmt == "tecplot":
        from lfpiv.formats.tecplot import write_tecplot

        return [write_tecplot(out / "vectors.dat", fields)]
    if fmt == "davis":
        from lfpiv.formats.davis import write_davis_set

        return write_davis_set(out, fields, name="vectors")
    from lfpiv.formats.matlab import write_mat

    return [write_mat(out / "vectors.mat", fields)]


def _write_tracks(store: RunStore, fmt: str, out: Path, pairs: list[int]) -> list[Path]:
    from lfpiv.formats.tracks import write_series_csv, write_tracks_csv, write_tracks_vtp_series
    from lfpiv.jobs.track import tracks_table

    if fmt == "series-csv":
        series = store.read_series_tracks()  # none (not tracked along the pairs): a RunStoreError, one line
    else:
        table = tracks_table(store, pairs)  # a damaged table is an error (RunStoreError), named
    try:
        if fmt == "series-csv":
            return [write_series_csv(out / "series_tracks.csv", series, dt_s=float(store.timing["dt_s"]))]
        if fmt == "tracks-csv":
            return [write_tracks_csv(out / "tracks.csv", table)]
        return write_tracks_vtp_series(out, table, rate_hz=store.timing.get("rate_hz"), pairs=pairs)
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from None
        raise


def export_run(store: RunStore, fmt: str, out: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Write the correlated pairs of the run's ``vectors/`` into the folder ``out`` (created if needed).

    Parameters
    ----------
    store
        The run, with ``vectors/``.
    fmt
        One of :data:`FORMATS` (see the module docstring).
    out
        The folder to write into.
    overwrite
        Replace the files of an earlier export of this format there.

    Returns
    -------
    list of pathlib.Path
        The files (and, for DaVis, the set's folder) written.

    Raises
    ------
    RunStoreError
        A run without vectors, or with none correlated.
    UsageError
        An unknown format, an ``out`` that is a file or a dangling link, a target that is a
        link, an earlier export without ``overwrite``, or what the format cannot write (one line).
    """
    if fmt not in FORMATS:
        raise UsageError(f"--format must be one of {', '.join(FORMATS)}, got '{fmt}'")
    vectors = store.vectors()
    pairs = store.correlated_pairs()
    if not pairs:
        raise RunStoreError(f"{store.path} has vectors/ but no correlated pair; run 'lfpiv correlate {store.path}'")
    if fmt in TRACK_FORMATS and vectors["attrs"].get("settings", {}).get("source") != "particle tracks":
        raise UsageError(f"--format {fmt}: the vectors of {store.path} come from correlation and hold no particle "
                         f"tracks; run 'lfpiv particles {store.path}' and 'lfpiv track {store.path}' first")
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise UsageError(f"--out {out} is a symbolic link to nothing ({os.readlink(out)}); give a directory")
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a directory")
    targets = _targets(fmt, out, pairs)
    links = [t for t in targets if t.is_symlink()]
    if links:
        raise UsageError(f"{links[0]} is a symbolic link, and export does not write through links; remove it or "
                         "choose another --out")
    earlier = [t for t in targets if t.exists()]
    if earlier and not overwrite:
        raise UsageError(f"--out {out} already holds {earlier[0].name}"
                         f"{f' and {len(earlier) - 1} more file(s)' if len(earlier) > 1 else ''} of an earlier "
                         "export; pass --overwrite to replace them, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    if fmt in TRACK_FORMATS:
        return _write_tracks(store, fmt, out, pairs)
    try:
        # every pair read from its chunks, checked: a damaged or missing one is an error, not zeros
        held = [store.read_vectors(p) for p in pairs]
        checked = {**vectors, **{k: np.stack([h[k] for h in held]) for k in held[0]}}
        fields = fields_of(checked, pairs, store.timing.get("rate_hz"), start=store.attrs.get("created"),
                           rows=list(range(len(pairs))))
        return _write(fmt, out, fields, str(store.path))
    except FormatError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        if exc.filename is None:  # a full disk under a writer that names no file: say where it was writing
            raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from None
        raise
