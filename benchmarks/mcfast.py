"""Issue 47's Mc goal: a whole frame's stages (elimination, operators, iterations), wall and CPU seconds,
Q against the truth and the voxels left, for chosen settings against the chapter's protocol, in one run.

Run from the repository root::

    python benchmarks/mcfast.py --case Mc                         # the named protocols and the reference
    python benchmarks/mcfast.py --case S --rows fixed,fast,fast-plain
    python benchmarks/mcfast.py --case Mc --rows "fast;coarse=3,los_iterations=10,subsets=4,iterations=100"

Each row reconstructs the case's frame (``benchmarks/recon.py``'s scene) from its image with
:meth:`lfcore.reconstruct.FrameReconstructor.reconstruct`, as ``lfpiv reconstruct`` does, each stage
timed by the wall clock and by the process's CPU seconds (``time.process_time``: robust to the other
processes on a shared machine; a CPU launch runs on every core, so CPU seconds may exceed wall ones).
A row is a protocol name (:data:`lfcore.reconstruct.PROTOCOLS`), ``fast-plain`` (``fast`` without
its coarse-to-fine elimination and subsets: the protocol before them), or ``name;key=value,...``
(the protocol with those settings changed), each resolved for the case's cameras as ``lfpiv
reconstruct`` resolves it (``fast`` on two cameras has no ordered subsets unless a row gives them).
A row's ``sub_apertures`` builds its own projector, as ``lfpiv reconstruct`` does. The key ``round_checks=N``
is the benchmark's, not a setting: the row's elimination lets each view make N checks before the next
view's turn (:data:`lfcore.projector.ROUND_CHECKS`; 0, one view after another, as before the turns)::

    python benchmarks/mcfast.py --case Mc2 --reference-iterations 0 --rows "fast;round_checks=0|fast"

The reference is the chapter's protocol (``ReconSettings.chapter``: uniform start, elimination,
ray-traced DRT weights, 400 iterations of every active voxel, no pruning). Without pruning every
iteration costs the same, so ``--reference-iterations 40`` (the default) times 40 and scales the
iterations by 10 (its Q is then not measured: ``--reference-iterations 400`` runs it whole).
``--checkpoints 20,50,100,200,400`` also measures the reference's Q after those many of its iterations
(the time that takes left out of every clock), so the best Q the chapter's protocol reaches at any count
is known from one run::

    python benchmarks/mcfast.py --case Mc2 --reference-iterations 400 --checkpoints 20,50,100,200,400

``--noise 1,3,3+response`` runs every row on several renderings of the same particles, in one process:
a factor F multiplies the renderer's shot and read noise (``read_noise_counts`` times F,
``gain_e_per_count`` divided by F squared), and ``+response`` (or ``--response``, for every item) adds
a camera's response (``lens_falloff`` 0.3, ``micro_vignetting`` 0.3, 20 dust spots, ``dark_fpn_counts``
5). The reference runs on the first item's images::

    python benchmarks/mcfast.py --case Mc2 --noise 1,3,3+response --rows "fast|fast;max_dark=0.0"

The elimination stage is the fine grid's; after a coarse grid (``coarse``), the coarse grid's
elimination, operator and iterations have their own column (CPU s). Each row's operators are listed by
their bytes (the coarse grid's, the fine grid's line-of-sight one, DRT's: the largest of each kind the
row made, with the voxels whose weights were made on the fly), and its own peak resident memory (the
process's ``VmHWM``, reset before each row; what the process held as the row began in brackets).
L's optics on a crop (``--case Lc``), whose plain plan would not fit, compiles its kernels on another
case first::

    python benchmarks/mcfast.py --case Lc --warm-case S --reference-iterations 0 --rows "fast|fast;coarse=4"
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
from lfcore import projector as projector_module  # noqa: E402
from lfcore import reconstruct as reconstruct_module  # noqa: E402
from lfcore.device import resolve_device  # noqa: E402
from lfcore.plan import projector_for  # noqa: E402
from lfcore.reconstruct import FrameReconstructor, protocol_settings  # noqa: E402

#: The stages and the FrameReconstructor methods whose time is theirs.
STAGES = {"elimination": ("eliminate", "coarse_eliminate"), "line-of-sight weights": ("los_operator",),
          "DRT operator": ("operator",), "iterations": ("iterate",)}
#: The coarse grid's stages (its reconstructor's methods), inside the fine ``coarse_eliminate``'s time.
COARSE_STAGES = {"coarse elimination": "eliminate", "coarse operator": "operator", "coarse iterations": "iterate"}
#: A camera's response, as ``--response`` adds it to the images (:class:`lfcore.rig.RenderConfig`'s keys).
RESPONSE = {"lens_falloff": 0.3, "micro_vignetting": 0.3, "dust_spots": 20, "dark_fpn_counts": 5.0}


def render_changes(item: str, render, *, response: bool = False) -> dict:
    """The ``[render]`` changes of one ``--noise`` item (``F`` or ``F+response``) on the rig's ``render``:
    shot and read noise F times the renderer's (read noise times F, electrons per count over F squared)."""
    factor, plus, extra = item.partition("+")
    if plus and extra != "response":
        raise SystemExit(f"--noise items are F or F+response, got '{item}'")
    f = float(factor)
    changes = {"read_noise_counts": render.read_noise_counts * f, "gain_e_per_count": render.gain_e_per_count / f**2}
    if plus or response:
        changes.update(RESPONSE)
    return changes


def parse_row(text: str, n_cameras: int = 1, *, extras: dict | None = None, camera_kind: str | None = "light-field"):
    """(label, settings) of a row: ``name`` or ``name;key=value,...``, resolved for ``n_cameras`` cameras
    as ``lfpiv reconstruct`` resolves it (``fast`` on several cameras has no subsets unless given).
    ``extras``: where given, the benchmark's own keys (``round_checks``) are put there, not in the settings.
    ``camera_kind``: the cameras' (light-field: ``fast`` on several without a method is its plan for several
    light-field cameras, :data:`lfcore.reconstruct.SEVERAL_LIGHT_FIELD_CAMERAS`)."""
    name, _, rest = text.partition(";")
    changes = {}
    if name == "fast-plain":
        name, changes = "fast", {"coarse": 1, "subsets": 1}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        changes[key.strip()] = (float(value) if "." in value else int(value)) if value[:1].isdigit() else value
    if "round_checks" in changes:
        checks = changes.pop("round_checks")
        if extras is not None:
            extras["round_checks"] = checks
    return text, protocol_settings(name, n_cameras=n_cameras, camera_kind=camera_kind, **changes)


def reset_peak_rss() -> bool:
    """Reset this process's peak resident memory (``VmHWM``, Linux 4.0 on), so that the next row's peak is
    its own; False where the kernel does not allow it (the peaks are then the process's so far)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _status_bytes(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0


def peak_rss() -> int:
    """This process's peak resident memory (since the last :func:`reset_peak_rss`), in bytes."""
    return _status_bytes("VmHWM:")


def rss() -> int:
    """This process's resident memory now, in bytes."""
    return _status_bytes("VmRSS:")


def memory_columns(res) -> str:
    """A row's memory columns: each operator's MiB (with the voxels made on the fly) and the peak RSS."""
    def mib(stage: str) -> str:
        held, fly = res.operator_sizes.get(stage, (0, 0))
        return f"{held / 2**20:.0f}" + (f" ({fly:,} on the fly)" if fly else "")
    return " | ".join([f"{mib('coarse operator')} / {mib('line-of-sight weights')} / {mib('DRT operator')}",
                       f"{res.peak_rss / 2**30:.2f} ({res.rss_before / 2**30:.2f})"])


def timed_frame(proj, settings, img, *, checkpoints=(), truth=None):
    """One frame: its result and per stage [wall s, CPU s] (the iterations' start counted as operators'
    time, as :class:`~lfcore.reconstruct.ReconResult` counts it).

    ``checkpoints``: iteration counts of the last :meth:`~FrameReconstructor.iterate` at which Q against
    ``truth`` is measured (on the volume of that iteration's intensities; its time is left out of every
    clock), returned as ``res.checkpoints`` {count: Q}. Meant for the chapter's protocol (no pruning, no
    subsets, a fixed count), where the volume after N of 400 iterations is the volume of N.
    """
    frames = FrameReconstructor(proj, settings)
    clock = {stage: [0.0, 0.0] for stage in STAGES}
    sizes: dict[str, tuple[int, int]] = {}  # operator bytes and voxels made on the fly, by stage
    coarse_clock = {stage: [0.0, 0.0] for stage in COARSE_STAGES}
    made = reconstruct_module.coarse_reconstructor

    def coarse_reconstructor(*a, **k):  # the coarse grid's reconstructor, its stages timed
        coarse = made(*a, **k)
        for stage, name in COARSE_STAGES.items():
            inner = getattr(coarse, name)

            def timed(*a2, _inner=inner, _stage=stage, **k2):
                w, c = time.perf_counter(), time.process_time()
                try:
                    out = _inner(*a2, **k2)
                    if _stage == "coarse operator":
                        sizes[_stage] = (int(out.nbytes), int(out.n_on_the_fly))
                    return out
                finally:
                    coarse_clock[_stage][0] += time.perf_counter() - w
                    coarse_clock[_stage][1] += time.process_time() - c
            setattr(coarse, name, timed)
        return coarse
    marks: dict[int, float] = {}
    left_out = [0.0, 0.0]  # wall, CPU seconds of the checkpoints' Q
    if checkpoints:
        iterate = frames.iterate

        def measured(op, *a, _iterate=iterate, **k):
            n, done = op.n_voxels, [0]

            def progress(step):
                done[0] += step
                if step == 1 and done[0] in checkpoints:
                    w, c = time.perf_counter(), time.process_time()
                    vol = frames.volume(op, frames._e[: max(n, 1)]).numpy().copy()
                    marks[done[0]] = metrics.q_recon(vol, truth)
                    left_out[0] += time.perf_counter() - w
                    left_out[1] += time.process_time() - c
            k["progress"] = progress
            return _iterate(op, *a, **k)
        frames.iterate = measured
    for stage, methods in STAGES.items():
        for name in methods:
            inner = getattr(frames, name)

            def wrapped(*a, _inner=inner, _stage=stage, **k):
                w, c = time.perf_counter(), time.process_time()
                try:
                    out = _inner(*a, **k)
                    if _stage == "DRT operator":
                        clock["DRT voxels"] = out.n_voxels
                    if _stage in ("line-of-sight weights", "DRT operator"):  # the largest of each kind
                        held = int(out.nbytes) if _stage == "line-of-sight weights" else frames.operator_bytes(out)
                        sizes[_stage] = max(sizes.get(_stage, (0, 0)), (held, int(out.n_on_the_fly)))
                    return out
                finally:
                    clock[_stage][0] += time.perf_counter() - w
                    clock[_stage][1] += time.process_time() - c
            setattr(frames, name, wrapped)
    reset_peak_rss()
    before = rss()
    w, c = time.perf_counter(), time.process_time()
    reconstruct_module.coarse_reconstructor = coarse_reconstructor
    try:
        res = frames.reconstruct(img)
    finally:
        reconstruct_module.coarse_reconstructor = made
    res.peak_rss, res.rss_before = peak_rss(), before
    total = [time.perf_counter() - w - left_out[0], time.process_time() - c - left_out[1]]
    for i in (0, 1):
        clock["iterations"][i] -= left_out[i]
        # the fine grid's elimination: the coarse grid's stages ran inside coarse_eliminate
        clock["elimination"][i] -= sum(v[i] for v in coarse_clock.values())
    clock.update(coarse_clock)
    # the stages nest (coarse_eliminate calls eliminate on another reconstructor, not this one's)
    drt = clock.pop("DRT voxels", 0)
    clock["other"] = [total[i] - sum(v[i] for v in clock.values()) for i in (0, 1)]
    res.drt_voxels = drt  # the voxels DRT's operator was made for
    res.checkpoints = marks
    res.operator_sizes = sizes
    return res, clock, total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="Mc")
    ap.add_argument("--device", default=None)
    ap.add_argument("--ppm", type=float, default=0.5)
    ap.add_argument("--rows", default="fixed,fast-plain,fast",
                    help="rows, separated by '|' or ',' between protocol names (see the module docstring)")
    ap.add_argument("--reference-iterations", type=int, default=40,
                    help="iterations of the chapter's protocol to time (scaled to its 400); 0: no reference")
    ap.add_argument("--checkpoints", default="",
                    help="iteration counts of the reference at which its Q is measured too (e.g. 20,50,100,200,400; "
                         "its time left out), for the best Q it reaches at any count")
    ap.add_argument("--noise", default="1",
                    help="images: comma-separated noise factors, each F or F+response (e.g. 1,3,3+response); every "
                         "row runs on each, the reference on the first")
    ap.add_argument("--response", action="store_true", help="a camera's response on every --noise item's images")
    ap.add_argument("--warm-case", default=None,
                    help="the case whose frames compile the kernels before the rows (default: --case's own; e.g. S "
                         "for Lc, whose plain plan's DRT operator would not fit)")
    args = ap.parse_args()
    checkpoints = tuple(int(c) for c in args.checkpoints.split(",") if c)
    device = resolve_device(args.device)
    bench = _recon_bench()
    rig, _ = bench.case_rig(args.case)
    items = [x.strip() for x in args.noise.split(",") if x.strip()]
    images = {}
    for item in items:
        changes = render_changes(item, rig.render, response=args.response)
        _, _, cams, grid, pts, images[item] = bench.scene(args.case, device, args.ppm, render_changes=changes)
    img = images[items[0]]
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(cams, grid, device=device)
    print(f"case {args.case}: grid {grid.shape} (z, y, x), {len(pts)} particles ({args.ppm:g} PPM), device {device}; "
          f"images: " + ", ".join(f"{k}: {render_changes(k, rig.render, response=args.response)}" for k in items))
    # the kernels compiled (and the first-call costs paid) before anything is timed: on the case's own
    # frame, or on --warm-case's where a whole-grid DRT operator of the case would not fit
    w_proj, w_img = proj, img
    if args.warm_case and args.warm_case != args.case:
        _, _, w_cams, w_grid, _, w_img = bench.scene(args.warm_case, device, args.ppm)
        w_proj = projector_for(w_cams, w_grid, device=device)
    for method in ("drt-mart", "mlos-mart"):
        FrameReconstructor(w_proj, protocol_settings("fixed", method=method, iterations=2)).reconstruct(w_img)
    FrameReconstructor(w_proj, protocol_settings("fast", iterations=4, los_iterations=2, stop_tolerance=0.0,
                                                 coarse=3, coarse_iterations=2)).reconstruct(w_img)
    del w_proj, w_img
    texts = args.rows.split("|") if "|" in args.rows else args.rows.split(",")
    extras = [{} for _ in texts]
    rows = [parse_row(r, len(cams), extras=x) for r, x in zip(texts, extras, strict=True)]
    projectors = {None: proj}  # by sub_apertures
    round_checks = projector_module.ROUND_CHECKS
    print("| row | images | iterations | stopped | Q | voxels active / DRT / left | elimination s wall (CPU) | "
          "line-of-sight weights s | DRT operator s | iterations s | coarse grid: elimination + operator + "
          "iterations CPU s | other s | total s wall (CPU) | CPU / reference's | operator | operators MiB: coarse / "
          "line-of-sight / DRT | peak RSS GiB (before the row) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    ref_cpu = None
    if args.reference_iterations:
        n = args.reference_iterations
        res, clock, total = timed_frame(proj, protocol_settings("chapter", iterations=n, projector="stored"), img,
                                        checkpoints=checkpoints, truth=truth)
        scale = 400 / n
        for i in (0, 1):
            total[i] += (scale - 1) * clock["iterations"][i]
            clock["iterations"][i] *= scale
        ref_cpu = total[1]
        q = f"{metrics.q_recon(res.volume, truth):.3f}" + ("" if n == 400 else f" (at {n})")
        label = "chapter (reference)" + ("" if n == 400 else f", {n} iterations timed, x{scale:g}")
        print(f"| {label} | {items[0]} | 400 | fixed count | {q} | {res.active_voxels:,} / {res.drt_voxels:,} / "
              f"{res.final_voxels:,} | {stage_columns(clock)} | {total[0]:.1f} ({total[1]:.1f}) | 1 | "
              f"{res.operator} | {memory_columns(res)} |", flush=True)
        if res.checkpoints:
            best = max(res.checkpoints, key=res.checkpoints.get)
            print("reference Q at " + ", ".join(f"{k}: {q:.3f}" for k, q in sorted(res.checkpoints.items()))
                  + f"; best {res.checkpoints[best]:.3f} at {best}", flush=True)
    for item in items:
        for (label, settings), extra in zip(rows, extras, strict=True):
            if settings.sub_apertures not in projectors:
                projectors[settings.sub_apertures] = projector_for(cams, grid, sub_apertures=settings.sub_apertures,
                                                                   device=device)
            projector_module.ROUND_CHECKS = extra.get("round_checks", round_checks)
            try:
                res, clock, total = timed_frame(projectors[settings.sub_apertures], settings, images[item])
            finally:
                projector_module.ROUND_CHECKS = round_checks
            q = metrics.q_recon(res.volume, truth)
            ratio = f"1/{ref_cpu / total[1]:.1f}" if ref_cpu else ""
            print(f"| {label} | {item} | {res.iterations} | {res.stopped} | {q:.3f} | {res.active_voxels:,} / "
                  f"{res.drt_voxels:,} / {res.final_voxels:,} | {stage_columns(clock)} | {total[0]:.1f} "
                  f"({total[1]:.1f}) | {ratio} | {res.operator} | {memory_columns(res)} |", flush=True)


def stage_columns(clock: dict) -> str:
    """The stages' columns of a row: wall (CPU) s of each, the coarse grid's three stages' CPU s summed."""
    coarse = " + ".join(f"{clock[s][1]:.1f}" for s in COARSE_STAGES)
    cols = [f"{clock[s][0]:.1f} ({clock[s][1]:.1f})" for s in STAGES]
    return " | ".join([*cols, coarse, f"{clock['other'][0]:.1f} ({clock['other'][1]:.1f})"])


if __name__ == "__main__":
    main()
