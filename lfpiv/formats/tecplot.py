"""Vector fields as one Tecplot ASCII data file (ordered zones, POINT packing), in SI units.

One ``ZONE`` per pair, ``I = nx, J = ny, K = nz`` (x varies fastest), ``ZONETYPE = ORDERED``,
``DATAPACKING = POINT``, with the pair's time as ``SOLUTIONTIME`` (s) and one ``STRANDID`` so
Tecplot 360 plays the zones as a time series. The variables are ``x y z`` (m) and the scalars of
:data:`lfpiv.formats.fields.QUANTITIES` (``u v w`` in m/s, the vorticity components and
divergence in 1/s, ``q_criterion`` in 1/s^2, ``peak_ratio``, ``flags``); their units are in the
``DATASETAUXDATA`` record ``Units`` (names carry none: readers such as VTK's find the
coordinates only by the names x, y, z). ASCII has no NaN: a missing vector (NaN) is written as 0,
and its flags mark it an outlier.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lfpiv.formats._files import replacing
from lfpiv.formats.fields import QUANTITIES, Fields, global_attributes

__all__ = ["write_tecplot"]


def _aux(text: str) -> str:
    return text.replace('"', "'")


def write_tecplot(path: str | os.PathLike[str], fields: Fields) -> Path:
    """Write the fields to one Tecplot ASCII ``.dat`` file (see the module docstring).

    Parameters
    ----------
    path
        The file to write; written under a temporary name, then renamed.
    fields
        The fields.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    nz, ny, nx = fields.shape
    x, y, z = fields.coords_m()
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")  # (z, y, x): x varies fastest when flattened, as I does
    coords = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    names = " ".join(f'"{n}"' for n in ("x", "y", "z", *(q.name for q in QUANTITIES)))
    types = " ".join(["DOUBLE"] * 3 + ["BYTE" if q.name == "flags" else "SINGLE" for q in QUANTITIES])
    fmt = ["%.12g"] * 3 + ["%d" if q.name == "flags" else "%.9g" for q in QUANTITIES]
    units = "; ".join(f"{q.name}: {q.symbol}" for q in QUANTITIES if q.units != "1")
    g = global_attributes(fields)
    with replacing(path) as tmp, open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write('TITLE = "lfpiv 3D velocity fields"\n')
        fh.write(f"VARIABLES = {names}\n")
        fh.write(f'DATASETAUXDATA Units = "x, y, z: m; {units}"\n')
        fh.write(f'DATASETAUXDATA Frame = "{_aux(g["frame"])}"\n')
        fh.write(f'DATASETAUXDATA dt_s = "{g["dt_s"]:.9g}"\n')
        fh.write(f'DATASETAUXDATA Windows = "{_aux(g["windows_xyz_voxels"])}"\n')
        for i, pair in enumerate(fields.pairs):
            fh.write(f'ZONE T="pair {pair}", I={nx}, J={ny}, K={nz}, ZONETYPE=ORDERED, DATAPACKING=POINT, '
                     f"SOLUTIONTIME={float(fields.time_s[i])!r}, STRANDID=1\n")
            fh.write(f"DT=({types})\n")
            values = [np.nan_to_num(np.asarray(q.get(fields)[i], dtype=np.float64), nan=0.0).ravel()
                      for q in QUANTITIES]
            np.savetxt(fh, np.column_stack([coords, *values]), fmt=fmt, delimiter=" ")
    return path
