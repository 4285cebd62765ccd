"""Reconstruction benchmark: DRT-MART against the MART baseline and the memory-bandwidth floor.

Run from the repository root::

    python benchmarks/recon.py --case S                  # tiny rig, CPU, seconds
    python benchmarks/recon.py --case S --ppm 1          # the chapter's 4x speed point
    python benchmarks/recon.py --case S2                 # two cameras at 90 degrees
    python benchmarks/recon.py --case M --device cuda    # 2048 x 2048, 14 px per lenslet
    python benchmarks/recon.py --case L --device cuda    # 6600 x 4400, 3300 x 2200 x 182 voxels
    python benchmarks/recon.py --case L --device cpu --slabs 8 --iterations 1   # hours: every stage logged

Cases (single camera, 0.5 PPM unless --ppm, PVR (2, 2, 10), except S2 and Mc2):

S   examples/tiny.toml: 192 x 160 pixels, 82 x 68 x 29 voxels. Its volume is only +-3.6
    lenslets of blur deep, so much of it lies where depth is poorly resolved: it tests code, it is
    not representative of speed ratios.
S2  the tiny rig's camera and a second one at 90 degrees about y, 0.8 x 0.7 x 0.8 mm at PVR
    (2, 2, 2) (73 x 64 x 73 voxels), reconstructed jointly: the dual-camera case.
Mc  the optics of M on a 512 x 512 crop of the sensor (245 x 245 x 131 voxels), 50 iterations:
    M's geometry at a size a CPU manages in minutes.
Mc2 Mc's camera and a second one at 90 degrees about y around a 4.5 mm cube, reconstructed
    jointly at the chapter's dual-camera PVR (3, 3, 3) (164 x 164 x 164 voxels), as
    examples/two_cameras.toml: each camera's depth is the other's lateral axis, so deep voxels
    would throw away what the second camera adds.
M   examples/one_camera.toml: 2048 x 2048 pixels, 14 pixels per hexagonal lenslet, 400 iterations.
L   the chapter's experiment: camera 0 of examples/two_cameras.toml (6600 x 4400 pixels),
    3300 x 2200 x 182 voxels, 400 iterations.
Lc  L's optics on a 660 x 440 crop of its sensor (330 x 220 x 182 voxels of L's size, a hundredth of
    L's box and its particles): L's depth and blur at a size a CPU manages in minutes, as Mc is to M.
D   the chapter's dual-camera box, examples/two_cameras.toml as it is: two 6600 x 4400 px cameras at
    90 degrees, 1939 x 1455 x 1939 voxels (5.5e9, more than int32 indices number: depth slabs
    only, ``--slabs``; ``--planes`` for a sample).
T4  Tomo-PIV: examples/tomo_4_cameras.toml, the chapter's arc of 4 pinhole cameras of 160 x 160
    pixels, 133 x 133 x 53 voxels at PVR 1, 0.05 ppp (--ppp), MLOS-SMART 20 iterations; T6 and
    T8 the 6- and 8-camera arcs. Beside MLOS-SMART, the MART baseline on the same projector
    (line-of-sight weights on every voxel of the box, no elimination).

Each case prints the weight build time (elimination and weights), the active fraction, ms per
iteration, peak memory, Q_recon against the truth, the same for MLOS-MART (DRT-MART's
elimination with the baseline's weights), and two ratios measured in the same run:
against the MART baseline (same iteration code, line-of-sight weights on every voxel; skipped
when its weights would not fit, with the size they would need) and against the memory-bandwidth
floor: the bytes one iteration must move (every stored weight read twice, its pixel's projection
updated and read, each voxel's intensity read and written) divided by the copy bandwidth of the
same device measured here.

``--projector matrix-free`` (or ``both``) runs DRT-MART on the matrix-free templates of
:mod:`lfcore.matrix_free` instead (or as well): the templates' build time and memory, ms per
iteration, Q, and the fidelity of 200 random active voxels' images against the stored weights.
With ``both``, ``--interleaved ROUNDS`` also times the ray-traced weights and the templates'
images of one frame in alternating blocks of 5 iterations: on a shared VM, whose memory bandwidth
drifts by 20% within minutes, their ratio is measured only so.

``--slabs N`` runs DRT-MART on the matrix-free projector in N depth slabs instead
(:class:`lfcore.slabs.SlabReconstructor`: the templates' images stored where they fit, else applied
in every iteration), logging each stage with the time since the start and the resident memory, then
the peak resident memory, and Q where the box's volume and its truth fit in a quarter of the memory.
With ``--protocol NAME`` the slabs run that protocol's whole plan instead (``fast``: the coarse grid
in memory, 20 line-of-sight iterations, DRT weights for the survivors, 6 ordered subsets, the
stopping rule; ``--coarse F`` its coarse factor), each stage logged with its wall and CPU
(``time.process_time``) seconds and the resident memory; ``--budget-gib`` bounds the memory its
weights and buffers may take (what does not fit is applied or made in every iteration)::

    python benchmarks/recon.py --case L --device cpu --slabs 1 --planes 80:103 --protocol fast --budget-gib 7.5

Line-of-sight weights that do not fit in the device's memory are made on the fly in each
iteration (``--weight-storage auto``, the default; L by MLOS-MART on one GPU): such a run
reports how many voxels' weights were, and no bandwidth floor, since it traces rather than
reads them. ``--weight-storage on-the-fly`` forces it, to compare with stored weights.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore import metrics  # noqa: E402
from lfcore.device import resolve_device, warp  # noqa: E402
from lfcore.particles import particle_count, seed_particles  # noqa: E402
from lfcore.pinhole_projector import PinholeProjector  # noqa: E402
from lfcore.projector import BYTES_PER_WEIGHT, STORAGE, LightFieldProjector, MemoryBudgetError  # noqa: E402
from lfcore.reconstruct import (  # noqa: E402
    PROTOCOLS,
    ReconSettings,
    estimate_background,
    preprocess,
    protocol_settings,
    reconstruct,
)
from lfcore.render import LightFieldRenderer, PinholeRenderer  # noqa: E402
from lfcore.rig import Rig  # noqa: E402
from lfcore.volume import VolumeGrid  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402

#: Bytes an iteration moves per stored weight (pix and w read in the projection and again in the
#: update, the projection's atomic read-modify-write, the gathers of image and projection) and per
#: reconstructed voxel (offsets twice, intensity read twice and written once).
BYTES_PER_ENTRY = 8 + 8 + 8 + 8
BYTES_PER_VOXEL = 16 + 12


def case_rig(case: str) -> tuple[Rig, int]:
    if case == "S":
        return load_rig(ROOT / "examples" / "tiny.toml"), 50
    if case == "S2":
        d = load_rig(ROOT / "examples" / "tiny.toml").to_dict()
        d["camera"].append(dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
        d["volume"].update(size_mm=[0.8, 0.7, 0.8], pvr=[2.0, 2.0, 2.0])
        return Rig.from_dict(d), 50
    if case == "M":
        return load_rig(ROOT / "examples" / "one_camera.toml"), 400
    if case in ("Mc", "Mc2"):
        d = load_rig(ROOT / "examples" / "one_camera.toml").to_dict()
        d["camera"][0]["sensor_px"] = [512, 512]
        d["volume"]["size_mm"] = [4.5, 4.5, 12.0]
        if case == "Mc2":  # a second camera at 90 degrees about y; a box both see whole
            d["camera"].append(dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
            d["volume"].update(size_mm=[4.5, 4.5, 4.5], pvr=[3.0, 3.0, 3.0])
        return Rig.from_dict(d), 50
    if case == "D":  # the chapter's dual-camera box as the example rig has it
        return load_rig(ROOT / "examples" / "two_cameras.toml"), 400
    d = load_rig(ROOT / "examples" / "two_cameras.toml").to_dict()
    d["camera"] = d["camera"][:1]
    # 3300 x 2200 x 182 voxels of 11 x 11 x 55 um at PVR (2, 2, 10) and |M| = 1
    nx, ny = 3300, 2200
    if case == "Lc":  # L's optics on a 660 x 440 crop of its sensor: the box's voxels and depth, a tenth across
        d["camera"][0]["sensor_px"] = [660, 440]
        nx, ny = 330, 220
    d["volume"].update(size_mm=[nx * 0.011, ny * 0.011, 182 * 0.055], pvr=[2.0, 2.0, 10.0])
    return Rig.from_dict(d), 400


def copy_bandwidth(device: str) -> float:
    """Bytes per second of a device-to-device copy of 256 MiB (read plus write)."""
    wp = warp()
    a = wp.zeros(1 << 26, dtype=float, device=device)
    b = wp.empty_like(a)
    wp.copy(b, a)
    wp.synchronize_device(device)
    t = time.perf_counter()
    reps = 5
    for _ in range(reps):
        wp.copy(b, a)
    wp.synchronize_device(device)
    return 2 * a.size * 4 * reps / (time.perf_counter() - t)


def peak_bytes(device: str) -> int:
    wp = warp()
    if device == "cpu":
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return int(wp.get_mempool_used_mem_high(device))


def scene(case: str, device: str, ppm: float, *, render_changes: dict | None = None):
    """The case's rig, iterations, cameras, grid and true particles, and one rendered image per camera.
    ``render_changes``: ``[render]`` keys changed for the images (noise, the camera's response)."""
    rig, its = case_rig(case)
    cams = rig.camera if case in ("S2", "Mc2", "D") else rig.camera[:1]
    pts = seed_particles(rig.volume, particle_count(rig, ppm=ppm), np.random.default_rng(1))
    render = rig.render.model_copy(update={"rays_per_particle": 5000, **(render_changes or {})})
    img = [LightFieldRenderer(c, render, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(
               pts, render.particle_counts, seed=1 + k)
           for k, c in enumerate(cams)]
    return rig, its, cams, VolumeGrid.from_rig(rig), pts, img


def floor_text(r, floor_ms) -> str:
    """The ratio to the bandwidth floor, or how many voxels' weights were made on the fly."""
    if r.on_the_fly_voxels:
        return f"weights of {r.on_the_fly_voxels} voxels made on the fly"
    return f"{r.ms_per_iteration / floor_ms(r):.1f}x the bandwidth floor of {floor_ms(r):.3f} ms"


def matrix_free_figures(proj, img, its: int, e0, drt, fly_its: int | None = None) -> None:
    """DRT-MART on the matrix-free templates: their build, memory, ms per iteration, Q, and the
    fidelity of random active voxels' images against the stored weights (the reference)."""
    from lfcore.matrix_free import fidelity

    fly_its = its if fly_its is None else fly_its  # the templates applied in every iteration: slower
    # first (and printed at once, so that a time limit still finds it) the templates' images of the
    # active voxels stored once, then the stored weights' iterations: what auto takes where they fit
    ex = reconstruct(proj, img, ReconSettings(iterations=its, projector="matrix-free", weight_storage="stored"))
    q_ex = metrics.q_recon(ex.volume, e0)
    print(f"  DRT-MART matrix-free, the templates' images stored: weights_s {ex.weights_s:.2f} s (templates, "
          f"elimination {ex.eliminate_s:.2f} s, images {ex.nnz} entries), memory {ex.weight_bytes / 2**20:.0f} MiB, "
          f"{ex.ms_per_iteration:.2f} ms/iteration, total {ex.weights_s + ex.iterate_s:.2f} s, Q {q_ex:.3f}",
          flush=True)
    mf = reconstruct(proj, img, ReconSettings(iterations=fly_its, projector="matrix-free", weight_storage="on-the-fly"))
    q = metrics.q_recon(mf.volume, e0)
    # the templates are those the reconstruction built (the projector's geometry alone)
    from lfcore.matrix_free import DrtTemplates

    t = time.perf_counter()
    templates = DrtTemplates(proj)
    build = time.perf_counter() - t
    lit = []
    st = ReconSettings()
    for im in img:
        level, sigma = estimate_background(im)
        lit.append(preprocess(im, level, sigma, st.threshold_sigma, grow=st.lit_grow)[1])
    active = proj.eliminate(lit, min_seen=st.min_seen, max_dark=st.max_dark).numpy()
    rng = np.random.default_rng(5)
    sample = rng.choice(active, size=min(200, active.size), replace=False) if active.size else active
    f = fidelity(proj, sample, templates) if sample.size else {"correlation": np.ones(1), "light": np.ones(1)}
    c, light = f["correlation"], np.abs(f["light"] - 1.0)
    print(f"  DRT-MART matrix-free, applied in every iteration ({fly_its} iterations): templates {build:.2f} s "
          f"({templates.n_templates} templates, {templates.n_spots} "
          f"spots ({templates.n_rigid} rigid, {templates.n_cut} cut), phase bins {templates.depth_phase.min()}-"
          f"{templates.depth_phase.max()} per axis, "
          f"{templates.nbytes / 2**20:.0f} MiB), first frame's weights_s {mf.weights_s:.2f} s (elimination "
          f"{mf.eliminate_s:.2f} s), memory {mf.weight_bytes / 2**20:.0f} MiB, {mf.ms_per_iteration:.2f} ms/iteration, "
          f"total {mf.weights_s + mf.iterate_s:.2f} s, Q {q:.3f}, "
          f"peak memory {peak_bytes(proj.device) / 2**30:.2f} GiB")
    print(f"    fidelity on {sample.size} active voxels: correlation min {c.min():.5f} median {np.median(c):.6f}, "
          f"total light off by at most {light.max():.2%} (median {np.median(light):.4%}); depth-blur bound "
          f"{templates.blur_error:.1%} of a footprint's lateral blur")
    if drt is not None:
        print(f"    images stored against ray-traced stored weights: {ex.ms_per_iteration / drt.ms_per_iteration:.2f}x "
              f"the time per iteration, weights_s {drt.weights_s:.2f} s -> {ex.weights_s:.2f} s, total "
              f"{drt.weights_s + drt.iterate_s:.2f} s -> {ex.weights_s + ex.iterate_s:.2f} s "
              f"({(drt.weights_s + drt.iterate_s) / (ex.weights_s + ex.iterate_s):.2f}x faster), entries {drt.nnz} -> "
              f"{ex.nnz}, Q {metrics.q_recon(drt.volume, e0):.3f} -> {q_ex:.3f}")
        print(f"    on the fly against stored weights: {mf.ms_per_iteration / drt.ms_per_iteration:.1f}x the time per "
              "iteration, "
              f"memory {mf.weight_bytes / 2**20:.0f} MiB vs {drt.weight_bytes / 2**20:.0f} MiB "
              f"({memory_ratio(mf.weight_bytes, drt.weight_bytes)}), "
              f"build {drt.weights_s - drt.eliminate_s:.2f} s -> {build:.2f} s, "
              f"Q {q:.3f} ({fly_its} iterations) vs {metrics.q_recon(drt.volume, e0):.3f} ({its})")


def interleaved(proj, img, *, rounds: int, its: int) -> None:
    """Per-iteration time of the ray-traced weights and of the templates' images on one frame,
    measured in alternating blocks of ``its`` iterations (each from the uniform start), so that
    the machine's drift over a run (other tenants' memory traffic on a shared VM) falls on both:
    the median of the rounds' ratios, with their range."""
    from lfcore.reconstruct import FrameReconstructor, preprocess_images

    wp = warp()
    traced = FrameReconstructor(proj, ReconSettings(projector="stored"))
    images = FrameReconstructor(proj, ReconSettings(projector="matrix-free", weight_storage="stored"))
    signals, lits, _, noise = preprocess_images(proj, img, traced.settings)
    image = wp.array(np.concatenate([s.ravel() for s in signals]), dtype=float, device=proj.device)
    voxels = traced.eliminate(lits)
    ops = ((traced, traced.operator(voxels)), (images, images.operator(voxels)))
    ms = np.zeros((rounds, 2))
    for r in range(rounds):
        for k in (0, 1) if r % 2 == 0 else (1, 0):  # each operator first in every other round
            fr, w = ops[k]
            ms[r, k] = 1e3 * fr.iterate(w, image, noise, iterations=its).iterate_s / its
    ratio = ms[:, 1] / ms[:, 0]
    nnz = [w.nnz for _, w in ops]
    print(f"  interleaved, {rounds} rounds of {its} iterations each: ray-traced weights median "
          f"{np.median(ms[:, 0]):.1f} ms/iteration ({ms[:, 0].min():.1f}-{ms[:, 0].max():.1f}), the templates' "
          f"images {np.median(ms[:, 1]):.1f} ({ms[:, 1].min():.1f}-{ms[:, 1].max():.1f}); images/traced per round: "
          f"median {np.median(ratio):.3f} (range {ratio.min():.3f}-{ratio.max():.3f}); entries {nnz[0]} vs {nnz[1]} "
          f"({nnz[1] / nnz[0]:.3f}x)")


def run_slabs(case: str, device: str, ppm: float, iterations: int | None, n_slabs: int, storage: str,
              planes: tuple[int, int] | None = None, protocol: str | None = None, coarse: int | None = None,
              budget_gib: float | None = None) -> None:
    """DRT-MART on the matrix-free projector in ``n_slabs`` depth slabs, every stage logged; with
    ``planes`` (z0, z1) only the box's planes z0 .. z1 - 1 are reconstructed (from the whole
    scene's images): a sample of a box too large to reconstruct whole in the time there is.

    ``protocol`` (a name of :data:`lfcore.reconstruct.PROTOCOLS`): its whole plan instead (e.g. ``fast``:
    the coarse grid, line-of-sight first iterations, ordered subsets, the stopping rule; ``iterations``
    its most), with its own projector choice; ``coarse`` overrides its coarse factor. ``budget_gib``:
    the memory the slabs' weights and buffers may take (default: what the host has free); what does not
    fit in it is applied or made in every iteration."""
    from lfcore.slabs import SlabReconstructor, plan_slabs

    t0 = time.perf_counter()
    c0 = time.process_time()
    last = [t0, c0]

    def log(line: str) -> None:
        # wall and CPU seconds since the start and since the last line, and the resident memory now
        t, c = time.perf_counter(), time.process_time()
        print(f"  [{t - t0:7.1f} s (+{t - last[0]:6.1f}), CPU {c - c0:7.1f} s (+{c - last[1]:6.1f}), "
              f"RSS {rss_bytes() / 2**30:5.2f} GiB] {line}", flush=True)
        last[:] = [t, c]

    _, its, cams, grid, pts, img = scene(case, device, ppm)
    its = iterations or its
    cam = cams[0]
    print(f"case {case} in {n_slabs} depth slabs: {len(cams)} x {cam.sensor_px[0]} x {cam.sensor_px[1]} px, "
          f"{' x '.join(map(str, grid.shape[::-1]))} voxels (x, y, z), {len(pts)} particles ({ppm:g} PPM), "
          f"{its} iterations, device {device}", flush=True)
    log("rendered")
    proj = LightFieldProjector(cams, grid, device=device)
    if planes is not None:  # the box's planes z0 .. z1 - 1 only, numbered as a slab of the box (its templates)
        z0, z1 = planes
        if not 0 <= z0 < z1 <= grid.shape[0]:
            raise SystemExit(f"--planes {z0}:{z1} is outside the box's planes 0:{grid.shape[0]}")
        o = grid.origin_mm
        proj = proj.planes(z0, z1)
        grid = proj.grid
        pts = pts[np.abs(pts[:, 2] - o[2] - (z0 + 0.5 * (z1 - z0 - 1)) * grid.voxel_mm[2]) <= 0.5 * (z1 - z0) *
                  grid.voxel_mm[2]]  # the truth of Q: the particles inside those planes
        print(f"  planes {z0}-{z1 - 1} only: {' x '.join(map(str, grid.shape[::-1]))} voxels, numbered from the "
              f"box's voxel {z0 * grid.shape[1] * grid.shape[2]:,}", flush=True)
    log("projector built")
    nz = grid.shape[0]
    # Q needs the whole volume and its truth on the host: only where both fit in a quarter of memory
    whole = np.zeros(grid.shape, np.float32) if 8 * grid.n_voxels < peak_capacity("cpu") // 4 else None

    def write(z0: int, z1: int, planes: np.ndarray) -> None:
        if whole is not None:
            whole[z0:z1] = planes

    if protocol is None:
        settings = ReconSettings(iterations=its, projector="matrix-free", weight_storage=storage)
    else:
        changes = {"weight_storage": storage}
        if iterations:
            changes["iterations"] = iterations
        if coarse is not None:
            changes["coarse"] = coarse
        settings = protocol_settings(protocol, n_cameras=len(cams), **changes)
        print(f"  protocol {protocol}: {settings.iterations} iterations at most (stop tolerance "
              f"{settings.stop_tolerance:g}), {settings.los_iterations} line-of-sight first, {settings.subsets} "
              f"subsets, coarse {settings.coarse} ({settings.coarse_iterations} iterations), projector "
              f"{settings.projector}, weight storage {settings.weight_storage}", flush=True)
    budget = None if budget_gib is None else int(budget_gib * 2**30)
    res = SlabReconstructor(proj, settings, slabs=plan_slabs(nz, n_slabs), budget_bytes=budget).reconstruct(
        img, write=write, log=log)
    log("reconstructed")
    q = f", Q {metrics.q_recon(whole, metrics.truth_volume(grid, pts)):.3f}" if whole is not None else ""
    plan = "DRT-MART matrix-free" if protocol is None else protocol
    print(f"  {plan} in {res.slabs} slabs: {res.active_voxels:,} active voxels "
          f"({res.active_fraction:.3%}), elimination {res.eliminate_s:.1f} s, weights_s {res.weights_s:.1f} s "
          f"(elimination, operators and start), {res.ms_per_iteration:.1f} ms/iteration, operator "
          f"{res.weight_bytes / 2**20:.0f} MiB ({res.projector}, {res.on_the_fly_voxels:,} voxels on the fly), "
          f"accounted peak {res.peak_bytes / 2**30:.2f} GiB, peak RSS {peak_bytes('cpu') / 2**30:.2f} GiB"
          f"{'' if device == 'cpu' else f', device peak {peak_bytes(device) / 2**30:.2f} GiB'}, total "
          f"{time.perf_counter() - t0:.0f} s (CPU {time.process_time() - c0:.0f} s){q}", flush=True)
    if protocol is not None:
        print(f"  {protocol}: {res.iterations} iterations ({res.stopped}), {res.final_voxels:,} voxels at the end, "
              f"operators {res.operator}", flush=True)


def rss_bytes() -> int:
    """This process's resident memory now."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def memory_ratio(mine: int, stored: int) -> str:
    """``mine`` bytes against ``stored`` ones in words ("4.5x less" or "1.3x more")."""
    if mine <= stored:
        return f"{stored / max(mine, 1):.1f}x less"
    return f"{mine / max(stored, 1):.1f}x more"


def run(case: str, device: str, ppm: float, iterations: int | None, mart: bool, with_drt: bool = True,
        storage: str = "auto", projector: str = "stored", fly_its: int | None = None,
        rounds: int | None = None) -> None:
    t = time.perf_counter()
    _, its, cams, grid, pts, img = scene(case, device, ppm)
    its = iterations or its
    cam = cams[0]
    n = len(pts)
    print(f"case {case}: {len(cams)} x {cam.sensor_px[0]} x {cam.sensor_px[1]} px, "
          f"{' x '.join(map(str, grid.shape[::-1]))} voxels (x, y, z), {n} particles ({ppm:g} PPM), {its} iterations, "
          f"device {device}; "
          f"rendered in {time.perf_counter() - t:.1f} s")
    bw = copy_bandwidth(device)
    proj = LightFieldProjector(cams, grid, device=device)
    e0 = metrics.truth_volume(grid, pts)
    print(f"  copy bandwidth {bw / 1e9:.1f} GB/s")

    def floor_ms(r) -> float:
        return 1e3 * (BYTES_PER_ENTRY * r.nnz + BYTES_PER_VOXEL * r.active_voxels) / bw

    drt = None
    if with_drt and projector in ("stored", "both"):
        # the reference: ray-traced stored weights (the default, "auto", takes the templates'
        # images where they pay, which are timed beside it with --projector both)
        drt = reconstruct(proj, img, ReconSettings(iterations=its, projector="stored"))
        q = metrics.q_recon(drt.volume, e0)
        print(f"  DRT-MART, ray-traced stored weights: weights {drt.weights_s:.2f} s "
              f"(elimination {drt.eliminate_s:.2f} s), "
              f"active {drt.active_fraction:.3%} ({drt.active_voxels} "
              f"voxels, {drt.nnz} weights, {drt.weight_bytes / 2**20:.0f} MiB), {drt.ms_per_iteration:.2f} "
              f"ms/iteration ({floor_text(drt, floor_ms)}), total {drt.weights_s + drt.iterate_s:.2f} s, Q {q:.3f}, "
              f"peak memory {peak_bytes(device) / 2**30:.2f} GiB")
    if with_drt and projector in ("matrix-free", "both"):
        matrix_free_figures(proj, img, its, e0, drt, fly_its)
        if rounds and projector == "both":
            interleaved(proj, img, rounds=rounds, its=5)
        if projector == "matrix-free":
            return
    # MLOS-MART: the same elimination, the baseline's weights on the surviving voxels
    mlos = reconstruct(proj, img, ReconSettings(method="mlos-mart", iterations=its, weight_storage=storage))
    tm = mlos.weights_s + mlos.iterate_s
    print(f"  MLOS-MART: weights {mlos.weights_s:.2f} s (elimination {mlos.eliminate_s:.2f} s), "
          f"active {mlos.active_fraction:.3%} ({mlos.active_voxels} "
          f"voxels, {mlos.nnz} weights, {mlos.weight_bytes / 2**20:.0f} MiB), {mlos.ms_per_iteration:.2f} "
          f"ms/iteration ({floor_text(mlos, floor_ms)}), total {tm:.2f} s, "
          f"Q {metrics.q_recon(mlos.volume, e0):.3f}, peak memory {peak_bytes(device) / 2**30:.2f} GiB")
    if not mart:
        return
    # the baseline's weights, counted on a sample of voxels first: they may not fit at all
    sample = np.random.default_rng(2).choice(grid.n_voxels, size=min(grid.n_voxels, 20000), replace=False)
    wp = warp()
    est = proj.weights(wp.array(np.sort(sample).astype(np.int32), device=device), method="los").nnz
    need = BYTES_PER_WEIGHT * est * grid.n_voxels / len(sample)
    if need > 0.8 * (peak_capacity(device)):
        print(f"  MART baseline: skipped, its weights would need about {need / 2**30:.0f} GiB")
        return
    base = reconstruct(proj, img, ReconSettings(method="mart", iterations=its, weight_storage=storage))
    qb = metrics.q_recon(base.volume, e0)
    tb = base.weights_s + base.iterate_s
    print(f"  MART baseline: weights {base.weights_s:.2f} s ({base.nnz} weights), {base.ms_per_iteration:.2f} "
          f"ms/iteration, total {tb:.2f} s, Q {qb:.3f}")
    if drt is not None:
        td = drt.weights_s + drt.iterate_s
        print(f"  DRT-MART vs MART at {its} iterations each: {tb / td:.1f}x faster "
              f"({base.ms_per_iteration / drt.ms_per_iteration:.1f}x per iteration), Q {q:.3f} vs {qb:.3f}")
    print(f"  MLOS-MART vs MART: {tb / tm:.1f}x faster")


TOMO_CASES = {"T4": 4, "T6": 6, "T8": 8}


def run_tomo(case: str, device: str, ppp: float, iterations: int | None, mart: bool) -> None:
    """MLOS-SMART of a Tomo-PIV arc (and the MART baseline on the same projector)."""
    t = time.perf_counter()
    rig = load_rig(ROOT / "examples" / f"tomo_{TOMO_CASES[case]}_cameras.toml")
    its = iterations or 20
    cams = rig.camera
    n = particle_count(rig, ppp=ppp)
    pts = seed_particles(rig.volume, n, np.random.default_rng(1))
    img = [PinholeRenderer(c, rig.render, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(
               pts, rig.render.particle_counts, seed=1 + k)
           for k, c in enumerate(cams)]
    grid = VolumeGrid.from_rig(rig)
    cam = cams[0]
    print(f"case {case}: {len(cams)} x {cam.sensor_px[0]} x {cam.sensor_px[1]} px pinhole cameras, "
          f"{' x '.join(map(str, grid.shape[::-1]))} voxels (x, y, z), {n} particles ({ppp:g} ppp), {its} iterations, "
          f"device {device}; rendered in {time.perf_counter() - t:.1f} s")
    bw = copy_bandwidth(device)
    print(f"  copy bandwidth {bw / 1e9:.1f} GB/s")

    def floor_ms(r) -> float:
        return 1e3 * (BYTES_PER_ENTRY * r.nnz + BYTES_PER_VOXEL * r.active_voxels) / bw

    proj = PinholeProjector(cams, grid, device=device)
    e0 = metrics.truth_volume(grid, pts)
    reconstruct(proj, img, ReconSettings(method="mlos-smart", iterations=1))  # compile the kernels first
    sm = reconstruct(proj, img, ReconSettings(method="mlos-smart", iterations=its))
    ts = sm.weights_s + sm.iterate_s
    print(f"  MLOS-SMART: weights {sm.weights_s:.2f} s (elimination {sm.eliminate_s:.2f} s), "
          f"active {sm.active_fraction:.3%} ({sm.active_voxels} voxels, {sm.nnz} weights, "
          f"{sm.weight_bytes / 2**20:.0f} MiB), {sm.ms_per_iteration:.2f} ms/iteration ({floor_text(sm, floor_ms)}), "
          f"total {ts:.2f} s, Q {metrics.q_recon(sm.volume, e0):.3f}, peak memory {peak_bytes(device) / 2**30:.2f} GiB")
    if not mart:
        return
    base = reconstruct(proj, img, ReconSettings(method="mart", iterations=its))
    tb = base.weights_s + base.iterate_s
    print(f"  MART baseline (every voxel): weights {base.weights_s:.2f} s ({base.nnz} weights), "
          f"{base.ms_per_iteration:.2f} ms/iteration, total {tb:.2f} s, Q {metrics.q_recon(base.volume, e0):.3f}")
    print(f"  MLOS-SMART vs MART: {tb / ts:.1f}x faster")


def profile_weights(case: str, device: str, ppm: float) -> None:
    """Time the elimination and each way of building the DRT weights, then every kernel of the
    default build and of the MLOS (line-of-sight) weights (synchronised around each launch)."""
    from _kernel_clock import kernel_clock, print_clock

    wp = warp()
    _, _, cams, grid, _, img = scene(case, device, ppm)
    proj = LightFieldProjector(cams, grid, device=device)
    st = ReconSettings()
    lit = []
    for im in img:  # the lit pixels, as reconstruct() finds them
        level, sigma = estimate_background(im)
        lit.append(preprocess(im, level, sigma, st.threshold_sigma, grow=st.lit_grow)[1])

    def timed(fn):
        wp.synchronize_device(device)
        t = time.perf_counter()
        out = fn()
        wp.synchronize_device(device)
        return out, time.perf_counter() - t

    proj.eliminate(lit, min_seen=st.min_seen, max_dark=st.max_dark)
    voxels, te = timed(lambda: proj.eliminate(lit, min_seen=st.min_seen, max_dark=st.max_dark))
    print(f"profile of the weight build, case {case} at {ppm:g} PPM on {device}: elimination {te:.3f} s, "
          f"{voxels.shape[0]} active voxels")
    variants = [("two-pass", "library"), ("two-pass", "per-voxel"), ("single-pass", "per-voxel")]
    few = voxels[: min(1000, voxels.shape[0])]
    for build, sort in variants:  # compile every kernel first
        proj.weights(few, method="drt", build=build, sort=sort)
    proj.weights(few, method="los")
    for method in ("drt", "los"):
        with kernel_clock(device) as spent:
            w, t = timed(lambda m=method: proj.weights(voxels, method=m))
        print(f"  kernels of the default {method} build ({t:.3f} s in all, {w.nnz} weights):")
        print_clock(spent, t, "host (copies, allocation, numpy)")
        del w
    for build, sort in variants:
        w, t = timed(lambda b=build, s=sort: proj.weights(voxels, method="drt", build=b, sort=s))
        print(f"  DRT {build:11s} {sort:9s}: {t:7.3f} s, {w.nnz} weights ({w.nnz / t / 1e6:.0f} M weights/s)")
        del w


def peak_capacity(device: str) -> int:
    if device == "cpu":
        import os

        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    return int(warp().get_device(device).total_memory)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", choices=("S", "S2", "Mc", "Mc2", "M", "L", "Lc", "D", *TOMO_CASES), action="append",
                    help="case(s) to run (default: S)")
    ap.add_argument("--device", default=None, help="cpu or cuda (default: a GPU if there is one)")
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--ppp", type=float, default=0.05, help="seeding of the Tomo-PIV cases T4, T6, T8")
    ap.add_argument("--iterations", type=int, default=None, help="override the case's iterations")
    ap.add_argument("--no-mart", action="store_true", help="skip the MART baseline")
    ap.add_argument("--no-drt", action="store_true", help="skip DRT-MART (MLOS-MART only, with --no-mart)")
    ap.add_argument("--weight-storage", choices=STORAGE, default="auto",
                    help="line-of-sight weights of MLOS-MART and the baseline (default: auto, stored if they fit)")
    ap.add_argument("--projector", choices=("stored", "matrix-free", "both"), default="stored",
                    help="DRT-MART on stored weights (default), on the matrix-free templates (then nothing else), "
                    "or both, with the templates' fidelity against the stored weights")
    ap.add_argument("--on-the-fly-iterations", type=int, default=None, metavar="N",
                    help="with --projector matrix-free or both: the templates applied in every iteration run only N "
                    "iterations (default: as many as the others)")
    ap.add_argument("--interleaved", type=int, default=None, metavar="ROUNDS",
                    help="with --projector both: also time the ray-traced weights and the templates' images in "
                    "ROUNDS alternating blocks of 5 iterations on one frame (their ratio, free of the machine's drift)")
    ap.add_argument("--slabs", type=int, default=None, metavar="N",
                    help="instead: DRT-MART on the matrix-free projector in N depth slabs, every stage logged")
    ap.add_argument("--planes", default=None, metavar="Z0:Z1",
                    help="with --slabs: reconstruct only the box's planes Z0 .. Z1 - 1 (from the whole scene's images)")
    ap.add_argument("--protocol", choices=tuple(PROTOCOLS), default=None,
                    help="with --slabs: the named protocol's whole plan (e.g. fast: coarse grid, line-of-sight first, "
                    "ordered subsets, the stopping rule; --iterations its most) instead of matrix-free DRT-MART")
    ap.add_argument("--coarse", type=int, default=None, metavar="F",
                    help="with --protocol: the coarse-to-fine elimination's factor (1: none)")
    ap.add_argument("--budget-gib", type=float, default=None, metavar="GIB",
                    help="with --slabs: memory the weights and buffers may take (default: the host's free memory); "
                    "weights beyond it are applied or made in every iteration")
    ap.add_argument("--profile-weights", action="store_true",
                    help="instead: time the elimination, each DRT weight build and every kernel of the builds")
    args = ap.parse_args()
    device = resolve_device(args.device)
    if args.profile_weights:
        for case in args.case or ["S"]:
            profile_weights(case, device, args.ppm)
        return 0
    for case in args.case or ["S"]:
        try:
            if args.slabs:
                planes = tuple(int(v) for v in args.planes.split(":")) if args.planes else None
                run_slabs(case, device, args.ppm, args.iterations, args.slabs, args.weight_storage, planes,
                          args.protocol, args.coarse, args.budget_gib)
                continue
            if case in TOMO_CASES:
                run_tomo(case, device, args.ppp, args.iterations, not args.no_mart)
                continue
            run(case, device, args.ppm, args.iterations, not args.no_mart, not args.no_drt, args.weight_storage,
                args.projector, args.on_the_fly_iterations, args.interleaved)
        except MemoryBudgetError as exc:  # the case does not fit this device: say so, go on
            print(f"  case {case}: {exc}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
