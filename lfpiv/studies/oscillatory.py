"""``lfpiv study oscillatory``: Table 4.1's unsteady oscillatory flows, end to end (Figs. 4.11-4.14),
and the accuracy goals of one and two cameras.

Each case renders pairs of a Table 4.1 flow, reconstructs both frames, correlates them by the
multi-grid correlation and measures the displacement error of every vector against the flow at
its window's centre at mid-pair time, in voxels of the case's grid and in object-side pixels.

The flows keep the chapter's proportions at every scale: the chapter's amplitude is 25 pixels
against a final window of 160 (0.156 of the window along the oscillating component) and its
wavelength omega x 1820 pixels, 11.4 final windows at omega = 1. lfpiv's cases A1-B4 have a
wavelength of omega times the volume's width (:mod:`lfcore.flows`), so a case's ``omega`` here is
the chapter's, and the flow is made with the omega that gives the same wavelength in windows.
The windows are the same in voxels for every PVR of a figure (the chapter's point: a finer PVR
puts fewer particles in a window), and the flow is the same in millimetres.

Controls, from known truths: a still pair (the particles of frame A again in frame B, other
noise) must give zero displacement; the true particles drawn as volumes (a perfect
reconstruction) and correlated the same way give the error the correlation itself leaves, so the
rest is the reconstruction's.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lfcore import metrics
from lfcore.correlate import CorrelationConfig
from lfcore.flows import Uniform
from lfcore.reconstruct import ReconSettings
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfpiv.studies import figures, rigs
from lfpiv.studies.pipeline import Pair, Reconstructor, Scene, correlate_pair
from lfpiv.studies.runner import Case, Finding, Setup, Study

NAMES = {"drt-mart": "DRT-MART", "mart": "MART", "mlos-mart": "MLOS-MART", "truth": "true particles"}
CASES_A = ("A1", "A2", "A3", "A4")
CASES_B = ("B1", "B2", "B3", "B4")
#: The chapter's amplitude over its final window (25 of 160 pixels) and wavelength over it at
#: omega = 1 (1820 of 160 pixels).
AMPLITUDE_PER_WINDOW = 25.0 / 160.0
WAVELENGTH_PER_WINDOW = 1820.0 / 160.0
#: The accuracy goals (RMS displacement error, voxels, x y z): one camera, two at 90 degrees.
GOALS = {"single": (0.1, 0.1, 0.3), "dual": (0.1, 0.1, 0.1)}
SEED = 14

#: Per scale. ``windows``: the passes (x, y, z voxels) on the one-camera and the two-camera rigs;
#: ``equal_time``: DRT-MART and MART iterations in the same time (Figs. 4.13-4.14); ``iterations``:
#: the counts of Fig. 4.12; ``pvr_xy`` and ``pvr_z``: Fig. 4.11's; ``pairs`` of each case and of
#: the goals.
PROTOCOL = {
    "tiny": {"windows": {"single": ((32, 32, 16), (16, 16, 16)), "dual": ((24, 24, 24), (16, 16, 16))},
             "overlap": 0.75, "equal_time": (5, 2), "iterations": [2, 5], "pvr_xy": [2, 3], "pvr_z": [10, 20],
             "omegas": [1.0], "pairs": 1, "goal_pairs": 1, "cases": ("A1", "A4", "B1", "B4")},
    "quick": {"windows": {"single": ((64, 64, 16), (32, 32, 16)), "dual": ((48, 48, 48), (32, 32, 32))},
              "overlap": 0.75, "equal_time": (100, 12), "iterations": [25, 50, 100, 200], "pvr_xy": [1, 2, 3],
              "pvr_z": [5, 10, 20], "omegas": [0.5, 1.0], "pairs": 1, "goal_pairs": 4},
    "chapter": {"windows": {"single": ((320, 320, 32), (160, 160, 16)), "dual": ((128, 128, 128), (64, 64, 64))},
                "overlap": 0.75, "equal_time": (200, 23), "iterations": [25, 50, 100, 200, 400], "pvr_xy": [1, 2, 3],
                "pvr_z": [5, 10, 20], "omegas": [0.25, 0.5, 1.0, 2.0], "pairs": 2, "goal_pairs": 4},
}


def _rig(setup: Setup, kind: str, pvr: list[float] | None, focus: str = "rig") -> Rig:
    """The case's rig: one camera or two, at ``pvr`` (None: the rig's), the focal planes where the
    rig has them or (``focus="faces"``) on the volume's faces nearest the cameras."""
    rig = rigs.dual_rig(setup.rig, setup.scale) if kind == "dual" else rigs.single_rig(setup.rig, setup.scale)
    if setup.scale == "quick" and setup.rig is None and kind == "single":
        # the tiny rig's own depth: Table 4.1's many cases at a cost a laptop affords (+-3.6 lenslets)
        d = rig.to_dict()
        d["volume"]["size_mm"] = [0.9, 0.75, 1.6]
        rig = Rig.from_dict(d)
    if pvr is not None:
        d = rig.to_dict()
        d["volume"]["pvr"] = list(pvr)
        rig = Rig.from_dict(d)
    return rigs.focus_at_near_faces(rig) if focus == "faces" else rig


def _pvr_key(case: str, axes: str, value: float, pvr: tuple[float, float, float]) -> str:
    """The case of Fig. 4.11 at PVR ``value`` along ``axes`` (the omega-1 case at the rig's own)."""
    own = pvr[0] if axes == "xy" else pvr[2]
    return f"{case}_w1_drt" if value == own else f"{case}_pvr{axes}{value:g}_drt"


def _flow_scale(rig: Rig, base_pvr: tuple[float, ...], window: tuple[int, int, int], case: str,
                omega: float) -> tuple[float, float]:
    """(displacement in object-side pixels, lfpiv's omega) of a case: the chapter's amplitude and
    wavelength in final windows of the rig's base PVR."""
    axis = 0 if case[0] == "A" else 2  # the oscillating component
    window_px = window[axis] * base_pvr[axis]
    pix = rig.camera[0].object_pixel_mm
    wavelength_mm = omega * WAVELENGTH_PER_WINDOW * window[0] * base_pvr[0] * pix
    return AMPLITUDE_PER_WINDOW * window_px, wavelength_mm / rig.volume.size_mm[0]


class OscillatoryStudy(Study):
    name = "oscillatory"
    title = "displacement errors of Table 4.1's oscillatory flows"
    figures = "Table 4.1 and Figs. 4.11-4.14"

    def plan(self, setup: Setup) -> list[Case]:
        p = PROTOCOL[setup.scale]
        nd, nm = p["equal_time"]
        base = {"omega": 1.0, "rig": "single", "pvr": None, "pairs": p["pairs"], "still": False, "bound": False,
                "focus": "rig"}
        cases: list[Case] = []

        def add(key: str, **kw: Any) -> None:
            cases.append(Case(key, {**base, **kw}))

        # controls and the accuracy goals
        add("still", flow="A1", method="drt-mart", iterations=[nd], still=True)
        add("goal_single", flow="A1", method="drt-mart", iterations=[nd], pairs=p["goal_pairs"], bound=True)
        add("goal_dual", flow="A1", rig="dual", method="drt-mart", iterations=[nd], pairs=p["goal_pairs"], bound=True)
        # the same with the focal planes on the volume's faces: the focal-plane limit moved out
        for kind in GOALS:
            add(f"goal_{kind}_faces", flow="A1", rig=kind, method="drt-mart", iterations=[nd], pairs=p["goal_pairs"],
                focus="faces")
        # Figs. 4.13 and 4.14: every case, DRT-MART against MART in the same time
        for omega in p["omegas"]:
            for case in p.get("cases", (*CASES_A, *CASES_B)):
                add(f"{case}_w{omega:g}_drt", flow=case, omega=omega, method="drt-mart", iterations=[nd],
                    bound=case in ("A1", "B1") and omega == 1.0)
                add(f"{case}_w{omega:g}_mart", flow=case, omega=omega, method="mart", iterations=[nm])
        # Fig. 4.11: PVR in x and y (A1), in z (B1); at the rig's own PVR the omega-1 cases serve
        pvr = _rig(setup, "single", None).volume.pvr
        for v in p["pvr_xy"]:
            if v != pvr[0] or 1.0 not in p["omegas"]:
                add(_pvr_key("A1", "xy", v, pvr), flow="A1", method="drt-mart", iterations=[nd], pvr="xy",
                    pvr_value=v)
        for v in p["pvr_z"]:
            if v != pvr[2] or 1.0 not in p["omegas"]:
                add(_pvr_key("B1", "z", v, pvr), flow="B1", method="drt-mart", iterations=[nd], pvr="z",
                    pvr_value=v)
        if 1.0 not in p["omegas"]:
            add("A1_w1_mart", flow="A1", method="mart", iterations=[nm])
        # Fig. 4.12: RMS against iterations
        for case in ("A1", "B1"):
            add(f"{case}_iterations", flow=case, method="drt-mart", iterations=p["iterations"])
        return cases

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        p = PROTOCOL[setup.scale]
        base = _rig(setup, params["rig"], None)
        base_pvr = tuple(base.volume.pvr)
        pvr = None
        if params["pvr"] == "xy" and params.get("pvr_value") is not None:
            pvr = [params["pvr_value"], params["pvr_value"], base_pvr[2]]
        elif params["pvr"] == "z":
            pvr = [base_pvr[0], base_pvr[1], params["pvr_value"]]
        rig = _rig(setup, params["rig"], pvr, params["focus"])
        grid = VolumeGrid.from_rig(rig)
        disp_px, omega = _flow_scale(base, base_pvr, p["windows"][params["rig"]][-1], params["flow"], params["omega"])
        windows = _fitted(p["windows"][params["rig"]], grid.shape)
        config = CorrelationConfig(windows=windows, overlap=p["overlap"])
        scene = Scene(rig, flow=params["flow"], ppm=0.5, displacement_px=disp_px, omega=omega, seed=SEED, device=device)
        flow = Uniform((0.0, 0.0, 0.0)) if params["still"] else scene.flow
        rec = Reconstructor(rig.camera, grid, render=rig.render, device=device, cache=True)
        errors: dict[str, list[np.ndarray]] = {str(n): [] for n in params["iterations"]}
        bound: list[np.ndarray] = []
        same: list[np.ndarray] = []
        z_of: list[np.ndarray] = []
        seconds = 0.0
        for k in range(params["pairs"]):
            pair = scene.pair(k)
            if params["still"]:  # frame B shows frame A's particles again, with noise of its own
                pair = _still(scene, pair)
            for its in params["iterations"]:
                settings = ReconSettings.chapter(method=params["method"], iterations=its)
                vols = []
                for f in (0, 1):
                    res, s = rec(pair.frame(f), settings)
                    vols.append(res.volume)
                    seconds += s
                v = correlate_pair(*vols, grid, config, flow=flow, t0_s=pair.t0_s, dt_s=scene.dt_s, device=device)
                errors[str(its)].append(v.error.reshape(-1, 3))
                if params["still"]:  # the very same image twice: the whole chain must give exactly nothing
                    again, _ = rec(pair.frame(0), settings)
                    vs = correlate_pair(vols[0], again.volume, grid, config, flow=flow, t0_s=pair.t0_s,
                                        dt_s=scene.dt_s, device=device)
                    same.append(vs.error.reshape(-1, 3))
            z_of.append(np.broadcast_to(v.z_mm[:, None, None], v.field.shape).ravel())
            if params["bound"]:
                tv = [metrics.truth_volume(grid, pair.particles[f], brightness=pair.brightness[f]) for f in (0, 1)]
                vb = correlate_pair(*tv, grid, config, flow=flow, t0_s=pair.t0_s, dt_s=scene.dt_s, device=device)
                bound.append(vb.error.reshape(-1, 3))
        pvr_now = np.asarray(rig.volume.pvr)
        out = {"voxel_px": list(pvr_now), "windows": [list(w) for w in windows], "displacement_px": disp_px,
               "lfpiv_omega": omega, "particles": int(scene.world.n_particles), "seconds": seconds,
               "vectors": int(len(errors[str(params["iterations"][0])][0])) if params["pairs"] else 0,
               "depth_lenslets": (np.concatenate(z_of) - rig.camera[0].focus_mm[2])
               / rig.camera[0].depth_per_lenslet_mm,
               "errors": {n: np.round(np.concatenate(e), 5) for n, e in errors.items()}}
        out["rms"] = {n: _rms(e) for n, e in out["errors"].items()}
        out["bias"] = {n: np.nanmean(e, axis=0) for n, e in out["errors"].items()}
        if bound:
            out["bound_rms"] = _rms(np.concatenate(bound))
        if same:
            out["same_image_rms"] = _rms(np.concatenate(same))
        return out

    # --- the table and the figure ---------------------------------------------------------------
    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        plan = {c.key: c.params for c in self.plan(setup)}
        rows = []
        for key, r in results.items():
            prm = plan[key]
            for its, rms in r["rms"].items():
                row = {"case": key, "flow": "still" if prm["still"] else prm["flow"], "omega": prm["omega"],
                       "lfpiv_omega": r["lfpiv_omega"], "rig": prm["rig"],
                       "pvr": ",".join(f"{v:g}" for v in r["voxel_px"]),
                       "method": prm["method"], "iterations": int(its), "pairs": prm["pairs"],
                       "vectors": r["vectors"] * prm["pairs"], "displacement_px": r["displacement_px"]}
                for i, a in enumerate("xyz"):
                    row[f"rms_{a}_vox"] = rms[i]
                    row[f"rms_{a}_px"] = rms[i] * r["voxel_px"][i]
                    row[f"bias_{a}_vox"] = r["bias"][its][i]
                for i, a in enumerate("xyz"):
                    row[f"bound_rms_{a}_vox"] = r["bound_rms"][i] if "bound_rms" in r else None
                rows.append(row)
        return rows

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        p = PROTOCOL[setup.scale]
        fig, ax = figures.panels(4, 4, title=f"Table 4.1 and Figs. 4.11-4.14 at --scale {setup.scale}")
        edges = np.linspace(-1.5, 1.5, 61)
        mid = 0.5 * (edges[1:] + edges[:-1])

        def err(key: str, axis: int, its: str | None = None) -> np.ndarray:
            r = results[key]
            e = np.asarray(r["errors"][its or next(iter(r["errors"]))], dtype=float)
            return e[:, axis]

        # Fig. 4.11a: A1, x and y errors at each PVR (in pixels, one scale for every PVR)
        a = ax[0, 0]
        pvr = results["A1_w1_mart"]["voxel_px"]
        for v in p["pvr_xy"]:
            key = _pvr_key("A1", "xy", v, pvr)
            e = np.concatenate([err(key, 0), err(key, 1)]) * v
            a.plot(mid, figures.pdf(e, edges), label=f"DRT-MART, PVR {v:g}")
        r = results["A1_w1_mart"]
        e = np.concatenate([err("A1_w1_mart", 0), err("A1_w1_mart", 1)]) * r["voxel_px"][0]
        a.plot(mid, figures.pdf(e, edges), "--", color=figures.METHOD_COLOURS["mart"],
               label=f"MART, PVR {r['voxel_px'][0]:g}")
        a.set_xlabel("displacement error in x and y (pixels)")
        a.set_ylabel("PDF")
        a.legend(fontsize=7)
        figures.label(a, "a", "A1: x and y error against PVR (Fig. 4.11a)")
        a = ax[0, 1]
        for v in p["pvr_z"]:
            a.plot(mid * 10, figures.pdf(err(_pvr_key("B1", "z", v, pvr), 2) * v, edges * 10),
                   label=f"DRT-MART, PVR z {v:g}")
        a.set_xlabel("displacement error in z (pixels)")
        a.set_ylabel("PDF")
        a.legend(fontsize=7)
        figures.label(a, "b", "B1: z error against PVR (Fig. 4.11b)")
        # Fig. 4.12: RMS against iterations, x (A1) and z (B1)
        for k, (case, axis) in enumerate((("A1", 0), ("B1", 2))):
            a = ax[0, 2 + k]
            r = results[f"{case}_iterations"]
            its = [int(n) for n in r["rms"]]
            a.plot(its, [r["rms"][str(n)][axis] for n in its], "o-", color=figures.METHOD_COLOURS["drt-mart"])
            figures.log_x(a)
            a.set_xlabel("iterations")
            a.set_ylabel(f"RMS error in {'xz'[k]} (voxels)")
            a.set_ylim(bottom=0)
            figures.label(a, "cd"[k], f"{case}: RMS error in {'xz'[k]} against iterations (Fig. 4.12)")
        # Figs. 4.13 and 4.14: every case at omega = 1, DRT-MART against MART
        omega = 1.0 if 1.0 in p["omegas"] else p["omegas"][0]
        chosen = p.get("cases", (*CASES_A, *CASES_B))
        for row, (cases, axis) in enumerate(((CASES_A, 0), (CASES_B, 2))):
            for k, case in enumerate(cases):
                a = ax[1 + row, k]
                if case not in chosen:
                    a.axis("off")
                    continue
                for w in p["omegas"]:
                    for m, ls in (("drt", "-"), ("mart", "--")):
                        key = f"{case}_w{w:g}_{m}"
                        method = "drt-mart" if m == "drt" else "mart"
                        alpha = 1.0 if w == omega else 0.45
                        a.plot(mid, figures.pdf(err(key, axis), edges), ls, color=figures.METHOD_COLOURS[method],
                               alpha=alpha, label=f"{NAMES[method]}, omega {w:g}")
                a.set_xlabel(f"displacement error in {'xz'[row]} (voxels)")
                a.set_ylabel("PDF")
                a.legend(fontsize=6)
                figures.label(a, "efgh"[k] if row == 0 else "ijkl"[k],
                              f"{case} (Fig. {'4.13' if row == 0 else '4.14'})")
        # the accuracy goals: RMS error against depth, and against the goals
        goals = [(k, f"goal_{k}{f}") for k in GOALS for f in ("", "_faces")]
        for col, axis in enumerate((0, 2)):
            a = ax[3, col]
            for n, (kind, key) in enumerate(goals):
                r = results[key]
                e = np.asarray(next(iter(r["errors"].values())), dtype=float)[:, axis]
                dl = np.round(np.asarray(r["depth_lenslets"], dtype=float), 3)
                planes = np.unique(dl)
                a.plot(planes, [np.sqrt(np.nanmean(e[dl == z] ** 2)) for z in planes], "o-" if kind == "dual" else
                       "s--", color=f"C{n}", label=f"{kind}, focus {'on the faces' if 'faces' in key else 'centred'}")
            a.axhline(GOALS["dual"][axis] if axis == 0 else GOALS["single"][axis], color="0.4", ls=":")
            a.set_xlabel("depth of the vectors from camera 0's focal plane (lenslets)")
            a.set_ylabel(f"RMS error in {'xz'[col]} (voxels)")
            a.legend(fontsize=6)
            figures.label(a, "mn"[col], f"A1 goals: error in {'xz'[col]} against depth (ours)")
        a = ax[3, 2]
        width = 0.8 / len(goals)
        for n, (kind, key) in enumerate(goals):
            e = np.asarray(next(iter(results[key]["rms"].values())), dtype=float)
            a.bar(np.arange(3) + n * width, e, width, color=f"C{n}",
                  label=f"{kind}, focus {'on the faces' if 'faces' in key else 'centred'}")
        for kind, ls in (("single", "--"), ("dual", ":")):
            a.hlines(GOALS[kind], np.arange(3) - 0.1, np.arange(3) + 0.9, colors="0.3", linestyles=ls)
        a.set_xticks(np.arange(3) + 0.4, ["x", "y", "z"])
        a.set_ylabel("RMS displacement error (voxels)")
        a.legend(fontsize=6)
        figures.label(a, "o", "A1 at 0.5 PPM against the goals (lines)")
        a = ax[3, 3]
        for n, (kind, key) in enumerate(goals):
            e = np.asarray(next(iter(results[key]["errors"].values())), dtype=float)
            a.plot(mid, figures.pdf(e[:, 0], edges), color=f"C{n}",
                   label=f"{kind}, focus {'on the faces' if 'faces' in key else 'centred'}")
        a.set_xlabel("displacement error in x (voxels)")
        a.set_ylabel("PDF")
        a.legend(fontsize=6)
        figures.label(a, "p", "A1 goals: x error (ours)")
        figures.save(fig, path)

    # --- the findings ---------------------------------------------------------------------------
    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        p = PROTOCOL[setup.scale]
        out = []

        def rms(key: str) -> np.ndarray:
            return np.asarray(next(iter(results[key]["rms"].values())), dtype=float)

        # Fig. 4.11a: DRT-MART better than MART at PVR 2; PVR 1 and 2 alike
        pvr = results["A1_w1_mart"]["voxel_px"]
        base = pvr[0]
        d_base, m_base = rms("A1_w1_drt"), rms("A1_w1_mart")
        lat = {v: float(np.hypot(*rms(_pvr_key("A1", "xy", v, pvr))[:2]) / np.sqrt(2) * v) for v in p["pvr_xy"]}
        out.append(Finding("Fig. 4.11a", "A1, x and y: DRT-MART beats MART; PVR 1 and 2 give about the same error",
                           f"RMS x, y at PVR {base:g}: DRT-MART {d_base[0]:.3f}, {d_base[1]:.3f} voxel, MART "
                           f"{m_base[0]:.3f}, {m_base[1]:.3f}; DRT-MART against PVR (pixels): "
                           + ", ".join(f"{v:g}: {e:.3f}" for v, e in lat.items()),
                           "reproduced" if np.all(d_base[:2] < m_base[:2]) else "not reproduced",
                           f"MART/DRT-MART {float(np.mean(m_base[:2] / d_base[:2])):.2f}x"))
        zs = {v: float(rms(_pvr_key("B1", "z", v, pvr))[2] * v) for v in p["pvr_z"]}
        best = min(zs, key=zs.get)
        out.append(Finding("Fig. 4.11b", "B1, z: DRT-MART is best at PVR 10 in z (of 5, 10 and 20)",
                           "RMS z (pixels) against PVR z: " + ", ".join(f"{v:g}: {e:.2f}" for v, e in zs.items()),
                           "reproduced" if best == 10 else "not reproduced", f"best at PVR {best:g}"))
        for case, axis, claim_its in (("A1", 0, 50), ("B1", 2, 200)):
            r = results[f"{case}_iterations"]
            its = [int(n) for n in r["rms"]]
            e = np.array([r["rms"][str(n)][axis] for n in its])
            settled = next((n for n, v in zip(its, e, strict=True) if v <= 1.1 * e.min()), its[-1])
            out.append(Finding("Fig. 4.12", f"{case}: about {claim_its} iterations bring the error in "
                               f"{'xz'[axis // 2]} down (x: 50, z: 200)",
                               f"RMS {'xz'[axis // 2]} "
                               + ", ".join(f"{n}: {v:.3f}" for n, v in zip(its, e, strict=True))
                               + " voxel", "reproduced" if abs(np.log2(max(settled, 1) / claim_its)) <= 1 else "partly",
                               f"within 10% of its least from {settled} iterations"))
        omega = 1.0 if 1.0 in p["omegas"] else p["omegas"][0]
        chosen = p.get("cases", (*CASES_A, *CASES_B))
        for every, axis, fig in ((CASES_A, 0, "Fig. 4.13"), (CASES_B, 2, "Fig. 4.14")):
            cases = [c for c in every if c in chosen]
            d = {c: rms(f"{c}_w{omega:g}_drt")[axis] for c in cases}
            m = {c: rms(f"{c}_w{omega:g}_mart")[axis] for c in cases}
            wins = sum(d[c] < m[c] for c in cases)
            worst = max(d, key=d.get)
            expect = cases[-1]
            steep = [w for w in p["omegas"] if w < 1]
            grad = ""
            if steep:
                w0 = min(p["omegas"])
                grad = f"; at omega {w0:g}: " + ", ".join(f"{c} {rms(f'{c}_w{w0:g}_drt')[axis]:.3f}" for c in cases)
            out.append(Finding(fig, f"DRT-MART beats MART (200 against 23 iterations) in every case; the worst case is "
                               f"{expect}, where the velocity varies along the depth",
                               f"RMS {'xz'[axis // 2]} at omega {omega:g}, DRT-MART/MART: "
                               + ", ".join(f"{c} {d[c]:.3f}/{m[c]:.3f}" for c in cases) + grad,
                               "reproduced" if wins == len(cases) and worst == expect else
                               ("partly" if wins or worst == expect else "not reproduced"),
                               f"DRT-MART better in {wins} of {len(cases)}; worst {worst}"))
        # the accuracy goals
        for kind, label in (("single", "one camera"), ("dual", "two cameras at 90 degrees")):
            r = results[f"goal_{kind}"]
            e, ef = rms(f"goal_{kind}"), rms(f"goal_{kind}_faces")
            goal = np.asarray(GOALS[kind])
            met, met_faces = bool(np.all(e <= goal)), bool(np.all(ef <= goal))
            short = ", ".join(f"{a} {v:.3f}" for a, v in zip("xyz", e, strict=True))
            bnd = np.asarray(r.get("bound_rms", [np.nan] * 3), dtype=float)
            missed = ", ".join(f"{a} by {v - g:.3f}" for a, v, g in zip("xyz", e, goal, strict=True) if v > g)
            out.append(Finding("Table 4.1 A1 (goal)", f"ours: A1 at 0.5 PPM, {label}, RMS at most "
                               f"{', '.join(f'{g:g}' for g in goal)} voxel in x, y, z",
                               f"RMS {short} voxel over {r['vectors'] * PROTOCOL[setup.scale]['goal_pairs']} vectors "
                               f"(true particles correlated alike: {', '.join(f'{v:.3f}' for v in bnd)}); focal "
                               f"planes on the volume's faces: {', '.join(f'{v:.3f}' for v in ef)}",
                               "reproduced" if met else ("partly" if met_faces else "not reproduced"),
                               "met" if met else (f"missed ({missed}) with the focal planes centred, met with them on "
                                                  "the faces" if met_faces else f"missed ({missed})")))
        s = rms("still")
        same = np.asarray(results["still"]["same_image_rms"], dtype=float)
        out.append(Finding("control", "ours: no displacement gives zero error",
                           f"the same image as both frames: RMS {', '.join(f'{v:.1e}' for v in same)} voxel; a still "
                           f"pair (the same particles, new noise): {', '.join(f'{v:.3f}' for v in s)} voxel, the "
                           "noise floor of reconstruction and correlation",
                           "reproduced" if np.all(same < 1e-4) else "not reproduced",
                           f"largest {same.max():.1e} voxel"))
        return out

    def protocol(self, setup: Setup) -> list[str]:
        p = PROTOCOL[setup.scale]
        single, dual = _rig(setup, "single", None), _rig(setup, "dual", None)
        nd, nm = p["equal_time"]
        ws, wd = p["windows"]["single"], p["windows"]["dual"]
        fmt = ", ".join
        return [f"One camera: {rigs.describe(single)}; windows {fmt('x'.join(map(str, w)) for w in ws)} voxels.",
                f"Two cameras: {rigs.describe(dual)}; windows {fmt('x'.join(map(str, w)) for w in wd)} voxels.",
                f"0.5 PPM, {p['pairs']} pair(s) a case ({p['goal_pairs']} for the goals), seed {SEED}; overlap "
                f"{p['overlap']:g}, two deformation passes; DRT-MART {nd} iterations against MART {nm} in the same "
                "time (the chapter: 200 against 23; relaxation 1 in the simultaneous form, the chapter 2.5).",
                f"The chapter's proportions: amplitude {AMPLITUDE_PER_WINDOW:.3f} of the final window along the "
                f"oscillating component, wavelength omega x {WAVELENGTH_PER_WINDOW:.1f} final windows; omegas "
                f"{fmt(f'{w:g}' for w in p['omegas'])} (the chapter: 0.25, 0.5, 1, 2).",
                f"Fig. 4.11: PVR {fmt(f'{v:g}' for v in p['pvr_xy'])} in x and y, {fmt(f'{v:g}' for v in p['pvr_z'])} "
                f"in z, windows fixed in voxels; Fig. 4.12: {fmt(map(str, p['iterations']))} iterations.",
                "Errors: every vector, edges included, against the flow at its window's centre at mid-pair time; "
                "outliers replaced as `lfpiv correlate` replaces them.",
                "The goals are measured twice: on the rig as it is (focal planes through the volume's centre) and "
                "with each camera's focal plane moved onto the face of the volume nearest to it."]


def _fitted(windows: tuple[tuple[int, int, int], ...], shape: tuple[int, int, int]
            ) -> tuple[tuple[int, int, int], ...]:
    """The windows, each side cut to the volume's (z, y, x) ``shape`` where it is longer (a
    multiple of 4 voxels): a coarse PVR leaves fewer voxels than the windows of the base PVR."""
    n = shape[::-1]
    return tuple(tuple(min(w, max(4, n[i] // 4 * 4)) for i, w in enumerate(win)) for win in windows)


def _still(scene: Scene, pair: Pair) -> Pair:
    """``pair`` with frame B's particles put back where frame A's are (rendered again with frame
    B's seeds, so its noise differs)."""
    from lfpiv.jobs.synth import render_pair

    particles = np.stack([pair.particles[0], pair.particles[0]])
    brightness = np.stack([pair.brightness[0], pair.brightness[0]])
    images = render_pair(scene.renderers, particles, brightness, seed=scene.seed, pair=pair.index)
    return Pair(index=pair.index, particles=particles, brightness=brightness, images=tuple(images), t0_s=pair.t0_s)


def _rms(e: np.ndarray) -> np.ndarray:
    return np.sqrt(np.nanmean(np.asarray(e, dtype=float) ** 2, axis=0))


STUDY = OscillatoryStudy()
