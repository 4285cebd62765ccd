"""Vector fields as a VTK ImageData time series (``.vti`` + ``.pvd``) in SI units, for ParaView.

One VTK XML ImageData file ``vectors_pairNNNN.vti`` per pair (NNNN the pair's index in the run)
and a ParaView collection ``vectors.pvd`` that lists them with their times in seconds. Each file
puts the grid's origin and spacing in metres and holds, as point data in raw appended binary
(little-endian; block headers UInt32 as VTK writes them, UInt64 where an array exceeds 4 GiB):
``velocity`` (3 components, m/s), ``vorticity`` (3, 1/s), ``divergence`` (1/s),
``q_criterion`` (1/s^2), ``peak_ratio`` and ``flags`` (UInt8), and the field data
``TimeValue`` (s). Because positions are in metres, ParaView's own Gradient filter
(with vorticity on) gives the exported ``vorticity``. VTK ImageData needs evenly spaced
coordinates; the vector grid of a run always is.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from lfpiv.formats._files import replacing
from lfpiv.formats.fields import Fields, uniform_spacing

__all__ = ["PVD_NAME", "vti_name", "write_vti", "write_vti_series"]

#: The collection file of a series.
PVD_NAME = "vectors.pvd"
_VTI = re.compile(r"vectors_pair\d{4,}\.vti")


def _num(v: float) -> str:
    """The shortest text that reads back as the same double (0.1, not 0.10000000000000001)."""
    return repr(float(v))


def vti_name(pair: int) -> str:
    """``vectors_pair0007.vti``: the file of pair ``pair`` in a series."""
    return f"vectors_pair{pair:04d}.vti"


def _arrays(f: Fields, i: int) -> list[tuple[str, np.ndarray, str, int]]:
    return [
        ("velocity", f.velocity[i].astype("<f4"), "Float32", 3),
        ("vorticity", f.vorticity[i].astype("<f4"), "Float32", 3),
        ("divergence", f.divergence[i].astype("<f4"), "Float32", 1),
        ("q_criterion", f.q_criterion[i].astype("<f4"), "Float32", 1),
        ("peak_ratio", f.peak_ratio[i].astype("<f4"), "Float32", 1),
        ("flags", f.flags[i].astype(np.uint8), "UInt8", 1),
    ]


def write_vti(path: str | os.PathLike[str], fields: Fields, *, index: int) -> Path:
    """Write one pair of the fields as VTK XML ImageData (see the module docstring).

    Parameters
    ----------
    path
        The ``.vti`` file; written under a temporary name, then renamed.
    fields
        The fields.
    index
        Which of ``fields.pairs`` (0 for the first held), not the pair's index in the run.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    FormatError
        If the grid is not evenly spaced.
    """
    path = Path(path)
    nz, ny, nx = fields.shape
    x, y, z = fields.coords_m()
    spacing = [uniform_spacing(c, axis=a) for c, a in ((x, "x"), (y, "y"), (z, "z"))]
    arrays = _arrays(fields, index)
    header = "<u8" if max(a[1].nbytes for a in arrays) >= 2**32 else "<u4"
    head, blobs, offset = [], [], 0
    for name, data, vtype, ncomp in arrays:
        raw = np.ascontiguousarray(data).tobytes()  # (z, y, x[, c]) C order: x varies fastest, as VTK wants
        head.append(f'        <DataArray type="{vtype}" Name="{name}" NumberOfComponents="{ncomp}" '
                    f'format="appended" offset="{offset}"/>')
        blobs.append(np.array(len(raw), dtype=header).tobytes() + raw)
        offset += len(blobs[-1])
    extent = f"0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"
    xml = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" '
        f'header_type="{"UInt64" if header == "<u8" else "UInt32"}">',
        f'  <ImageData WholeExtent="{extent}" Origin="{_num(x[0])} {_num(y[0])} {_num(z[0])}" '
        f'Spacing="{_num(spacing[0])} {_num(spacing[1])} {_num(spacing[2])}">',
        "    <FieldData>",
        '      <DataArray type="Float64" Name="TimeValue" NumberOfTuples="1" format="ascii">'
        f"{_num(fields.time_s[index])}</DataArray>",
        "    </FieldData>",
        f'    <Piece Extent="{extent}">',
        '      <PointData Vectors="velocity" Scalars="divergence">',
        *head,
        "      </PointData>",
        "    </Piece>",
        "  </ImageData>",
        '  <AppendedData encoding="raw">',
        "   _",
    ])
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        fh.write(xml.encode())
        for b in blobs:
            fh.write(b)
        fh.write(b"\n  </AppendedData>\n</VTKFile>\n")
    return path


def write_vti_series(out_dir: str | os.PathLike[str], fields: Fields) -> list[Path]:
    """One ``vectors_pairNNNN.vti`` per pair and ``vectors.pvd`` listing them by time (SI units).

    A series exported into ``out_dir`` before is replaced whole: once the new files are written,
    the files of pairs this one lacks are removed, so the folder never mixes two exports. Other
    files are left alone.

    Parameters
    ----------
    out_dir
        An existing folder.
    fields
        The fields.

    Returns
    -------
    list of pathlib.Path
        The ``.vti`` files in pair order, then the ``.pvd``.
    """
    out = Path(out_dir)
    files = [write_vti(out / vti_name(pair), fields, index=i) for i, pair in enumerate(fields.pairs)]
    keep = {p.name for p in files}
    for old in out.iterdir():
        if _VTI.fullmatch(old.name) and old.name not in keep:
            old.unlink()
    entries = [f'    <DataSet timestep="{_num(t)}" part="0" file="{p.name}"/>'
               for t, p in zip(fields.time_s, files, strict=True)]
    pvd = out / PVD_NAME
    with replacing(pvd) as tmp:
        tmp.write_text("\n".join(['<?xml version="1.0"?>', '<VTKFile type="Collection" version="1.0">',
                                  "  <Collection>", *entries, "  </Collection>", "</VTKFile>", ""]))
    return [*files, pvd]
