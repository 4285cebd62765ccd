"""Files recorded elsewhere in, files for other tools out.

Readers of camera images recorded by other software (:mod:`lfpiv.formats.images`: TIFF, PNG,
BMP, and DaVis images through :mod:`lfpiv.formats.davis`), and writers of a run's vector
fields (:class:`lfpiv.formats.fields.Fields`) for the tools labs open them with, all in SI
units (metres, m/s, 1/s):

=====================================  ==================================================
:mod:`lfpiv.formats.netcdf`            netCDF-4 (HDF5), CF-1.8: ParaView, VisIt, xarray
:mod:`lfpiv.formats.vti`               VTK ImageData series (``.vti`` + ``.pvd``): ParaView
:mod:`lfpiv.formats.tecplot`           Tecplot ASCII (ordered zones, POINT packing)
:mod:`lfpiv.formats.davis`             DaVis vector sets (``.set`` of ``.vc7``): DaVis
:mod:`lfpiv.formats.matlab`            MATLAB ``.mat`` (v5) in ``meshgrid`` order
:mod:`lfpiv.formats.tracks`            particle tracks: VTK PolyData lines, CSV
=====================================  ==================================================

The functions take arrays, paths and small dataclasses; none opens a run store. Every module
imports its third-party library when it is first used, so importing this package is cheap.
"""

from __future__ import annotations

from lfpiv.formats.errors import FormatError

__all__ = ["FormatError"]
