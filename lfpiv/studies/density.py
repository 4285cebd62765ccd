"""``lfpiv study density``: Q against seeding density (Fig. 4.8), ghosts and the depth profile
(Fig. 4.9), and the MART/DRT-MART time ratio against density (Fig. 4.10).

At each density one frame is reconstructed by DRT-MART and by the MART baseline at the chapter's
two protocols: its own (DRT-MART 400 iterations against MART 200) and equal time (DRT-MART 200
against MART 23), and by MLOS-MART at DRT-MART's count. Every method is timed from the raw image
to the volume, its weights included (no weight cache), within one case on one worker, so each
ratio is of two times taken in the same run. For Fig. 4.9, several frames at the chapter's
0.5 PPM are reconstructed on a box that reaches beyond the seeded region in depth; their sum,
averaged over y, is the x-z map, and its mean against z the depth profile.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lfcore import metrics
from lfcore.reconstruct import ReconSettings
from lfcore.volume import VolumeGrid
from lfpiv.studies import figures, rigs
from lfpiv.studies.pipeline import Reconstructor, Scene
from lfpiv.studies.runner import Case, Finding, Setup, Study

NAMES = {"drt-mart": "DRT-MART", "mart": "MART", "mlos-mart": "MLOS-MART"}

#: Per scale: densities; the chapter's protocol (DRT-MART, MART iterations) and the equal-time one;
#: frames of Fig. 4.9, its iterations and the box's margin in depth (a fraction of the seeded depth
#: on each side).
PROTOCOL = {
    "tiny": {"ppm": [0.25, 1.0], "protocol": (5, 3), "equal_time": (5, 2), "ghost_frames": 2, "ghost_its": 5,
             "margin": 0.25},
    "quick": {"ppm": [0.1, 0.25, 0.5, 1.0, 2.0], "protocol": (200, 100), "equal_time": (200, 23),
              "ghost_frames": 2, "ghost_its": 50, "margin": 0.25},
    "chapter": {"ppm": [0.1, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0], "protocol": (400, 200), "equal_time": (200, 23),
                "ghost_frames": 30, "ghost_its": 400, "margin": 0.25},
}
SEED = 13


class DensityStudy(Study):
    name = "density"
    title = "reconstruction quality and speed against seeding density"
    figures = "Figs. 4.8, 4.9 and 4.10"

    def plan(self, setup: Setup) -> list[Case]:
        p = PROTOCOL[setup.scale]
        cases = [Case(f"ppm{ppm:g}", {"ppm": ppm, "protocol": list(p["protocol"]), "equal_time": list(p["equal_time"])})
                 for ppm in p["ppm"]]
        cases.append(Case("ghosts", {"ppm": 0.5, "frames": p["ghost_frames"], "iterations": p["ghost_its"],
                                     "margin": p["margin"]}))
        return cases

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        rig = rigs.single_rig(setup.rig, setup.scale)
        if "frames" in params:
            return self._ghosts(rig, params, device)
        grid = VolumeGrid.from_rig(rig)
        scene = Scene(rig, flow="uniform", ppm=params["ppm"], seed=SEED, device=device)
        pair = scene.pair(0)
        e0 = metrics.truth_volume(grid, pair.particles[0], brightness=pair.brightness[0])
        # no cache: every time includes its weights
        rec = Reconstructor(rig.camera, grid, render=rig.render, device=device)
        (nd, nm), (ed, em) = params["protocol"], params["equal_time"]
        runs = {}
        for method, its in dict.fromkeys([("drt-mart", nd), ("mart", nm), ("drt-mart", ed), ("mart", em),
                                          ("mlos-mart", nd)]):
            res, seconds = rec(pair.frame(0), ReconSettings.chapter(method=method, iterations=its))
            ev = metrics.evaluate_volume(res.volume, grid, pair.particles[0], pair.brightness[0],
                                         centre_mm=rig.volume.centre_mm, size_mm=rig.volume.size_mm)
            runs[f"{method}_{its}"] = {"q": metrics.q_recon(res.volume, e0), "seconds": seconds,
                                       "weights_s": res.weights_s, "iterate_s": res.iterate_s,
                                       "active_fraction": res.active_fraction, "recall": ev.match.recall,
                                       "ghost_fraction": ev.match.ghost_fraction}
        return {"particles": int(scene.world.n_particles), "runs": runs,
                "ratio_protocol": runs[f"mart_{nm}"]["seconds"] / runs[f"drt-mart_{nd}"]["seconds"],
                "ratio_equal_time": runs[f"mart_{em}"]["seconds"] / runs[f"drt-mart_{ed}"]["seconds"]}

    def _ghosts(self, rig, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        depth = rig.volume.size_mm[2]
        grid = VolumeGrid.from_rig(rig, margin_mm=(0.0, 0.0, params["margin"] * depth))
        scene = Scene(rig, flow="uniform", ppm=params["ppm"], seed=SEED + 1, device=device)
        rec = Reconstructor(rig.camera, grid, render=rig.render, device=device, cache=True)
        total = np.zeros(grid.shape)
        outside, ghosts = [], []
        for k in range((params["frames"] + 1) // 2):
            pair = scene.pair(k)
            for f in (0, 1)[: params["frames"] - 2 * k]:
                res, _ = rec(pair.frame(f), ReconSettings.chapter(iterations=params["iterations"]))
                total += res.volume
                ev = metrics.evaluate_volume(res.volume, grid, pair.particles[f], pair.brightness[f],
                                             centre_mm=rig.volume.centre_mm, size_mm=rig.volume.size_mm)
                outside.append(ev.outside)
                ghosts.append(ev.match.ghost_fraction)
        z = grid.axis_mm("z")
        lo = rig.volume.centre_mm[2] - 0.5 * depth
        return {"xz": total.mean(axis=1), "x_mm": grid.axis_mm("x"), "z_mm": z, "profile": total.mean(axis=(1, 2)),
                "seeded_mm": [lo, lo + depth], "focus_mm": rig.camera[0].focus_mm[2],
                "depth_per_lenslet_mm": rig.camera[0].depth_per_lenslet_mm,
                "outside_fraction": float(np.mean(outside)), "ghost_fraction": float(np.mean(ghosts)),
                "frames": params["frames"]}

    def _points(self, results: Mapping[str, dict[str, Any]]) -> list[tuple[float, dict[str, Any]]]:
        return sorted((float(k[3:]), r) for k, r in results.items() if k.startswith("ppm"))

    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        rows = []
        for ppm, r in self._points(results):
            for key, run in r["runs"].items():
                m, its = key.rsplit("_", 1)
                rows.append({"ppm": ppm, "particles": r["particles"], "method": m, "iterations": int(its),
                             "Q": run["q"], "seconds": run["seconds"], "weights_s": run["weights_s"],
                             "iterate_s": run["iterate_s"], "active_fraction": run["active_fraction"],
                             "recall": run["recall"], "ghost_fraction": run["ghost_fraction"]})
        g = results["ghosts"]
        rows.append({"ppm": 0.5, "method": "drt-mart (Fig. 4.9 box)", "iterations": PROTOCOL[setup.scale]["ghost_its"],
                     "ghost_fraction": g["ghost_fraction"], "outside_fraction": g["outside_fraction"],
                     "frames": g["frames"]})
        return rows

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        p = PROTOCOL[setup.scale]
        (nd, nm), (ed, em) = p["protocol"], p["equal_time"]
        pts = self._points(results)
        ppm = [x for x, _ in pts]
        fig, ax = figures.panels(1, 4, title=f"Figs. 4.8-4.10 at --scale {setup.scale} (one camera)")
        a = ax[0, 0]
        for key, style, lab in ((f"drt-mart_{nd}", "o-", f"DRT-MART {nd}"), (f"mart_{nm}", "s-", f"MART {nm}"),
                                (f"mlos-mart_{nd}", "^-", f"MLOS-MART {nd}"),
                                (f"drt-mart_{ed}", "o--", f"DRT-MART {ed}"),
                                (f"mart_{em}", "s--", f"MART {em}")):
            if style == "o--" and ed == nd:  # the equal-time DRT-MART is the protocol's
                continue
            m = key.rsplit("_", 1)[0]
            a.plot(ppm, [r["runs"][key]["q"] for _, r in pts], style, color=figures.METHOD_COLOURS[m], label=lab)
        a.set_xlabel("particles per microlens (PPM)")
        a.set_ylabel("Q_recon")
        a.set_ylim(0, 1)
        a.legend(fontsize=7)
        figures.label(a, "a", "Q against density (Fig. 4.8)")
        g = results["ghosts"]
        x, z = np.asarray(g["x_mm"]), np.asarray(g["z_mm"])
        a = ax[0, 1]
        a.imshow(np.asarray(g["xz"]), origin="lower", aspect="auto", cmap="viridis", extent=(x[0], x[-1], z[0], z[-1]))
        for s in g["seeded_mm"]:
            a.axhline(s, color="w", ls="--", lw=1)
        a.set_xlabel("x (mm)")
        a.set_ylabel("z (mm)")
        figures.label(a, "b", f"sum of {g['frames']} volumes, mean over y (Fig. 4.9a)")
        a = ax[0, 2]
        a.plot(z, g["profile"], color=figures.METHOD_COLOURS["drt-mart"])
        a.axvspan(*g["seeded_mm"], color="0.92", zorder=0, label="seeded region")
        f, dpl = g["focus_mm"], g["depth_per_lenslet_mm"]
        a.axvspan(f - dpl, f + dpl, color="tab:orange", alpha=0.2, zorder=0, label="within a lenslet of focus")
        a.set_xlabel("z (mm)")
        a.set_ylabel("mean voxel intensity")
        a.legend(fontsize=7)
        figures.label(a, "c", "intensity against depth (Fig. 4.9b)")
        a = ax[0, 3]
        a.plot(ppm, [r["ratio_protocol"] for _, r in pts], "o-", label=f"MART {nm} / DRT-MART {nd} (chapter's)")
        a.plot(ppm, [r["ratio_equal_time"] for _, r in pts], "s--", label=f"MART {em} / DRT-MART {ed} (equal time)")
        a.axhline(1.0, color="0.5", ls=":")
        a.set_xlabel("particles per microlens (PPM)")
        a.set_ylabel("time of MART / time of DRT-MART")
        a.legend(fontsize=7)
        figures.label(a, "d", "time ratio against density (Fig. 4.10)")
        figures.save(fig, path)

    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        p = PROTOCOL[setup.scale]
        (nd, nm), (ed, em) = p["protocol"], p["equal_time"]
        pts = self._points(results)
        qd = np.array([r["runs"][f"drt-mart_{nd}"]["q"] for _, r in pts])
        qm = np.array([r["runs"][f"mart_{nm}"]["q"] for _, r in pts])
        wins = int(np.sum(qd > qm))
        out = [Finding("Fig. 4.8", f"DRT-MART ({nd} its) reaches a higher Q than MART ({nm}) at every density",
                       "Q DRT-MART / MART: " + ", ".join(f"{x:g} PPM {a:.3f}/{b:.3f}" for (x, _), a, b
                                                       in zip(pts, qd, qm, strict=True)),
                       "reproduced" if wins == len(pts) else ("partly" if wins else "not reproduced"),
                       f"higher at {wins} of {len(pts)} densities, by {np.mean(qd - qm):+.3f} on average")]
        falls = bool(np.all(np.diff(qd) < 0.02) and qd[-1] < qd[0] and np.all(np.diff(qm) < 0.02) and qm[-1] < qm[0])
        out.append(Finding("Fig. 4.8", "Q falls as the density rises, with either method",
                           f"DRT-MART {qd[0]:.3f} -> {qd[-1]:.3f}, MART {qm[0]:.3f} -> {qm[-1]:.3f} from {pts[0][0]:g} "
                           f"to {pts[-1][0]:g} PPM", "reproduced" if falls else "partly",
                           f"{qd[-1] - qd[0]:+.3f} (DRT-MART)"))
        g = results["ghosts"]
        z = np.asarray(g["z_mm"])
        prof = np.asarray(g["profile"])
        lo, hi = g["seeded_mm"]
        inside = (z >= lo) & (z <= hi)
        near = inside & (np.abs(z - g["focus_mm"]) <= g["depth_per_lenslet_mm"])
        rest = inside & ~near
        dip = float(prof[near].mean() / prof[rest].mean()) if near.any() and rest.any() else float("nan")
        out.append(Finding("Fig. 4.9", "no intensity is reconstructed beyond the seeded region (no ghosts there); "
                           "the intensity dips at the focal plane",
                           f"{100 * g['outside_fraction']:.2f}% of the intensity outside the seeded region; mean "
                           f"intensity within a lenslet of focus {dip:.2f}x that elsewhere; ghosts "
                           f"{100 * g['ghost_fraction']:.0f}% "
                           "of the detections", "reproduced" if g["outside_fraction"] < 0.02 and dip < 1 else "partly",
                           f"{100 * g['outside_fraction']:.2f}% outside, dip {dip:.2f}"))
        ratios = {x: r["ratio_protocol"] for x, r in pts}
        near1 = min(ratios, key=lambda x: abs(x - 1.0))
        d1 = dict(pts)[near1]["runs"][f"drt-mart_{nd}"]
        faster = [x for x, v in ratios.items() if v > 1]
        out.append(Finding("Fig. 4.10", f"DRT-MART ({nd} its) is faster than MART ({nm}) up to about 2 PPM, about "
                           "4x at 1 PPM",
                           f"MART/DRT-MART time {ratios[near1]:.2f} at {near1:g} PPM; faster at "
                           f"{', '.join(f'{x:g}' for x in faster) or 'no density'} PPM; equal-time protocol "
                           f"({ed}/{em}): "
                           + ", ".join(f"{x:g} PPM {r['ratio_equal_time']:.2f}" for x, r in pts)
                           + f"; at {near1:g} PPM DRT-MART spent {d1['weights_s']:.1f} of its {d1['seconds']:.1f} s on "
                           f"elimination and weights ({100 * d1['active_fraction']:.0f}% of the voxels active)",
                           "reproduced" if ratios[near1] >= 3.5 else
                           ("partly" if ratios[near1] > 1 else "not reproduced"),
                           f"{ratios[near1]:.2f}x at {near1:g} PPM against 4x"))
        return out

    def protocol(self, setup: Setup) -> list[str]:
        p = PROTOCOL[setup.scale]
        rig = rigs.single_rig(setup.rig, setup.scale)
        (nd, nm), (ed, em) = p["protocol"], p["equal_time"]
        return [f"Rig: {rigs.describe(rig)}.",
                f"Densities {', '.join(f'{x:g}' for x in p['ppm'])} PPM, one frame each, seed {SEED}; DRT-MART {nd} "
                f"against MART {nm} (the chapter: 400 against 200) and {ed} against {em} (the chapter's equal time); "
                "simultaneous form, relaxation 1 (the chapter: 2.5, sequential).",
                "Times from the raw image to the volume, weights included, both methods in the same case on the same "
                "device (a CPU here: a GPU changes the ratios, since the weight builds and iterations scale "
                "differently).",
                f"Fig. 4.9: {p['ghost_frames']} frames at 0.5 PPM, DRT-MART {p['ghost_its']} iterations, the box "
                f"{100 * p['margin']:.0f}% of the seeded depth deeper on each side (the chapter: 30 images)."]


STUDY = DensityStudy()
