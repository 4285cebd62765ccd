"""``lfpiv particles``: iterative particle reconstruction of a run's frames into ``particles/``."""

from __future__ import annotations

import argparse

from lfpiv.commands import (
    add_along_pairs,
    add_device,
    add_pair_range,
    add_workers,
    camera_names,
    fraction,
    iterations,
    non_negative_float,
    old_spelling_notes,
    pairs_option,
    positive_float,
    positive_int,
    run_flat_fields,
    whole_number,
    workers_phrase,
    xyz_triple,
)
from lfpiv.errors import UsageError


def shakes(text: str) -> int:
    """argparse type of ``--shakes``: a whole number, 0 or more."""
    return whole_number(text, 0)


def mask_sigmas(text: str) -> float | str:
    """argparse type of ``--residual-mask``: ``auto`` or a finite number of at least 0."""
    return "auto" if text == "auto" else non_negative_float(text)


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("particles", help="reconstruct every frame's particles (positions, intensities) by IPR",
                       description="Iterative particle reconstruction (the reconstruction of Shake-the-Box) on the "
                       "rig's own forward model: candidates from the peaks of a quick reconstruction (or by ray "
                       "bundling, --candidates rays), each "
                       "particle's position and intensity fitted to the images, the faint, the merged and those "
                       "outside the box (by more than 2 voxels with the point model) pruned, and the residual "
                       "searched again. Writes particles/: x, y, z (mm), "
                       "intensity and a fit residual of every particle of every frame.")
    c.add_argument("run", metavar="RUN", help="run store with recorded frames")
    add_pair_range(c, "every recorded pair")
    c.add_argument("--cameras", type=camera_names, default=None, metavar="NAMES",
                   help="comma-separated cameras to use (default: all)")
    c.add_argument("--method", choices=("drt-mart", "mlos-mart", "mlos-smart"), default=None,
                   help="the reconstruction whose weights model the particles and give the candidates (default: "
                   "drt-mart for light-field cameras, mlos-smart for pinhole ones)")
    c.add_argument("--candidate-iterations", type=iterations, default=None, metavar="N",
                   help="iterations of the quick reconstruction whose peaks are the candidates (with "
                   "--candidate-protocol fast, the most the stopping rule runs; default: 50)")
    c.add_argument("--candidate-protocol", choices=("fast", "fixed", "chapter"), default=None,
                   help="the quick reconstruction's protocol, as lfpiv reconstruct --protocol: fast, line-of-sight "
                   "weights first, DRT weights for the voxels still bright, ordered subsets, the stopping rule and, "
                   "in boxes of a million voxels or more, coarse-to-fine elimination; fixed, plain DRT-MART of "
                   "--candidate-iterations iterations (the candidates before this option; default: fast)")
    c.add_argument("--candidate-weights", choices=("protocol", "line-of-sight"), default=None,
                   help="the quick reconstruction's weights: protocol, those of --candidate-protocol (fast: DRT "
                   "weights traced for the voxels still bright after its line-of-sight iterations); "
                   "line-of-sight, MLOS-MART's line-of-sight weights throughout on the same grids, no DRT weight "
                   "traced (less CPU and memory a voxel; on a deep box add --candidate-smoothing; default: "
                   "protocol)")
    c.add_argument("--candidate-smoothing", type=non_negative_float, default=None, metavar="VOXELS",
                   help="the quick reconstruction's volume smoothed by a Gaussian of this sigma (voxels across, a "
                   "third of it along z) before its peaks are found: line-of-sight weights' volume of a deep box is "
                   "speckled, a particle's light in several peaks (3 on L's optics; default: 0, none)")
    c.add_argument("--candidates", choices=("reconstruction", "rays"), default="reconstruction",
                   help="where the candidates come from: reconstruction, the peaks of the quick reconstruction "
                   "(--candidate-protocol; its cost grows with the box's voxels); rays, ray bundling: the bright "
                   "pixels' rays voted into the box, the most voted places checked against every lenslet's own "
                   "pixel and refined where the lenslets' rays meet (its cost grows with the bright pixels; the "
                   "fit is the same; default: reconstruction)")
    c.add_argument("--threshold", type=fraction, default=None,
                   help="candidates are peaks above this fraction of the brightest voxel (default: 0.05)")
    c.add_argument("--shakes", type=shakes, default=12, metavar="N",
                   help="fit iterations of every particle's position and intensity (default: 12)")
    c.add_argument("--min-intensity", type=non_negative_float, default=0.5, metavar="F",
                   help="prune particles fainter than F times the median (default: 0.5) of --min-intensity-of")
    c.add_argument("--min-intensity-of", choices=("auto", "frame", "sheet"), default="auto",
                   help="the median --min-intensity is a share of: frame, the frame's particles'; sheet, that of "
                   "the tenth of the particles nearest each along the rig's laser sheet axis ([laser] sheet_axis), "
                   "the light where the particle is: a sheet that dims towards its faces does not prune the dim "
                   "real particles there; auto, sheet where the rig's sheet_profile is not uniform, else frame "
                   "(default: auto)")
    c.add_argument("--merge-voxels", type=positive_float, default=1.0, metavar="D",
                   help="merge particles closer than D voxels (default: 1)")
    c.add_argument("--split", type=non_negative_float, default=1.4, metavar="F",
                   help="split particles brighter than F times the median in two and fit again: two overlapping "
                   "particles seen as one peak (0: never; default: 1.4)")
    c.add_argument("--rounds", type=positive_int, default=3, metavar="N",
                   help="passes of candidates, fit and prune, the later ones on the residual images (default: 3)")
    c.add_argument("--model", choices=("point", "voxels"), default="point",
                   help="a particle's image: point, that of a point at its own position (a light-field camera's "
                   "DRT weights traced from it with the main lens' diffraction blur at the rig's laser wavelength, "
                   "a pinhole camera's Gaussian spot of the rig's [render] particle_image_px); voxels, the blend of "
                   "its 8 neighbouring voxels' weights (default: point)")
    c.add_argument("--relocate", type=shakes, default=4, metavar="N",
                   help="after each round's fit, try every particle up to N voxels either side in depth and one "
                   "laterally, and move it where it explains more of the images (point model; 0: never; default: 4)")
    c.add_argument("--relocate-screen", type=non_negative_float, default=0.0, metavar="S",
                   help="trace the relocation's moves first at S of the point model's sub-apertures per aperture "
                   "diameter and only each particle's best few in full (0 to 1; 0: every move in full; default: 0)")
    c.add_argument("--jacobian-reuse", type=non_negative_float, default=0.0, metavar="V",
                   help="in the fit, keep a particle's Jacobian columns while it has moved at most V voxels since "
                   "they were traced (point model; below 1; 0: every particle traced every step; default: 0)")
    c.add_argument("--max-std", type=non_negative_float, default=0.0, metavar="V",
                   help="at the end, leave out particles whose position is less sure than V voxels on any axis "
                   "(its standard deviation from the fit): fewer ghosts near a light-field camera's focal plane, "
                   "fewer particles found (0: keep all; default: 0)")
    c.add_argument("--noise-model", choices=("auto", "shot", "flat"), default="auto",
                   help="how the fit weighs the pixels: shot, each by the inverse of its noise variance, the "
                   "background's noise plus a share of the particles' light there fitted to the residual (a pixel "
                   "on a bright particle is noisier than one on a far-out-of-focus particle's thin light); flat, "
                   "every pixel alike (plain least squares); auto, shot where the cameras used (--cameras) include "
                   "a light-field camera, flat for pinhole cameras alone (default: auto)")
    c.add_argument("--noise-floor", type=non_negative_float, default=0.0, metavar="F",
                   help="with --noise-model shot (or auto where it chooses shot), weigh no pixel less than F times "
                   "its camera's background (0 to 1; 0: no floor, the default): the images' bright pixels may "
                   "differ from the model by more than their noise, and unfloored the fit leans on the particles' "
                   "wings")
    add_along_pairs(c, along_help="a time-resolved run (every frame dt after the one before, as 'lfpiv synth "
                    "--time-resolved' makes): reconstruct the frames in time order, and fit first in each frame "
                    "the positions where the tracks through the frames before it put their particles "
                    "(Shake-the-Box's prediction: each track carried on by a polynomial through its last "
                    "positions, a particle on no track by its neighbouring tracks' displacement), beside the quick "
                    "reconstruction's peaks; a prediction with no particle fades away. It finds fast particles the "
                    "peaks miss; one process, frame after frame (not with --workers or --scheduler). The default "
                    "where the run is time-resolved, the chosen pairs are consecutive (two or more) and neither "
                    "--workers nor --scheduler is given; the command says which ran and why; given, it is refused "
                    "where it cannot run",
                    pair_by_pair_help="reconstruct every frame on its own, also on a time-resolved run (each frame's "
                    "particles as before --along-pairs became the default there)")
    c.add_argument("--search-voxels", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="along the pairs: the pair tracking's first search radius that starts the tracks, as 'lfpiv "
                   "track --search-voxels' (default: 4,4,2)")
    c.add_argument("--link-voxels", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="along the pairs: the search radius around where a track's own velocity puts it in the next "
                   "frame, as 'lfpiv track --link-voxels' (default: 1,1,1)")
    c.add_argument("--residual-mask", type=mask_sigmas, default="auto", metavar="S",
                   help="in the residual rounds, mask the pixels where the particles found so far are brighter than "
                   "S times the camera's background noise, so that their noise removes no voxel from the quick "
                   "reconstruction whose peaks are the next candidates: faint out-of-focus particles beside "
                   "bright ones are found (0: none; auto, 3 where the cameras used include a light-field camera, "
                   "0 for pinhole cameras alone; default: auto)")
    add_device(c)
    add_workers(c, "reconstruct the particles of")
    c.add_argument("--flat-field", default=None, metavar="CALIB",
                   help="calibration store with white (and dark) images (lfpiv calibrate mla): correct every raw "
                   "frame per pixel by them before the particles are fitted, as lfpiv reconstruct --flat-field "
                   "and the live monitor do (the pixels they show unlit or dead weigh nothing in the fit; "
                   "default: the raw frames)")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.batch import dask_client
    from lfpiv.jobs.particles import (
        LIGHT_FIELD_FIT,
        AlongPairs,
        check_along_workers,
        fit_defaults,
        intensity_axis,
        ipr_settings,
        particles_run,
        used_cameras,
    )
    from lfpiv.pair_runner import WORKERS_GIVEN, AlongChoice, along_option_error
    from lfpiv.runs import open_run

    given = {k: v for k, v in (("search_voxels", args.search_voxels), ("link_voxels", args.link_voxels))
             if v is not None}
    if given and args.along_pairs == "off":
        raise UsageError(f"{', '.join('--' + k.replace('_', '-') for k in given)} only apply to the tracks that "
                         "predict a time-resolved run's particles: leave out --pair-by-pair, or leave them out")
    along = AlongPairs(**given) if args.along_pairs != "off" else None
    if args.along_pairs == "on":
        check_along_workers(args.workers, args.scheduler)  # before any worker starts
    elif given and (args.workers or args.scheduler):  # auto goes frame by frame on workers: refused before they start
        raise UsageError(along_option_error([f"--{k.replace('_', '-')}" for k in given],
                                            AlongChoice(False, WORKERS_GIVEN)))

    # the quick reconstruction's own options where given (ipr_settings refuses them with ray bundling)
    quick = {k: v for k, v in (("candidate_iterations", args.candidate_iterations),
                               ("candidate_protocol", args.candidate_protocol),
                               ("candidate_weights", args.candidate_weights),
                               ("candidate_smoothing", args.candidate_smoothing),
                               ("candidate_threshold", args.threshold)) if v is not None}
    options = dict(method=args.method, **quick, candidate_source=args.candidates, shakes=args.shakes,
                   min_intensity=args.min_intensity,
                   merge_voxels=args.merge_voxels, rounds=args.rounds, split_intensity=args.split, model=args.model,
                   relocate_depth=args.relocate, relocate_screen=args.relocate_screen, max_position_std=args.max_std,
                   jacobian_reuse=args.jacobian_reuse,
                   noise_floor=args.noise_floor)
    fit = {"noise_model": args.noise_model, "residual_mask": args.residual_mask}
    # bad options are refused before the run is opened (auto as the light-field cameras' choice, with which
    # --noise-floor goes; the cameras' own choice is checked again below)
    ipr_settings(**options, **{k: LIGHT_FIELD_FIT[k] if v == "auto" else v for k, v in fit.items()})
    store = open_run(args.run, mode="r+")
    # the fit's weights and residual mask where auto are the cameras' (shot + 3 with a light-field camera, flat
    # + 0 for pinhole cameras alone: what particles/ records); the point model's diffraction blur and pinhole
    # particle images are the rig's
    settings = ipr_settings(**options, **fit_defaults(used_cameras(store.rig, args.cameras), **fit),
                            wavelength_nm=store.rig.laser.wavelength_nm,
                            particle_image_px=store.rig.render.particle_image_px,
                            intensity_axis=intensity_axis(store.rig, args.min_intensity_of))
    flats, flat_info = run_flat_fields(store.rig, args.flat_field, args.cameras)
    with dask_client(args.workers, args.scheduler) as client:
        done = particles_run(store, settings, args.pairs, cameras=args.cameras, device=args.device,
                             progress=not args.quiet, skip_done=args.skip_done, option=pairs_option(args),
                             client=client, along_pairs=along, along_mode=args.along_pairs,
                             along_options=[f"--{k.replace('_', '-')}" for k in given], announce=_say,
                             flats=flats, flat_field=flat_info)
    if not done.pairs:
        print(f"every selected pair of {store.path} has its particles with these settings already; nothing to do")
        old_spelling_notes(args)
        return 0
    n = sum(done.counts)
    secs = sum(done.seconds)
    print(f"wrote {store.path}/particles: {len(done.pairs)} pair(s), {n} particles in {len(done.counts)} frame(s) "
          f"({n / len(done.counts):.0f} a frame, from {sum(done.candidates)} candidates); {secs:.1f} s on "
          f"{done.device} ({secs / len(done.counts):.2f} s a frame){workers_phrase(args)}")
    if done.along.on:
        print(f"along the pairs: {sum(done.predicted)} positions predicted by the tracks so far "
              f"({sum(done.predicted) / len(done.counts):.0f} a frame) fitted first")
    if args.max_std > 0:
        print(f"left out as unsure (--max-std {args.max_std:g} voxel): {sum(done.unsure)} particles "
              f"({sum(done.unsure) / max(n + sum(done.unsure), 1):.1%} of those fitted)")
    old_spelling_notes(args)
    return 0


def _say(line: str) -> None:
    """The job's line saying along the pairs or pair by pair, printed as it comes (before the
    long work; flushed, so it is not held back behind the progress bar)."""
    print(line, flush=True)
