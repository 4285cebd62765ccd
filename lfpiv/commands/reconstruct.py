"""``lfpiv reconstruct``: DRT-MART (or the MART baseline) of a run's pairs into ``volumes/``."""

from __future__ import annotations

import argparse
import sys

from lfpiv.commands import (
    MAX_ITERATIONS,
    add_device,
    add_pair_range,
    add_workers,
    camera_names,
    check_pvr,
    iterations,
    non_negative_float,
    old_spelling_notes,
    pairs_option,
    positive_float,
    positive_int,
    run_flat_fields,
    sub_apertures,
    warn,
    whole_number,
    workers_phrase,
    xyz_triple,
)


def los_iterations(text: str) -> int:
    """``--los-iterations``: a whole number from 0 to :data:`lfpiv.commands.MAX_ITERATIONS`."""
    return whole_number(text, 0, MAX_ITERATIONS)


def subsets_option(text: str) -> int:
    """``--subsets``: a whole number from 1 to :data:`lfcore.subsets.MAX_SUBSETS`."""
    from lfpiv.jobs.reconstruct import MAX_SUBSETS

    return whole_number(text, 1, MAX_SUBSETS)


def coarse_option(text: str) -> int:
    """``--coarse``: a whole number from 1 (none) to :data:`lfcore.coarse.MAX_COARSE`."""
    from lfpiv.jobs.reconstruct import MAX_COARSE

    return whole_number(text, 1, MAX_COARSE)


def subset_halving_option(text: str) -> int:
    """``--subset-halving``: a whole number of passes from 0 (never) to :data:`lfpiv.commands.MAX_ITERATIONS`."""
    return whole_number(text, 0, MAX_ITERATIONS)


def stop_tolerance(text: str) -> float:
    """``--stop-tolerance``: a fraction from 0 (a fixed count) to below 1."""
    v = non_negative_float(text)
    if v >= 1:
        raise argparse.ArgumentTypeError(f"expected a fraction of the residual from 0 to below 1, got '{text}'")
    return v


def slabs_option(text: str) -> int | str:
    """``--slabs``: a whole number of depth slabs (1 or more) or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of slabs (1 or more) or auto, got '{text}'")
    return n


def protocol_help(default: str) -> str:
    """``--protocol``'s help, ``default`` the protocol without the option."""
    return (f"a named set of settings (default: {default}), which the other options change: fast stops each frame "
            "when its projections have converged (at most 400 iterations), iterates DRT-MART's first 20 on "
            "line-of-sight weights, in 6 ordered subsets, eliminates on a coarser grid first in boxes of a million "
            "voxels or more and prunes the dark voxels (on several light-field cameras without --method, MLOS-MART "
            "at relaxation 2, at most 75 iterations, after a 2x coarser grid with 15 iterations; on other rigs of "
            "several cameras or with --method, at most 75 iterations, the first 30 on line-of-sight weights, without "
            "ordered subsets or the coarse grid); fixed runs 50 "
            "iterations with pruning; chapter is the chapter's protocol (400 iterations of every active voxel from a "
            "uniform start, as lfpiv study runs it)")


#: ``--projector``'s help, the same for every command that reconstructs (reconstruct, monitor).
PROJECTOR_HELP = ("what applies DRT-MART's operator: stored ray-traced weights, or matrix-free templates per depth and "
                  "lenslet phase (no ray tracing; their images of the active voxels are stored where they fit, at the "
                  "stored weights' speed, else applied in every iteration, in memory set by the cameras and depth "
                  "planes, not the voxels, but slower; see --weight-storage); auto (default): per frame the templates' "
                  "images where they cost less to build than tracing the voxels (frames with many more active voxels "
                  "than templates) and fit, else stored weights, and the templates where neither fits")


def add_projector(parser: argparse.ArgumentParser) -> None:
    """``--projector auto|stored|matrix-free`` (the choices of :data:`lfcore.matrix_free.PROJECTORS`)."""
    from lfpiv.jobs.reconstruct import PROJECTORS

    parser.add_argument("--projector", choices=PROJECTORS, default="auto", help=PROJECTOR_HELP)


def register(sub: argparse._SubParsersAction) -> None:
    from lfpiv.jobs.reconstruct import (
        DEFAULT_PROTOCOL,
        LOS_STOP_VOXELS,
        PROTOCOLS,
        STOP_TOLERANCE,
        STOP_VOXELS,
        SUBSET_HALVING,
    )

    r = sub.add_parser(
        "reconstruct", help="reconstruct 3D particle volumes from a run's light-field images",
        description="Reconstruct both frames of every selected pair into volumes/ of the run store, "
        "jointly from every camera's image (or those given by --cameras). DRT-MART eliminates the voxels "
        "that cannot hold a particle, builds dense ray-traced weights for the rest and iterates MART on "
        "them; --method mart is the conventional baseline (line-of-sight weights, no elimination); --method "
        "mlos-mart eliminates as DRT-MART does, then iterates with the baseline's weights. Pinhole (Tomo-PIV) "
        "cameras are reconstructed by --method mlos-smart (their default): MLOS elimination, line-of-sight "
        "weights and SMART iterations.")
    r.add_argument("run", metavar="RUN", help="run store (a .zarr directory)")
    r.add_argument("--method", choices=("drt-mart", "mart", "mlos-mart", "mlos-smart"), default=None,
                   help="default: drt-mart for light-field cameras (mlos-mart, the plan of --protocol fast, on "
                   "several light-field cameras), mlos-smart for pinhole ones")
    r.add_argument("--protocol", choices=tuple(PROTOCOLS), default=None,
                   help=protocol_help(DEFAULT_PROTOCOL) + "; with --skip-done, the protocol the run's volumes "
                   "were made by")
    r.add_argument("--iterations", type=iterations, default=None,
                   help="a fixed count of MART iterations, every frame (default: the protocol's: 50 for fixed, 400 "
                   "for chapter; fast stops each frame by the rule)")
    r.add_argument("--max-iterations", type=iterations, default=None, metavar="N",
                   help="with the stopping rule, the most iterations a frame runs (default: the protocol's iterations: "
                   "400 for fast and chapter, 20 for fast on several light-field cameras, 75 on other rigs of several "
                   "cameras, 50 for fixed); turns the rule on where "
                   "the protocol has none")
    r.add_argument("--stop-tolerance", type=stop_tolerance, default=None, metavar="FRACTION",
                   help="the stopping rule: every 10 iterations, stop once the projections' relative residual fell "
                   f"by less than this fraction of itself and fewer than {STOP_VOXELS:g} of the voxels left "
                   f"({LOS_STOP_VOXELS:g} in fast's plan for several light-field cameras; default: "
                   f"the protocol's: {STOP_TOLERANCE:g} for fast; 0: a fixed count)")
    r.add_argument("--relaxation", type=positive_float, default=None,
                   help="relaxation mu (default: 1; at most 2 for the simultaneous form; the chapter's "
                   "sequential MART used 2.5)")
    r.add_argument("--form", choices=("simultaneous", "sequential"), default="simultaneous",
                   help="simultaneous (default; parallel, for GPUs) or sequential (eq. 4.1 pixel by pixel)")
    r.add_argument("--pvr", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="pixel-voxel ratio per axis (default: the rig's volume.pvr)")
    r.add_argument("--margin-mm", type=xyz_triple, default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                   help="grow the box beyond the rig's volume on every side (default: 0,0,0)")
    r.add_argument("--cameras", type=camera_names, default=None, metavar="NAMES",
                   help="comma-separated cameras to use (default: all)")
    add_pair_range(r, "every recorded pair")
    r.add_argument("--background", type=non_negative_float, default=None, metavar="COUNTS",
                   help="background level to subtract (default: estimated per image)")
    r.add_argument("--threshold-sigma", type=positive_float, default=2.0,
                   help="a pixel is lit above background + this many noise sigmas (default: 2)")
    r.add_argument("--prune", type=non_negative_float, default=None, metavar="FRACTION",
                   help="every --prune-every iterations the voxels dimmer than this fraction of the brightest leave "
                   "the reconstruction (MART keeps a dark voxel dark; the later iterations then touch only what may "
                   "hold a particle; default: 0.01, 0 for the chapter's protocol; 0: every voxel to the last "
                   "iteration)")
    r.add_argument("--prune-every", type=positive_int, default=10, metavar="N",
                   help="iterations between the prunings, and before the first (default: 10)")
    r.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                   help="start frame B of each pair from frame A carried along a predicted displacement "
                   "(--warm-predictor), instead of from a uniform volume, and iterate it --warm-iterations times "
                   "(default: the fast protocol's, by each pair's own predictor, so that a volume depends on its own "
                   "pair alone; left out with --iterations or in depth slabs; no warm start for the other "
                   "protocols); --no-warm-start starts every frame uniform")
    r.add_argument("--warm-predictor", choices=("own", "last"), default=None,  # lfcore.warm.WARM_PREDICTORS
                   help="with the warm start, where frame B's predicted displacement comes from: own, its own pair "
                   "(frame A's volume correlated with a few line-of-sight iterations of B, so that B depends on its "
                   "pair alone and every pair's B starts warm), or last, the field the last pair a reconstructor "
                   "made measured (pairs in order; the first pair's B starts uniform) (default: own)")
    r.add_argument("--warm-iterations", type=positive_int, default=None, metavar="N",
                   help="iterations of a warm-started frame (default: a fifth of --iterations)")
    r.add_argument("--los-iterations", type=los_iterations, default=None, metavar="N",
                   help="drt-mart: the first N iterations on the MART baseline's line-of-sight weights (cheap to "
                   "build), then DRT weights only for the voxels still bright (those --prune keeps), the rest of "
                   "--iterations on them (default: 20 for the fast protocol, 30 on several cameras, 0 otherwise: DRT "
                   "weights from the start)")
    r.add_argument("--subsets", type=subsets_option, default=None, metavar="N",
                   help="ordered subsets (OS-SMART): each iteration updates the voxels from N interleaved subsets "
                   "of the pixels in turn, for about the work of one update from all of them, so its first passes go "
                   "about as far as N plain iterations each (4 subsets took 4x fewer --iterations on the rigs "
                   "measured); stored weights held whole (in memory or in depth slabs), the others run the "
                   "plain form; with the stopping rule it measures and prunes per pass, "
                   "divided by N (default: 6 for the fast protocol, 1 otherwise: the plain simultaneous form)")
    r.add_argument("--subset-halving", type=subset_halving_option, default=None, metavar="PASSES",
                   help="with --subsets: every this many passes the subsets are joined in pairs, down to one (the "
                   "plain form), so that the last passes settle on one volume (default: "
                   f"{SUBSET_HALVING or '0, the same subsets in every pass'})")
    r.add_argument("--coarse", type=coarse_option, default=None, metavar="N",
                   help="drt-mart or mlos-mart on light-field cameras: coarse-to-fine elimination, first a few "
                   "line-of-sight iterations on a grid N times coarser along every axis, then only the voxels inside "
                   "the coarse "
                   "ones still bright (those --prune keeps) are eliminated, weighted and iterated, from their coarse "
                   "voxel's intensity; boxes of at least a million voxels (default: 3 for the fast protocol, 1 "
                   "otherwise: the whole grid eliminated)")
    r.add_argument("--coarse-iterations", type=positive_int, default=None, metavar="N",
                   help="with --coarse: the line-of-sight iterations on the coarse grid (default: 30 for the fast "
                   "protocol, 20 otherwise)")
    r.add_argument("--smooth", type=non_negative_float, default=0.6, metavar="VOXELS",
                   help="Gaussian sigma applied to the result, in voxels (default: 0.6; 0: none)")
    r.add_argument("--sub-apertures", type=sub_apertures, default=None,
                   help="main-lens sub-apertures per axis for the DRT weights (default: pixels per lenslet)")
    r.add_argument("--calibration", default=None, metavar="CALIB",
                   help="calibration store (lfpiv calibrate fit): reconstruct with its fitted camera models "
                   "instead of the rig stored in the run")
    r.add_argument("--flat-field", default=None, metavar="CALIB",
                   help="calibration store with white (and dark) images (lfpiv calibrate mla): correct every raw "
                   "frame per pixel by them (dark subtracted, the lens' and micro-images' vignetting and dust "
                   "divided out) and leave the pixels they show unlit or dead out of the reconstruction (default: "
                   "the raw frames, one background level per camera)")
    r.add_argument("--weight-storage", choices=("auto", "stored", "on-the-fly"), default="auto",
                   help="line-of-sight weights (mart, mlos-mart) and the matrix-free templates' images "
                   "(--projector matrix-free): auto (default) stores them if they fit in the device's memory and "
                   "makes the rest again in each iteration (slower, the same volume); stored refuses a volume whose "
                   "weights do not fit; on-the-fly stores none")
    add_projector(r)
    r.add_argument("--slabs", type=slabs_option, default=None, metavar="N|auto",
                   help="reconstruct each volume in N depth slabs, written into the store slab by slab (the same "
                   "volume, without a buffer of the whole box: for volumes larger than memory); auto: in memory "
                   "where the box fits, otherwise in as many slabs as the memory needs (default: in memory)")
    add_device(r)
    add_workers(r, "reconstruct")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.batch import dask_client
    from lfpiv.jobs.reconstruct import (
        BYTES_PER_BOX_VOXEL,
        DEFAULT_PROTOCOL,
        camera_count,
        cameras_kind,
        iterations_summary,
        plan_words,
        protocol_run_settings,
        reconstruct_run,
        recorded_stages,
        resumed_protocol,
        run_method,
        voxel_shape_notes,
    )
    from lfpiv.runs import open_run

    check_pvr(args.pvr)
    # the cameras' default method needs the run's rig (read only: a bad option leaves the store untouched)
    run_rig = open_run(args.run).rig
    # light-field cameras leave the method to the protocol's plan (fast on several: MLOS-MART)
    method = run_method(run_rig, args.cameras, args.method)
    if args.protocol is None:
        # a run is finished as it was begun: --skip-done goes on with its volumes' protocol
        resumed = resumed_protocol(args.run) if args.skip_done else None
        if resumed is not None and resumed != DEFAULT_PROTOCOL:
            print(f"lfpiv: note: going on with --protocol {resumed}, which the volumes of {args.run} were made with "
                  f"(give --protocol {DEFAULT_PROTOCOL} to make them again by the default)", file=sys.stderr)
        args.protocol = resumed or DEFAULT_PROTOCOL
    settings = protocol_run_settings(args.protocol, iterations=args.iterations, max_iterations=args.max_iterations,
                                     n_cameras=camera_count(run_rig, args.cameras),
                                     camera_kind=cameras_kind(run_rig, args.cameras),
                                     stop_tolerance=args.stop_tolerance, method=method, relaxation=args.relaxation,
                                     form=args.form, sub_apertures=args.sub_apertures, background=args.background,
                                     threshold_sigma=args.threshold_sigma, smooth=args.smooth,
                                     weight_storage=args.weight_storage, projector=args.projector, prune=args.prune,
                                     prune_every=args.prune_every, warm_start=args.warm_start,
                                     warm_iterations=args.warm_iterations, warm_predictor=args.warm_predictor,
                                     los_iterations=args.los_iterations,
                                     subsets=args.subsets, subset_halving=args.subset_halving, coarse=args.coarse,
                                     coarse_iterations=args.coarse_iterations)
    args.method = settings.method
    plan = plan_words(args.protocol, n_cameras=camera_count(run_rig, args.cameras),
                      camera_kind=cameras_kind(run_rig, args.cameras), method=method,
                      los_iterations=args.los_iterations, projector=args.projector)
    store = open_run(args.run, mode="r+")
    rig, calibration = None, None
    if args.calibration is not None:
        from lfpiv.jobs.calibrate import calibrated_rig

        rig, calibration = calibrated_rig(store.rig, args.calibration, args.cameras)
    flats, flat_info = run_flat_fields(store.rig, args.flat_field, args.cameras)
    warn(voxel_shape_notes(rig or store.rig, args.cameras, args.pvr))
    with dask_client(args.workers, args.scheduler) as client:
        results = reconstruct_run(store, settings, pvr=args.pvr, margin_mm=args.margin_mm, pairs=args.pairs,
                                  cameras=args.cameras, device=args.device, progress=not args.quiet, rig=rig,
                                  calibration=calibration, skip_done=args.skip_done, client=client,
                                  option=pairs_option(args), slabs=args.slabs, flats=flats,
                                  flat_field=flat_info, protocol=args.protocol,
                                  warm_optional=args.warm_start is None, subsets_optional=args.subsets is None)
    old_spelling_notes(args)
    if not results:
        print(f"every selected pair of {store.path} is already reconstructed with these settings; nothing to do")
        return 0
    grid = store.volume_grid()
    act = sum(r.active_fraction for r in results) / len(results)
    left = sum(r.final_voxels / max(r.active_voxels, 1) for r in results) / len(results)
    ms = sum(r.ms_per_iteration for r in results) / len(results)
    wb = max(r.weight_bytes for r in results)
    ws = sum(r.weights_s for r in results) / len(results)
    ran = sorted({r.projector for r in results})
    images = " and their images" if any(r.nnz for r in results if r.projector == "matrix-free") else ""
    operator = (f"matrix-free templates{images} {wb / 2**20:.1f} MiB" if ran == ["matrix-free"] else
                f"weights {wb / 2**20:.1f} MiB" if ran == ["stored"] else
                f"stored weights or matrix-free templates, at most {wb / 2**20:.1f} MiB")
    print(f"reconstructed {len(results)} volume(s) of {' x '.join(map(str, grid.shape[::-1]))} voxels (x, y, z) "
          f"with {args.method}{' and the models of ' + args.calibration if calibration else ''} into "
          f"{store.path}/volumes{workers_phrase(args)}; per volume: {act:.2%} of voxels active"
          f"{f' ({left:.0%} of them left after pruning)' if left < 1 else ''}, "
          f"{operator} built in {ws:.2f} s, {ms:.1f} ms per iteration")
    print(f"protocol {args.protocol}{plan}: {iterations_summary(results, settings)}")
    stages = recorded_stages(store)
    if stages:
        print(f"each frame ran: {stages}")
    warm = [r for r in results if r.warm]
    if warm:
        took = (f"at most {settings.warm_count} iterations each instead of {settings.iterations}" if settings.stopping
                else f"{warm[0].iterations} iterations each instead of {settings.iterations}")
        whose = "their own pair's" if settings.warm_predictor == "own" else "the last pair's"
        print(f"{len(warm)} frame(s) B started from their frame A carried along {whose} displacement: {took}")
    elif args.warm_start and settings.warm_predictor == "last":
        print("no frame was warm-started: the first pair a reconstructor makes starts uniform (its B has no "
              "predictor yet); reconstruct two pairs or more in one run")
    split = max(r.slabs for r in results)
    if split > 1:
        peak = max(r.peak_bytes for r in results)
        print(f"each volume was reconstructed in {split} depth slabs, written into the store slab by slab; peak "
              f"memory of the weights and buffers {peak / 2**20:.1f} MiB (in memory the box's buffers alone take "
              f"{BYTES_PER_BOX_VOXEL * grid.n_voxels / 2**20:.1f} MiB)")
    applied = sum(1 for r in results if r.projector == "matrix-free" and not r.nnz and r.active_voxels)
    if applied and args.weight_storage == "auto":
        print(f"the matrix-free templates' images of {applied} of {len(results)} volume(s) did not fit in the device's "
              "memory beside the templates: applied from the templates in each iteration instead (the same volume, "
              "more slowly)")
    fly = max(r.on_the_fly_voxels for r in results)
    if fly:
        why = " (they did not fit in the device's memory)" if args.weight_storage == "auto" else ""
        print(f"the weights of up to {fly:,} active voxels per volume were made again in each iteration instead "
              f"of stored{why}: the same volume, more slowly")
    return 0
