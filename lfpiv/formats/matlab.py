"""Vector fields as one MATLAB ``.mat`` file (v5, compressed), in SI units and ``meshgrid`` order.

MATLAB's ``[X, Y, Z] = meshgrid(x, y, z)`` gives arrays of size ``[ny nx nz]`` (rows along y,
columns along x, pages along z); the file uses that order, so that ``quiver3``, ``slice``,
``isosurface`` and ``curl`` take its arrays as they are:

``x``, ``y``, ``z``
    ``[ny nx nz]`` positions of the vectors in metres, as ``meshgrid`` gives them.
``u``, ``v``, ``w``, ``vorticity_x``, ``vorticity_y``, ``vorticity_z``, ``divergence``, ``q_criterion``, ``peak_ratio``
    ``[ny nx nz npairs]`` (double; m/s, 1/s, 1/s^2, 1): ``u(:, :, :, k)`` is the k-th pair.
``flags``
    ``[ny nx nz npairs]`` uint8: 1 outlier, 2 replaced.
``t``, ``pair``
    ``[1 npairs]`` each pair's time (s since the run's start) and its index in the run.
``units``, ``info``
    A struct of the units of every variable; a struct of the correlation settings
    (``dt_s``, ``windows_xyz_voxels``, ``overlap_xyz``, ``frame``, ``start``).

For example ``[cx, cy, cz] = curl(x, y, z, u(:,:,:,1), v(:,:,:,1), w(:,:,:,1))`` equals
``vorticity_x(:,:,:,1)`` ... A v5 file holds at most 2 GiB per variable; larger fields are
refused with a pointer to the netCDF export (MATLAB's ``ncread`` reads it).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lfpiv.formats._files import replacing
from lfpiv.formats.errors import FormatError
from lfpiv.formats.fields import QUANTITIES, Fields, global_attributes

__all__ = ["to_meshgrid", "write_mat"]

_V5_LIMIT = 2**31 - 1  # bytes of one variable in a MATLAB v5 file


def to_meshgrid(a: np.ndarray) -> np.ndarray:
    """(z, y, x[, ...]) -> (y, x, z[, ...]), MATLAB's ``meshgrid`` order; (pairs, z, y, x) -> (y, x, z, pairs)."""
    a = np.asarray(a)
    if a.ndim == 3:
        return np.transpose(a, (1, 2, 0))
    if a.ndim == 4:
        return np.transpose(a, (2, 3, 1, 0))
    raise FormatError(f"expected an array (z, y, x) or (pairs, z, y, x), got shape {a.shape}")


def write_mat(path: str | os.PathLike[str], fields: Fields) -> Path:
    """Write the fields to one MATLAB ``.mat`` file (see the module docstring).

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

    Raises
    ------
    FormatError
        If a variable exceeds the 2 GiB of a v5 file.
    """
    from scipy.io import savemat

    path = Path(path)
    x, y, z = fields.coords_m()
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    out: dict[str, object] = {"x": to_meshgrid(xx), "y": to_meshgrid(yy), "z": to_meshgrid(zz)}
    for q in QUANTITIES:
        data = q.get(fields)
        out[q.name] = to_meshgrid(np.asarray(data, dtype=np.uint8 if q.name == "flags" else np.float64))
    for name, a in out.items():
        size = np.asarray(a).nbytes
        if size > _V5_LIMIT:
            raise FormatError(f"the variable {name} needs {size / 2**30:.1f} GiB, more than the 2 GiB a MATLAB v5 file "
                              "holds; export fewer pairs, or export netcdf and read it with ncread")
    out["t"] = np.asarray(fields.time_s, dtype=np.float64).reshape(1, -1)
    out["pair"] = np.asarray(fields.pairs, dtype=np.float64).reshape(1, -1)
    out["units"] = {"x": "m", "y": "m", "z": "m", "t": "s", "pair": "1",
                    **{q.name: q.symbol for q in QUANTITIES}}
    g = global_attributes(fields)
    out["info"] = {**g, "overlap_xyz": np.asarray(g["overlap_xyz"], dtype=np.float64).reshape(1, -1),
                   "start": fields.start or "", "layout": "meshgrid order [ny nx nz npairs]"}
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        savemat(fh, out, do_compression=True, oned_as="row")
    return path
