"""Named protocols (``lfpiv reconstruct --protocol``) and the stopping rule against the MART baseline
at equal time: Q against the truth, iterations, why they stopped, voxels left and the whole frame's
time (elimination, operators, iterations), in one run.

Run from the repository root::

    python benchmarks/stopping.py --case S
    python benchmarks/stopping.py --case S --ppm 2            # a denser frame: the rule runs it longer
    python benchmarks/stopping.py --case Mc --protocols fixed,fast --no-mart     # minutes on a CPU
    python benchmarks/stopping.py --case S --subsets 1,4      # each protocol plain and by 4 ordered subsets
    python benchmarks/mcfast.py --case Mc                     # the stages' wall and CPU times against the chapter's
    python benchmarks/stopping.py --rig all                   # every example rig: the defaults against MART
    python benchmarks/stopping.py --rig examples/tiny.toml --rig examples/demo.toml --ppm 1
    python benchmarks/stopping.py --rig all --caps 75,50,50/30   # the defaults at each most, several cameras

Each row reconstructs the case's frame (``benchmarks/recon.py``'s scene) from its image with
:meth:`lfcore.reconstruct.FrameReconstructor.reconstruct`, as ``lfpiv reconstruct`` does, with the
named protocol's settings (:data:`lfcore.reconstruct.PROTOCOLS`; one frame, so no warm start).
The MART baseline (line-of-sight weights on every voxel of the box, every voxel to the end) then
runs as many iterations as fit in each protocol's time (its per-iteration time measured on a short
run first), so its Q is at equal time.

``--rig`` (a rig file, repeated, or ``all`` for every ``examples/*.toml``) measures each rig's
defaults instead: one frame A of the rig rendered as ``lfpiv synth`` renders it (its world and
renderers, :class:`lfpiv.studies.pipeline.Scene`; the rig's default seeding, 0.5 PPM or 0.05 ppp,
unless ``--ppm`` or ``--ppp``), the truth from its particles and their brightness, reconstructed with
``protocol_settings(--protocol, n_cameras=n, method=<the rig's default method>)`` (``fast``:
``lfpiv reconstruct``'s default protocol; mlos-smart for pinhole rigs, drt-mart otherwise), against
``--method mart`` (the chapter protocol's plain MART: a uniform start on every voxel of the box,
line-of-sight weights, relaxation 1, no pruning; on pinhole cameras the same) at the same CPU
seconds (``time.process_time``: the VM is shared, so wall time is noisy). The rigs too big for a CPU
minute are cropped as :data:`CROPS` says (``--no-crop``: as they are).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.convergence import _recon_bench  # noqa: E402  (benchmarks/recon.py's scenes)
from lfcore import metrics  # noqa: E402
from lfcore.device import resolve_device  # noqa: E402
from lfcore.particles import seeding_density  # noqa: E402
from lfcore.plan import camera_kind, default_method, projector_for  # noqa: E402
from lfcore.reconstruct import FrameReconstructor, protocol_settings  # noqa: E402
from lfcore.render import derive_seed  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402
from lfpiv.studies.pipeline import Scene  # noqa: E402

#: The example rigs cropped for a CPU (``--rig``; ``--no-crop`` runs them whole): their sensors cut
#: to the centre's pixels (columns, rows) and their boxes to what those see, the optics kept.
#: one_camera: 2048 x 2048 px, 983 x 983 x 131 voxels whole; the crop is Mc's (benchmarks/recon.py) at
#: half its width: 123 x 123 x 131 voxels, the whole 12 mm depth. two_cameras: two 6600 x 4400 px
#: cameras and 1939 x 1455 x 1939 voxels whole (the chapter's box, D); cropped to a 1.2 mm cube seen by
#: both, 73 x 73 x 73 voxels at its PVR 3.
CROPS: dict[str, dict] = {
    "one_camera": {"sensor_px": [256, 256], "size_mm": [2.25, 2.25, 12.0]},
    "two_cameras": {"sensor_px": [256, 256], "size_mm": [1.2, 1.2, 1.2]},
}


def timed(proj, settings, img, truth, *, clock=time.perf_counter):
    """One frame of ``settings`` as ``reconstruct`` makes it: its result, Q and seconds by ``clock``
    (wall seconds; ``time.process_time`` for CPU seconds)."""
    frames = FrameReconstructor(proj, settings)
    t = clock()
    res = frames.reconstruct(img)
    total = clock() - t
    return res, metrics.q_recon(res.volume, truth), total


def cropped(path: Path, crop: bool) -> tuple[Rig, str]:
    """The rig of ``path``, cropped as :data:`CROPS` says where ``crop``, and what was cropped."""
    rig = load_rig(path)
    change = CROPS.get(path.stem) if crop else None
    if not change:
        return rig, ""
    d = rig.to_dict()
    for cam in d["camera"]:
        cam["sensor_px"] = change["sensor_px"]
    d["volume"]["size_mm"] = change["size_mm"]
    px = " x ".join(map(str, change["sensor_px"]))
    mm = " x ".join(f"{v:g}" for v in change["size_mm"])
    return Rig.from_dict(d), f"cropped: {px} px, {mm} mm"


def cpu_timed(proj, settings, img, truth):
    """:func:`timed` in CPU seconds."""
    return timed(proj, settings, img, truth, clock=time.process_time)


def rig_row(path: Path, args, device: str) -> str:
    """One rig's row: the defaults' Q, iterations and CPU seconds, and MART's Q at their CPU seconds."""
    rig, note, density, n_particles, img, grid, truth = _frame_a(path, args, device)
    cams = list(rig.camera)
    # as lfpiv reconstruct resolves it: light-field cameras leave the method to the protocol's plan
    kind = camera_kind(cams)
    given = None if kind == "light-field" else default_method(cams)
    method = protocol_settings(args.protocol, n_cameras=len(cams), camera_kind=kind, method=given).method
    proj = projector_for(cams, grid, device=device)
    shape = " x ".join(map(str, grid.shape[::-1]))
    print(f"{path.stem}: {len(cams)} camera(s), {shape} voxels (x, y, z), {n_particles} particles ({density})"
          f"{', ' + note if note else ''}", flush=True)
    defaults = protocol_settings(args.protocol, n_cameras=len(cams), camera_kind=kind, method=given)
    # the kernels loaded (and the first-call costs paid) before anything is timed
    FrameReconstructor(proj, protocol_settings(args.protocol, n_cameras=len(cams), camera_kind=kind, method=given,
                                               iterations=2)).reconstruct(img)
    res, q, cpu = cpu_timed(proj, defaults, img, truth)
    print(f"  defaults ({args.protocol}, {method}): Q {q:.3f}, {res.iterations} iterations ({res.stopped}), "
          f"{cpu:.1f} CPU s (elimination {res.eliminate_s:.1f}, weights {res.weights_s - res.eliminate_s:.1f}, "
          f"iterations {res.iterate_s:.1f} wall s), voxels {res.active_voxels:,} active, {res.final_voxels:,} left",
          flush=True)
    probe = args.mart_probe
    base, base_q, base_cpu = cpu_timed(proj, protocol_settings("chapter", method="mart", iterations=probe), img, truth)
    # the baseline's CPU before its iterations (weights of every voxel) and per iteration, by wall shares
    wall = base.weights_s + base.iterate_s
    fixed = base_cpu * base.weights_s / wall if wall > 0 else base_cpu
    per_it = (base_cpu - fixed) / probe
    print(f"  MART probe: {base.active_voxels:,} voxels, {probe} iterations in {base_cpu:.1f} CPU s "
          f"({fixed:.1f} before the iterations, {1e3 * per_it:.0f} ms an iteration), Q {base_q:.3f}", flush=True)
    n = int((cpu - fixed) / per_it) if cpu > fixed and per_it > 0 else 0
    if n == 0:
        mart = f"(its weights alone take {fixed:.1f} CPU s) | 0 |"
        win = "defaults (MART cannot start)"
    else:
        mres, mq, mcpu = cpu_timed(proj, protocol_settings("chapter", method="mart", iterations=n), img, truth)
        print(f"  MART at equal time: {n} iterations, Q {mq:.3f}, {mcpu:.1f} CPU s", flush=True)
        mart = f"{mq:.3f} | {n} | {mcpu:.1f}"
        win = "defaults" if q > mq else "MART"
    same = ""
    if args.equal_iterations:  # not at equal time: whether MART's iterations themselves reach the defaults' Q
        _, eq, ecpu = cpu_timed(proj, protocol_settings("chapter", method="mart", iterations=res.iterations), img,
                                truth)
        print(f"  MART at the defaults' {res.iterations} iterations: Q {eq:.3f}, {ecpu:.1f} CPU s", flush=True)
        same = f" {eq:.3f} in {ecpu:.1f} |"
    return (f"| {path.stem} | {len(cams)} | {method} | {q:.3f} | {res.iterations} ({res.stopped}) | {cpu:.1f} | "
            f"{mart} | {base_q:.3f} in {base_cpu:.1f} |{same} {win} |")


def rig_frame(path: Path, args, device: str):
    """The rig's frame A as ``lfpiv synth`` renders pair 0: its projector, image, truth and its cameras."""
    rig, note, _, _, img, grid, truth = _frame_a(path, args, device)
    return projector_for(list(rig.camera), grid, device=device), img, truth, list(rig.camera), note


def _frame_a(path: Path, args, device: str):
    """The rig (cropped unless ``--no-crop``), the crop's note, its seeding ("0.5 PPM" or "0.05 ppp"),
    its particles in frame A, and frame A's images, grid and truth volume as ``lfpiv synth`` renders
    pair 0 (its seeds: the run's, the pair, the frame, the camera)."""
    rig, note = cropped(path, not args.no_crop)
    # --ppm seeds the rigs with a light-field camera, --ppp those of pinhole cameras alone
    ppm, ppp = (seeding_density(rig, ppm=args.ppm) if rig.lightfield_cameras else seeding_density(rig, ppp=args.ppp))
    scene = Scene(rig, ppm=ppm if ppm is not None else 0.5, ppp=ppp, seed=1, device=device)
    particles, brightness = scene.world.pair(0)
    img = [r.frame(particles[0], brightness[0], seed=derive_seed(scene.seed, 0, 0, c))
           for c, r in enumerate(scene.renderers)]
    grid = VolumeGrid.from_rig(rig)
    truth = metrics.truth_volume(grid, particles[0], brightness=brightness[0])
    density = f"{ppm:g} PPM" if ppm is not None else f"{ppp:g} ppp"
    return rig, note, density, len(particles[0]), img, grid, truth


def cap_rows(path: Path, args, device: str) -> list[str]:
    """``--caps``: the defaults of a rig of several cameras at each most iterations (``iterations`` of
    :func:`protocol_settings`, the stopping rule's most), in one process: Q, iterations, CPU seconds."""
    proj, img, truth, cams, note = rig_frame(path, args, device)
    if len(cams) < 2:
        return []
    method = default_method(cams)
    print(f"{path.stem}: {len(cams)} cameras{', ' + note if note else ''}", flush=True)
    FrameReconstructor(proj, protocol_settings(args.protocol, n_cameras=len(cams), method=method,
                                               iterations=2)).reconstruct(img)
    rows = []
    for cap in args.caps.split(","):
        most, _, los = cap.partition("/")  # N or N/L: at most N iterations, the first L on line-of-sight weights
        changes = {"iterations": int(most), **({"los_iterations": int(los)} if los and method == "drt-mart" else {})}
        settings = protocol_settings(args.protocol, n_cameras=len(cams), method=method, **changes)
        res, q, cpu = cpu_timed(proj, settings, img, truth)
        rows.append(f"| {path.stem} | {len(cams)} | {method} | {cap} | {q:.3f} | {res.iterations} ({res.stopped}) | "
                    f"{cpu:.1f} |")
        print(rows[-1], flush=True)
    return rows


def rig_table(args, device: str) -> None:
    """The defaults against MART at equal CPU time on each rig of ``--rig``."""
    paths = []
    for r in args.rig:
        paths += sorted((ROOT / "examples").glob("*.toml")) if r == "all" else [Path(r)]
    if args.caps:
        rows = [row for path in paths for row in cap_rows(path, args, device)]
        print("\n| rig | cameras | method | most iterations (/ line-of-sight) | Q | iterations (stopped) | CPU s |")
        print("| --- " * 7 + "|")
        print("\n".join(rows))
        return
    rows = []
    t = time.perf_counter()
    for path in paths:
        rows.append(rig_row(path, args, device))
        print(rows[-1], flush=True)
    print(f"\nall rigs in {time.perf_counter() - t:.0f} s wall\n")
    print("| rig | cameras | method | defaults Q | iterations (stopped) | CPU s | MART Q at equal CPU | "
          f"iterations | CPU s | MART Q at {args.mart_probe} iterations, CPU s |"
          f"{' MART Q at the defaults iterations, CPU s |' if args.equal_iterations else ''} wins |")
    print("| --- " * (11 + args.equal_iterations) + "|")
    print("\n".join(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="S")
    ap.add_argument("--rig", action="append", default=[],
                    help="a rig file to measure the defaults of against MART (repeatable; all: examples/*.toml)")
    ap.add_argument("--protocol", default="fast", help="with --rig: the defaults' protocol")
    ap.add_argument("--ppp", type=float, default=None,
                    help="with --rig: the pinhole rigs' seeding in particles per pixel")
    ap.add_argument("--caps", default=None, metavar="N[/L],...",
                    help="with --rig: the defaults at each of these most iterations (N/L: the first L of them on "
                    "line-of-sight weights, drt-mart) on rigs of several cameras (no MART)")
    ap.add_argument("--no-crop", action="store_true", help="with --rig: the big rigs as they are (CROPS)")
    ap.add_argument("--mart-probe", type=int, default=5, help="with --rig: MART iterations timed per iteration")
    ap.add_argument("--device", default=None)
    ap.add_argument("--ppm", type=float, default=None,
                    help="seeding (cases: 0.5; rigs with a light-field camera: the rig's default)")
    ap.add_argument("--equal-iterations", action="store_true",
                    help="with --rig: MART also at the defaults' iteration count, however long it takes")
    ap.add_argument("--protocols", default="fixed,fast", help="named protocols, comma-separated (chapter, fixed, fast)")
    ap.add_argument("--no-mart", action="store_true", help="skip the MART baseline at equal time")
    ap.add_argument("--subsets", default="0",
                    help="ordered subsets to run each protocol with, comma-separated (0: the protocol's own)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    if args.rig:
        rig_table(args, device)
        return
    args.ppm = 0.5 if args.ppm is None else args.ppm
    _, _, cams, grid, pts, img = _recon_bench().scene(args.case, device, args.ppm)
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    print(f"case {args.case}: grid {grid.shape} (z, y, x), {len(pts)} particles ({args.ppm:g} PPM), device {device}")
    print("| protocol | iterations | stopped | Q | voxels left (of active) | elimination s | operators s | "
          "iterations s | total s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    # the kernels compiled (and the first-call costs paid) before anything is timed
    for method in ("drt-mart", "mlos-mart", "mart"):
        FrameReconstructor(proj, protocol_settings("fixed", method=method, iterations=2)).reconstruct(img)
    times = {}
    for name, n_sub in [(p, int(k)) for p in args.protocols.split(",") for k in args.subsets.split(",")]:
        settings = protocol_settings(name, n_cameras=len(cams), **({"subsets": n_sub} if n_sub else {}))
        res, q, total = timed(proj, settings, img, truth)
        if n_sub > 1:
            name = f"{name}, {n_sub} subsets"
        times[name] = total
        print(f"| {name} | {res.iterations} | {res.stopped} | {q:.3f} | {res.final_voxels:,} ({res.active_voxels:,}) | "
              f"{res.eliminate_s:.1f} | {res.weights_s - res.eliminate_s:.1f} | {res.iterate_s:.1f} | {total:.1f} |",
              flush=True)
    if args.no_mart:
        return
    probe = 5
    res, _, total = timed(proj, protocol_settings("chapter", method="mart", iterations=probe), img, truth)
    fixed_s, per_it = total - res.iterate_s, res.iterate_s / probe
    print(f"MART baseline: {res.active_voxels:,} voxels, {fixed_s:.1f} s before the iterations, "
          f"{1e3 * per_it:.1f} ms per iteration")
    for name, t in times.items():
        n = max(1, int((t - fixed_s) / per_it)) if t > fixed_s else 0
        if n == 0:
            print(f"| MART at {name}'s time ({t:.1f} s) | 0 | | (its weights alone take {fixed_s:.1f} s) | | | | | |")
            continue
        res, q, total = timed(proj, protocol_settings("chapter", method="mart", iterations=n), img, truth)
        print(f"| MART at {name}'s time | {n} | {res.stopped} | {q:.3f} | {res.final_voxels:,} | "
              f"{res.eliminate_s:.1f} | {res.weights_s - res.eliminate_s:.1f} | {res.iterate_s:.1f} | {total:.1f} |",
              flush=True)


if __name__ == "__main__":
    main()
