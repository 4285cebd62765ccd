"""Particles, not voxels: iterative particle reconstruction (``lfpiv particles``, :mod:`lfcore.ipr`)
beside DRT-MART's volume peaks, against the truth.

Run from the repository root::

    python benchmarks/particles.py                       # tiny rig, 0.5 PPM, 3 frames
    python benchmarks/particles.py --ppm 0.3 --frames 5
    python benchmarks/particles.py --sweep 0.1,0.25,0.5,1,2 --frames 1   # where the goals stop being met
    python benchmarks/particles.py --case S2 --frames 1                  # two cameras at 90 degrees
    python benchmarks/particles.py --model voxels                        # the first particle model
    python benchmarks/particles.py --case S2 --frames 1 --focus-gap 3,10 --rays 40000 --max-std 0.05
    python benchmarks/particles.py --case S2off --no-mart                # S2 focused beyond the box
    python benchmarks/particles.py --case Soff                           # one camera focused beyond the box
    python benchmarks/particles.py --case Mc --frames 1                  # issue 48's 512 x 512 one-camera rig
    python benchmarks/particles.py --case Mcoff --frames 1               # ... focused beyond its box
    python benchmarks/particles.py --case Lc --frames 1 --no-mart        # L's optics on a 660 x 440 crop
    python benchmarks/particles.py --case Lcoff --frames 1 --no-mart     # ... focused beyond its box
    python benchmarks/particles.py --case Mc --frames 1 --candidates fixed   # candidates from plain DRT-MART
    python benchmarks/particles.py --case Lc --frames 1 --no-mart --candidates-only --candidate-source both

``--candidate-source`` is IPR's ``candidate_source`` (``reconstruction``, its default, or ``rays``: ray
bundling, :mod:`lfcore.raybundle`, with ``--ray-keep-bins`` and ``--ray-min-score``), or ``both``: IPR
from each on the same frames in one process, rays first, the routes then named ``ipr-rays``,
``ipr-recon`` and ``candidates-rays``, ``candidates-recon``::

    python benchmarks/particles.py --case Soff --no-mart --candidate-source both

``--candidates-only`` stops each frame after IPR's first round's candidates (scored against the truth as the
``candidates`` routes, with their CPU seconds): the candidate stages compared without the fit.
``--candidates`` is IPR's ``candidate_protocol`` (``fast``, its default, or ``fixed``: plain DRT-MART)
and ``--candidate-iterations`` its ``candidate_iterations``. ``--rays`` renders with more rays a
particle than the rig's (less Monte-Carlo sampling noise in the frames); ``--shakes``, ``--split``,
``--rounds``, ``--relocate``, ``--relocate-screen``, ``--jacobian-reuse``, ``--max-std`` and ``--model`` set
IPR's settings of those names. ``benchmarks/particles_budget.py`` is the error budget behind these
figures (fits started at the true positions, candidates, ghosts).

Case: Table 4.1's A1-like random seeding at ``--ppm`` (or each density of ``--sweep``) on the
one-camera tiny rig (``examples/tiny.toml``, 192 x 160 px, 29 x 68 x 82 voxels) or ``--case``, a
case of ``benchmarks/recon.py`` (S2: two cameras at 90 degrees), frames rendered with noise by the
Monte-Carlo renderer (each camera its own image). ``S2off`` is S2 with each camera's focus point moved
0.6 mm along its optical axis away from the camera (``--focus-shift -0.6``; positive moves it toward
the camera), so that both focal planes lie 0.2 mm (18 voxels) beyond the box, as in
``examples/two_cameras_off_focus.toml``; ``--focus-shift`` moves any rig's focus points so, one camera
included. ``Soff`` is the one-camera tiny rig (case S) focused so, ``--focus-shift -1.0`` by default, as in
``examples/one_camera_off_focus.toml``: its focal plane 0.2 mm (3.6 of its 55 um depth voxels) beyond
the 1.6 mm deep box. ``Mcoff`` is issue 48's 512 x 512 one-camera rig (``Mc``: the M optics cropped, 245 x
245 x 131 voxels of 18.3 x 18.3 x 91.7 um, a box 12 mm deep) focused so, ``--focus-shift -6.8`` by default:
its focal plane 0.8 mm (8.7 depth voxels) beyond the box's far face, about as many lenslets of blur
(0.9; Mc's optics blur 0.09 mm on the lenslets per mm out of focus, the tiny rig's 0.25) as Soff's 0.2
mm. ``Lc`` is L's optics (the chapter's 29 MP camera: 77 um f/4 lenslets 14 pixels across, M = -1) on a
660 x 440 crop of its sensor, 330 x 220 x 182 voxels of 11 x 11 x 55 um (a box 10 mm deep, focused on its
middle), 878 particles at 0.5 PPM: a hundredth of L's box and particles (``benchmarks/recon.py``'s
``Lc``). ``Lcoff`` is Lc focused so, ``--focus-shift -5.3`` by default: its focal plane 0.3 mm (5.4 depth
voxels) beyond the box's far face, about as many lenslets of blur (0.96; L's optics blur 0.25 mm on the
lenslets per mm out of focus) as Mcoff's 0.8 mm. Each
frame is reconstructed twice:

ipr
    :class:`lfcore.ipr.ParticleReconstructor` with its defaults (its candidates come from the peaks of
    a quick reconstruction by ``lfpiv reconstruct``'s ``fast`` protocol, at most 50 iterations).
drt-mart
    DRT-MART with the default 50 iterations and the peaks of its volume
    (:func:`lfcore.metrics.detect_particles`, threshold 0.1), the route ``lfpiv evaluate`` measures.

Both are matched one-to-one to the truth within ``--match-voxels`` voxels per axis
(:func:`lfcore.metrics.match_particles`): recall, ghosts (found with no true particle within the
tolerance, as a share of those found), RMS and median position error per axis in voxels, how many
matched particles are more than 0.2 voxel off on some axis, and the wall time per frame (same
process, same machine; besides, IPR's CPU seconds per stage: the candidates' reconstructions and peaks,
the particle model's set-up, the fit with its splits, moves and prunings, and the process's peak
resident memory). The first round's candidates (the quick reconstruction's peaks) are matched to the
truth too: what the fit starts from. The issue's goals: recall >= 90%, ghosts <= 5%, RMS <= 0.1 voxel
laterally and 0.3 in depth. Also reported: the same figures for the particles at least
``--focus-gap`` voxels from every camera's focal plane (voxels along that camera's depth), where a
light-field camera sees a particle's position (on the focal plane a particle's light falls in one
lenslet).
"""

from __future__ import annotations

import argparse
import importlib.util
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore import metrics  # noqa: E402
from lfcore.ipr import CANDIDATE_SOURCES, CANDIDATE_WEIGHTS, MODELS, IprSettings, ParticleReconstructor, to_mm  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import PROTOCOLS, ReconSettings, protocol_settings, reconstruct  # noqa: E402
from lfcore.render import renderer_for  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402

#: Cases focused beyond the box: each camera's focus shift (mm, along its optical axis; negative: away
#: from the camera) that puts its focal plane 0.2 mm beyond the box's far face.
OFF_FOCUS = {"S2off": -0.6, "Soff": -1.0, "Mcoff": -6.8, "Lcoff": -5.3}


def recon_bench():
    """benchmarks/recon.py as a module (its cases' rigs: ``case_rig``)."""
    spec = importlib.util.spec_from_file_location("recon_bench", ROOT / "benchmarks" / "recon.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(ROOT / "examples" / "tiny.toml"))
    ap.add_argument("--case", default=None,
                    help="a case of benchmarks/recon.py instead of --rig (S, S2, Mc, Lc, ...), or S2off / Soff / "
                         "Mcoff / Lcoff (S2 / S / Mc / Lc focused beyond the box)")
    ap.add_argument("--focus-shift", type=float, default=None, metavar="MM",
                    help="move every camera's focus point this far along its optical axis (positive: toward the "
                         "camera; negative: away from it, the box then lies before the focal plane); S2off's "
                         "default: -0.6 mm, Soff's -1.0 mm, Mcoff's -6.8 mm, Lcoff's -5.3 mm")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--sweep", default=None, metavar="PPMS",
                    help="comma-separated densities (PPM) instead of --ppm: one line of figures per density")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--rays", type=int, default=0,
                    help="rays a particle of the rendered frames (0: the rig's [render] rays_per_particle)")
    ap.add_argument("--match-voxels", type=float, default=1.0)
    ap.add_argument("--focus-gap", default="3", metavar="VOXELS",
                    help="comma-separated gaps from the focal planes: one line of figures per gap")
    ap.add_argument("--candidates", choices=tuple(PROTOCOLS), default=IprSettings().candidate_protocol,
                    help="IPR's candidate_protocol: the quick reconstruction's protocol")
    ap.add_argument("--candidate-source", choices=(*CANDIDATE_SOURCES, "both"), default=IprSettings().candidate_source,
                    help="IPR's candidate_source: the quick reconstruction's peaks or ray bundling (rays); both: "
                         "IPR twice on the same frames in this process, rays first (so that the peak RSS after it "
                         "is its own)")
    ap.add_argument("--ray-keep-bins", type=float, default=IprSettings().ray_keep_bins,
                    help="IPR's ray_keep_bins (with --candidate-source rays)")
    ap.add_argument("--ray-min-score", type=float, default=IprSettings().ray_min_score,
                    help="IPR's ray_min_score (with --candidate-source rays)")
    ap.add_argument("--candidate-weights", choices=CANDIDATE_WEIGHTS, default=IprSettings().candidate_weights,
                    help="IPR's candidate_weights: the protocol's, or line-of-sight weights throughout (no DRT "
                    "weights)")
    ap.add_argument("--candidate-smoothing", type=float, default=IprSettings().candidate_smoothing,
                    metavar="VOXELS", help="IPR's candidate_smoothing (a Gaussian's sigma across, voxels)")
    ap.add_argument("--candidate-storage", choices=("auto", "on-the-fly"), default="auto",
                    help="the quick reconstruction's weight_storage: on-the-fly makes every row again in each "
                    "iteration (what fits a small memory)")
    ap.add_argument("--candidate-relaxation", type=float, default=None, metavar="R",
                    help="the quick reconstruction's relaxation (default: its protocol's)")
    ap.add_argument("--candidate-threshold", type=float, default=IprSettings().candidate_threshold,
                    help="IPR's candidate_threshold (a fraction of the brightest voxel)")
    ap.add_argument("--candidate-iterations", type=int, default=IprSettings().candidate_iterations,
                    help="IPR's candidate_iterations")
    ap.add_argument("--model", choices=MODELS, default=IprSettings().model, help="IPR's particle model")
    ap.add_argument("--split", type=float, default=IprSettings().split_intensity, help="IPR's split_intensity")
    ap.add_argument("--rounds", type=int, default=IprSettings().rounds, help="IPR's rounds")
    ap.add_argument("--shakes", type=int, default=IprSettings().shakes, help="IPR's fit iterations (shakes)")
    ap.add_argument("--relocate", type=int, default=IprSettings().relocate_depth, help="IPR's relocate_depth")
    ap.add_argument("--jacobian-reuse", type=float, default=IprSettings().jacobian_reuse,
                    help="IPR's jacobian_reuse (a particle moved at most this many voxels keeps its Jacobian's "
                    "columns in the fit; 0: every particle traced every shake)")
    ap.add_argument("--relocate-screen", type=float, default=IprSettings().relocate_screen,
                    help="IPR's relocate_screen (the relocation's moves screened at this share of the sub-apertures; "
                         "0: none)")
    ap.add_argument("--max-std", type=float, default=IprSettings().max_position_std,
                    help="IPR's max_position_std (voxels; 0: keep all)")
    ap.add_argument("--no-mart", action="store_true", help="IPR only (no DRT-MART peaks beside it)")
    ap.add_argument("--candidates-only", action="store_true",
                    help="only IPR's first round's candidates (each source's), scored against the truth: no fit")
    ap.add_argument("--device", default="cpu", help="where the reconstructions and the point model run (cpu, cuda)")
    args = ap.parse_args()
    rig, shift = case_rig(args.case, focus_shift=args.focus_shift) if args.case else (load_rig(args.rig), 0.0)
    if not args.case and args.focus_shift:
        rig, shift = shift_focus(rig, args.focus_shift), args.focus_shift
    name = f"case {args.case}" if args.case else f"rig {Path(args.rig).name}"
    if shift:
        name += f", each camera's focus moved {shift:g} mm along its optical axis (+: toward it)"
    grid = VolumeGrid.from_rig(rig)
    proj = projector_for(rig.camera, grid, device=args.device)
    tol = args.match_voxels * np.asarray(grid.voxel_mm)
    render = rig.render.model_copy(update={"rays_per_particle": args.rays}) if args.rays else rig.render
    renderers = [renderer_for(c, render, wavelength_nm=rig.laser.wavelength_nm, device=args.device)
                 for c in rig.camera]
    sources = ("rays", "reconstruction") if args.candidate_source == "both" else (args.candidate_source,)
    # the quick reconstruction's protocol with another relaxation or weight storage where asked
    storage = None if args.candidate_storage == "auto" else args.candidate_storage
    changes = {k: v for k, v in (("relaxation", args.candidate_relaxation), ("weight_storage", storage))
               if v is not None}
    if storage and args.candidate_weights == "line-of-sight":  # rows made again: MLOS-MART's, on the protocol's grids
        changes.update(method="mlos-mart", coarse=PROTOCOLS[args.candidates].get("coarse", 1))
    quick = protocol_settings(args.candidates, n_cameras=len(rig.camera), **changes) if changes else None
    iprs = {src: ParticleReconstructor(proj, recon=quick, settings=IprSettings(
        method=changes.get("method"),
        candidate_protocol=args.candidates, candidate_source=src,
        ray_keep_bins=args.ray_keep_bins, ray_min_score=args.ray_min_score,
        candidate_threshold=args.candidate_threshold, candidate_smoothing=args.candidate_smoothing,
        candidate_iterations=args.candidate_iterations, candidate_weights=args.candidate_weights, model=args.model,
        shakes=args.shakes, split_intensity=args.split, rounds=args.rounds,
        relocate_depth=args.relocate, relocate_screen=args.relocate_screen, max_position_std=args.max_std,
        jacobian_reuse=args.jacobian_reuse,
        wavelength_nm=rig.laser.wavelength_nm, particle_image_px=rig.render.particle_image_px)) for src in sources}
    # a route's name: "ipr" and "candidates" with one source, suffixed by it with both
    tag = {src: f"-{src[:5]}" if len(sources) > 1 else "" for src in sources}
    densities = [float(p) for p in args.sweep.split(",")] if args.sweep else [args.ppm]
    gaps = [float(g) for g in args.focus_gap.split(",")]
    source = " and ".join(f"by ray bundling (keep bins {args.ray_keep_bins:g}, min score {args.ray_min_score:g})"
                          if src == "rays" else f"{args.candidates}" for src in sources)
    print(f"{name}: {len(rig.camera)} camera(s), grid {grid.shape} (z, y, x) voxels of {grid.voxel_mm} mm; "
          f"{args.frames} frame(s) per density; matching within {args.match_voxels} voxel per axis; IPR model "
          f"{args.model}, relocate {args.relocate} (screen {args.relocate_screen:g}), jacobian reuse "
          f"{args.jacobian_reuse:g}, max std {args.max_std}, candidates "
          f"{source} (at most "
          f"{args.candidate_iterations} iterations, weights {args.candidate_weights}, relaxation "
          f"{args.candidate_relaxation or 'of the protocol'}, threshold {args.candidate_threshold:g}, smoothing "
          f"{args.candidate_smoothing}); {render.rays_per_particle} "
          f"rays a particle")
    clocks = {src: stage_clock(ipr) for src, ipr in iprs.items()}
    routes = (*(f"ipr{tag[src]}" for src in sources), *(() if args.no_mart else ("drt-mart",)))
    for ppm in densities:
        n = particle_count(rig, ppm=ppm)
        rows = {r: [] for r in routes}
        for src in sources:
            rows[f"candidates{tag[src]}"] = []
        for f in range(args.frames):
            pts = seed_particles(rig.volume, n, np.random.default_rng(100 + f))
            imgs = [r.frame(pts, rig.render.particle_counts, seed=7 + f + 1000 * k) for k, r in enumerate(renderers)]
            depth = focus_distance(rig, grid, pts)

            def score(route: str, pos: np.ndarray, t: float, f: int = f, pts: np.ndarray = pts,
                      depth: np.ndarray = depth, rows: dict = rows) -> None:
                every = metrics.match_particles(pos, pts, tol)
                depth_found = focus_distance(rig, grid, pos)
                away = [metrics.match_particles(pos[depth_found >= g], pts[depth >= g], tol) for g in gaps]
                rows[route].append((every, *away, t))
                rms = np.sqrt(np.mean(every.error_mm**2, axis=0)) / np.asarray(grid.voxel_mm)
                print(f"frame {f}: {route} recall {every.n_matched / max(every.n_true, 1):.3f}, ghosts "
                      f"{every.n_detected - every.n_matched}/{every.n_detected}, rms x,y,z {rms[0]:.3f}, {rms[1]:.3f}, "
                      f"{rms[2]:.3f} voxel", flush=True)

            for src, ipr in iprs.items():
                cpu = clocks[src]
                t0 = time.perf_counter()
                cpu.clear()
                if args.candidates_only:
                    ipr._candidates(imgs)
                    print(f"frame {f}: candidates{tag[src]} CPU s {cpu['first'][1]:.1f} (wall "
                          f"{time.perf_counter() - t0:.1f} s); peak RSS {peak_rss_gib():.2f} GiB", flush=True)
                    score(f"candidates{tag[src]}", *cpu["first"])
                    continue
                c0 = time.process_time()
                res = ipr.reconstruct(imgs)
                wall = time.perf_counter() - t0
                c_all = time.process_time() - c0
                fit = c_all - cpu["candidates"] - cpu["operator"]
                print(f"frame {f}: IPR{tag[src]} CPU s: candidates {cpu['candidates']:.1f} ({cpu['first'][1]:.1f} in "
                      f"the first round), particle model {cpu['operator']:.1f}, fit {fit:.1f}, all {c_all:.1f} (wall "
                      f"{wall:.1f} s); {res.candidates} candidates, {res.n} particles, {res.rounds} rounds; fit "
                      f"{fit / max(res.candidates, 1):.3f} CPU s a candidate, {fit / max(res.n, 1):.3f} a particle "
                      f"found; peak RSS {cpu['first_rss']:.2f} GiB after the first candidates, "
                      f"{peak_rss_gib():.2f} GiB now", flush=True)
                print(f"frame {f}: IPR{tag[src]} CPU s by round: {round_text(cpu, c0 + c_all)}", flush=True)
                score(f"ipr{tag[src]}", res.positions_mm, c_all)
                score(f"candidates{tag[src]}", *cpu["first"])
            if "drt-mart" in routes:
                t0 = time.perf_counter()
                c0 = time.process_time()
                vol = reconstruct(proj, imgs, ReconSettings()).volume
                found_mart, _, _ = metrics.detect_particles(vol, grid, threshold=0.1)
                wall = time.perf_counter() - t0
                print(f"frame {f}: DRT-MART CPU s {time.process_time() - c0:.1f} (wall {wall:.1f}); "
                      f"peak RSS {peak_rss_gib():.2f} GiB", flush=True)
                score("drt-mart", found_mart, wall)
        print(f"-- {ppm} PPM: {n} particles")
        for route, rs in rows.items():
            if not rs:  # (IPR's routes with --candidates-only)
                continue
            for label, k in (("all", 0), *((f">= {g:g} voxels from focus", 1 + i) for i, g in enumerate(gaps))):
                err = np.concatenate([r[k].error_mm for r in rs])
                rms = np.sqrt(np.mean(err**2, axis=0)) / np.asarray(grid.voxel_mm)
                matched = sum(r[k].n_matched for r in rs)
                n_true = sum(r[k].n_true for r in rs)
                n_det = max(sum(r[k].n_detected for r in rs), 1)
                off = np.abs(err) / np.asarray(grid.voxel_mm) if len(err) else np.zeros((0, 3))
                med = np.median(off, axis=0) if len(off) else np.zeros(3)
                print(f"{route:9s} {label:28s} recall {matched / max(n_true, 1):.3f}  ghosts "
                      f"{(n_det - matched) / n_det:.3f} ({n_det - matched}/{n_det})  rms x,y,z {rms[0]:.3f}, "
                      f"{rms[1]:.3f}, {rms[2]:.3f} voxel; median {med[0]:.3f}, {med[1]:.3f}, {med[2]:.3f}; "
                      f"{int((off.max(axis=1) > 0.2).sum()) if len(off) else 0} more than 0.2 voxel off")
            what = ("CPU s per frame (first round)" if route.startswith("candidates") else
                    "CPU s per frame" if route.startswith("ipr") else "time per frame")
            print(f"{route:9s} {what} {np.mean([r[-1] for r in rs]):.2f} s")
    print(f"peak RSS {peak_rss_gib():.2f} GiB")


def peak_rss_gib() -> float:
    """The process's peak resident memory so far, GiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def stage_clock(ipr: ParticleReconstructor) -> dict:
    """Wrap ``ipr``'s candidates (the quick reconstruction and its peaks) and particle model set-up to
    count their process CPU seconds (robust to the other processes on a shared machine) into the
    returned dict (``candidates``, ``operator``; ``first``: the first round's candidates, world mm, and
    their CPU seconds), which the caller clears before each frame."""
    clock: dict = {}
    for name, key in (("_candidates", "candidates"), ("_model", "operator")):
        inner = getattr(ipr, name)

        def wrapped(*a, _inner=inner, _key=key, **k):
            c = time.process_time()
            out = _inner(*a, **k)
            done = time.process_time()
            dt = done - c
            if _key == "candidates":
                if "candidates" not in clock:
                    clock["first"] = (to_mm(ipr.projector.grid, out), dt)
                    clock["first_rss"] = peak_rss_gib()
                # each round's candidates: (CPU s, how many found, when they were done)
                clock.setdefault("rounds", []).append((dt, len(out), done))
                print(f"  round {len(clock['rounds'])}'s candidates: {len(out)} in {dt:.1f} CPU s; peak RSS "
                      f"{peak_rss_gib():.2f} GiB", flush=True)
            clock[_key] = clock.get(_key, 0.0) + dt
            return out
        setattr(ipr, name, wrapped)
    if ipr.settings.candidate_source == "reconstruction":
        inner_recon = ipr.frames.reconstruct

        def recon(*a, _inner=inner_recon, **k):
            before = peak_rss_gib()
            out = _inner(*a, **k)
            # the quick reconstruction: what it held and did (the largest operator's MiB, its stages' seconds)
            print(f"  quick reconstruction: {out.iterations} iterations ({out.stopped}), {out.active_voxels:,} voxels "
                  f"active, {out.final_voxels:,} left; operator {out.operator}, {out.weight_bytes / 2**20:.0f} MiB at "
                  f"most; weights {out.weights_s:.1f} s, iterations {out.iterate_s:.1f} s (wall); peak RSS "
                  f"{before:.2f} GiB before it", flush=True)
            return out
        ipr.frames.reconstruct = recon
    return clock


def round_text(clock: dict, end: float) -> str:
    """Each round's candidates' CPU seconds and count, and the CPU seconds from them to the next
    round's candidates (or ``end``, the frame's last process time): the round's model and fit."""
    rounds = clock.get("rounds", [])
    parts = []
    for r, (dt, n, done) in enumerate(rounds):
        nxt = rounds[r + 1][2] - rounds[r + 1][0] if r + 1 < len(rounds) else end
        parts.append(f"round {r + 1}: {n} candidates in {dt:.1f} s, then {nxt - done:.1f} s")
        # ("then": the particle model's set-up and the fit, splits, moves and prunings of that round)
    return "; ".join(parts)


def case_rig(case: str, *, focus_shift: float | None = None) -> tuple[Rig, float]:
    """A case's rig: ``benchmarks/recon.py``'s case of that name, or a case of :data:`OFF_FOCUS`
    (its name less ``off``) refocused by its shift.

    Parameters
    ----------
    case
        S, S2, Mc, Lc, ... (``benchmarks/recon.py``) or S2off, Soff, Mcoff, Lcoff.
    focus_shift
        Every camera's focus point moved this far along its optical axis, mm (positive: toward the
        camera); None: the case's own (:data:`OFF_FOCUS`, else none).

    Returns
    -------
    tuple
        The rig and the focus shift applied, mm (0: none).
    """
    base = case.removesuffix("off") if case in OFF_FOCUS else case
    rig, _ = recon_bench().case_rig(base)
    shift = OFF_FOCUS.get(case, 0.0) if focus_shift is None else focus_shift
    return (shift_focus(rig, shift) if shift else rig), shift


def shift_focus(rig, shift_mm: float):
    """The rig with every camera's focus point moved ``shift_mm`` along its optical axis (positive:
    toward the camera), the box and the cameras' magnification unchanged: the camera refocused, its
    focal plane (and the blind depths beside it) moved out of the box when the shift exceeds the box's
    half-depth along that axis."""
    d = rig.to_dict()
    for cam, c in zip(rig.camera, d["camera"], strict=True):
        c["focus_mm"] = [float(v) for v in np.asarray(cam.focus_mm) + shift_mm * cam.optical_axis]
    return type(rig).from_dict(d)


def focus_distance(rig, grid: VolumeGrid, points_mm: np.ndarray) -> np.ndarray:
    """(n,) each world point's distance from the nearest camera's focal plane, in voxels along that
    camera's depth (the grid axis nearest its viewing direction). For one camera looking along z: the
    distance in z voxels from its focus point's plane."""
    voxel = np.asarray(grid.voxel_mm)
    out = np.full(len(points_mm), np.inf)
    for cam in rig.camera:
        axis = np.asarray(cam.rotation, dtype=np.float64)[:, 2]  # viewing direction, world (x, y, z)
        depth_voxel = float(voxel[int(np.argmax(np.abs(axis)))])
        d = np.abs((np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) - np.asarray(cam.focus_mm)) @ axis)
        out = np.minimum(out, d / depth_voxel)
    return out


if __name__ == "__main__":
    main()
