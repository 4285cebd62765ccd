"""Export a run's vector fields for ParaView, Tecplot and xarray users (``lfpiv export``).

netCDF
    One classic netCDF file (64-bit offsets, written with scipy's ``netcdf_file``) with the
    dimensions (pair, z, y, x), the coordinate variables x, y, z in mm, and per pair u, v, w
    (m/s), vorticity (1/s), divergence (1/s), Q-criterion (1/s^2), flags and peak ratio, with
    CF-style ``units`` and ``long_name`` attributes. ``xarray.open_dataset`` reads it as is.
VTK
    One VTK XML ImageData file (``.vti``) per pair, the point data in raw appended binary, and
    a ParaView collection (``vectors.pvd``) that lists them by time.

Pairs that were not correlated are left out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lfcore.runstore import RunStore, RunStoreError
from lfcore.vectors import divergence, q_criterion, vorticity
from lfpiv.errors import UsageError

__all__ = ["FORMATS", "Fields", "export_run", "fields_of", "write_netcdf", "write_vti_series"]

#: Export formats (``lfpiv export --format``).
FORMATS = ("netcdf", "vtk")


def export_run(store: RunStore, fmt: str, out: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Write the correlated pairs of the run's ``vectors/`` into the folder ``out`` (created if needed).

    ``fmt`` is one of :data:`FORMATS`. Files of an earlier export there are replaced only with
    ``overwrite``, and never written through a symbolic link.

    Returns
    -------
    list of pathlib.Path
        The files written.

    Raises
    ------
    RunStoreError
        A run without vectors, or with none correlated.
    UsageError
        An ``out`` that is a file or a dangling link, a target that is a link, or an earlier
        export without ``overwrite``.
    """
    if fmt not in FORMATS:
        raise UsageError(f"--format must be one of {', '.join(FORMATS)}, got '{fmt}'")
    vectors = store.vectors()
    pairs = store.correlated_pairs()
    if not pairs:
        raise RunStoreError(f"{store.path} has vectors/ but no correlated pair; run 'lfpiv correlate {store.path}'")
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise UsageError(f"--out {out} is a symbolic link to nothing ({os.readlink(out)}); give a directory")
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a directory")
    # what this export writes, and what an earlier one left (a VTK series is replaced whole)
    names = (["vectors.nc"] if fmt == "netcdf" else
             ["vectors.pvd", *(f"vectors_pair{p:04d}.vti" for p in pairs),
              *(f.name for f in out.glob("vectors_pair[0-9][0-9][0-9][0-9].vti"))])
    targets = sorted({out / n for n in names})
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
    fields = fields_of(vectors, pairs, store.timing.get("rate_hz"))
    if fmt == "netcdf":
        return [write_netcdf(out / "vectors.nc", fields, source=str(store.path))]
    return write_vti_series(out, fields)


@dataclass
class Fields:
    """The vector fields of the correlated pairs with their derived quantities."""

    pairs: list[int]
    time_s: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    velocity: np.ndarray  # (pairs, z, y, x, 3) m/s
    vorticity: np.ndarray  # (pairs, z, y, x, 3) 1/s
    divergence: np.ndarray  # (pairs, z, y, x) 1/s
    q_criterion: np.ndarray  # (pairs, z, y, x) 1/s^2
    flags: np.ndarray  # (pairs, z, y, x) uint8
    peak_ratio: np.ndarray  # (pairs, z, y, x)
    attrs: dict


def fields_of(vectors: dict, pairs: list[int], rate_hz: float | None) -> Fields:
    """Derived quantities of the pairs ``pairs`` of ``RunStore.vectors()``."""
    x, y, z = vectors["x_mm"], vectors["y_mm"], vectors["z_mm"]
    vel = np.stack([vectors[c][pairs] for c in "uvw"], axis=-1).astype(np.float64)
    vort = np.stack([vorticity(v, x, y, z) for v in vel]) if pairs else np.zeros_like(vel)
    div = np.stack([divergence(v, x, y, z) for v in vel]) if pairs else vel[..., 0]
    q = np.stack([q_criterion(v, x, y, z) for v in vel]) if pairs else vel[..., 0]
    t = np.asarray(pairs, dtype=np.float64) / rate_hz if rate_hz else np.asarray(pairs, dtype=np.float64)
    return Fields(pairs=list(pairs), time_s=t, x_mm=x, y_mm=y, z_mm=z, velocity=vel, vorticity=vort, divergence=div,
                  q_criterion=q, flags=vectors["flags"][pairs], peak_ratio=vectors["peak_ratio"][pairs],
                  attrs=vectors["attrs"])


def write_netcdf(path: str | Path, f: Fields, source: str = "") -> Path:
    """Write the fields to one netCDF file (see the module docstring); returns its path."""
    from scipy.io import netcdf_file

    path = Path(path)
    with netcdf_file(path, "w", version=2) as nc:
        nc.Conventions = "CF-1.8"
        nc.title = "lfpiv 3D velocity fields"
        nc.source = source
        nc.dt_s = float(f.attrs.get("dt_s", np.nan))
        nc.windows_xyz_voxels = "; ".join("x".join(str(n) for n in w) for w in f.attrs.get("windows", []))
        nc.overlap_xyz = np.asarray(f.attrs.get("overlap", []), dtype=np.float64)
        nc.createDimension("pair", len(f.pairs))
        for name, c in (("z", f.z_mm), ("y", f.y_mm), ("x", f.x_mm)):
            nc.createDimension(name, len(c))
            v = nc.createVariable(name, "f8", (name,))
            v[:] = c
            v.units = "mm"
            v.long_name = f"world {name} of the vector grid"
            v.axis = name.upper()
        v = nc.createVariable("pair", "i4", ("pair",))
        v[:] = np.asarray(f.pairs, dtype=np.int32)
        v.long_name = "pair index in the run"
        v = nc.createVariable("time", "f8", ("pair",))
        v[:] = f.time_s
        v.units = "s"
        v.long_name = "time of frame A since the first pair"
        dims = ("pair", "z", "y", "x")
        scalars = [
            ("u", f.velocity[..., 0], "m/s", "velocity along x"),
            ("v", f.velocity[..., 1], "m/s", "velocity along y"),
            ("w", f.velocity[..., 2], "m/s", "velocity along z"),
            ("vorticity_x", f.vorticity[..., 0], "1/s", "vorticity along x"),
            ("vorticity_y", f.vorticity[..., 1], "1/s", "vorticity along y"),
            ("vorticity_z", f.vorticity[..., 2], "1/s", "vorticity along z"),
            ("divergence", f.divergence, "1/s", "du/dx + dv/dy + dw/dz"),
            ("q_criterion", f.q_criterion, "1/s2", "Q-criterion"),
            ("peak_ratio", f.peak_ratio, "1", "highest over second-highest correlation peak"),
        ]
        for name, data, units, what in scalars:
            v = nc.createVariable(name, "f4", dims)
            v[:] = np.asarray(data, dtype=np.float32)
            v.units = units
            v.long_name = what
        v = nc.createVariable("flags", "b", dims)  # netCDF-3 has no unsigned byte; the bits fit
        v[:] = np.asarray(f.flags, dtype=np.int8)
        v.flag_masks = np.array([1, 2], dtype=np.int8)
        v.flag_meanings = "outlier replaced"
        v.long_name = "vector quality flags"
    return path


def _vti(path: Path, f: Fields, i: int) -> None:
    """One pair as VTK XML ImageData with raw appended point data (UInt32 block headers)."""
    nz, ny, nx = f.velocity.shape[1:4]

    def spacing(c: np.ndarray) -> float:
        return float(c[1] - c[0]) if len(c) > 1 else 1.0

    arrays = [
        ("velocity", f.velocity[i].astype(np.float32), "Float32", 3),
        ("vorticity", f.vorticity[i].astype(np.float32), "Float32", 3),
        ("divergence", f.divergence[i].astype(np.float32), "Float32", 1),
        ("q_criterion", f.q_criterion[i].astype(np.float32), "Float32", 1),
        ("peak_ratio", f.peak_ratio[i].astype(np.float32), "Float32", 1),
        ("flags", f.flags[i].astype(np.uint8), "UInt8", 1),
    ]
    head, blobs, offset = [], [], 0
    for name, data, vtype, ncomp in arrays:
        raw = np.ascontiguousarray(data).tobytes()  # (z, y, x[, c]) C order: x varies fastest, as VTK wants
        head.append(f'        <DataArray type="{vtype}" Name="{name}" NumberOfComponents="{ncomp}" '
                    f'format="appended" offset="{offset}"/>')
        blob = np.uint32(len(raw)).tobytes() + raw
        blobs.append(blob)
        offset += len(blob)
    extent = f"0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"
    origin = f"{f.x_mm[0]:.9g} {f.y_mm[0]:.9g} {f.z_mm[0]:.9g}"
    space = f"{spacing(f.x_mm):.9g} {spacing(f.y_mm):.9g} {spacing(f.z_mm):.9g}"
    xml = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt32">',
        f'  <ImageData WholeExtent="{extent}" Origin="{origin}" Spacing="{space}">',
        f'    <Piece Extent="{extent}">',
        '      <PointData Vectors="velocity" Scalars="divergence">',
        *head,
        "      </PointData>",
        "    </Piece>",
        "  </ImageData>",
        '  <AppendedData encoding="raw">',
        "   _",
    ])
    if not np.little_endian:  # pragma: no cover - the files say LittleEndian
        raise RuntimeError("writing VTK files needs a little-endian machine")
    with open(path, "wb") as fh:
        fh.write(xml.encode())
        for b in blobs:
            fh.write(b)
        fh.write(b"\n  </AppendedData>\n</VTKFile>\n")


def write_vti_series(out_dir: str | Path, f: Fields) -> list[Path]:
    """One ``vectors_pairNNNN.vti`` per pair and ``vectors.pvd`` listing them by time (mm, m/s).

    A series exported into ``out_dir`` before is replaced whole: its files of pairs this one
    lacks are removed, so the folder never mixes two exports.
    """
    out = Path(out_dir)
    for old in out.glob("vectors_pair[0-9][0-9][0-9][0-9].vti"):
        old.unlink()
    files = []
    entries = []
    for i, pair in enumerate(f.pairs):
        p = out / f"vectors_pair{pair:04d}.vti"
        _vti(p, f, i)
        files.append(p)
        entries.append(f'    <DataSet timestep="{f.time_s[i]:.9g}" part="0" file="{p.name}"/>')
    pvd = out / "vectors.pvd"
    pvd.write_text("\n".join(['<?xml version="1.0"?>', '<VTKFile type="Collection" version="1.0">',
                              "  <Collection>", *entries, "  </Collection>", "</VTKFile>", ""]))
    return [*files, pvd]
