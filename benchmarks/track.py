"""Particle tracking's field (``lfpiv track``, :mod:`lfcore.track`) against the truth: bins or a
smooth field, with or without a predictor, beside correlation's.

Run from the repository root::

    python benchmarks/track.py                                   # both cases, tracks only
    python benchmarks/track.py --case vortex --bins 8x8x4,16x16x8
    python benchmarks/track.py --end-to-end                      # also synth -> particles -> track, and
                                                                 # reconstruct -> correlate, by the CLI
    python benchmarks/track.py --fit-scale 85578                 # the fit field's CPU time at the L scale

Cases (the particles of a known flow, :class:`lfcore.world.ParticleWorld`):

uniform
    Table 4.1's A1-like uniform displacement (``--flow uniform``, 4 px) on the one-camera tiny rig
    (``examples/tiny.toml``, 29 x 68 x 82 voxels) at ``--ppm`` (0.5).
vortex
    The demo's vortex ring on the demo rig (``examples/demo.toml``, two cameras) at its own seeding.

**Tracks only** (default): the true positions of frames A and B, each blurred by Gaussian
position noise of ``--noise`` voxels per axis (0.1, 0.1, 0.2: what ``lfpiv particles`` reaches on the
tiny rig), tracked by :func:`lfcore.track.track_pair` with each field (``bins``, ``smooth``, ``fit``, ``divfree``)
and bin size; the field's RMS error against the truth at the bins' centres at mid-pair time
(:func:`lfcore.metrics.grid_velocity`), as a share of the peak speed (the issue's goal for the
vortex ring: at most 5%), and per axis in voxels; and the share of bins with a vector.
**End to end** (``--end-to-end``, minutes on a 2-core VM): one pair through the commands
(``synth``; ``reconstruct`` and ``correlate`` with the demo's windows at 50% overlap; ``particles``
and ``track`` with each field, without a predictor and with the ``volumes`` one), ``lfpiv
evaluate``'s figures: the velocity error over the points with a vector (``filled``: their share),
and the wall time (``particles`` plus ``track``; ``reconstruct`` plus ``correlate``).
**Fit at scale** (``--fit-scale N``): the CPU time of the ``fit`` and ``divfree`` fields
(:func:`lfcore.track.fit_tracks`) and of the ``smooth`` one (:func:`lfcore.track.smooth_tracks`) in the
same run, on N tracks of a smooth flow with 0.15 voxel of noise, in a box of 2200 x 1470 x 400 voxels
of 10 x 10 x 50 um (the L scene's 1.3e9 voxels; its 85,578 particles: ``--fit-scale 85578``) with
16 x 16 x 8-voxel bins, and each field's RMS error there.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore import metrics  # noqa: E402
from lfcore.flows import flow_from_params  # noqa: E402
from lfcore.track import TrackSettings, track_pair  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfcore.world import ParticleWorld  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402

CASES = {"uniform": ("tiny.toml", "uniform", 4.0), "vortex": ("demo.toml", "vortex-ring", None)}


def _bins(text: str) -> list[tuple[int, int, int]]:
    return [tuple(int(v) for v in b.split("x")) for b in text.split(",")]  # type: ignore[misc]


def tracks_only(case: str, args: argparse.Namespace) -> None:
    rig_name, flow, disp = CASES[case]
    rig = load_rig(ROOT / "examples" / rig_name)
    ppm = args.ppm if case == "uniform" else None
    world = ParticleWorld(rig, flow=flow, ppm=ppm, displacement_px=disp, seed=3)
    grid = VolumeGrid.from_rig(rig)
    voxel = np.asarray(grid.voxel_mm)
    fl = flow_from_params(world.flow_params)
    rng = np.random.default_rng(0)
    print(f"\n{case}: {rig_name}, {world.n_particles} particles a frame, grid {grid.shape[::-1]} voxels (x, y, z), "
          f"noise {args.noise} voxel, {args.pairs} pair(s)")
    print(f"{'field':8s} {'bins':>9s} {'% peak':>7s} {'rms x, y, z (voxel)':>22s} {'filled':>7s} {'s/pair':>7s}")
    for b in _bins(args.bins if case == "vortex" else args.uniform_bins):
        for fld in ("bins", "smooth", "fit", "divfree"):
            errs, vox, filled, secs = [], [], [], 0.0
            for k in range(args.pairs):
                (a, bb), _ = world.pair(k)
                a = a + rng.normal(size=a.shape) * np.asarray(args.noise) * voxel
                bb = bb + rng.normal(size=bb.shape) * np.asarray(args.noise) * voxel
                t0 = time.perf_counter()
                res = track_pair(a, bb[rng.permutation(len(bb))], grid,
                                 settings=TrackSettings(bin_voxels=b, field=fld,
                                                        search_voxels=tuple(args.search)))
                secs += time.perf_counter() - t0
                dt = world.dt_s
                vel = res.field_mm * 1e-3 / dt
                ref = metrics.grid_velocity(fl, res.x_mm, res.y_mm, res.z_mm, world.t0_s(k) + 0.5 * dt)
                e = metrics.velocity_errors(vel, ref)
                errs.append(float(np.linalg.norm(e.rms_m_s)) / e.peak_m_s)
                vox.append(e.rms_m_s * dt * 1e3 / voxel)
                filled.append(float(np.isfinite(vel[..., 0]).mean()))
            v = np.mean(vox, axis=0)
            print(f"{fld:8s} {'x'.join(map(str, b)):>9s} {100 * np.mean(errs):7.1f} "
                  f"{v[0]:6.3f}, {v[1]:6.3f}, {v[2]:6.3f} {100 * np.mean(filled):6.0f}% {secs / args.pairs:7.2f}")


def _cli(*argv: object) -> tuple[str, float]:
    """Run an ``lfpiv`` command in this process: its stdout and wall time (an error stops the benchmark)."""
    import contextlib
    import io

    from lfpiv.cli import main as lfpiv_main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = lfpiv_main([str(a) for a in argv])
    if rc != 0:
        raise SystemExit(f"lfpiv {' '.join(map(str, argv))}: exit {rc}: {err.getvalue().strip()}")
    return out.getvalue(), time.perf_counter() - t0


def _vector_figures(run: Path) -> str:
    out, _ = _cli("evaluate", run)
    grid = re.search(r"^vectors:?\s+\d+ pair\(s\) of (\d+ x \d+ x \d+) vectors", out, re.M)
    err = re.search(r"velocity error: RMS .* m/s \(([\d.]+), ([\d.]+), ([\d.]+) voxel\); ([\d.]+)% of the peak", out)
    if not (grid and err):
        raise SystemExit(f"no vector figures in:\n{out}")
    return (f"{grid.group(1):>12s} {float(err.group(4)):7.1f} {err.group(1):>6s}, {err.group(2):>6s}, "
            f"{err.group(3):>6s}")


def end_to_end(case: str, args: argparse.Namespace, work: Path) -> None:
    """The case through the commands: particles and tracks beside DRT-MART and correlation."""
    import shutil

    rig_name, flow, disp = CASES[case]
    run = work / f"{case}.zarr"
    seeding = ["--ppm", str(args.ppm), "--displacement-px", str(disp)] if case == "uniform" else []
    _, t_synth = _cli("synth", "--rig", ROOT / "examples" / rig_name, "--out", run, "--pairs", "1", "--flow", flow,
                      *seeding, "--quiet")
    _, t_rec = _cli("reconstruct", run, "--device", "cpu")
    from lfpiv.jobs.demo import demo_windows  # the windows the demo correlates with, at 50% overlap

    _, t_cor = _cli("correlate", run, "--windows", demo_windows(str(run)), "--overlap", "0.5", "--device", "cpu",
                    "--quiet")
    print(f"\n{case} end to end: {rig_name}, 1 pair (synth {t_synth:.0f} s)")
    print(f"{'route':40s} {'vectors':>12s} {'% peak':>7s} {'rms x, y, z (voxel)':>22s} {'filled':>7s} {'s':>6s}")
    print(f"{'drt-mart + correlate (demo windows)':40s} {_vector_figures(run)} {'':>7s} {t_rec + t_cor:6.1f}")
    _, t_ipr = _cli("particles", run, "--device", "cpu", "--quiet")
    for b in _bins(args.bins if case == "vortex" else args.uniform_bins):
        for fld in ("bins", "smooth", "fit", "divfree"):
            for pred in ("none", "volumes"):
                one = work / f"{case}-{fld}-{pred}.zarr"
                shutil.copytree(run, one)
                said, t_trk = _cli("track", one, "--bin", "x".join(map(str, b)), "--field", fld, "--predictor", pred,
                                   "--device", "cpu", "--quiet")
                filled = re.search(r"(\d+)% of the bins hold a vector", said)
                label = f"particles + track {fld}, {pred} {'x'.join(map(str, b))}"
                print(f"{label:40s} {_vector_figures(one)} {filled.group(1) if filled else '?':>6s}% "
                      f"{t_ipr + t_trk:6.1f}", flush=True)
                shutil.rmtree(one)


def fit_scale(n: int) -> None:
    """CPU time and error of the fit and smooth fields of ``n`` noisy tracks in an L-sized box."""
    from lfcore.track import fit_tracks, smooth_tracks

    vox, bins = np.array([0.01, 0.01, 0.05]), np.array([16, 16, 8])
    size = np.array([2200, 1470, 400]) * vox
    rng = np.random.default_rng(0)
    pos = (rng.random((n, 3)) - 0.5) * size
    k = 2 * np.pi / size[0]

    def flow(p: np.ndarray) -> np.ndarray:  # displacement, mm: a wave in x, a cell in y-z
        return np.column_stack([5 * np.cos(k * p[:, 0]), 2 * np.sin(k * p[:, 1]) * np.cos(k * p[:, 2] / 3),
                                0.5 * p[:, 0] / size[0]]) * vox

    d = flow(pos) + rng.normal(size=pos.shape) * 0.15 * vox
    centres = [-0.5 * size[a] + (np.arange(int(np.ceil(size[a] / vox[a] / bins[a]))) + 0.5) * bins[a] * vox[a]
               for a in range(3)]
    zz, yy, xx = np.meshgrid(centres[2], centres[1], centres[0], indexing="ij")
    truth = flow(np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]))
    print(f"\nfit at scale: {n} tracks, {truth.shape[0]} bins of 16 x 16 x 8 voxels, 0.15 voxel of noise")
    print(f"{'field':8s} {'cpu s':>8s} {'rms x, y, z (voxel)':>22s} {'filled':>7s}")
    for fld in ("smooth", "fit", "divfree"):
        t0 = time.process_time()
        if fld in ("fit", "divfree"):
            f = fit_tracks(pos, d, centres, reach_mm=bins * vox, box_mm=(-0.5 * size, 0.5 * size),
                           divergence_free=fld == "divfree")[0]
        else:
            f = smooth_tracks(pos, d, centres, sigma_mm=0.5 * bins * vox, min_tracks=1)[0]
        cpu = time.process_time() - t0
        e = (f.reshape(-1, 3) - truth) / vox
        ok = np.all(np.isfinite(e), axis=1)
        r = np.sqrt(np.mean(e[ok] ** 2, axis=0))
        print(f"{fld:8s} {cpu:8.1f} {r[0]:6.3f}, {r[1]:6.3f}, {r[2]:6.3f} {100 * ok.mean():6.0f}%", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=(*CASES, "all"), default="all")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--noise", type=float, nargs=3, default=(0.1, 0.1, 0.2), metavar=("X", "Y", "Z"))
    ap.add_argument("--search", type=float, nargs=3, default=(4.0, 4.0, 2.0), metavar=("X", "Y", "Z"))
    ap.add_argument("--bins", default="8x8x4,12x12x6,16x16x8", help="the vortex's bin sizes, voxels")
    ap.add_argument("--uniform-bins", default="16x16x8", help="the uniform case's bin sizes, voxels")
    ap.add_argument("--end-to-end", action="store_true", help="also through the commands (minutes)")
    ap.add_argument("--fit-scale", type=int, default=0, metavar="N",
                    help="only time the fit and smooth fields of N tracks in an L-sized box (85578: the L scene's)")
    args = ap.parse_args()
    if args.fit_scale:
        fit_scale(args.fit_scale)
        return
    for case in CASES if args.case == "all" else (args.case,):
        tracks_only(case, args)
    if args.end_to_end:
        import tempfile

        with tempfile.TemporaryDirectory() as work:
            for case in CASES if args.case == "all" else (args.case,):
                end_to_end(case, args, Path(work))


if __name__ == "__main__":
    main()
