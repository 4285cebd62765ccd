"""``lfpiv evaluate``: quality of a synthetic run's reconstruction against its truth."""

from __future__ import annotations

import argparse

from lfpiv.commands import (
    add_pair_range,
    fraction,
    old_spelling_notes,
    pairs_option,
    png_path,
    positive_float,
    warn_outdated_vectors,
)


def register(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="compare a synthetic run's volumes, particles and vectors with the truth",
                       description="Print Q_recon, particle recall, ghosts, position errors, particle "
                       "diameters and the intensity outside the seeded region for every reconstructed frame, and "
                       "the recall, ghosts and position error per axis of the particles of 'lfpiv particles', and "
                       "the velocity error, outliers and divergence error of the vectors. A recorded or imported "
                       "run has no truth: only the outliers and the divergence error are measured.")
    e.add_argument("run", metavar="RUN", help="synthetic run store with volumes/")
    add_pair_range(e, "every pair reconstructed or correlated")
    e.add_argument("--threshold", type=fraction, default=0.1,
                   help="detect peaks above this fraction of the brightest voxel (default: 0.1)")
    e.add_argument("--match-voxels", type=positive_float, default=2.0,
                   help="a detection matches a true particle within this many voxels per axis (default: 2)")
    e.add_argument("--particle-match-voxels", type=positive_float, default=1.0, metavar="D",
                   help="a particle of particles/ matches a true one within D voxels per axis (default: 1)")
    e.add_argument("--plot", type=png_path, default=None, metavar="PNG",
                   help="also write intensity-against-depth and projections")
    e.set_defaults(func=run)


def _print_particles(store, args: argparse.Namespace) -> None:
    from lfpiv.jobs.evaluate import evaluate_particles, particle_rows

    evals = evaluate_particles(store, args.pairs, match_voxels=args.particle_match_voxels, option=pairs_option(args))
    rows = particle_rows(evals)
    cols = list(rows[0])
    width = {c: max(len(c), *(len(r[c]) for r in rows)) for c in cols}
    print(f"particles ({store.particle_attrs()['method']} IPR), matching within {args.particle_match_voxels:g} "
          "voxels per axis:")
    print("  ".join(c.ljust(width[c]) for c in cols))
    for r in rows:
        print("  ".join(r[c].ljust(width[c]) for c in cols))


def run(args: argparse.Namespace) -> int:
    from lfpiv.errors import UsageError
    from lfpiv.jobs.evaluate import evaluate_run, evaluate_vectors, summary_rows
    from lfpiv.runs import open_run

    store = open_run(args.run)
    truth = store.truth() is not None
    if not (store.has_volumes or store.has_vectors or store.has_particles):
        what = "" if truth else " is a recorded run with no truth and"
        raise UsageError(f"{store.path}{what} has neither volumes nor vectors yet; "
                         f"run 'lfpiv reconstruct {store.path}' first (or 'lfpiv particles {store.path}')")
    if not truth:
        # a recorded or imported run: what needs no truth (outliers, divergence) is still measured
        print("reconstruction: a recorded run with no truth: Q, recall and position errors need a synthetic run")
    elif store.has_volumes:
        evals = evaluate_run(store, pairs=args.pairs, threshold=args.threshold, match_voxels=args.match_voxels,
                             option=pairs_option(args))
        rows = summary_rows(evals)
        cols = list(rows[0])
        width = {c: max(len(c), *(len(r[c]) for r in rows)) for c in cols}
        print(f"reconstruction ({store.volume_attrs()['method']}), matching within "
              f"{args.match_voxels:g} voxels per axis:")
        print("  ".join(c.ljust(width[c]) for c in cols))
        for r in rows:
            print("  ".join(r[c].ljust(width[c]) for c in cols))
        if args.plot:
            from lfpiv.plots import plot_reconstruction

            print(f"picture: {plot_reconstruction(store, evals, args.plot)}")
    elif not store.has_particles:
        print(f"volumes: none (run 'lfpiv reconstruct {store.path}')")
    if truth and store.has_particles:
        _print_particles(store, args)
    warn_outdated_vectors(store)
    for label, text in evaluate_vectors(store, args.pairs, option=pairs_option(args)):
        print(f"{label}: {text}")
    old_spelling_notes(args)
    return 0
