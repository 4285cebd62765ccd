"""``lfpiv study lf-vs-tomo``: one light-field camera against 4-, 6- and 8-camera Tomo-PIV, through
the light-field-to-Tomo camera pixel ratio (LTPR, eq. 4.5; Figs. 4.23 and 4.24).

LTPR = (p_x p_y) of the light-field camera / (p_x p_y N_c) of the Tomo-PIV system. The chapter's
cases: light-field cameras of 800 x 800 and 1600 x 1600 pixels at PMR (pixels per lenslet) 7, 14
and 28, 0.5 PPM, DRT-MART at PVR (2, 2, 10); Tomo-PIV with 4, 6 and 8 cameras of 160 x 160 pixels
on a semicircle in the x-z plane (``examples/tomo_N_cameras.toml``: f 85 mm, 0.075 mm per pixel),
0.05 and 0.1 ppp, MLOS-SMART at PVR 1. Each light-field camera looks along z at the Tomo-PIV
rig's field of view (160 x 0.075 = 12 mm across its sensor, 5.5 um pixels, f/2.5 with matched
microlenses), so both see the same volume: 800 pixels give LTPR 6.25, 4.17 and 3.13 against 4,
6 and 8 Tomo cameras, 1600 pixels 25, 16.67 and 12.5.

Below ``chapter`` scale every sensor is cut by the same factor (``FACTOR``) and the volume with
it (its depth by twice the factor), the pixels' size in the volume kept: the LTPR of every
pairing, the voxels, the particle images and the seeding densities stay the chapter's, only the
field of view and the depth shrink.

Each case renders one pair of a uniform shift (0.15 mm, two Tomo pixels, along (0.8, 0.5,
0.33)), reconstructs both frames, correlates them and measures Q (frame A), the particle
centres' errors (detected peaks matched to the truth, Fig. 4.23) and the RMS displacement
error of each component against the shift (Fig. 4.24), in micrometres, so that the two kinds'
different voxels compare.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lfcore import metrics
from lfcore.correlate import CorrelationConfig
from lfcore.reconstruct import ReconSettings
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfpiv.jobs.correlate import fitting_windows
from lfpiv.rigfile import load_rig
from lfpiv.studies import figures
from lfpiv.studies.pipeline import Reconstructor, Scene, correlate_pair
from lfpiv.studies.runner import Case, Finding, Setup, Study

__all__ = ["FACTOR", "PROTOCOL", "ltpr", "lf_rig", "tomo_rig"]

#: Per scale: the light-field sensors (the chapter's pixels across, before ``FACTOR``), PMRs,
#: Tomo-PIV camera counts and densities, iterations of each method and rays per particle.
PROTOCOL = {
    "tiny": {"lf_px": [800, 1600], "pmr": [7, 14], "cameras": [4, 8], "ppp": [0.05], "lf_its": 5, "tomo_its": 5,
             "rays": 500},
    "quick": {"lf_px": [800, 1600], "pmr": [7, 14, 28], "cameras": [4, 6, 8], "ppp": [0.05, 0.1], "lf_its": 50,
              "tomo_its": 20, "rays": 2000},
    "chapter": {"lf_px": [800, 1600], "pmr": [7, 14, 28], "cameras": [4, 6, 8], "ppp": [0.05, 0.1],
                "lf_its": 200, "tomo_its": 40, "rays": 20000},
}
#: Every sensor and the volume, as a fraction of the chapter's, per scale.
FACTOR = {"tiny": 0.125, "quick": 0.25, "chapter": 1.0}
#: The Tomo-PIV cameras' pixels across (the chapter's) and their pixel in the volume, mm.
TOMO_PX = 160
TOMO_PIXEL_MM = 0.075
#: The chapter's volume, mm (x, y, z), which every camera of the arc sees whole.
VOLUME_MM = (10.0, 10.0, 4.0)
#: The uniform shift, mm, and the seeding of the light-field cases.
SHIFT_MM = 0.15
LF_PPM = 0.5
LF_PIXEL_UM = 5.5
LF_F_NUMBER = 2.5
SEED = 17


def ltpr(lf_px: int, cameras: int, tomo_px: int = TOMO_PX) -> float:
    """Eq. 4.5 for square sensors: light-field pixels over all the Tomo-PIV cameras' pixels."""
    return lf_px * lf_px / (tomo_px * tomo_px * cameras)


def _sizes(scale: str) -> tuple[float, np.ndarray]:
    """The scale's factor and volume (x, y, z) mm: x and y cut by the factor, z by twice it (at
    most the chapter's depth), which the outermost cameras of the arc still see whole and which
    leaves the light-field voxels (10 pixels deep) a dozen voxels or more of depth."""
    f = FACTOR[scale]
    return f, np.asarray(VOLUME_MM) * np.array([f, f, min(1.0, 2.0 * f)])


def tomo_rig(cameras: int, scale: str) -> Rig:
    """The chapter's arc of ``cameras`` pinhole cameras (``examples/tomo_N_cameras.toml``), each
    sensor and the volume cut to ``FACTOR[scale]`` of theirs."""
    from lfpiv.commands import examples_dir

    f, size = _sizes(scale)
    d = load_rig(examples_dir() / f"tomo_{cameras}_cameras.toml").to_dict()
    px = max(8, round(TOMO_PX * f))
    for c in d["camera"]:
        c["sensor_px"] = [px, px]
    d["volume"]["size_mm"] = [round(float(v), 6) for v in size]
    d["laser"].update(sheet_profile="top-hat", sheet_axis="z", sheet_thickness_mm=float(size[2]))
    return Rig.from_dict(d)


def lf_rig(lf_px: int, pmr: int, scale: str) -> Rig:
    """A light-field camera of ``lf_px`` pixels across (the chapter's count; ``FACTOR[scale]`` of it
    at this scale) and ``pmr`` pixels per hexagonal lenslet, looking along z at the Tomo-PIV
    rig's field of view, f/2.5 with microlenses of matched f-number, PVR (2, 2, 10)."""
    from lfpiv.commands import examples_dir

    f, size = _sizes(scale)
    d = load_rig(examples_dir() / "one_camera.toml").to_dict()
    cam = d["camera"][0]
    m = -(lf_px * LF_PIXEL_UM * 1e-3) / (TOMO_PX * TOMO_PIXEL_MM)  # the sensor spans the Tomo field of view
    px = round(lf_px * f)
    px += px % 2  # an even sensor: a lenslet centre on its centre
    pitch = pmr * LF_PIXEL_UM
    cam.update(sensor_px=[px, px], pixel_pitch_um=LF_PIXEL_UM, mla_grid="hex", mla_pitch_um=pitch,
               mla_focal_length_um=round(pitch * LF_F_NUMBER * (1.0 - m), 6), f_number=LF_F_NUMBER,
               magnification=round(m, 9), rotation_deg=[0.0, 0.0, 0.0], focus_mm=[0.0, 0.0, 0.0])
    d["volume"].update(centre_mm=[0.0, 0.0, 0.0], size_mm=[round(float(v), 6) for v in size], pvr=[2.0, 2.0, 10.0])
    d["laser"].update(sheet_profile="top-hat", sheet_axis="z", sheet_thickness_mm=float(size[2]))
    return Rig.from_dict(d)


def _windows(grid: VolumeGrid) -> tuple[tuple[int, int, int], ...]:
    """Two passes: the largest power-of-two windows up to 32 that fit twice, then half of them
    (at least 4 voxels, the correlation's smallest)."""
    first, second = fitting_windows(grid.shape)
    return first, tuple(max(4, w) for w in second)


def run_pair(rig: Rig, *, method: str, iterations: int, ppm: float | None = None, ppp: float | None = None,
             rays: int | None = None, device: str | None = None) -> dict[str, Any]:
    """One pair of the uniform shift on ``rig``: reconstructed by ``method``, correlated, measured.

    Returns
    -------
    dict
        ``q`` (frame A), ``particle_rms_um`` (x, y, z RMS of the matched particle centres'
        errors), ``recall``, ``ghost_fraction``, ``displacement_rms_um`` (x, y, z RMS error of
        the vectors against the shift), ``shift_um``, ``voxel_um``, ``shape`` (z, y, x),
        ``particles``, ``windows``, ``seconds`` (the two reconstructions).
    """
    cam = rig.camera[0]
    scene = Scene(rig, flow="uniform", ppm=ppm if ppm is not None else 0.5, ppp=ppp,
                  displacement_px=SHIFT_MM / cam.object_pixel_mm, seed=SEED, rays_per_particle=rays, device=device)
    pair = scene.pair(0)
    grid = VolumeGrid.from_rig(rig)
    rec = Reconstructor(rig.camera, grid, render=rig.render, device=device)
    settings = ReconSettings.chapter(method=method, iterations=iterations)
    vols, seconds = [], 0.0
    for f in (0, 1):
        res, s = rec(pair.frame(f), settings)
        vols.append(res.volume)
        seconds += s
    ev = metrics.evaluate_volume(vols[0], grid, pair.particles[0], pair.brightness[0], centre_mm=rig.volume.centre_mm,
                                 size_mm=rig.volume.size_mm)
    err = ev.match.error_mm
    windows = _windows(grid)
    vec = correlate_pair(vols[0], vols[1], grid, CorrelationConfig(windows=windows, overlap=0.5), flow=scene.flow,
                         t0_s=pair.t0_s, dt_s=scene.dt_s, device=device)
    e_um = vec.error * np.asarray(grid.voxel_mm) * 1e3  # voxels to um, per component
    flat = e_um.reshape(-1, 3)
    flat = flat[np.all(np.isfinite(flat), axis=1)]
    shift = vec.truth.reshape(-1, 3)[0] * np.asarray(grid.voxel_mm) * 1e3
    return {"q": float(ev.q), "particle_rms_um": (np.sqrt(np.mean(err**2, axis=0)) * 1e3).tolist() if len(err)
            else [float("nan")] * 3, "recall": float(ev.match.recall), "ghost_fraction": float(ev.match.ghost_fraction),
            "displacement_rms_um": np.sqrt(np.mean(flat**2, axis=0)).tolist() if len(flat) else [float("nan")] * 3,
            "shift_um": shift.tolist(), "voxel_um": [1e3 * v for v in grid.voxel_mm], "shape": list(grid.shape),
            "particles": int(scene.world.n_particles), "windows": [list(w) for w in windows],
            "vectors": int(len(flat)), "seconds": seconds}


def _mean(v: Any) -> float:
    a = np.asarray(v, dtype=float)
    return float(np.sqrt(np.nanmean(a**2)))  # RMS over the three components


class LfVsTomoStudy(Study):
    name = "lf-vs-tomo"
    title = "one light-field camera against Tomo-PIV, by their pixel ratio (LTPR)"
    figures = "Figs. 4.23 and 4.24 (eq. 4.5)"

    def plan(self, setup: Setup) -> list[Case]:
        p = PROTOCOL[setup.scale]
        cases = [Case(f"tomo{n}_ppp{ppp:g}", {"kind": "tomo", "cameras": n, "ppp": ppp, "iterations": p["tomo_its"]})
                 for ppp in p["ppp"] for n in p["cameras"]]
        cases += [Case(f"lf{px}_pmr{pmr}", {"kind": "lf", "lf_px": px, "pmr": pmr, "ppm": LF_PPM,
                                            "iterations": p["lf_its"], "rays": p["rays"]})
                  for px in p["lf_px"] for pmr in p["pmr"]]
        return cases

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        if params["kind"] == "tomo":
            rig = tomo_rig(params["cameras"], setup.scale)
            return run_pair(rig, method="mlos-smart", iterations=params["iterations"], ppp=params["ppp"],
                            device=device)
        rig = lf_rig(params["lf_px"], params["pmr"], setup.scale)
        out = run_pair(rig, method="drt-mart", iterations=params["iterations"], ppm=params["ppm"],
                       rays=params["rays"], device=device)
        out["sensor_px"] = list(rig.camera[0].sensor_px)
        return out

    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        p = PROTOCOL[setup.scale]
        rows = []

        def row(kind: str, r: dict[str, Any], **what: Any) -> dict[str, Any]:
            d = r["displacement_rms_um"]
            c = r["particle_rms_um"]
            return {"kind": kind, **what, "Q": r["q"], "recall": r["recall"], "ghost_fraction": r["ghost_fraction"],
                    "disp_rms_x_um": d[0], "disp_rms_y_um": d[1], "disp_rms_z_um": d[2], "disp_rms_um": _mean(d),
                    "centre_rms_x_um": c[0], "centre_rms_y_um": c[1], "centre_rms_z_um": c[2],
                    "voxel_x_um": r["voxel_um"][0], "voxel_z_um": r["voxel_um"][2], "seconds": r["seconds"]}

        for ppp in p["ppp"]:
            for n in p["cameras"]:
                rows.append(row("tomo", results[f"tomo{n}_ppp{ppp:g}"], cameras=n, ppp=ppp, lf_px="", pmr="",
                                LTPR=""))
        for px in p["lf_px"]:
            for pmr in p["pmr"]:
                for n in p["cameras"]:  # one light-field case against each Tomo-PIV system
                    rows.append(row("lf", results[f"lf{px}_pmr{pmr}"], cameras=n, ppp="", lf_px=px, pmr=pmr,
                                    LTPR=round(ltpr(px, n), 4)))
        return rows

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        p = PROTOCOL[setup.scale]
        fig, ax = figures.panels(2, 2, title=f"Figs. 4.23-4.24 at --scale {setup.scale}")
        ppp0 = p["ppp"][0]
        for k, (key, label, letter) in enumerate((("disp", "RMS displacement error (um)", "a"),
                                                  ("q", "Q_recon", "b"))):
            a = ax[0, k]
            for j, pmr in enumerate(p["pmr"]):
                xs, ys = [], []
                for px in p["lf_px"]:
                    r = results[f"lf{px}_pmr{pmr}"]
                    for n in p["cameras"]:
                        xs.append(ltpr(px, n))
                        ys.append(_mean(r["displacement_rms_um"]) if key == "disp" else r["q"])
                order = np.argsort(xs)
                a.plot(np.asarray(xs)[order], np.asarray(ys)[order], "o-", color=f"C{j}", label=f"LF-PIV PMR {pmr}")
            for n, marker in zip(p["cameras"], "s^Dv", strict=False):
                r = results[f"tomo{n}_ppp{ppp0:g}"]
                v = _mean(r["displacement_rms_um"]) if key == "disp" else r["q"]
                xs = [ltpr(px, n) for px in p["lf_px"]]
                a.plot(xs, [v] * len(xs), marker, color="k", mfc="none", label=f"Tomo-PIV {n} cameras, {ppp0:g} ppp")
            figures.log_x(a)
            a.set_xlabel("LTPR (eq. 4.5)")
            a.set_ylabel(label)
            if key == "q":
                a.set_ylim(0, 1)
            else:
                a.set_yscale("log")  # the two kinds' errors differ by an order of magnitude
            a.legend(fontsize=7)
            figures.label(a, letter, f"{label.split(' (')[0]} against LTPR (Fig. 4.24)")
        a = ax[1, 0]
        names, vals = [], []
        for ppp in p["ppp"]:
            for n in p["cameras"]:
                names.append(f"{n} cams\n{ppp:g} ppp")
                vals.append(results[f"tomo{n}_ppp{ppp:g}"]["displacement_rms_um"])
        _bars(a, names, vals)
        figures.label(a, "c", "Tomo-PIV: RMS error per component (Fig. 4.24b)")
        a = ax[1, 1]
        names, vals = [], []
        for px in p["lf_px"]:
            for pmr in p["pmr"]:
                names.append(f"{px} px\nPMR {pmr}")
                vals.append(results[f"lf{px}_pmr{pmr}"]["displacement_rms_um"])
        _bars(a, names, vals)
        figures.label(a, "d", "LF-PIV: RMS error per component (Fig. 4.24a)")
        figures.save(fig, path)

    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        p = PROTOCOL[setup.scale]
        out = []
        ppp0 = p["ppp"][0]
        tomo = {n: _mean(results[f"tomo{n}_ppp{ppp0:g}"]["displacement_rms_um"]) for n in p["cameras"]}
        fewest, most = min(p["cameras"]), max(p["cameras"])
        out.append(Finding("Fig. 4.24b", "Tomo-PIV's error falls as cameras are added",
                           f"{ppp0:g} ppp, RMS error " + ", ".join(f"{n} cameras {v:.2f} um" for n, v in tomo.items()),
                           "reproduced" if all(np.diff([tomo[n] for n in sorted(tomo)]) <= 0) else
                           ("partly" if tomo[most] < tomo[fewest] else "not reproduced"),
                           f"{tomo[fewest] / max(tomo[most], 1e-12):.2f}x from {fewest} to {most} cameras"))
        centre = {n: _mean(results[f"tomo{n}_ppp{ppp0:g}"]["particle_rms_um"]) for n in p["cameras"]}
        qn = {n: results[f"tomo{n}_ppp{ppp0:g}"]["q"] for n in p["cameras"]}
        out.append(Finding("Fig. 4.23a", "Tomo-PIV reconstructs the particles more accurately with more cameras",
                           f"{ppp0:g} ppp, particle centres' RMS error "
                           + ", ".join(f"{n} cameras {centre[n]:.1f} um (Q {qn[n]:.3f})" for n in p["cameras"]),
                           "reproduced" if centre[most] < centre[fewest] and qn[most] > qn[fewest] else
                           ("partly" if centre[most] < centre[fewest] or qn[most] > qn[fewest] else "not reproduced"),
                           f"{centre[fewest] / max(centre[most], 1e-12):.2f}x from {fewest} to {most} cameras"))
        if len(p["ppp"]) > 1:
            lo, hi = p["ppp"][0], p["ppp"][-1]
            c = {n: (_mean(results[f"tomo{n}_ppp{lo:g}"]["particle_rms_um"]),
                     _mean(results[f"tomo{n}_ppp{hi:g}"]["particle_rms_um"])) for n in p["cameras"]}
            qs = {n: (results[f"tomo{n}_ppp{lo:g}"]["q"], results[f"tomo{n}_ppp{hi:g}"]["q"]) for n in p["cameras"]}
            worse = [n for n in p["cameras"] if c[n][1] > c[n][0] and qs[n][1] < qs[n][0]]
            out.append(Finding("Fig. 4.23a-b", f"Tomo-PIV reconstructs less accurately at {hi:g} ppp than at "
                               f"{lo:g} ppp (ghost particles)",
                               f"particle centres' RMS error, Q at {lo:g} / {hi:g} ppp: "
                               + ", ".join(f"{n} cameras {a:.1f} / {b:.1f} um, {qs[n][0]:.3f} / {qs[n][1]:.3f}"
                                           for n, (a, b) in c.items()),
                               "reproduced" if len(worse) == len(p["cameras"]) else ("partly" if worse else
                                                                                    "not reproduced"),
                               f"less accurate at {hi:g} ppp with {len(worse)} of {len(p['cameras'])} camera counts"))
        lf = {(px, pmr): _mean(results[f"lf{px}_pmr{pmr}"]["displacement_rms_um"]) for px in p["lf_px"]
              for pmr in p["pmr"]}
        small, large = min(p["lf_px"]), max(p["lf_px"])
        better = [pmr for pmr in p["pmr"] if lf[(large, pmr)] < lf[(small, pmr)]]
        out.append(Finding("Fig. 4.24a", f"a light-field camera of more pixels ({large} against {small}) is more "
                           "accurate at every PMR",
                           ", ".join(f"PMR {pmr}: {lf[(small, pmr)]:.2f} / {lf[(large, pmr)]:.2f} um"
                                     for pmr in p["pmr"]) + f" at {small} / {large} px",
                           "reproduced" if len(better) == len(p["pmr"]) else ("partly" if better else "not reproduced"),
                           f"more accurate at {len(better)} of {len(p['pmr'])} PMRs"))
        cz = {(px, pmr): results[f"lf{px}_pmr{pmr}"]["particle_rms_um"][2] for px in p["lf_px"] for pmr in p["pmr"]}
        finer = [pmr for pmr in p["pmr"] if (cz[(large, pmr)] or np.inf) < (cz[(small, pmr)] or np.inf)]
        out.append(Finding("Fig. 4.23c-d", "a larger LTPR (more light-field pixels) reconstructs the particles' depth "
                           "more accurately", "particle centres' z RMS error at " + f"{small} / {large} px: "
                           + ", ".join(f"PMR {m} {cz[(small, m)]:.0f} / {cz[(large, m)]:.0f} um" for m in p["pmr"]),
                           "reproduced" if len(finer) == len(p["pmr"]) else ("partly" if finer else "not reproduced"),
                           f"finer at {len(finer)} of {len(p['pmr'])} PMRs"))
        if 14 in p["pmr"] and len(p["pmr"]) > 2:
            best = min(p["pmr"], key=lambda m: lf[(large, m)])
            out.append(Finding("Fig. 4.24a", "PMR 14 strikes the best compromise of depth resolution and lenslet "
                               "count", f"{large} px: " + ", ".join(f"PMR {m} {lf[(large, m)]:.2f} um"
                                                                    for m in p["pmr"]),
                               "reproduced" if best == 14 else "not reproduced", f"best at PMR {best}"))
        # the key claim: at high LTPR one light-field camera reaches Tomo-PIV's accuracy
        best_pmr = min(p["pmr"], key=lambda m: lf[(large, m)])
        best = results[f"lf{large}_pmr{best_pmr}"]["displacement_rms_um"]
        best_lf = lf[(large, best_pmr)]
        lateral = _mean(best[:2])
        reached = [n for n in p["cameras"] if best_lf <= tomo[n]]
        sideways = [n for n in p["cameras"]
                    if lateral <= _mean(results[f"tomo{n}_ppp{ppp0:g}"]["displacement_rms_um"][:2])]
        hi_ltpr = ", ".join(f"{ltpr(large, n):.3g}" for n in p["cameras"])
        tz = {n: results[f"tomo{n}_ppp{ppp0:g}"]["displacement_rms_um"][2] for n in p["cameras"]}
        out.append(Finding("Figs. 4.23-4.24", "at high LTPR (12.5-25) one light-field camera reaches Tomo-PIV's "
                           "accuracy", f"best {large}-px LF-PIV (PMR {best_pmr}, LTPR {hi_ltpr}): RMS x, y, z "
                           + ", ".join(f"{v:.1f}" for v in best) + " um; Tomo-PIV "
                           + "; ".join(f"{n} cameras " + ", ".join(f"{v:.1f}" for v in
                                                                   results[f"tomo{n}_ppp{ppp0:g}"]["displacement_rms_um"])
                                       for n in p["cameras"]) + " um",
                           "reproduced" if reached else ("partly" if sideways else "not reproduced"),
                           f"as accurate overall as {len(reached)} of {len(p['cameras'])} Tomo-PIV systems; across "
                           f"the view (x, y) as {len(sideways)} of them; in depth {best[2]:.1f} against "
                           f"{min(tz.values()):.1f}-{max(tz.values()):.1f} um"))
        low = lf[(small, min(p["pmr"]))]
        comparable = [n for n in p["cameras"] if low <= 2.0 * tomo[n]]
        out.append(Finding("Fig. 4.24", f"even at low LTPR ({', '.join(f'{ltpr(small, n):.3g}' for n in p['cameras'])}"
                           f") and PMR {min(p['pmr'])}, LF-PIV is comparable to Tomo-PIV",
                           f"{small} px PMR {min(p['pmr'])}: {low:.2f} um against Tomo-PIV "
                           + ", ".join(f"{tomo[n]:.2f}" for n in p["cameras"]) + " um",
                           "reproduced" if len(comparable) == len(p["cameras"]) else
                           ("partly" if comparable else "not reproduced"),
                           f"within 2x of {len(comparable)} of {len(p['cameras'])} systems"))
        return out

    def protocol(self, setup: Setup) -> list[str]:
        p = PROTOCOL[setup.scale]
        f = FACTOR[setup.scale]
        tomo = tomo_rig(p["cameras"][0], setup.scale)
        grid_t = VolumeGrid.from_rig(tomo)
        lines = []
        if setup.rig is not None:
            lines.append(f"This study compares the chapter's own rigs (below); the {setup.rig_name} rig is not used.")
        if f < 1:
            lines.append(f"Scaled down: every sensor and the volume are {f:g} of the chapter's (Tomo-PIV cameras "
                         f"{tomo.camera[0].sensor_px[0]} px across instead of {TOMO_PX}, light-field cameras "
                         + " and ".join(f"{round(px * f)}" for px in p["lf_px"]) + " px instead of "
                         + " and ".join(map(str, p["lf_px"])) + f"), the volume's depth {min(1.0, 2 * f):g} of the "
                         "chapter's, the pixels' size in the volume kept: every LTPR, voxel, particle image and "
                         "density is the chapter's, the field of view and the depth are smaller.")
        lines.append(f"Volume {' x '.join(f'{v:g}' for v in tomo.volume.size_mm)} mm; Tomo-PIV on "
                     f"{' x '.join(map(str, grid_t.shape[::-1]))} voxels (PVR 1, {1e3 * grid_t.voxel_mm[0]:.0f} um), "
                     f"{', '.join(map(str, p['cameras']))} cameras of the chapter's arc, "
                     f"{', '.join(f'{x:g}' for x in p['ppp'])} ppp, MLOS-SMART {p['tomo_its']} iterations.")
        for px in p["lf_px"]:
            rig = lf_rig(px, p["pmr"][0], setup.scale)
            g = VolumeGrid.from_rig(rig)
            lines.append(f"LF-PIV {px} px (here {rig.camera[0].sensor_px[0]}), M = {rig.camera[0].magnification:.3g}, "
                         f"PMR {', '.join(map(str, p['pmr']))}, {LF_PPM:g} PPM, {p['rays']} rays per particle, "
                         f"DRT-MART {p['lf_its']} iterations on {' x '.join(map(str, g.shape[::-1]))} voxels "
                         f"(PVR 2, 2, 10); LTPR {', '.join(f'{ltpr(px, n):.3g}' for n in p['cameras'])}.")
        lines.append(f"One pair of a uniform shift of {SHIFT_MM:g} mm (the chapter: a DNS jet), correlated in two "
                     "passes of the largest power-of-two windows that fit twice, then half of them, 50% overlap; "
                     "errors in um so that both kinds' voxels compare (the chapter: in voxels of each).")
        return lines


def _bars(a, names: list[str], vals: list[list[float]]) -> None:
    x = np.arange(len(names))
    v = np.asarray(vals, dtype=float)
    for k, comp in enumerate("xyz"):
        a.bar(x + (k - 1) * 0.27, v[:, k], width=0.27, label=comp, color=f"C{k}")
    a.set_xticks(x)
    a.set_xticklabels(names, fontsize=7)
    a.set_ylabel("RMS displacement error (um)")
    a.legend(fontsize=7)


STUDY = LfVsTomoStudy()
