"""What a run store or a calibration store holds (``lfpiv info``)."""

from __future__ import annotations

from pathlib import Path

from calibration.store import CalibrationStore, CalibrationStoreError, UnfinishedCalibrationError
from lfcore.mla import lenslet_count
from lfcore.plan import Plan, PlanError
from lfcore.rig import is_pinhole
from lfcore.runstore import RunStore, RunStoreError
from lfcore.volume import VolumeGrid

__all__ = ["describe"]


def _fmt_params(params: dict) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, list):
            return "(" + ", ".join(fmt(x) for x in v) + ")"
        return str(v)

    return ", ".join(f"{k}={fmt(v)}" for k, v in params.items() if k != "name")


def _count(pairs: list[int]) -> str:
    """``"3 pair(s) (0 to 2)"``, or ``"no pair"``."""
    if not pairs:
        return "no pair"
    span = f"{pairs[0]}" if len(pairs) == 1 else f"{pairs[0]} to {pairs[-1]}"
    return f"{len(pairs)} pair(s) ({span})"


def _windows(windows: list[list[int]]) -> str:
    """``"32x32x16 then 16x16x8"``: the window sizes of every pass."""
    return " then ".join("x".join(map(str, w)) for w in windows)


def _projector(asked: str, operator: dict | None) -> str:
    """``"projector matrix-free, operator 35.1 MiB, 29.5 ms per iteration"``: the projector asked
    for (with what ran, where ``auto`` chose) and the operator's figures of ``volumes/``
    (:func:`lfpiv.jobs.reconstruct.operator_figures`; volumes made before they were recorded
    have none, and say only the projector)."""
    if not isinstance(operator, dict) or not operator.get("frames"):
        return f"projector {asked}"
    ran = operator.get("projector") or asked
    return (f"projector {asked}{f' ({ran})' if ran != asked else ''}, operator "
            f"{float(operator.get('bytes', 0)) / 2**20:.1f} MiB, {float(operator.get('ms_per_iteration', 0.0)):.1f} "
            "ms per iteration")


def _warm(settings: dict) -> str:
    """``" (frames B warm-started by their own pair: 10)"``: what the warm start did, by which predictor
    (``warm_predictor``: ``own``, or ``last``, the last pair's field, which volumes recorded before the
    setting existed used), or ``""``."""
    if not settings.get("warm_start"):
        return ""
    from lfcore.reconstruct import warm_count

    its, warm = settings.get("iterations"), settings.get("warm_iterations")
    n = warm_count(its, warm) if isinstance(its, int) and (warm is None or isinstance(warm, int)) else "?"
    by = "their own pair" if settings.get("warm_predictor", "last") == "own" else "the last pair"
    return f" (frames B warm-started by {by}: {n})"


def _iterations(settings: dict) -> str:
    """``"50 iterations"``, or ``"at most 400 iterations (stopping rule)"``."""
    its, tol = settings.get("iterations"), settings.get("stop_tolerance") or 0
    return f"at most {its} iterations (stopping rule)" if isinstance(tol, (int, float)) and tol > 0 else \
        f"{its} iterations"


def _convergence(figures: object, settings: dict) -> str:
    """What the frames' iterations took (:func:`lfpiv.jobs.reconstruct.convergence_figures`), or ``""``
    for volumes made before it was recorded (or a damaged record)."""
    if not isinstance(figures, dict) or not figures.get("frames"):
        return ""
    from lfpiv.jobs.reconstruct import describe_convergence

    tol, its = settings.get("stop_tolerance") or 0.0, settings.get("iterations")
    try:
        return describe_convergence(figures, float(tol), int(its) if isinstance(its, int) else 0)
    except (TypeError, ValueError, IndexError):
        return ""


def _plan(recorded: object, operator: object) -> str:
    """``"auto on cpu, weight cache, in memory; ran traced weights"``: the plan the volumes were made
    by (:class:`lfcore.plan.Plan`) and the operators that ran; ``""`` for volumes made before plans
    were recorded (or a damaged record)."""
    if not isinstance(recorded, dict):
        return ""
    try:
        plan = Plan.from_dict(recorded)
    except PlanError:
        return ""
    ran = operator.get("operators") if isinstance(operator, dict) else None
    return plan.summary() + (f"; ran {', '.join(map(str, ran))}" if isinstance(ran, list) and ran else "")


def describe(path: str | Path) -> list[str]:
    """The lines ``lfpiv info`` prints: a run's cameras, pairs, flow, state and derived data, or
    what a calibration store holds (as ``lfpiv calibrate report``).

    Raises
    ------
    RunStoreError
        ``path`` is neither a run store nor a calibration store.
    """
    try:
        store = RunStore.open(path)
    except RunStoreError as not_a_run:
        try:
            calibration = CalibrationStore.open(path)
        except UnfinishedCalibrationError:
            raise  # a calibration store, but not one yet: say so
        except CalibrationStoreError:
            raise not_a_run from None
        return list(calibration.summary())
    a = store.attrs
    rig = store.rig
    t = store.timing
    grid = VolumeGrid.from_rig(rig)
    v = rig.volume
    lines = [
        ("run", str(store.path)),
        ("state", f"{store.state} ({store.committed_pairs} of {store.n_pairs} pairs committed)"),
        ("created", f"{a.get('created')} by lfpiv {a.get('software_version')}"),
        ("timing", (f"dt {t['dt_s'] * 1e3:g} ms, " if t.get("dt_s") else "dt unknown, ")
                   + (f"pairs at {t['rate_hz']:g} Hz" if t.get("rate_hz") else "pair rate unknown")),
        ("volume", f"{' x '.join(f'{s:g}' for s in v.size_mm)} mm centred at "
                   f"({', '.join(f'{c:g}' for c in v.centre_mm)}); {' x '.join(str(n) for n in grid.shape[::-1])} "
                   f"voxels (x, y, z) at PVR ({', '.join(f'{p:g}' for p in v.pvr)})"),
    ]
    for cam in rig.camera:
        rotation = f"rotation ({', '.join(f'{r:g}' for r in cam.rotation_deg)}) deg"
        if is_pinhole(cam):
            lines.append(("camera", f"{cam.name}: pinhole, {cam.sensor_px[0]} x {cam.sensor_px[1]} px of "
                                    f"{cam.pixel_pitch_um:g} um, F {cam.focal_length_mm:g} mm, "
                                    f"M {cam.magnification:.5g} "
                                    f"({cam.object_pixel_mm * 1e3:.4g} um per pixel in the volume), {rotation}"))
            continue
        lines.append(("camera", f"{cam.name}: {cam.sensor_px[0]} x {cam.sensor_px[1]} px of {cam.pixel_pitch_um:g} um, "
                                f"{cam.mla_grid} MLA {cam.mla_pitch_um:g} um ({lenslet_count(cam)} lenslets, "
                                f"{cam.pixels_per_lenslet:.1f} px across), F {cam.main_focal_length_mm:g} mm "
                                f"f/{cam.f_number:g}, M {cam.magnification:g}, {rotation}"))
    truth = store.truth()
    if truth:
        flow = truth["attrs"]["flow"]
        lines.append(("flow", f"{flow['name']}: {_fmt_params(flow)}"))
        ppm, ppp = truth["attrs"].get("ppm"), truth["attrs"].get("ppp")
        lines.append(("truth", f"{truth['particles'].shape[2]} particles per frame"
                               + (f" ({ppm:g} PPM)" if ppm else f" ({ppp:g} ppp)" if ppp else "")
                               + f", seed {truth['attrs'].get('seed')}"))
    else:
        lines.append(("flow", "unknown (recorded run, no truth)"))
    made = a.get("import")
    if made:
        cams = made.get("plan", {}).get("cameras", {})
        lines.append(("imported", f"{len(made.get('sources', []))} file(s) ({made.get('plan', {}).get('layout')} "
                                  f"layout) from " + "; ".join(f"{n}: {c.get('pattern')}" for n, c in cams.items())))
    if a.get("abort_reason"):
        lines.append(("aborted", str(a["abort_reason"])))
    drops = store.drops()
    lines.append(("drops", "none" if not drops else f"{len(drops)} frame(s) lost, e.g. {drops[0]['reason']}"))
    w = store.writer
    if w:
        lines.append(("writer", f"being written by pid {w.get('pid')} on {w.get('host')} ({w.get('command')!r}, since "
                                f"{w.get('since')})"))
    if store.has_volumes:
        va = store.volume_attrs()
        g = store.volume_grid()
        lines.append(("volumes", f"{_count(store.reconstructed_pairs())} reconstructed by {va['method']}, "
                                 f"{_iterations(va['settings'])}{_warm(va['settings'])}, "
                                 f"{' x '.join(str(n) for n in g.shape[::-1])} voxels, "
                                 f"{_projector(va['settings'].get('projector', 'auto'), va.get('operator'))}"))
        plan = _plan(va.get("plan"), va.get("operator"))
        if plan:
            lines.append(("plan", plan))
        went = _convergence(va.get("convergence"), va["settings"])
        protocol = va["settings"].get("protocol")
        if went or protocol:
            lines.append(("frames", (f"protocol {protocol}: " if protocol else "") + (went or "not recorded")))
        from lfpiv.jobs.reconstruct import stages_of

        stages = stages_of(va.get("plan"))
        if stages:
            lines.append(("stages", stages))
    else:
        lines.append(("volumes", f"none (lfpiv reconstruct {store.path})"))
    if store.has_vectors:
        windows = store.vector_attrs()["windows"]
        lines.append(("vectors", f"{_count(store.correlated_pairs())} correlated, windows "
                                 f"{_windows(windows)}"
                                 + ("; from volumes since replaced" if store.vectors_outdated else "")))
    if store.has_particles:
        pa = store.group["particles"].attrs
        n_rows = store.group["particles"]["table"].shape[0]
        ps = pa.get("settings", {})
        # the fit's weights and residual mask as recorded (auto's choice; a group written before they
        # existed was fitted flat with no mask)
        fit = f"{ps.get('noise_model', 'flat')} fit, residual mask {float(ps.get('residual_mask', 0.0)):g}"
        lines.append(("particles", f"{_count(store.particle_pairs())} reconstructed ({pa.get('method')} IPR, "
                                   f"{ps.get('rounds')} round(s), {fit}), {n_rows:,} particle rows"))
    for name, command in (("volumes", "reconstruct"), ("vectors", "correlate"), ("particles", "particles")):
        pending = store.pending(name)
        if pending is not None:
            try:
                a = store.volume_attrs(group=pending) if name == "volumes" else store.vector_attrs(group=pending)
            except RunStoreError as exc:  # an unfinished replacement, damaged: said, and the rest shown
                lines.append((f"{name}.pending", f"an unfinished replacement, damaged: {exc}"))
                continue
            made = (f"{a.get('method')}, {a.get('settings', {}).get('iterations')} iterations" if name == "volumes"
                    else f"windows {_windows(a.get('windows', []))}" if name == "vectors"
                    else f"{a.get('method')} IPR")
            stale = name == "vectors" and a.get("volumes_id") != store.volumes_id
            lines.append((f"{name}.pending", f"a replacement ({made}) interrupted after "
                                             f"{_count(a.get(RunStore.DONE[name], []))}; "
                          + ("it was correlated from volumes since replaced, and the next correlate drops it"
                             if stale else f"it takes the place of {name}/ once the same settings are given "
                                           f"again with --skip-done")))
        if store.replaced_left(name):
            lines.append((f"{name}.replaced", f"a replacement interrupted as it was put in place; the next "
                                              f"'lfpiv {command}' of this run settles it"))
    width = max(len(k) for k, _ in lines)
    return [f"{k:<{width}}  {val}" for k, val in lines]
