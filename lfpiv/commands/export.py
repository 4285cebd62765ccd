"""``lfpiv export``: write a run's vector fields for the tools labs open them with."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from lfpiv.jobs.export import FORMATS

    e = sub.add_parser("export", help="write a run's vector fields for ParaView, Tecplot, DaVis, MATLAB, xarray",
                       description="Write the correlated pairs of a run's vectors/ with vorticity, divergence and "
                       "Q-criterion, in SI units (m, m/s, 1/s): --format netcdf gives vectors.nc (netCDF-4, CF-1.8, "
                       "dimensions time, z, y, x; ParaView, xarray); vtk one VTK ImageData file per pair and a "
                       "ParaView collection vectors.pvd; tecplot vectors.dat (ASCII, one zone per pair); davis a "
                       "DaVis vector set vectors.set; mat vectors.mat (MATLAB, meshgrid order). The particle tracks "
                       "of 'lfpiv track': tracks-vtk one VTK PolyData file of lines from frame A to frame B per pair "
                       "and a ParaView collection tracks.pvd; tracks-csv tracks.csv, one row per track; series-csv "
                       "series_tracks.csv, the tracks of 'lfpiv track --along-pairs' through a time-resolved series, "
                       "one row a point with its time.")
    e.add_argument("run", metavar="RUN", help="run store with vectors (a .zarr directory)")
    e.add_argument("--format", required=True, choices=tuple(FORMATS), help=", ".join(FORMATS))
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
