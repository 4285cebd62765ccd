"""Vector fields as one netCDF-4 (HDF5) file following CF-1.8, for ParaView, VisIt and xarray.

Layout
    Dimensions ``(time, z, y, x)``, one time step per pair. Coordinate variables ``time``
    (seconds since the run's start: ``units = "seconds since <start>"``, ``axis = "T"``), and
    ``x``, ``y``, ``z`` in metres; the auxiliary variable ``pair`` (time) holds each step's pair
    index. The scalars of :data:`lfpiv.formats.fields.QUANTITIES` (u, v, w in m s-1, the
    vorticity components, divergence and Q-criterion, peak ratio as float32; ``flags`` as
    unsigned bytes with CF ``flag_masks`` / ``flag_meanings``), each ``(time, z, y, x)``,
    deflate-compressed one chunk a time step. Units are UDUNITS strings; every variable has a
    ``long_name``. CF has standard names for time and for status flags but none for the
    coordinates and velocities of a laboratory frame (``eastward_*``, ``x_wind``,
    ``sea_water_x_velocity`` mean other things), so the others have none.
What VTK's ``vtkNetCDFCFReader`` (ParaView's "NetCDF CF" reader) needs, from its source and tried
with ``vtk`` 9.7
    - A time dimension: it takes a variable's first dimension as time when that dimension's
      coordinate variable has time units (``"... since ..."``, ``"s"``, ...) or ``axis = "T"``,
      and drops it; what is left may have at most 3 dimensions ("More than 3 dims without
      time not supported" otherwise, the error the old ``(pair, z, y, x)`` file gave).
    - Coordinate variables named like their dimensions, read as doubles; evenly spaced ones make
      the output ``vtkImageData`` with that origin and spacing (netCDF's last dimension is VTK's
      x), uneven ones a ``vtkRectilinearGrid``.
    - Text attributes (``NC_CHAR``): it reads ``units`` and ``axis`` with ``nc_get_att_text``,
      which fails on the variable-length strings (``NC_STRING``) that h5netcdf writes; such a
      file loses its time dimension and coordinates. The netCDF4 library writes ``NC_CHAR``.
    - No ``axis = "X"`` / ``"Y"`` on the coordinates: the reader takes X as longitude and Y as
      latitude and, with its default "spherical coordinates" on, wraps the grid onto a sphere
      (a ``vtkStructuredGrid`` with cell data). For the same reason no units of degrees, and no
      ``positive = "down"`` (it flips the axis).
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Any

import numpy as np

from lfpiv.formats._files import replacing
from lfpiv.formats.errors import FormatError
from lfpiv.formats.fields import FLAG_MEANINGS, QUANTITIES, Fields, global_attributes

__all__ = ["time_units", "write_netcdf"]


def time_units(start: str | None) -> str:
    """CF units of the time coordinate: ``"seconds since 2026-01-01 12:00:00"`` (UTC), or ``"s"`` without a start.

    Raises
    ------
    FormatError
        If ``start`` is not an ISO 8601 time.
    """
    if start is None:
        return "s"
    try:
        t = _dt.datetime.fromisoformat(str(start))
    except ValueError:
        raise FormatError(f"the run's start {start!r} is not an ISO 8601 time such as 2026-01-01T12:00:00+00:00; "
                          "check the store's 'created' attribute") from None
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return f"seconds since {t.isoformat(sep=' ')}"


def write_netcdf(path: str | os.PathLike[str], fields: Fields, *, source: str = "", compression: int = 4) -> Path:
    """Write the fields to one netCDF-4 file (see the module docstring).

    The file is written beside ``path`` under a temporary name and then renamed, so an earlier
    file at ``path`` stays whole until the new one is complete.

    Parameters
    ----------
    path
        The file to write (``vectors.nc``).
    fields
        The fields (:func:`lfpiv.formats.fields.fields_of`).
    source
        What the fields came from (the run store's path), recorded in the ``source`` attribute.
    compression
        Deflate level, 0 (none) to 9.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    import netCDF4

    if not 0 <= int(compression) <= 9:
        raise FormatError(f"the netCDF compression level must be 0 to 9, got {compression}")
    path = Path(path)
    units = time_units(fields.start)  # a bad start is refused before anything is written
    with replacing(path) as tmp, netCDF4.Dataset(tmp, "w", format="NETCDF4") as ds:
        _fill(ds, fields, units=units, source=source, compression=int(compression))
    return path


def _fill(ds: Any, fields: Fields, *, units: str, source: str, compression: int) -> None:
    """Dimensions, coordinates, scalars and attributes of the file (see the module docstring)."""
    from lfpiv import __version__

    nz, ny, nx = fields.shape
    x, y, z = fields.coords_m()
    g = global_attributes(fields)
    ds.setncatts({
        "Conventions": "CF-1.8",
        "title": "lfpiv 3D velocity fields",
        "source": f"lfpiv {__version__} light-field PIV" + (f" from {source}" if source else ""),
        "history": f"{_dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')} written by lfpiv {__version__}",
        "comment": f"positions in {g['frame']}; one time step per correlated pair",
        "dt_s": g["dt_s"],
        "windows_xyz_voxels": g["windows_xyz_voxels"],
        "overlap_xyz": np.asarray(g["overlap_xyz"], dtype=np.float64),
    })
    ds.createDimension("time", len(fields.pairs))
    for name, n in (("z", nz), ("y", ny), ("x", nx)):
        ds.createDimension(name, n)
    t = ds.createVariable("time", "f8", ("time",))
    t[:] = np.asarray(fields.time_s, dtype=np.float64)
    t.setncatts({"units": units, "standard_name": "time", "calendar": "standard", "axis": "T",
                 "long_name": "time of frame A since the start of the run"})
    p = ds.createVariable("pair", "i4", ("time",))
    p[:] = np.asarray(fields.pairs, dtype=np.int32)
    p.long_name = "index of the pair in the run"
    for name, c in (("z", z), ("y", y), ("x", x)):
        v = ds.createVariable(name, "f8", (name,))
        v[:] = c
        # no `axis`: VTK's CF reader takes X / Y as longitude / latitude (module docstring)
        v.setncatts({"units": "m", "long_name": f"world {name} of the vector grid (window centres)"})
    for q in QUANTITIES:
        flags = q.name == "flags"
        v = ds.createVariable(q.name, "u1" if flags else "f4", ("time", "z", "y", "x"),
                              compression="zlib" if compression else None, complevel=compression, shuffle=True,
                              chunksizes=(1, nz, ny, nx))  # one chunk a time step
        v[:] = np.asarray(q.get(fields), dtype=np.uint8 if flags else np.float32)
        v.long_name = q.long_name
        if flags:
            v.setncatts({"standard_name": "status_flag",
                         "flag_masks": np.array([m for m, _ in FLAG_MEANINGS], dtype=np.uint8),
                         "flag_meanings": " ".join(n for _, n in FLAG_MEANINGS)})
        else:
            v.units = q.units
