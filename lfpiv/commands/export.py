"""``lfpiv export``: write a run's vector fields as netCDF or VTK files."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("export", help="write a run's vector fields as netCDF or VTK for ParaView, Tecplot, xarray",
                       description="Write the correlated pairs of a run's vectors/ with vorticity, divergence and "
                       "Q-criterion: --format netcdf gives one vectors.nc (dimensions pair, z, y, x; mm, m/s); "
                       "--format vtk gives one VTK ImageData file per pair and a ParaView collection vectors.pvd.")
    e.add_argument("run", metavar="RUN", help="run store with vectors (a .zarr directory)")
    e.add_argument("--format", required=True, choices=("netcdf", "vtk"), help="netcdf or vtk")
    e.add_argument("--out", required=True, metavar="DIR", help="directory to write into (created if needed)")
    e.add_argument("--overwrite", action="store_true",
                   help="replace the files of an earlier export of this format in --out")
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os
    from pathlib import Path

    from lfcore.runstore import RunStore, RunStoreError
    from lfpiv.commands import warn_outdated_vectors
    from lfpiv.errors import UsageError
    from lfpiv.export import fields_of, write_netcdf, write_vti_series

    store = RunStore.open(args.run)
    vectors = store.vectors()
    warn_outdated_vectors(store)
    pairs = store.correlated_pairs()
    if not pairs:
        raise RunStoreError(f"{store.path} has vectors/ but no correlated pair; run 'lfpiv correlate {store.path}'")
    out = Path(args.out)
    if out.is_symlink() and not out.exists():
        raise UsageError(f"--out {out} is a symbolic link to nothing ({os.readlink(out)}); give a directory")
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a directory")
    # what this export writes, and what an earlier one left (a VTK series is replaced whole)
    names = (["vectors.nc"] if args.format == "netcdf" else
             ["vectors.pvd", *(f"vectors_pair{p:04d}.vti" for p in pairs),
              *(f.name for f in out.glob("vectors_pair[0-9][0-9][0-9][0-9].vti"))])
    targets = sorted({out / n for n in names})
    links = [t for t in targets if t.is_symlink()]
    if links:
        raise UsageError(f"{links[0]} is a symbolic link, and export does not write through links; remove it or "
                         "choose another --out")
    earlier = [t for t in targets if t.exists()]
    if earlier and not args.overwrite:
        raise UsageError(f"--out {out} already holds {earlier[0].name}"
                         f"{f' and {len(earlier) - 1} more file(s)' if len(earlier) > 1 else ''} of an earlier "
                         "export; pass --overwrite to replace them, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    fields = fields_of(vectors, pairs, store.timing.get("rate_hz"))
    if args.format == "netcdf":
        files = [write_netcdf(out / "vectors.nc", fields, source=str(store.path))]
    else:
        files = write_vti_series(out, fields)
    print(f"wrote {len(files)} file(s) to {out}: {', '.join(f.name for f in files[:4])}"
          f"{' ...' if len(files) > 4 else ''}")
    return 0
