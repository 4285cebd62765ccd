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
from lfcore.runstore import RunStore, RunStoreError
from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.errors import UsageError
from lfpiv.pair_runner import particle_pairs, select_pairs

__all__ = ["FrameEvaluation", "ParticleEvaluation", "VectorEvaluation", "evaluate_particles", "evaluate_run",
           "particle_rows", "evaluate_vector_fields", "evaluate_vectors",
           "summary_rows"]


@dataclass(frozen=True)
class FrameEvaluation(metrics.VolumeEvaluation):
    """Quality of one reconstructed volume (pair ``pair``, frame 0 = A or 1 = B) against the truth."""

    pair: int = 0
    frame: int = 0


def evaluate_run(store: RunStore, pairs: slice | None = None, threshold: float = 0.1,
                 match_voxels: float = 2.0, *, option: str = "--pair-range") -> list[FrameEvaluation]:
    """Q, detection and matching, diameters and depth profile of every reconstructed frame.

    Parameters
    ----------
    store
        A synthetic run with ``volumes/``.
    pairs
        The ``--pair-range`` (None: every reconstructed pair); ``option`` names it in messages.
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
        store.volumes()
    except RunStoreError as exc:
        raise UsageError(str(exc)) from None
    done = store.reconstructed_pairs()
    chosen = [p for p in select_pairs(pairs, store.n_pairs, option=option) if p in done]
    if not chosen:
        raise UsageError(f"none of the selected pairs is reconstructed (reconstructed: {done or 'none'}); "
                         f"run 'lfpiv reconstruct {store.path}' first")
    grid = store.volume_grid()
    seeded = store.rig.volume
    out = []
    for p in chosen:
        for f in (0, 1):
            vol = store.read_volume(p, f)  # a damaged or missing chunk is an error, not zeros
            e = metrics.evaluate_volume(vol, grid, truth["particles"][p, f], truth["brightness"][p, f],
                                        centre_mm=seeded.centre_mm, size_mm=seeded.size_mm, threshold=threshold,
                                        match_voxels=match_voxels)
            out.append(FrameEvaluation(**vars(e), pair=p, frame=f))
    return out


@dataclass(frozen=True)
class ParticleEvaluation:
    """One frame's reconstructed particles (``particles/``) against the truth.

    Attributes
    ----------
    pair, frame
        Pair and frame (0: A, 1: B).
    match
        The particles matched one-to-one to the true ones (:func:`lfcore.metrics.match_particles`):
        recall, ghosts (particles found with no true one within the tolerance) and the errors.
    rms_voxels
        RMS position error per axis (x, y, z) in voxels of the grid the particles were fitted on.
    voxel_mm
        That grid's voxel size (x, y, z), mm.
    """

    pair: int
    frame: int
    match: metrics.MatchResult
    rms_voxels: np.ndarray
    voxel_mm: np.ndarray


def evaluate_particles(store: RunStore, pairs: slice | None = None, match_voxels: float = 1.0, *,
                       option: str = "--pair-range") -> list[ParticleEvaluation]:
    """Recall, ghosts and position error per axis of every frame's particles against the truth.

    Parameters
    ----------
    store
        A synthetic run with ``particles/``.
    pairs
        The ``--pair-range`` (None: every pair with particles); ``option`` names it in messages.
    match_voxels
        A particle matches a true one within this many voxels per axis.

    Raises
    ------
    UsageError
        A recorded run (no truth), a run without particles, or none of the pairs selected.
    """
    truth = store.truth()
    if truth is None:
        raise UsageError(f"{store.path} is a recorded run with no truth; evaluate needs a synthetic run")
    attrs, chosen = particle_pairs(store, pairs, option=option)
    voxel = np.asarray(attrs["voxel_mm"], dtype=np.float64)
    out = []
    for p in chosen:
        for f in (0, 1):
            found = store.read_particles(p, f)
            m = metrics.match_particles(found[:, :3], truth["particles"][p, f], match_voxels * voxel)
            out.append(ParticleEvaluation(pair=p, frame=f, match=m, rms_voxels=m.rms_error_mm / voxel,
                                          voxel_mm=voxel))
    return out


def particle_rows(evals: list[ParticleEvaluation]) -> list[dict[str, str]]:
    """Printable rows of :func:`evaluate_particles`, one per frame plus the total."""
    rows = []
    for e in evals:
        m = e.match
        rows.append({"pair": str(e.pair), "frame": "AB"[e.frame], "particles": str(m.n_detected),
                     "true": str(m.n_true), "recall": f"{m.recall:.3f}",
                     "ghosts": f"{m.ghosts} ({100 * m.ghost_fraction:.1f}%)",
                     "rms x,y,z vox": ", ".join(f"{v:.3f}" for v in e.rms_voxels)})
    if len(evals) > 1:
        err = np.concatenate([e.match.error_mm for e in evals])
        rms = np.sqrt(np.mean(err**2, axis=0)) / evals[0].voxel_mm if len(err) else np.full(3, np.nan)
        n_true = sum(e.match.n_true for e in evals)
        n_det = sum(e.match.n_detected for e in evals)
        ghosts = sum(e.match.ghosts for e in evals)
        rows.append({"pair": "all", "frame": "", "particles": str(n_det), "true": str(n_true),
                     "recall": f"{sum(e.match.n_matched for e in evals) / max(n_true, 1):.3f}",
                     "ghosts": f"{ghosts} ({100 * ghosts / max(n_det, 1):.1f}%)",
                     "rms x,y,z vox": ", ".join(f"{v:.3f}" for v in rms)})
    return rows


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


@dataclass(frozen=True)
class VectorEvaluation:
    """A run's vectors against its truth (:func:`evaluate_vector_fields`).

    Attributes
    ----------
    pairs
        The correlated pairs evaluated.
    counts
        (x, y, z) vectors per pair.
    windows
        Window sizes (x, y, z) of every pass, voxels.
    errors
        RMS velocity error per component and the peak speed, against the truth flow at the
        window centres at mid-pair time (None without truth).
    rms_voxels
        The RMS errors as displacements in voxels of the current volumes (None without truth, or
        when the vectors came from volumes since replaced).
    outliers, replaced
        Fractions of the vectors flagged outliers and replaced.
    divergence_mean, divergence_median
        The chapter's divergence error |du/dx + dv/dy + dw/dz|, 1/s.
    """

    pairs: list[int]
    counts: tuple[int, int, int]
    windows: list[list[int]]
    errors: metrics.VelocityErrors | None
    rms_voxels: np.ndarray | None
    outliers: float
    replaced: float
    divergence_mean: float
    divergence_median: float


def evaluate_vector_fields(store: RunStore, pairs: slice | None = None, *,
                           option: str = "--pair-range") -> VectorEvaluation | str:
    """The figures of a run's vectors over the correlated pairs among ``pairs`` (None: all), or
    why there are none (a one-line reason). ``option`` names the pair range in messages."""
    if not store.has_vectors:
        return f"none yet (run 'lfpiv correlate {store.path}')"
    vec = store.vectors()
    done = store.correlated_pairs()
    if not done:
        return "vectors/ exists but no pair has been correlated"
    pairs = [p for p in select_pairs(pairs, store.n_pairs, option=option) if p in done]
    if not pairs:
        return f"none of the selected pairs is correlated (correlated: {done})"
    a = vec["attrs"]
    x, y, z = vec["x_mm"], vec["y_mm"], vec["z_mm"]
    held = [store.read_vectors(p) for p in pairs]  # a damaged or missing chunk is an error, not zeros
    # (pairs, z, y, x, 3)
    vel = np.stack([np.stack([h[c] for c in "uvw"], axis=-1) for h in held]).astype(np.float64)
    flags = np.stack([h["flags"] for h in held])
    dt = float(a["dt_s"])
    truth = store.truth()
    errors = vox = None
    flow = store.truth_flow()  # None: recorded, or points given by the user
    if truth is not None and flow is not None:
        ref = np.stack([metrics.grid_velocity(flow, x, y, z, truth["t0_s"][p] + 0.5 * dt) for p in pairs])
        errors = metrics.velocity_errors(vel, ref)
        if store.has_volumes and not store.vectors_outdated:  # the same errors in voxels of their volumes
            vox = errors.rms_m_s * dt * 1e3 / np.asarray(store.volume_grid().voxel_mm)
        elif store.has_particles and a.get("settings", {}).get("source") == "particle tracks":  # lfpiv track's
            vox = errors.rms_m_s * dt * 1e3 / np.asarray(store.particle_attrs()["voxel_mm"])
    div = metrics.divergence_error(vel, x, y, z)
    with warnings.catch_warnings():  # bins of tracks without a vector are NaN, and may be all of them
        warnings.simplefilter("ignore", RuntimeWarning)
        div_mean, div_median = float(np.nanmean(div)), float(np.nanmedian(div))
    return VectorEvaluation(pairs=pairs, counts=(len(x), len(y), len(z)), windows=[list(w) for w in a["windows"]],
                            errors=errors, rms_voxels=vox,
                            outliers=float(np.count_nonzero(flags & FLAG_OUTLIER) / flags.size),
                            replaced=float(np.count_nonzero(flags & FLAG_REPLACED) / flags.size),
                            divergence_mean=div_mean, divergence_median=div_median)


def evaluate_vectors(store: RunStore, pairs: slice | None = None, *, option: str = "--pair-range"
                     ) -> list[tuple[str, str]]:
    """Lines (label, text) about a run's vectors for ``lfpiv evaluate`` (:func:`evaluate_vector_fields`)."""
    ev = evaluate_vector_fields(store, pairs, option=option)
    if isinstance(ev, str):
        return [("vectors", ev)]
    nx, ny, nz = ev.counts
    lines = [("vectors", f"{len(ev.pairs)} pair(s) of {nx} x {ny} x {nz} vectors (x, y, z); windows "
                         f"{', '.join('x'.join(map(str, w)) for w in ev.windows)} voxels")]
    if ev.errors is not None:
        rms = ev.errors.rms_m_s
        vox = "" if ev.rms_voxels is None else " (" + ", ".join(f"{e:.3f}" for e in ev.rms_voxels) + " voxel)"
        lines.append(("velocity error", f"RMS u, v, w {rms[0]:.3g}, {rms[1]:.3g}, {rms[2]:.3g} m/s{vox}; "
                                        f"{100 * ev.errors.of_peak:.1f}% of the peak speed "
                                        f"{ev.errors.peak_m_s:.3g} m/s"))
    lines.append(("outliers", f"{100.0 * ev.outliers:.1f}% of the vectors ({100.0 * ev.replaced:.1f}% replaced)"))
    lines.append(("divergence error", f"|du/dx + dv/dy + dw/dz| mean {ev.divergence_mean:.3g} 1/s, median "
                                      f"{ev.divergence_median:.3g} 1/s"))
    return lines
