"""The demo's own steps (``lfpiv demo``): its output folder, its windows, its pictures, and the two
routes side by side (:func:`route_figures`, :func:`route_table`).

The rest of the demo is ordinary ``lfpiv`` commands (:mod:`lfpiv.commands.demo`).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lfcore.device import resolve_device
from lfcore.rig import Rig
from lfcore.runstore import RunStore, RunStoreError
from lfpiv.errors import UsageError
from lfpiv.jobs.correlate import fitting_windows
from lfpiv.jobs.evaluate import evaluate_vector_fields
from lfpiv.plots import plot_raw_images, plot_routes, plot_vectors

__all__ = ["MARKER", "RouteFigures", "check_device", "copy_recording", "default_plan_method", "demo_windows",
           "pictures", "prepare_folder", "route_figures", "route_table", "routes_picture"]

#: What a copy of the recording leaves out: what the processing wrote (the particle route's copy
#: starts from the recorded frames and the truth alone).
_PROCESSED = ("volumes", "vectors", "particles", "tracks")

#: Marks a folder written by the demo, so that a later demo may replace it (and nothing else).
MARKER = ".lfpiv-demo"


def check_device(device: str) -> None:
    """A one-line error for a compute device this machine lacks (before anything is cleared)."""
    resolve_device(device)


def default_plan_method(rig: Rig) -> str:
    """The method ``lfpiv reconstruct`` runs on all of ``rig``'s cameras without options (the default
    protocol's plan: MLOS-MART on several light-field cameras, DRT-MART on one, MLOS-SMART on pinhole ones)."""
    from lfpiv.jobs.reconstruct import DEFAULT_PROTOCOL, camera_count, cameras_kind, protocol_run_settings, run_method

    return protocol_run_settings(DEFAULT_PROTOCOL, n_cameras=camera_count(rig), camera_kind=cameras_kind(rig),
                                 method=run_method(rig)).method


def prepare_folder(out: Path) -> None:
    """Make ``out`` the demo's empty folder: a previous demo's is replaced, any other non-empty
    folder is refused."""
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the demo's output")
    if out.exists() and any(out.iterdir()):
        if not (out / MARKER).exists() and not _legacy_demo(out):
            raise UsageError(f"{out} is not empty and was not written by 'lfpiv demo'; choose another --out")
        shutil.rmtree(out)  # only ever a previous demo's folder
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by 'lfpiv demo'; the next demo replaces this folder\n")


def _legacy_demo(out: Path) -> bool:
    # lfpiv 0.1's demo left only run.zarr (with attrs demo = true) and raw_images.png.
    if {p.name for p in out.iterdir()} - {"run.zarr", "raw_images.png"}:
        return False
    try:
        return RunStore.open(out / "run.zarr").attrs.get("demo") is True
    except RunStoreError:
        return False


def demo_windows(run: str) -> str:
    """``--windows`` for the run's volumes (:func:`lfpiv.jobs.correlate.fitting_windows`)."""
    return ",".join("x".join(map(str, w)) for w in fitting_windows(RunStore.open(run).volume_grid().shape))


def pictures(run: str, out: Path) -> list[Path]:
    """The raw images and the vectors of the run's first pair, as PNG files in ``out``."""
    store = RunStore.open(run)
    return [plot_raw_images(store, out / "raw_images.png"), plot_vectors(store, out / "vectors.png")]


def copy_recording(run: str, dest: str) -> None:
    """A copy of the run store ``run`` at ``dest`` with its recorded frames and truth but none of
    its processing (volumes, vectors, particles, tracks): where the demo's particle route writes
    its own ``vectors/`` beside the voxel route's."""
    shutil.copytree(run, dest, ignore=lambda folder, names: [n for n in names if Path(folder) == Path(run)
                                                               and n in _PROCESSED])


@dataclass(frozen=True)
class RouteFigures:
    """One route's time and error against the truth in the demo.

    Attributes
    ----------
    route
        What it is called in the table.
    pairs
        The pairs it processed.
    seconds
        Wall time of its steps (reconstruction and correlation, or particles and tracking), s.
    of_peak
        RMS velocity error over the vectors it measured, as a fraction of the truth's peak speed on
        its grid; NaN without truth.
    rms_voxels
        RMS displacement error (x, y, z), voxels; None where unknown.
    vectors, filled
        Vectors of its grid, and those it measured (bins of tracks with too few tracks are empty).
    """

    route: str
    pairs: int
    seconds: float
    of_peak: float
    rms_voxels: tuple[float, float, float] | None
    vectors: int
    filled: int


def route_figures(run: str, route: str, seconds: float, pairs: int) -> RouteFigures:
    """The figures of the vectors of ``run``'s first ``pairs`` pairs (:func:`evaluate_vector_fields`)
    against its truth, with the ``seconds`` its route took."""
    store = RunStore.open(run)
    ev = evaluate_vector_fields(store, slice(0, pairs))
    if isinstance(ev, str):
        raise UsageError(f"{run}: no vectors to compare ({ev})")
    u = np.stack([store.read_vectors(p)["u"] for p in ev.pairs])
    return RouteFigures(route=route, pairs=len(ev.pairs), seconds=seconds,
                        of_peak=float("nan") if ev.errors is None else float(ev.errors.of_peak),
                        rms_voxels=None if ev.rms_voxels is None else tuple(float(v) for v in ev.rms_voxels),
                        vectors=int(u.size), filled=int(np.count_nonzero(np.isfinite(u))))


def route_table(rows: list[RouteFigures]) -> str:
    """The routes side by side as a small text table: pairs, seconds (in all and per pair), the
    velocity error as a share of the peak speed, the RMS error per axis in voxels and the vectors
    measured."""
    head = ("route", "pairs", "time (s)", "s/pair", "error (% of peak)", "RMS x, y, z (voxel)", "vectors")
    body = []
    for r in rows:
        rms = "n/a" if r.rms_voxels is None else ", ".join(f"{v:.3f}" for v in r.rms_voxels)
        err = "n/a" if not np.isfinite(r.of_peak) else f"{100 * r.of_peak:.1f}%"
        body.append((r.route, str(r.pairs), f"{r.seconds:.1f}", f"{r.seconds / max(r.pairs, 1):.1f}", err, rms,
                     f"{r.filled}/{r.vectors}"))
    width = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(head)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, width, strict=True)).rstrip()
                     for line in (head, *body))


def routes_picture(runs: list[tuple[str, str]], out: Path) -> Path:
    """Both routes' in-plane vectors of the first pair beside the truth's, as ``out``
    (:func:`lfpiv.plots.plot_routes`); ``runs`` is (label, run store) per route."""
    return plot_routes([(label, RunStore.open(run)) for label, run in runs], out)
