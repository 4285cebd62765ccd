"""``lfpiv correlate``: 3D multi-grid cross-correlation of a run's volumes into ``vectors/``."""

from __future__ import annotations

import argparse
import re
from typing import Any

from lfpiv.commands import (
    add_device,
    add_old_spelling,
    add_pair_range,
    add_workers,
    named,
    old_spelling_notes,
    pairs_option,
    positive_float,
    workers_phrase,
)
from lfpiv.commands.reconstruct import slabs_option
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
    c.add_argument("--deform-passes", dest="deform_passes", type=int, default=2, metavar="N",
                   help="passes with volume deformation at the final window size (default: 2)")
    # --iterations means MART sweeps wherever it appears: the old spelling of --deform-passes
    add_old_spelling(c, "--iterations", "--deform-passes", "deform_passes", type=int)
    add_pair_range(c, "every reconstructed pair")
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
    c.add_argument("--slabs", type=slabs_option, default=None, metavar="N|auto",
                   help="correlate each pair in N depth slabs, each read from the store with the halo of planes its "
                   "passes need (the same vectors, without the whole volumes in memory); auto: in memory where the "
                   "pair fits, otherwise in as many slabs as the memory needs (default: in memory)")
    add_device(c)
    add_workers(c, "correlate")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.batch import dask_client
    from lfpiv.jobs.correlate import correlate_run, correlation_config, pairs_to_correlate
    from lfpiv.runs import open_run

    store = open_run(args.run, mode="r+")
    pairs = pairs_to_correlate(store, args.pairs, option=pairs_option(args))
    if args.deform_passes < 0:
        raise UsageError(f"{named(args, '--deform-passes')} must be 0 or more, got {args.deform_passes}")
    cfg = correlation_config(windows=args.windows, overlap=args.overlap, deform_iterations=args.deform_passes,
                             zero_pad=args.zero_pad, median_filter=args.median_filter, epsilon=args.epsilon,
                             threshold=args.threshold, interpolation=args.interpolation,
                             search_radius=args.search_radius, first_overlap=args.first_overlap)
    with dask_client(args.workers, args.scheduler) as client:
        done = correlate_run(store, cfg, pairs, device=args.device, progress=not args.quiet,
                             skip_done=args.skip_done, client=client, slabs=args.slabs)
    if not done.pairs:
        print(f"every selected pair of {store.path} is already correlated with these settings; nothing to do")
        old_spelling_notes(args)
        return 0
    g = done.grid
    n_vec = g.size * len(done.pairs)
    nx, ny, nz = g.counts
    print(f"wrote {store.path}/vectors: {len(done.pairs)} pair(s) of {nx} x {ny} x {nz} vectors (x, y, z), "
          f"final windows {'x'.join(map(str, g.window))} voxels; {100.0 * done.outliers / n_vec:.1f}% outliers "
          f"replaced; {done.seconds:.1f} s{workers_phrase(args)} on {done.device} "
          f"({n_vec / done.seconds:.3g} vectors/s)")
    if done.slabs > 1:
        print(f"each pair was correlated in {done.slabs} depth slabs, read from the store slab by slab with the halo "
              f"its passes need; peak memory of the volumes and buffers {done.peak_bytes / 2**20:.1f} MiB, of which "
              f"{done.slab_bytes / 2**20:.1f} MiB for the deepest slab's volumes (the whole pair's take "
              f"{done.box_bytes / 2**20:.1f} MiB)")
    old_spelling_notes(args)
    return 0


def __getattr__(name: str) -> Any:
    # Old names of this module, kept working (with a warning) and imported only when asked for,
    # so that the command line does not load the jobs to start.
    if name == "evaluate_vectors":  # moved to lfpiv.jobs.evaluate (also lfpiv.evaluate)
        from lfpiv._deprecation import deprecated_alias
        from lfpiv.jobs.evaluate import evaluate_vectors

        alias = globals()[name] = deprecated_alias(evaluate_vectors, f"{__name__}.{name}", since="0.1.0")
        return alias
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

