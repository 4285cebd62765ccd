"""``lfpiv study dual``: one camera against two against seeding density (Fig. 4.33), Q against the
separation angle (Fig. 4.34) and depth-resolution maps (Fig. 4.35).

- Fig. 4.33: one frame at each density reconstructed by DRT-MART from the first camera alone and
  from both, on the same (the two-camera rig's) voxels, Q at each iteration count.
- Fig. 4.34: the first camera and a copy of it turned by the separation angle about world y
  (0 degrees: the same view twice, 180: facing it), Q at two densities.
- Fig. 4.35: the depth resolution at points of the x-z plane through the volume's centre, for
  cameras at 0, 30, 60 and 90 degrees. Depth is along the bisector of the two optical axes (the
  chapter's convention). Two points are told apart when their light fields differ: here, when
  the normalised correlation of the two points' noise-free images (every camera's, rendered by
  the instrument's own ray tracer) has fallen to one half. The resolution at a point is the
  mean of the distances, towards the cameras and away, at which that happens.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lfcore import metrics
from lfcore.reconstruct import ReconSettings
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfpiv.studies import figures, rigs
from lfpiv.studies.pipeline import Reconstructor, Scene
from lfpiv.studies.runner import Case, Finding, Setup, Study

#: Per scale: Fig. 4.33's densities and iteration counts; Fig. 4.34's angles, densities and
#: iterations; Fig. 4.35's angles, points per side of the map and rays per point.
PROTOCOL = {
    "tiny": {"ppm": [0.5], "iterations": [2, 5], "angles": [0, 90], "angle_ppm": [0.5], "angle_its": 5,
             "map_angles": [0, 90], "map_points": 3, "rays": 2000},
    "quick": {"ppm": [0.1, 0.5, 1.0], "iterations": [5, 10, 20, 50, 100], "angles": list(range(0, 181, 30)),
              "angle_ppm": [0.5, 1.0], "angle_its": 20, "map_angles": [0, 30, 60, 90], "map_points": 9,
              "rays": 20000},
    "chapter": {"ppm": [0.1, 0.5, 1.0], "iterations": [5, 10, 20, 50, 100, 200, 400],
                "angles": list(range(0, 181, 10)), "angle_ppm": [0.5, 1.0], "angle_its": 200,
                "map_angles": [0, 30, 60, 90], "map_points": 25, "rays": 100000},
}
SEED = 15
#: The normalised correlation of two points' images at which they count as told apart.
APART = 0.5


class DualStudy(Study):
    name = "dual"
    title = "one light-field camera against two"
    figures = "Figs. 4.33, 4.34 and 4.35"

    def plan(self, setup: Setup) -> list[Case]:
        p = PROTOCOL[setup.scale]
        cases = [Case(f"cams{n}_ppm{ppm:g}", {"cameras": n, "ppm": ppm, "iterations": p["iterations"]})
                 for ppm in p["ppm"] for n in (1, 2)]
        cases += [Case(f"angle{a}", {"angle": a, "ppm": p["angle_ppm"], "iterations": p["angle_its"]})
                  for a in p["angles"]]
        cases += [Case(f"map{a}", {"map_angle": a, "points": p["map_points"], "rays": p["rays"]})
                  for a in p["map_angles"]]
        return cases

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        rig = rigs.dual_rig(setup.rig, setup.scale)
        if "map_angle" in params:
            return resolution_map(rigs.with_angle(rig, params["map_angle"]), params["points"], params["rays"], device)
        grid = VolumeGrid.from_rig(rig)
        if "angle" in params:
            rig = rigs.with_angle(rig, params["angle"])
            out = {}
            for ppm in params["ppm"]:
                pair = Scene(rig, flow="uniform", ppm=ppm, seed=SEED, device=device).pair(0)
                rec = Reconstructor(rig.camera, grid, render=rig.render, device=device)
                res, _ = rec(pair.frame(0), ReconSettings.chapter(iterations=params["iterations"]))
                out[f"{ppm:g}"] = metrics.q_recon(res.volume, metrics.truth_volume(grid, pair.particles[0],
                                                                                   brightness=pair.brightness[0]))
            return {"q": out}
        scene = Scene(rig, flow="uniform", ppm=params["ppm"], seed=SEED, device=device)
        pair = scene.pair(0)
        cams = rig.camera[: params["cameras"]]
        e0 = metrics.truth_volume(grid, pair.particles[0], brightness=pair.brightness[0])
        rec = Reconstructor(cams, grid, render=rig.render, device=device, cache=True)
        qs = []
        for its in params["iterations"]:
            res, _ = rec(pair.frame(0)[: params["cameras"]], ReconSettings.chapter(iterations=its))
            qs.append(metrics.q_recon(res.volume, e0))
        return {"q": qs, "iterations": params["iterations"], "particles": int(scene.world.n_particles)}

    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        rows = []
        for key, r in results.items():
            if key.startswith("cams"):
                n, ppm = key[4:].split("_ppm")
                rows += [{"figure": "4.33", "cameras": int(n), "ppm": float(ppm), "iterations": its, "Q": q}
                         for its, q in zip(r["iterations"], r["q"], strict=True)]
            elif key.startswith("angle"):
                rows += [{"figure": "4.34", "cameras": 2, "angle_deg": int(key[5:]), "ppm": float(ppm), "Q": q}
                         for ppm, q in r["q"].items()]
            else:
                res = np.asarray(r["resolution_mm"], dtype=float)
                rows.append({"figure": "4.35", "cameras": 2, "angle_deg": int(key[3:]),
                             "resolution_median_mm": float(np.nanmedian(res)),
                             "resolution_min_mm": float(np.nanmin(res)), "resolution_max_mm": float(np.nanmax(res))})
        return rows

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        p = PROTOCOL[setup.scale]
        maps = [a for a in p["map_angles"]]
        fig, ax = figures.panels(2, max(2, len(maps)), title=f"Figs. 4.33-4.35 at --scale {setup.scale}")
        a = ax[0, 0]
        for k, ppm in enumerate(p["ppm"]):
            for n, ls in ((1, "--"), (2, "-")):
                r = results[f"cams{n}_ppm{ppm:g}"]
                a.plot(r["iterations"], r["q"], ls, marker="o", color=f"C{k}", label=f"{n} camera(s), {ppm:g} PPM")
        figures.log_x(a)
        a.set_ylim(0, 1)
        a.set_xlabel("iterations")
        a.set_ylabel("Q_recon")
        a.legend(fontsize=7)
        figures.label(a, "a", "Q against iterations, one camera and two (Fig. 4.33)")
        a = ax[0, 1]
        for k, ppm in enumerate(p["angle_ppm"]):
            a.plot(p["angles"], [results[f"angle{g}"]["q"][f"{ppm:g}"] for g in p["angles"]], "o-", color=f"C{k}",
                   label=f"{ppm:g} PPM")
        a.set_xlabel("separation angle (degrees)")
        a.set_ylabel("Q_recon")
        a.set_xticks(p["angles"][:: max(1, len(p["angles"]) // 7)])
        a.legend(fontsize=7)
        figures.label(a, "b", "Q against separation angle (Fig. 4.34)")
        for a in ax[0, 2:]:
            a.axis("off")
        vmax = max(float(np.nanmax(results[f"map{g}"]["resolution_mm"])) for g in maps)
        for k, g in enumerate(maps):
            r = results[f"map{g}"]
            a = ax[1, k]
            lat, dep = np.asarray(r["lateral_mm"]), np.asarray(r["depth_mm"])
            im = a.imshow(np.asarray(r["resolution_mm"], dtype=float), origin="lower", cmap="viridis_r", vmin=0,
                          vmax=vmax, extent=(lat[0], lat[-1], dep[0], dep[-1]), aspect="auto")
            fig.colorbar(im, ax=a, label="depth resolution (mm)")
            a.set_xlabel("across the bisector (mm)")
            a.set_ylabel("along the bisector, depth (mm)")
            figures.label(a, "cdef"[k], f"{g} degrees (Fig. 4.35)")
        figures.save(fig, path)

    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        p = PROTOCOL[setup.scale]
        out = []
        better, pairs, drop = 0, 0, {}
        for ppm in p["ppm"]:
            q1, q2 = (np.asarray(results[f"cams{n}_ppm{ppm:g}"]["q"]) for n in (1, 2))
            better += int(np.sum(q2 > q1))
            pairs += len(q1)
            drop[ppm] = (q1[-1], q2[-1])
        lo, hi = min(p["ppm"]), max(p["ppm"])
        out.append(Finding("Fig. 4.33", "two cameras give a higher Q than one at every iteration count and density",
                           "last count, Q one / two cameras: " + ", ".join(f"{x:g} PPM {a:.3f}/{b:.3f}"
                                                                          for x, (a, b) in drop.items()),
                           "reproduced" if better == pairs else ("partly" if better else "not reproduced"),
                           f"higher in {better} of {pairs}"))
        d1, d2 = drop[lo][0] - drop[hi][0], drop[lo][1] - drop[hi][1]
        verdict = ("not measured" if lo == hi else "reproduced" if d1 > 0 and d2 > 0 and d2 < d1 else
                   "partly" if d1 > 0 or d2 > 0 else "not reproduced")
        out.append(Finding("Fig. 4.33", "a lower density gives a higher Q, and two cameras lose less of it at "
                           "high density",
                           f"from {lo:g} to {hi:g} PPM Q falls by {d1:.3f} with one camera, {d2:.3f} with two",
                           verdict, f"{d1:.3f} against {d2:.3f}"))
        conv = {}
        for n in (1, 2):
            r = results[f"cams{n}_ppm{0.5 if 0.5 in p['ppm'] else lo:g}"]
            q = np.asarray(r["q"])
            conv[n] = next(its for its, v in zip(r["iterations"], q, strict=True) if v >= 0.95 * q.max())
        out.append(Finding("Fig. 4.33", "two cameras converge in fewer iterations",
                           f"95% of the best Q at {conv[1]} iterations with one camera, {conv[2]} with two",
                           "reproduced" if conv[2] <= conv[1] else "not reproduced", f"{conv[1]} against {conv[2]}"))
        for ppm in p["angle_ppm"]:
            q = {g: results[f"angle{g}"]["q"][f"{ppm:g}"] for g in p["angles"]}
            peak = max(q, key=q.get)
            out.append(Finding("Fig. 4.34", "Q peaks at a separation angle of 90 degrees",
                               f"{ppm:g} PPM: best Q {q[peak]:.3f} at {peak} degrees; {q.get(90, float('nan')):.3f} at "
                               f"90, {q[min(q)]:.3f} at {min(q)}", "reproduced" if abs(peak - 90) <= 10 else
                               ("partly" if abs(peak - 90) <= 30 else "not reproduced"), f"peak at {peak} degrees"))
        if len(p["angle_ppm"]) > 1:
            a, b = p["angle_ppm"][:2]
            higher = sum(results[f"angle{g}"]["q"][f"{a:g}"] > results[f"angle{g}"]["q"][f"{b:g}"] for g in p["angles"])
            out.append(Finding("Fig. 4.34", f"{a:g} PPM gives a slightly higher Q than {b:g} PPM at every angle",
                               f"higher at {higher} of {len(p['angles'])} angles", "reproduced" if
                               higher == len(p["angles"]) else "partly", f"{higher} of {len(p['angles'])}"))
        med = {g: float(np.nanmedian(results[f"map{g}"]["resolution_mm"])) for g in p["map_angles"]}
        first, last = min(med), max(med)
        out.append(Finding("Fig. 4.35", "the depth resolution improves from 0 to 90 degrees (about 0.55 to 0.1 mm on "
                           "the chapter's rig, 5.5x), and the region of poor resolution shrinks",
                           "median resolution " + ", ".join(f"{g} deg {v:.3f} mm" for g, v in med.items()),
                           "reproduced" if med[last] < med[first] and all(np.diff(list(med.values())) <= 1e-9)
                           else ("partly" if med[last] < med[first] else "not reproduced"),
                           f"{med[first] / med[last]:.1f}x from {first} to {last} degrees"))
        return out

    def protocol(self, setup: Setup) -> list[str]:
        p = PROTOCOL[setup.scale]
        rig = rigs.dual_rig(setup.rig, setup.scale)
        return [f"Rig: {rigs.describe(rig)}; the one-camera runs use its first camera on the same voxels.",
                f"Fig. 4.33: densities {', '.join(f'{x:g}' for x in p['ppm'])} PPM, one frame, DRT-MART at "
                f"{', '.join(map(str, p['iterations']))} iterations, relaxation 1, seed {SEED}.",
                f"Fig. 4.34: angles {p['angles'][0]}-{p['angles'][-1]} degrees in steps of "
                f"{p['angles'][1] - p['angles'][0]} (the chapter: 10), {', '.join(f'{x:g}' for x in p['angle_ppm'])} "
                f"PPM, DRT-MART {p['angle_its']} iterations.",
                f"Fig. 4.35: {p['map_points']} x {p['map_points']} points of the x-z plane, {p['rays']} rays a point; "
                f"two points are told apart when their images correlate at {APART:g} or less (the chapter: when "
                "their rays reach different groups of lenslets)."]


def resolution_map(rig: Rig, points: int, rays: int, device: str | None = None) -> dict[str, Any]:
    """Depth resolution on a map of the x-z plane through the volume's centre (Fig. 4.35).

    Parameters
    ----------
    rig
        Its first one or two cameras are used; depth is along the bisector of their optical axes
        (the one camera's axis alone).
    points
        Points along each side of the map, which spans 0.8 of the volume's smaller x-z extent.
    rays
        Rays per point of the noise-free images.
    device
        Warp device of the renderers.

    Returns
    -------
    dict
        ``resolution_mm`` (points, points), indexed (depth, across), NaN where the images never
        fell to :data:`APART`; ``lateral_mm`` and ``depth_mm`` the map's 1-D coordinates about the
        volume's centre; ``angle_deg`` the cameras' separation.
    """
    render = rig.render.model_copy(update={"rays_per_particle": int(rays)})
    cams = rig.camera[:2]
    renderers = [LightFieldRenderer(c, render, wavelength_nm=rig.laser.wavelength_nm, device=device) for c in cams]
    axes = [c.optical_axis for c in cams]
    b = np.sum(axes, axis=0)
    b = b / np.linalg.norm(b) if np.linalg.norm(b) > 1e-9 else axes[0]  # facing cameras: the first's axis
    lat = np.cross([0.0, 1.0, 0.0], b)
    lat /= np.linalg.norm(lat)
    centre = np.asarray(rig.volume.centre_mm, dtype=float)
    half = 0.5 * float(min(rig.volume.size_mm[0], rig.volume.size_mm[2])) * 0.8
    u = np.linspace(-half, half, points)
    step0 = 0.25 * min(rig.volume.size_mm) / 64
    steps = step0 * 1.35 ** np.arange(24)

    def image(p: np.ndarray) -> np.ndarray:
        # the same seed for every point: the same rays, so the images change smoothly with the point
        v = np.concatenate([r.irradiance(p[None], 1.0e4, seed=SEED).ravel() for r in renderers])
        return v / max(float(np.linalg.norm(v)), 1e-30)

    res = np.full((points, points), np.nan)
    for i, d in enumerate(u):
        for j, w in enumerate(u):
            p = centre + w * lat + d * b
            ref = image(p)
            found = []
            for sign in (1.0, -1.0):
                prev_s, prev_c = 0.0, 1.0
                for s in steps:
                    c = float(ref @ image(p + sign * s * b))
                    if c <= APART:  # interpolate between the last two distances
                        found.append(prev_s + (s - prev_s) * (prev_c - APART) / max(prev_c - c, 1e-12))
                        break
                    prev_s, prev_c = s, c
            if found:
                res[i, j] = float(np.mean(found))
    angle = math.degrees(math.acos(float(np.clip(np.dot(axes[0], axes[-1]), -1, 1))))
    return {"resolution_mm": res, "lateral_mm": u, "depth_mm": u, "angle_deg": angle, "rays": rays}


STUDY = DualStudy()
