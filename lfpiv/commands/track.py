"""``lfpiv track``: a run's particles paired from frame A to frame B, binned into ``vectors/``."""

from __future__ import annotations

import argparse

from lfpiv.commands import (
    add_along_pairs,
    add_device,
    add_pair_range,
    add_workers,
    old_spelling_notes,
    pairs_option,
    positive_int,
    workers_phrase,
    xyz_triple,
)
from lfpiv.errors import UsageError


def bins(text: str) -> tuple[int, int, int]:
    """argparse type of ``--bin``: XxYxZ voxels, e.g. 16x16x8."""
    parts = text.lower().split("x")
    try:
        v = tuple(int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a bin size; write XxYxZ in voxels, e.g. 16x16x8") from None
    if len(v) != 3 or min(v) < 1:
        raise argparse.ArgumentTypeError(f"'{text}' is not a bin size; write XxYxZ in voxels, e.g. 16x16x8")
    return v  # type: ignore[return-value]


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("track", help="pair each pair's particles from frame A to B and bin them into vectors/",
                       description="Pair the particles of frame A (lfpiv particles) with frame B's, one-to-one and "
                       "nearest first around a predictor (in the first pass --predictor's, the median of the 8 tracks "
                       "nearest each particle after it), reject outliers by the normalized median test over the "
                       "nearest tracks, and write a field made from the tracks (each bin's mean, a smooth average or "
                       "a fitted smooth field) to "
                       "vectors/, the layout correlate writes, so evaluate and export read it unchanged; the tracks "
                       "are kept with it ('lfpiv export --format tracks-vtk' or tracks-csv writes them). On a "
                       "time-resolved run the particles are followed through every frame and each pair's field made "
                       "from their fitted paths (--along-pairs, the default there; --pair-by-pair to track each pair "
                       "on its own).")
    c.add_argument("run", metavar="RUN", help="run store with particles/")
    add_pair_range(c, "every pair with particles")
    c.add_argument("--predictor", choices=("none", "volumes", "previous"), default="none",
                   help="the first pass's predicted displacement: none (zero); volumes, a coarse correlation of the "
                   "pair's volumes where 'lfpiv reconstruct' wrote them (a quick reconstruction will do); previous, "
                   "the field of the pair tracked just before (time-resolved runs) (default: none)")
    c.add_argument("--search-voxels", type=xyz_triple, default=(4.0, 4.0, 2.0), metavar="X,Y,Z",
                   help="the first pass's search radius around the predictor: the largest displacement expected, or "
                   "with a predictor its largest error (default: 4,4,2)")
    c.add_argument("--refine-voxels", type=xyz_triple, default=(1.0, 1.0, 1.0), metavar="X,Y,Z",
                   help="the later passes' least search radius around their predictor (a linear fit through the "
                   "pass before's nearest tracks), per axis widened to 4 times those tracks' scatter about it where "
                   "that is wider, at most --search-voxels (default: 1,1,1)")
    c.add_argument("--passes", type=positive_int, default=2, help="pairing passes (default: 2)")
    c.add_argument("--bin", type=bins, default=(16, 16, 8), metavar="XxYxZ",
                   help="the field's bins in voxels (default: 16x16x8)")
    c.add_argument("--min-tracks", type=positive_int, default=2, metavar="N",
                   help="fewest tracks a bin needs for a vector (default: 2)")
    c.add_argument("--field", choices=("fit", "divfree", "smooth", "bins"), default=None,
                   help="how the field is made from the tracks: smooth, their Gaussian-weighted average around each "
                   "bin's centre; bins, the mean of each bin's tracks; fit, a smoothing spline through all the tracks, "
                   "its smoothing chosen by cross-validation, at the bins' centres inside the box with --min-tracks "
                   "tracks within a bin; divfree, as fit but the three components fitted together by a kernel whose "
                   "fields are free of divergence (an incompressible flow), the penalty on divergence chosen by "
                   "cross-validation, and fit's field where that is better on held-out tracks (default: fit; "
                   "divfree along the pairs of a time-resolved run)")
    c.add_argument("--smooth-voxels", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="the smooth field's Gaussian sigma in voxels (default: half a bin)")
    add_along_pairs(c, along_help="a time-resolved run (every frame dt after the one before, as 'lfpiv synth "
                    "--time-resolved' makes): link every frame's particles into tracks through the frames (each "
                    "track carried on by its own velocity, started by the pair tracking), fit each track of "
                    "--min-frames or more by local polynomials in time (Shake-the-Box's long tracks), and make "
                    "each pair's field from the fitted tracks at its mid-time. The default where the run is "
                    "time-resolved, the chosen pairs are consecutive and hold --min-frames frames or more, and "
                    "neither --workers, --scheduler nor --predictor previous is given; the command says which ran "
                    "and why; given, it is refused where it cannot run",
                    pair_by_pair_help="track each pair on its own, also on a time-resolved run (as before "
                    "--along-pairs became the default there)")
    c.add_argument("--link-voxels", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="along the pairs: the search radius around where a track's own velocity puts it in the next "
                   "frame (default: 1,1,1)")
    c.add_argument("--min-frames", type=positive_int, default=None, metavar="N",
                   help="along the pairs: fewest frames a track needs to be fitted and used (default: 4)")
    c.add_argument("--fit-frames", type=positive_int, default=None, metavar="N",
                   help="along the pairs: how many of a track's frames, the nearest the pair's mid-time, each fit uses "
                   "(default: 6)")
    c.add_argument("--fit-order", type=positive_int, default=None, metavar="N",
                   help="along the pairs: the tracks' polynomial order in time (default: 2, as Shake-the-Box)")
    c.add_argument("--pool-pairs", type=int, default=None, metavar="K",
                   help="along the pairs, with --field fit or divfree: offer each pair's field the tracks of the K "
                   "pairs before and after it, moved by the flow pattern's translation from pair to pair "
                   "(estimated from the tracks: a vortex ring travelling at its own speed, a wake carried by a "
                   "stream), and keep them only where the pair's own held-out tracks are predicted better with them "
                   "(default along the pairs: 4 with --field fit or divfree, 0 otherwise; 0: each pair's own tracks)")
    c.add_argument("--bridge-frames", type=int, default=None, metavar="N",
                   help="along the pairs: join a track that ends to one that starts up to N frames later where its own "
                   "velocity puts it, so a particle that reconstruction missed in a frame or two keeps its track, "
                   "and a pair whose particle is missing in frame A or B gets the track's fitted positions there "
                   "(default: 0, tracks without gaps)")
    c.add_argument("--relink", action=argparse.BooleanOptionalAction, default=None,
                   help="along the pairs: a track whose own velocity finds no particle in the next frame takes the "
                   "pair tracking's link of its particle instead of ending, and the pair tracking's last pass pairs "
                   "what it left unpaired within --search-voxels: particles on paths that turn faster than "
                   "--link-voxels allows from frame to frame (a vortex core) keep their tracks (default along the "
                   "pairs: on; --no-relink: off, where a smooth flow seen by one camera would keep depth-misplaced "
                   "particles on their tracks)")
    c.add_argument("--csv", default=None, metavar="FILE",
                   help="also write every tracked pair's tracks to FILE: pair, frame A's x, y, z and frame B's (mm), "
                   "u, v, w (m/s), outlier")
    add_device(c)
    add_workers(c, "track the")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.batch import dask_client
    from lfpiv.jobs.track import along_defaults, series_settings, track_run, track_settings, tracks_csv
    from lfpiv.runs import open_run

    settings = track_settings(search_voxels=args.search_voxels, refine_voxels=args.refine_voxels,
                              passes=args.passes, bin_voxels=args.bin, min_tracks=args.min_tracks,
                              field=args.field or "fit",
                              smooth_voxels=args.smooth_voxels)
    # the series' options (None where not given: SeriesSettings' defaults) only mean something along the pairs
    given = {k: v for k, v in (("link_voxels", args.link_voxels), ("min_frames", args.min_frames),
                               ("fit_frames", args.fit_frames), ("degree", args.fit_order),
                               ("pool_pairs", args.pool_pairs), ("bridge_frames", args.bridge_frames),
                               ("relink", args.relink))
             if v is not None}
    names = {"link_voxels": "--link-voxels", "min_frames": "--min-frames", "fit_frames": "--fit-frames",
             "degree": "--fit-order", "pool_pairs": "--pool-pairs", "bridge_frames": "--bridge-frames",
             "relink": "--relink"}
    if given and args.along_pairs == "off":
        raise UsageError(f"{', '.join(names[k] for k in given)} only apply to tracks along a time-resolved series: "
                         "leave out --pair-by-pair, or leave them out")
    # along the pairs, what is not given is along_defaults' (ALONG_DEFAULTS, then SeriesSettings' own)
    series = series_settings(**along_defaults(args.field, **given)) if args.along_pairs != "off" else None
    store = open_run(args.run, mode="r+")
    if args.csv:
        from pathlib import Path

        csv = Path(args.csv)
        if csv.exists():
            raise UsageError(f"--csv {csv}: it exists; give a new file (outputs are never replaced silently)")
        if not csv.resolve().parent.is_dir():
            raise UsageError(f"--csv {csv}: no folder {csv.parent}; give a file in an existing folder")
    if args.predictor == "previous" and (args.workers or args.scheduler):  # before any worker starts
        raise UsageError("--predictor previous tracks the pairs in order, each from the one before: leave out "
                         "--workers and --scheduler, or choose --predictor volumes")
    if args.along_pairs == "on" and (args.workers or args.scheduler):
        raise UsageError("--along-pairs links every frame's particles in order, each frame from the one before: "
                         "leave out --workers and --scheduler")
    if given and args.along_pairs == "auto" and (args.workers or args.scheduler):  # before any worker starts
        from lfpiv.pair_runner import WORKERS_GIVEN, AlongChoice, along_option_error

        raise UsageError(along_option_error([names[k] for k in given], AlongChoice(False, WORKERS_GIVEN)))
    with dask_client(args.workers, args.scheduler) as client:
        done = track_run(store, settings, args.pairs, predictor=args.predictor, progress=not args.quiet,
                         skip_done=args.skip_done, option=pairs_option(args), client=client, device=args.device,
                         along_pairs=series, along_mode=args.along_pairs, along_options=[names[k] for k in given],
                         announce=lambda line: print(line, flush=True),  # said before the long work
                         field_given=args.field is not None)
    if done.series_frames and series is not None and done.along.on:
        print(f"linked {done.series_tracks} tracks of at least {series.min_frames} frames through the "
              f"{done.series_frames} frames (mean length {done.series_length:.1f} frames), fitted by polynomials "
              f"of order {series.degree} in time through {series.fit_frames} frames"
              + (f", gaps of up to {series.bridge_frames} missing frame(s) bridged" if series.bridge_frames else "")
              + (", tracks a straight line lost carried on by the pair tracking's links" if series.relink else ""))
        if done.pool_offered:
            import numpy as np

            shift = ", ".join(f"{v:.2f}" for v in np.median(np.asarray(done.pool_shifts), axis=0))
            print(f"pooled the tracks of up to {series.pool_pairs} pair(s) either side into {done.pool_taken} of the "
                  f"{done.pool_offered} pairs' fields (the others' own held-out tracks were not predicted better); the "
                  f"pattern's translation per pair (x, y, z) {shift} voxel (median of the pairs)")
    if done.pairs:
        nx, ny, nz = done.shape
        print(f"wrote {store.path}/vectors: {len(done.pairs)} pair(s) of {nx} x {ny} x {nz} bins (x, y, z) from "
              f"{done.tracks} tracks ({100.0 * done.outliers / max(done.tracks, 1):.1f}% outliers left out); "
              f"{100.0 * done.vectors / max(done.bins, 1):.0f}% of the bins hold a vector; {done.field} field, "
              f"predictor {args.predictor}{', along the pairs' if done.along.on else ''}; {done.seconds:.1f} s"
              f"{workers_phrase(args)}")
    else:
        print(f"every selected pair of {store.path} is tracked already with these settings; nothing to do")
    if args.csv:
        print(f"wrote {args.csv}: {tracks_csv(store, args.csv)} tracks of every tracked pair")
    old_spelling_notes(args)
    return 0
