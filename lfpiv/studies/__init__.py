"""The chapter's studies, reproduced (``lfpiv study``): one module per study, one runner for all.

- ``iterations``: Q against iterations and relaxation for DRT-MART, MART and MLOS-MART (Fig. 4.6);
  maximum voxel intensity against depth (Fig. 4.7).
- ``diameters``: reconstructed particle-diameter PDFs in x, y and z (Fig. 4.5), elongation.
- ``density``: Q against PPM (Fig. 4.8), ghosts and the depth profile (Fig. 4.9), the MART/DRT
  time ratio against PPM (Fig. 4.10).
- ``oscillatory``: Table 4.1's cases: displacement-error PDFs and RMS against iterations
  (Figs. 4.11-4.14), and the accuracy goals of one and two cameras.
- ``dual``: one camera against two against PPM (Fig. 4.33), Q against separation angle (Fig. 4.34),
  depth-resolution maps (Fig. 4.35).
- ``vortex-ring``: divergence-error PDFs of one and two cameras, with and without post-processing
  (Fig. 4.40), and the velocity error against the truth.
- ``lf-vs-tomo``: one light-field camera (800 and 1600 pixels across, PMR 7, 14, 28) against
  Tomo-PIV of 4, 6 and 8 pinhole cameras: Q and displacement error against LTPR (eq. 4.5,
  Figs. 4.23-4.24).

Each study is a :class:`lfpiv.studies.runner.Study`; :func:`lfpiv.studies.runner.run_study` runs it.
"""

from __future__ import annotations

import importlib

from lfpiv.studies.runner import Study

__all__ = ["STUDY_NAMES", "study_named"]

#: The studies in the order ``lfpiv study all`` runs them.
STUDY_NAMES = ("iterations", "diameters", "density", "oscillatory", "dual", "vortex-ring", "lf-vs-tomo")

_MODULES = {"vortex-ring": "vortex_ring", "lf-vs-tomo": "lf_vs_tomo"}


def study_named(name: str) -> Study:
    """The study called ``name`` (one of :data:`STUDY_NAMES`)."""
    if name not in STUDY_NAMES:
        raise KeyError(name)
    module = importlib.import_module(f"lfpiv.studies.{_MODULES.get(name, name)}")
    return module.STUDY
