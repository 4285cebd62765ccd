"""A synthetic run's volumes and vectors against its truth (``lfpiv evaluate``).

The measures themselves are :mod:`lfcore.metrics`'; this module reads the run store, picks the
pairs and turns the figures into the lines ``lfpiv evaluate`` prints.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfcore import metrics
from lfcore.flows import flow_from_params
from lfcore.runstore import RunStore, RunStoreError
from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.errors import UsageError
from lfpiv.pair_runner import select_pairs

__all__ = ["FrameEvaluation", "evaluate_run", "evaluate_vectors", "summary_rows"]


@dataclass(frozen=True)
class FrameEvaluation(metrics.VolumeEvaluation):
    """Quality of one reconstructed volume (pair ``pair``, frame 0 = A or 1 = B) against the truth."""

    pair: int = 0
    frame: int = 0


def evaluate_run(store: RunStore, pairs: slice | None = None, threshold: float = 0.1,
                 match_voxels: float = 2.0) -> list[FrameEvaluation]:
    """Q, detection and matching, diameters and depth profile of every reconstructed frame.

    Parameters
    ----------
    store
        A synthetic run with ``volumes/``.
    pairs
        The ``--pairs`` range (None: every reconstructed pair).
    threshold, match_voxels
        As :func:`lfcore.metrics.evaluate_volume`.

    Raises
    ------
    UsageError
        A recorded run (no truth) or a run without volumes.
    """
    truth = store.truth()
    if truth is None:
        raise UsageError(f"{store.path} is a recorded run with no truth; evaluate needs a synthetic run")
    try:
        vols = store.volumes()
    except RunStoreError as exc:
        raise UsageError(str(exc)) from None
    done = store.reconstructed_pairs()
    chosen = [p for p in select_pairs(pairs, store.n_pairs) if p in done]
    if not chosen:
        raise UsageError(f"none of the selected pairs is reconstructed (reconstructed: {done or 'none'}); "
                         f"run 'lfpiv reconstruct {store.path}' first")
    grid = store.volume_grid()
    seeded = store.rig.volume
    out = []
    for p in chosen:
        for f in (0, 1):
            e = metrics.evaluate_volume(vols[p, f], grid, truth["particles"][p, f], truth["brightness"][p, f],
                                        centre_mm=seeded.centre_mm, size_mm=seeded.size_mm, threshold=threshold,
                                        match_voxels=match_voxels)
            out.append(FrameEvaluation(**vars(e), pair=p, frame=f))
    return out


def summary_rows(evals: list[FrameEvaluation]) -> list[dict[str, Any]]:
    """Printable rows, one per frame plus the mean."""
    rows = []
    for e in evals:
        rms = e.match.rms_error_mm * 1e3
        rows.append({"pair": str(e.pair), "frame": "AB"[e.frame], "Q": f"{e.q:.3f}",
                     "recall": f"{e.match.recall:.2f}", "ghosts": f"{e.match.ghosts}/{e.match.n_detected}",
                     "rms err x,y,z um": ", ".join(f"{v:.1f}" for v in rms),
                     "diam x,y,z vox": ", ".join(f"{v:.1f}" for v in e.diameters_vox),
                     "outside": f"{100 * e.outside:.2f}%"})
    if len(evals) > 1:
        with warnings.catch_warnings():  # no frame matched a particle: nan, printed as such
            warnings.simplefilter("ignore", RuntimeWarning)
            rms = np.nanmean([e.match.rms_error_mm for e in evals], axis=0) * 1e3
            diam = np.nanmean([e.diameters_vox for e in evals], axis=0)
        rows.append({"pair": "mean", "frame": "", "Q": f"{np.mean([e.q for e in evals]):.3f}",
                     "recall": f"{np.mean([e.match.recall for e in evals]):.2f}",
                     "ghosts": f"{sum(e.match.ghosts for e in evals)}/{sum(e.match.n_detected for e in evals)}",
                     "rms err x,y,z um": ", ".join(f"{v:.1f}" for v in rms),
                     "diam x,y,z vox": ", ".join(f"{v:.1f}" for v in diam),
                     "outside": f"{100 * np.mean([e.outside for e in evals]):.2f}%"})
    return rows


def evaluate_vectors(store: RunStore, pairs: slice | None = None) -> list[tuple[str, str]]:
    """Lines (label, text) about a run's vectors for ``lfpiv evaluate``, over the correlated
    pairs among ``pairs`` (the ``--pairs`` range; None: all).

    RMS velocity error per component against the synthetic truth flow (in m/s and in voxels,
    evaluated at the window centres at mid-pair time), the outlier fraction, and the
    chapter's divergence error |du/dx + dv/dy + dw/dz|.
    """
    if not store.has_vectors:
        return [("vectors", f"none yet (run 'lfpiv correlate {store.path}')")]
    vec = store.vectors()
    done = store.correlated_pairs()
    if not done:
        return [("vectors", "vectors/ exists but no pair has been correlated")]
    pairs = [p for p in select_pairs(pairs, store.n_pairs) if p in done]
    if not pairs:
        return [("vectors", f"none of the selected pairs is correlated (correlated: {done})")]
    a = vec["attrs"]
    x, y, z = vec["x_mm"], vec["y_mm"], vec["z_mm"]
    vel = np.stack([vec[c][pairs] for c in "uvw"], axis=-1).astype(np.float64)  # (pairs, z, y, x, 3)
    flags = vec["flags"][pairs]
    dt = float(a["dt_s"])
    lines = [("vectors", f"{len(pairs)} pair(s) of {len(x)} x {len(y)} x {len(z)} vectors (x, y, z); windows "
                         f"{', '.join('x'.join(map(str, w)) for w in a['windows'])} voxels")]
    truth = store.truth()
    if truth is not None:
        flow = flow_from_params(truth["attrs"]["flow"])
        ref = np.stack([metrics.grid_velocity(flow, x, y, z, truth["t0_s"][p] + 0.5 * dt) for p in pairs])
        err = metrics.velocity_errors(vel, ref)
        rms = err.rms_m_s
        vox = ""
        if store.has_volumes and not store.vectors_outdated:  # the same errors in voxels of their volumes
            in_vox = rms * dt * 1e3 / np.asarray(store.volume_grid().voxel_mm)
            vox = " (" + ", ".join(f"{e:.3f}" for e in in_vox) + " voxel)"
        lines.append(("velocity error", f"RMS u, v, w {rms[0]:.3g}, {rms[1]:.3g}, {rms[2]:.3g} m/s{vox}; "
                                        f"{100 * err.of_peak:.1f}% of the peak speed {err.peak_m_s:.3g} m/s"))
    n = flags.size
    lines.append(("outliers", f"{100.0 * np.count_nonzero(flags & FLAG_OUTLIER) / n:.1f}% of the vectors "
                              f"({100.0 * np.count_nonzero(flags & FLAG_REPLACED) / n:.1f}% replaced)"))
    div = metrics.divergence_error(vel, x, y, z)
    lines.append(("divergence error", f"|du/dx + dv/dy + dw/dz| mean {np.nanmean(div):.3g} 1/s, median "
                                      f"{np.nanmedian(div):.3g} 1/s"))
    return lines
