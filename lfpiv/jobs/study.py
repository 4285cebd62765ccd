"""The chapter's studies (``lfpiv study``): one, or all, into a folder of tables, figures and reports.

The studies themselves are :mod:`lfpiv.studies`; this module picks them, loads the user's rig,
starts the Dask workers and writes the index of ``lfpiv study all``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from lfcore.files import replace_file
from lfcore.rig import is_pinhole
from lfpiv.batch import dask_client
from lfpiv.errors import UsageError
from lfpiv.rigfile import load_rig
from lfpiv.studies import STUDY_NAMES, study_named
from lfpiv.studies.runner import SCALES, Setup, StudyOutcome, render_index, run_study

__all__ = ["SCALES", "STUDY_NAMES", "StudyOutcome", "run_studies", "study_setup"]


def study_setup(*, scale: str = "quick", rig: str | Path | None = None, device: str | None = None) -> Setup:
    """The setup of a run: the scale, the user's rig file (None: the scale's defaults) and the device.

    Raises
    ------
    UsageError
        An unknown scale; a rig file that cannot be read (:class:`lfcore.rig.RigError`, one line);
        a rig without a light-field camera (the studies are of light-field PIV; a mixed rig's
        pinhole cameras are left out of them, and its name says so).
    """
    if scale not in SCALES:
        raise UsageError(f"--scale must be one of {', '.join(SCALES)}, got '{scale}'")
    if device is not None:
        from lfcore.device import resolve_device

        resolve_device(device)  # a device this machine lacks: one line before any work
    if rig is None:
        return Setup(scale=scale, device=device)
    loaded = load_rig(rig)
    d = loaded.to_dict()
    name = f"`{Path(rig).name}`"
    light_field = [c for c, cam in zip(d["camera"], loaded.camera, strict=True) if not is_pinhole(cam)]
    if not light_field:
        raise UsageError(f"rig {rig} has only pinhole cameras; the chapter's studies are of light-field PIV: "
                         "give a rig with at least one light-field camera (kind = \"lightfield\")")
    if len(light_field) < len(d["camera"]):
        d["camera"] = light_field
        name += " (its light-field cameras)"
    return Setup(scale=scale, rig=d, rig_name=name, device=device)


def run_studies(names: Sequence[str], setup: Setup, out: str | Path, *, skip_done: bool = False,
                overwrite: bool = False, workers: int | None = None, scheduler: str | None = None,
                progress: Callable[[str], None] | None = None) -> list[StudyOutcome]:
    """Run the named studies (``"all"`` for every one) into ``out``, one folder each.

    Parameters
    ----------
    names
        Study names of :data:`lfpiv.studies.STUDY_NAMES`, or ``["all"]``.
    setup
        Scale, rig and device (:func:`study_setup`).
    out
        The output folder.
    skip_done, overwrite
        Keep the cases done before (resume), or do them all again.
    workers, scheduler
        Dask workers on this machine or a running cluster's (:func:`lfpiv.batch.dask_client`).
    progress
        Called with a line after each case.

    Returns
    -------
    list of StudyOutcome
        One per study, in the order run. With several studies, ``out/README.md`` indexes them.

    Raises
    ------
    UsageError
        An unknown study name, or results of an earlier run with neither ``skip_done`` nor
        ``overwrite``.
    """
    chosen = list(STUDY_NAMES) if "all" in names else list(dict.fromkeys(names))
    unknown = [n for n in chosen if n not in STUDY_NAMES]
    if unknown:
        raise UsageError(f"no study '{unknown[0]}'; choose one of {', '.join(STUDY_NAMES)} or all")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the studies' results")
    if not (skip_done or overwrite):  # every study checked before the first is run
        for n in chosen:
            folder = out / n / "cases"
            if folder.is_dir() and any(folder.glob("*.json")):
                raise UsageError(f"{out / n} holds the results of an earlier run; give --skip-done to keep them and "
                                 "do the rest, or --overwrite to do every case again")
    outcomes = []
    with dask_client(workers, scheduler) as client:
        for n in chosen:
            outcomes.append(run_study(study_named(n), setup, out, skip_done=skip_done, overwrite=overwrite,
                                      client=client, progress=progress))
    if len(outcomes) > 1:
        index = out / "README.md"
        replace_file(index, render_index(outcomes, setup))
    return outcomes
