"""``lfpiv correlate``: 3D multi-grid cross-correlation of a run's volumes into ``vectors/``.

Also :func:`evaluate_vectors`, the vector lines of ``lfpiv evaluate``.
"""

from __future__ import annotations

import argparse
import re

import numpy as np

from lfpiv.commands import add_device, add_workers, pair_range, positive_float, workers_phrase
from lfpiv.errors import UsageError

DEFAULT_WINDOWS = "320x320x64,160x160x32"


def parse_windows(text: str) -> tuple[tuple[int, int, int], ...]:
    """'320x320x64,160x160x32' -> ((320, 320, 64), (160, 160, 32)), each (x, y, z) voxels."""
    out = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*[xX]\s*(\d+)\s*", part)
        if not m:
            raise argparse.ArgumentTypeError(f"'{part}' is not a window size; write XxYxZ in voxels, e.g. "
                                             f"{DEFAULT_WINDOWS}")
        w = tuple(int(g) for g in m.groups())
        if min(w) < 4:
            raise argparse.ArgumentTypeError(f"window {part.strip()} is too small: every side needs at least 4 voxels")
        if out and any(a > b for a, b in zip(w, out[-1], strict=True)):
            # multi-grid refines: each pass predicts the next from larger windows
            raise argparse.ArgumentTypeError(f"window {part.strip()} is larger than the one before it; list the "
                                             f"passes largest first, e.g. {DEFAULT_WINDOWS}")
        out.append(w)
    return tuple(out)


def _per_axis(text: str, cast, expected: str) -> list:
    """'a' or 'a,b,...' -> the values converted by ``cast``, one value repeated for x, y and z;
    a value ``cast`` refuses is reported as not ``expected``."""
    try:
        vals = [cast(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not {expected}") from None
    return vals * 3 if len(vals) == 1 else vals


def parse_overlap(text: str) -> tuple[float, float, float]:
    """'0.75' or '0.75,0.75,0.5' (x, y, z) -> a fraction per axis, each in [0, 1)."""
    vals = _per_axis(text, float, "a number or three numbers x,y,z")
    if len(vals) != 3 or not all(0.0 <= v < 1.0 for v in vals):
        raise argparse.ArgumentTypeError(f"overlap must be at least 0 and below 1 (one value, or x,y,z), got {text}")
    return tuple(vals)  # type: ignore[return-value]


def parse_radius(text: str) -> tuple[int, int, int]:
    """'3' or '3,3,2' (x, y, z) -> a search radius in voxels per axis."""
    vals = _per_axis(text, int, "a whole number of voxels or three of them x,y,z")
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"give one radius or three (x,y,z), got {text}")
    return tuple(vals)  # type: ignore[return-value]


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("correlate", help="3D multi-grid cross-correlation of a run's volumes into vectors/",
                       description="Correlate the two reconstructed volumes of each pair with 3D multi-grid FFT "
                       "cross-correlation (window shift, then volume deformation; with --search-radius, volume "
                       "deformation and direct correlation around the predictor after the first pass), find and "
                       "replace outliers (normalized median test) and write the velocity in m/s to the run's "
                       "vectors/.")
    c.add_argument("run", metavar="RUN", help="run store with volumes (a .zarr directory)")
    c.add_argument("--windows", type=parse_windows, default=parse_windows(DEFAULT_WINDOWS), metavar="XxYxZ,...",
                   help="interrogation volume of each pass, x by y by z voxels, largest first "
                   f"(default: {DEFAULT_WINDOWS}, the chapter's)")
    c.add_argument("--overlap", type=parse_overlap, default=(0.75, 0.75, 0.75), metavar="F[,F,F]",
                   help="overlap of neighbouring windows, one fraction or x,y,z (default: 0.75)")
    c.add_argument("--iterations", type=int, default=2, metavar="N",
                   help="passes with volume deformation at the final window size (default: 2)")
    c.add_argument("--pairs", type=pair_range, default=None, metavar="START:STOP",
                   help="pairs to correlate, e.g. 0:10 or 3 (default: every reconstructed pair)")
    c.add_argument("--epsilon", type=positive_float, default=0.1,
                   help="median test: acceptable fluctuation in voxels (default: 0.1)")
    c.add_argument("--threshold", type=positive_float, default=2.0,
                   help="median test: largest normalized residual of a valid vector (default: 2)")
    c.add_argument("--median-filter", action="store_true", help="apply the chapter's 3x3(x3) median filter at the end")
    c.add_argument("--zero-pad", action="store_true",
                   help="pad windows to twice their size (linear instead of circular correlation; 8x the FFT work)")
    c.add_argument("--interpolation", choices=("cubic", "linear"), default="cubic",
                   help="volume deformation: cubic B-spline or trilinear (default: cubic)")
    c.add_argument("--search-radius", type=parse_radius, default=None, metavar="R[,R,R]",
                   help="correlate the passes after the first directly at lags within R voxels of the "
                   "predictor (x,y,z or one value, 2 to 8) instead of by FFT: faster and unbiased; those "
                   "passes deform the volumes (default: FFT in every pass)")
    c.add_argument("--first-overlap", type=parse_overlap, default=None, metavar="F[,F,F]",
                   help="overlap of the first pass's windows, which only predict (default: --overlap)")
    add_device(c)
    add_workers(c, "correlate")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run)


def _select_pairs(store, sel: slice | None) -> list[int]:
    from lfcore.runstore import RunStoreError
    from lfpiv.recon import select_pairs

    store.volumes()  # a run without volumes says so
    done = store.reconstructed_pairs()
    if not done:
        raise RunStoreError(f"{store.path} has no reconstructed pairs yet; run 'lfpiv reconstruct {store.path}' first")
    if sel is None:
        return done
    wanted = select_pairs(sel, store.n_pairs)
    missing = [p for p in wanted if p not in done]
    if missing:
        raise UsageError(f"--pairs: pair(s) {', '.join(map(str, missing[:5]))}{' ...' if len(missing) > 5 else ''} "
                         f"are not reconstructed (reconstructed: {', '.join(map(str, done[:10]))})")
    return wanted


def run(args: argparse.Namespace) -> int:
    from lfcore.correlate import CorrelationConfig, CorrelationError
    from lfcore.runstore import RunStore
    from lfcore.vectors import MedianTest
    from lfpiv.batch import dask_client
    from lfpiv.correlation import correlate_run

    store = RunStore.open(args.run, mode="r+")
    pairs = _select_pairs(store, args.pairs)
    if args.iterations < 0:
        raise UsageError(f"--iterations must be 0 or more, got {args.iterations}")
    try:
        cfg = CorrelationConfig(windows=args.windows, overlap=args.overlap, deform_iterations=args.iterations,
                                zero_pad=args.zero_pad, median_filter=args.median_filter,
                                median_test=MedianTest(epsilon=args.epsilon, threshold=args.threshold),
                                interpolation=args.interpolation, search_radius=args.search_radius,
                                first_overlap=args.first_overlap)
    except CorrelationError as exc:
        raise UsageError(str(exc)) from None
    with dask_client(args.workers, args.scheduler) as client:
        done = correlate_run(store, cfg, pairs, device=args.device, progress=not args.quiet,
                             skip_done=args.skip_done, client=client)
    if not done.pairs:
        print(f"every selected pair of {store.path} is already correlated with these settings; nothing to do")
        return 0
    g = done.grid
    n_vec = g.size * len(done.pairs)
    nx, ny, nz = g.counts
    print(f"wrote {store.path}/vectors: {len(done.pairs)} pair(s) of {nx} x {ny} x {nz} vectors (x, y, z), "
          f"final windows {'x'.join(map(str, g.window))} voxels; {100.0 * done.outliers / n_vec:.1f}% outliers "
          f"replaced; {done.seconds:.1f} s{workers_phrase(args)} on {done.device} "
          f"({n_vec / done.seconds:.3g} vectors/s)")
    return 0


def evaluate_vectors(store, pairs: slice | None = None) -> list[tuple[str, str]]:
    """Lines (label, text) about a run's vectors for ``lfpiv evaluate``, over the correlated
    pairs among ``pairs`` (the ``--pairs`` range; None: all).

    RMS velocity error per component against the synthetic truth flow (in m/s and in voxels,
    evaluated at the window centres at mid-pair time), the outlier fraction, and the
    chapter's divergence error |du/dx + dv/dy + dw/dz|.
    """
    from lfcore.flows import flow_from_params
    from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED, divergence
    from lfpiv.recon import select_pairs

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
        zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
        pts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
        ref = np.stack([flow.velocity(pts, truth["t0_s"][p] + 0.5 * dt).reshape(vel.shape[1:]) for p in pairs])
        err = vel - ref
        rms = np.sqrt(np.nanmean(err**2, axis=(0, 1, 2, 3)))
        peak = float(np.nanmax(np.linalg.norm(ref, axis=-1)))
        vox = ""
        if store.has_volumes and not store.vectors_outdated:  # the same errors in voxels of their volumes
            in_vox = rms * dt * 1e3 / np.asarray(store.volume_grid().voxel_mm)
            vox = " (" + ", ".join(f"{e:.3f}" for e in in_vox) + " voxel)"
        lines.append(("velocity error", f"RMS u, v, w {rms[0]:.3g}, {rms[1]:.3g}, {rms[2]:.3g} m/s{vox}; "
                                        f"{100 * np.linalg.norm(rms) / peak:.1f}% of the peak speed {peak:.3g} m/s"))
    n = flags.size
    lines.append(("outliers", f"{100.0 * np.count_nonzero(flags & FLAG_OUTLIER) / n:.1f}% of the vectors "
                              f"({100.0 * np.count_nonzero(flags & FLAG_REPLACED) / n:.1f}% replaced)"))
    div = np.abs(np.stack([divergence(v, x, y, z) for v in vel]))
    lines.append(("divergence error", f"|du/dx + dv/dy + dw/dz| mean {np.nanmean(div):.3g} 1/s, median "
                                      f"{np.nanmedian(div):.3g} 1/s"))
    return lines

