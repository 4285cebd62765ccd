"""Error budget of iterative particle reconstruction (:mod:`lfcore.ipr`) on one frame, against the truth.

Run from the repository root::

    python benchmarks/particles_budget.py --case S2      # two cameras at 90 degrees
    python benchmarks/particles_budget.py                # the one-camera tiny rig

One frame (the first of ``benchmarks/particles.py``'s) rendered three ways: noise-free with many rays
(the renderer's image of the points), noise-free with the rig's rays, and the frame with noise. For
each, IPR's fit (:func:`lfcore.ipr._fit`) is started at the TRUE positions (intensities fitted at
them first) and the drift measured: RMS per axis (x, y, z voxels) for isolated particles (under a
tenth of a particle's image shared with others) and overlapping ones. Where it converges from the
truth bounds what the search can reach: the model's bias against the renderer (noise-free), the
noise's share (noisy). Then the candidates: the share of true particles with a candidate within 1
and 2 voxels per axis; and the full reconstruction's ghosts sorted by what is near them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from particles import focus_distance, recon_bench  # noqa: E402

from lfcore import ipr, metrics  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import estimate_background  # noqa: E402
from lfcore.render import renderer_for  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402


def best_intensities(model, b: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The intensities that fit ``b`` best with the particles held at ``u`` (least squares)."""
    c = model.unit_images(u)
    g = (c.T @ c).tocsc() + sparse.identity(len(u)) * 1e-9
    return np.maximum(spsolve(g, c.T @ b), 0.0)


def overlap(model, u: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """(n,) the share of each particle's image that the others' images cover (weighted by its own)."""
    c = model.unit_images(u)
    total = c @ intensity
    own = np.asarray(c.multiply(c).sum(axis=0)).ravel() * intensity
    dot = np.asarray(c.T @ total).ravel() - own
    return dot / np.where(own > 0, own, np.inf)


#: bands of distance from the nearest camera's focal plane (voxels along its depth) the drifts are told in
BANDS = ((0, 5), (5, 10), (10, 20))


def drift_report(label: str, u0: np.ndarray, u: np.ndarray, share: np.ndarray, focus: np.ndarray) -> None:
    d = (u - u0)[:, ::-1]  # (x, y, z) voxels
    bands = [(f"{lo}-{hi} vx from a focal plane", (focus >= lo) & (focus < hi)) for lo, hi in BANDS]
    bands.append((f"{BANDS[-1][1]}+ vx from every focal plane", focus >= BANDS[-1][1]))
    for name, sel in (("all", np.ones(len(u0), bool)), ("isolated", share < 0.1), ("overlapping", share >= 0.1),
                      *bands):
        if not sel.any():
            continue
        rms = np.sqrt(np.mean(d[sel] ** 2, axis=0))
        far = np.mean(np.max(np.abs(d[sel]), axis=1) > 0.5)
        print(f"  {label:20s} {name:31s} n={sel.sum():4d}  drift rms x,y,z {rms[0]:.3f} {rms[1]:.3f} {rms[2]:.3f}"
              f"  > 0.5 voxel {far:.1%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(ROOT / "examples" / "tiny.toml"))
    ap.add_argument("--case", default=None)
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--bands", default=None, metavar="EDGES",
                    help="comma-separated band edges from the focal planes, voxels (default 0,5,10,20)")
    ap.add_argument("--shakes", type=int, default=12)
    ap.add_argument("--step", type=float, default=0.05, help="the point model's forward-difference step, voxels")
    ap.add_argument("--full", action="store_true", help="also the full reconstruction's ghosts")
    ap.add_argument("--rays", default="400000,40000,4000",
                    help="rays a particle of the noise-free images to fit (the rig's count also gives the noisy frame)")
    ap.add_argument("--isolated", type=int, default=0, help="also fit this many particles each alone in its images")
    ap.add_argument("--isolated-rays", type=int, default=400_000)
    args = ap.parse_args()
    if args.bands:
        global BANDS
        edges = [float(e) for e in args.bands.split(",")]
        BANDS = tuple(zip(edges[:-1], edges[1:], strict=True))
    rig = recon_bench().case_rig(args.case)[0] if args.case else load_rig(args.rig)
    grid = VolumeGrid.from_rig(rig)
    voxel = np.asarray(grid.voxel_mm)
    proj = projector_for(rig.camera, grid, device="cpu")
    settings = ipr.IprSettings(wavelength_nm=rig.laser.wavelength_nm, particle_image_px=rig.render.particle_image_px)
    rec = ipr.ParticleReconstructor(proj, settings=settings)
    n = particle_count(rig, ppm=args.ppm)
    f = args.frame
    pts = seed_particles(rig.volume, n, np.random.default_rng(100 + f))
    counts = rig.render.particle_counts
    u0 = ipr.to_index(grid, pts)
    model = ipr._PointModel(proj, wavelength_nm=rig.laser.wavelength_nm, particle_image_px=rig.render.particle_image_px,
                            step=args.step)
    print(f"{len(rig.camera)} camera(s), grid {grid.shape}, {n} particles, fit {args.shakes} shakes, "
          f"step {args.step} voxel")
    frames = {}
    for rays in [int(x) for x in args.rays.split(",") if x]:
        cfg = rig.render.model_copy(update={"rays_per_particle": rays})
        for noisy in ((False, True) if rays == rig.render.rays_per_particle else (False,)):
            imgs = []
            for k, c in enumerate(rig.camera):
                r = renderer_for(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu")
                imgs.append(r.frame(pts, counts, seed=7 + f + 1000 * k) if noisy
                            else r.irradiance(pts, counts, seed=7 + f + 1000 * k))
            b = np.concatenate([np.asarray(img, np.float64).ravel() - (estimate_background(img)[0] if noisy else 0.0)
                                for img in imgs])
            label = f"{rays} rays, " + ("with noise (the benchmark's frame)" if noisy else "noise-free")
            frames[label] = (imgs, b, noisy)
    if args.isolated:
        # each particle alone in its own images: the model's bias against the renderer, no neighbours
        cfg = rig.render.model_copy(update={"rays_per_particle": args.isolated_rays})
        rs = [renderer_for(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device="cpu") for c in rig.camera]
        d = []
        for p in range(min(args.isolated, n)):
            b = np.concatenate([r.irradiance(pts[p:p + 1], counts, seed=11 + p + 1000 * k).ravel().astype(np.float64)
                                for k, r in enumerate(rs)])
            i0 = best_intensities(model, b, u0[p:p + 1])
            u, _ = ipr._fit(model, b, u0[p:p + 1], i0, shakes=args.shakes, max_step=settings.max_step_voxels)
            d.append(u[0] - u0[p])
        d = np.array(d)[:, ::-1]
        print(f"each particle alone ({len(d)}, {args.isolated_rays} rays, noise-free): drift rms x,y,z "
              f"{np.sqrt(np.mean(d**2, axis=0)).round(3)}, largest |.| {np.abs(d).max(axis=0).round(3)}")
    share = None
    for label, (_, b, _) in frames.items():
        t0 = time.perf_counter()
        i0 = best_intensities(model, b, u0)
        if share is None:
            share = overlap(model, u0, np.full(len(u0), counts))
            print(f"  overlap: {np.mean(share < 0.1):.0%} isolated (under 0.1 of the image shared)")
        cost0 = float(np.sum((b - model.image(u0, i0)) ** 2))
        u, i = ipr._fit(model, b, u0, i0, shakes=args.shakes, max_step=settings.max_step_voxels)
        cost = float(np.sum((b - model.image(u, i)) ** 2))
        print(f"{label}: intensity at the truth {np.median(i0):.0f} (median; rendered {counts:.0f}), "
              f"residual {cost0:.3e} -> {cost:.3e} after the fit ({time.perf_counter() - t0:.1f} s)")
        drift_report("fit from the truth", u0, u, share, focus_distance(rig, grid, pts))
    imgs, b, _ = [v for v in frames.values() if v[2]][0]
    cand = rec._candidates(imgs)
    for tol in (1.0, 2.0):
        d = np.abs(cand[None, :, :] - u0[:, None, :]).max(axis=2) if len(cand) else np.full((n, 1), np.inf)
        print(f"candidates: {len(cand)}; true particles with one within {tol:g} voxel: "
              f"{np.mean(d.min(axis=1) <= tol):.3f}")
    if args.full:
        t0 = time.perf_counter()
        res = rec.reconstruct(imgs)
        found = ipr.to_index(grid, res.positions_mm)
        m = metrics.match_particles(res.positions_mm, pts, voxel)
        print(f"full IPR: {res.n} found, {m.n_matched} matched within 1 voxel, ({time.perf_counter() - t0:.1f} s)")
        # each found particle: its nearest true one (max-axis voxels) and whether that one has a nearer find
        tree_t = cKDTree(u0)
        dt, it = tree_t.query(found, k=1, p=np.inf)
        tree_f = cKDTree(found)
        dback, _ = tree_f.query(u0[it], k=1, p=np.inf)
        ghosts = dt > 1.0
        displaced = ghosts & (dt <= 3.0) & (dback >= dt - 1e-9)  # the nearest find of that true particle
        extra = ghosts & (dt <= 3.0) & (dback < dt - 1e-9)  # another find is nearer: a duplicate/split
        print(f"ghosts {ghosts.sum()}: a true particle 1-3 voxels off with no nearer find (displaced) "
              f"{displaced.sum()}, one with a nearer find (extra/split) {extra.sum()}, none within 3 voxels "
              f"{(ghosts & (dt > 3)).sum()}")
        err = (found[ghosts] - u0[it[ghosts]])[:, ::-1]
        print("  ghosts' offsets from their nearest true particle (x, y, z voxels), median |.|:",
              np.round(np.median(np.abs(err), axis=0), 2))
        print("  ghosts' intensity / median:", np.round(np.median(res.intensity[ghosts]) / np.median(res.intensity), 2))


if __name__ == "__main__":
    main()
