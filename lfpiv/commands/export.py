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
    from lfpiv.commands import warn_outdated_vectors
    from lfpiv.jobs.export import export_run
    from lfpiv.runs import open_run

    store = open_run(args.run)
    store.vectors()  # a run without vectors says so before the note below
    warn_outdated_vectors(store)
    files = export_run(store, args.format, args.out, overwrite=args.overwrite)
    print(f"wrote {len(files)} file(s) to {args.out}: {', '.join(f.name for f in files[:4])}"
          f"{' ...' if len(files) > 4 else ''}")
    return 0
