"""``lfpiv study diameters``: reconstructed particle diameters in x, y and z (Fig. 4.5) and their
elongation along the optical axis (Fig. 4.4).

Both frames of one pair of randomly seeded particles are reconstructed by DRT-MART and the MART
baseline at the chapter's equal-time protocol (DRT-MART 400 iterations against MART 23) and by
MART at DRT-MART's count, and MLOS-MART beside them. Every particle found in a volume (a local
maximum above a tenth of the brightest voxel, as ``lfpiv evaluate``) is measured through its peak
along x, y and z where its intensity falls to exp(-2) of the peak (two standard deviations: the
chapter's definition, 3 voxels for the ideal particle). The diameters are given in voxels and
in object-side pixels (voxels times the PVR), the chapter's unit. The true particles, drawn as
Q_recon's 3-voxel blobs and measured the same way, are the reference: 3 voxels on every axis.
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

NAMES = {"drt-mart": "DRT-MART", "mart": "MART", "mlos-mart": "MLOS-MART", "truth": "truth"}

#: Per scale: seeding, pairs, and the (method, iterations) of every case.
PROTOCOL = {
    "tiny": {"ppm": 0.5, "pairs": 1, "runs": [("drt-mart", 5), ("mart", 2), ("mart", 5), ("mlos-mart", 5)]},
    "quick": {"ppm": 0.5, "pairs": 1, "runs": [("drt-mart", 200), ("mart", 23), ("mart", 200), ("mlos-mart", 200)]},
    "chapter": {"ppm": 0.5, "pairs": 2, "runs": [("drt-mart", 400), ("mart", 23), ("mart", 400),
                                                 ("mlos-mart", 400)]},
}
SEED = 12
#: Bins of the PDFs, in object-side pixels.
EDGES_XY = np.arange(0.0, 16.5, 0.5)
EDGES_Z_VOXELS = np.arange(0.0, 12.25, 0.25)


class DiametersStudy(Study):
    name = "diameters"
    title = "reconstructed particle diameters and elongation"
    figures = "Figs. 4.4 and 4.5"

    def plan(self, setup: Setup) -> list[Case]:
        p = PROTOCOL[setup.scale]
        cases = [Case("truth", {"method": "truth", "iterations": 0, "ppm": p["ppm"], "pairs": p["pairs"]})]
        cases += [Case(f"{m}_{its}", {"method": m, "iterations": its, "ppm": p["ppm"], "pairs": p["pairs"]})
                  for m, its in p["runs"]]
        return cases

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        rig = rigs.single_rig(setup.rig, setup.scale)
        grid = VolumeGrid.from_rig(rig)
        scene = Scene(rig, flow="uniform", ppm=params["ppm"], seed=SEED, device=device)
        rec = None if params["method"] == "truth" else Reconstructor(rig.camera, grid, render=rig.render, device=device)
        settings = ReconSettings.chapter(method=params["method"] if rec else "drt-mart",
                                         iterations=params["iterations"])
        diam, depth, seconds = [], [], 0.0
        focus = rig.camera[0].focus_mm[2]
        for k in range(params["pairs"]):
            pair = scene.pair(k)
            for f in (0, 1):
                if rec is None:
                    vol = metrics.truth_volume(grid, pair.particles[f], brightness=pair.brightness[f])
                else:
                    res, s = rec(pair.frame(f), settings)
                    vol, seconds = res.volume, seconds + s
                pos, _, idx = metrics.detect_particles(vol, grid)
                diam.append(metrics.particle_diameters(vol, idx))
                depth.append((pos[:, 2] - focus) / rig.camera[0].depth_per_lenslet_mm)
        d = np.concatenate(diam) if diam else np.zeros((0, 3))
        return {"diameters_vox": d, "depth_lenslets": np.concatenate(depth), "pvr": list(rig.volume.pvr),
                "seconds": seconds, "particles": int(scene.world.n_particles)}

    @staticmethod
    def _px(r: dict[str, Any]) -> np.ndarray:
        return np.asarray(r["diameters_vox"], dtype=float).reshape(-1, 3) * np.asarray(r["pvr"])

    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        rows = []
        for key, r in results.items():
            dv = np.asarray(r["diameters_vox"], dtype=float).reshape(-1, 3)
            px = self._px(r)
            method, its = (key, 0) if key == "truth" else (key.rsplit("_", 1)[0], int(key.rsplit("_", 1)[1]))
            row = {"method": method, "iterations": its, "detected": len(dv), "seconds": r["seconds"]}
            for i, a in enumerate("xyz"):
                q = np.percentile(dv[:, i], [25, 50, 75]) if len(dv) else [np.nan] * 3
                row[f"d{a}_median_vox"] = q[1]
                row[f"d{a}_iqr_vox"] = f"{q[0]:.2f}-{q[2]:.2f}"
                row[f"d{a}_median_px"] = float(np.median(px[:, i])) if len(px) else np.nan
            row["elongation_z_over_x"] = row["dz_median_px"] / row["dx_median_px"] if len(px) else np.nan
            rows.append(row)
        return rows

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        fig, ax = figures.panels(1, 4, title=f"Fig. 4.5 at --scale {setup.scale}: reconstructed particle diameters "
                                             "(at exp(-2) of the peak)")
        pvr = np.asarray(next(iter(results.values()))["pvr"])
        marts = sorted((k for k in results if k.startswith("mart_")), key=lambda k: int(k.rsplit("_", 1)[1]))
        equal_time = marts[0] if marts else None
        edges = [EDGES_XY, EDGES_XY, EDGES_Z_VOXELS * pvr[2]]
        for key, r in results.items():
            px = self._px(r)
            method = key if key == "truth" else key.rsplit("_", 1)[0]
            its = "" if key == "truth" else f", {key.rsplit('_', 1)[1]} its"
            # dashed: MART at the equal-time count
            style = {"color": figures.METHOD_COLOURS[method], "ls": "--" if key == equal_time else "-"}
            for i in range(3):
                e = edges[i]
                ax[0, i].plot(0.5 * (e[1:] + e[:-1]), figures.pdf(px[:, i], e), label=f"{NAMES[method]}{its}",
                              **style)
            dl = np.asarray(r["depth_lenslets"])
            if len(px) and method != "truth":
                bins = np.linspace(dl.min(), dl.max(), 9)
                centre, med = [], []
                for lo, hi in zip(bins[:-1], bins[1:], strict=True):
                    sel = (dl >= lo) & (dl <= hi)
                    if sel.sum() >= 3:
                        centre.append(0.5 * (lo + hi))
                        med.append(float(np.median(px[sel, 2] / np.maximum(px[sel, 0], 1e-9))))
                ax[0, 3].plot(centre, med, marker="o", label=f"{NAMES[method]}{its}", **style)
        for i, a in enumerate("xyz"):
            ax[0, i].set_xlabel(f"d{a} (object-side pixels)")
            ax[0, i].set_ylabel("PDF")
            ax[0, i].legend(fontsize=7)
            figures.label(ax[0, i], "abc"[i], f"{a} direction" + (" (depth)" if a == "z" else ""))
        ax[0, 3].set_xlabel("depth from the focal plane (lenslets of blur)")
        ax[0, 3].set_ylabel("median dz / dx")
        ax[0, 3].legend(fontsize=7)
        figures.label(ax[0, 3], "d", "elongation against depth (ours)")
        figures.save(fig, path)

    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        med = {k: np.median(self._px(r), axis=0) if len(self._px(r)) else np.full(3, np.nan)
               for k, r in results.items()}
        drt = next(k for k in results if k.startswith("drt-mart_"))
        marts = sorted((k for k in results if k.startswith("mart_")), key=lambda k: int(k.rsplit("_", 1)[1]))
        m_eq, m_long = marts[0], marts[-1]
        out = []
        lat_d, lat_m = float(np.mean(med[drt][:2])), float(np.mean(med[m_long][:2]))
        out.append(Finding("Fig. 4.5a-b", "x and y: DRT-MART particles about 2-4 pixels across, MART 5-7",
                           f"median DRT-MART {lat_d:.1f} px, MART ({m_long.rsplit('_', 1)[1]} its) {lat_m:.1f} px, "
                           "MART "
                           f"({m_eq.rsplit('_', 1)[1]} its) {float(np.mean(med[m_eq][:2])):.1f} px; truth "
                           f"{float(np.mean(med['truth'][:2])):.1f} px",
                           "reproduced" if lat_d < lat_m else "not reproduced", f"{lat_m / lat_d:.2f}x"))
        zd, zm, ze = float(med[drt][2]), float(med[m_long][2]), float(med[m_eq][2])
        out.append(Finding("Fig. 4.5c", "z (depth): DRT-MART about 10-25 pixels, MART 35-45: far more elongated",
                           f"median DRT-MART {zd:.0f} px, MART {zm:.0f} px ({m_long.rsplit('_', 1)[1]} its), "
                           f"{ze:.0f} px ({m_eq.rsplit('_', 1)[1]} its); truth {float(med['truth'][2]):.0f} px",
                           "reproduced" if zd < zm and zd < ze else
                           ("partly" if zd < max(zm, ze) else "not reproduced"),
                           f"{min(zm, ze) / zd:.2f}x"))
        el = {k: float(med[k][2] / med[k][0]) for k in (drt, m_eq)}
        out.append(Finding("Fig. 4.4", "in the same time, DRT-MART (400 iterations) gives less elongated particles "
                           "than MART (23)",
                           f"dz/dx: DRT-MART ({drt.rsplit('_', 1)[1]} its) {el[drt]:.1f}, MART "
                           f"({m_eq.rsplit('_', 1)[1]} its) {el[m_eq]:.1f}; reconstruction time "
                           f"{results[drt]['seconds']:.1f} s against {results[m_eq]['seconds']:.1f} s",
                           "reproduced" if el[drt] < el[m_eq] else "not reproduced", f"{el[m_eq] / el[drt]:.2f}x"))
        return out

    def protocol(self, setup: Setup) -> list[str]:
        p = PROTOCOL[setup.scale]
        rig = rigs.single_rig(setup.rig, setup.scale)
        runs = ", ".join(f"{NAMES[m]} {its}" for m, its in p["runs"])
        return [f"Rig: {rigs.describe(rig)}.",
                f"{p['pairs']} pair(s), both frames, {p['ppm']:g} PPM, seed {SEED}; iterations: {runs} (the chapter: "
                "DRT-MART 400, MART 23 in the same time, and MART 400).",
                "Diameters of every detected particle (local maxima above 0.1 of the brightest voxel), ghosts "
                "included, at exp(-2) of the peak; pixels are object-side pixels (voxels x PVR)."]


STUDY = DiametersStudy()
