"""How dense a seeding one camera's particle route takes, beside DRT-MART + correlation (issue 48).

Run from the repository root::

    python benchmarks/density.py                             # 0.1, 0.25, 0.5, 1, 2 PPM, seed 14
    python benchmarks/density.py --ppms 0.5,1 --seeds 14,15
    python benchmarks/density.py --ppms '' --time-resolved 1,2   # 3 time-resolved pairs, tracked along them
    python benchmarks/density.py --ppms 0.1 --json out.json  # the figures as JSON too

For each density (``--ppms``, particles per microlens) and seed, end to end through the ``lfpiv``
command (a child process per stage, as a user runs it), on the tiny one-camera rig focused beyond its
box (``examples/one_camera_off_focus.toml``, 192 x 160 px, 82 x 68 x 29 voxels of 11 x 11 x 55 um):

1. ``lfpiv synth --flow A1 --omega 4.449 --displacement-px 10 --ppm P --seed S --pairs 1``: Table 4.1's
   A1 (u = 5 voxels x cos(k x)), one double-frame pair, Monte-Carlo frames with noise;
2. the voxel route on two copies of it: ``lfpiv reconstruct`` with its defaults (for one light-field
   camera the ``fast`` protocol) and with ``--protocol fixed --iterations 100`` (the seventh session's
   A1 run), each then ``lfpiv correlate --windows 64x64x16,32x32x16 --overlap 0.75`` and ``lfpiv
   evaluate``;
3. the particle route on a copy of the fixed reconstruction's run (its volumes are the tracking's
   predictor, as the seventh session ran A1): ``lfpiv particles`` (defaults), ``lfpiv track --predictor
   volumes --search-voxels 2,2,2`` (otherwise defaults: the fitted field on 16 x 16 x 8 bins) and
   ``lfpiv evaluate``.

With ``--time-resolved PPMS`` also a time-resolved series of ``--tr-pairs`` pairs at each of those densities
(``synth --time-resolved``), ``lfpiv particles`` and ``lfpiv track --along-pairs --search-voxels
6,2,2`` (no predictor, as the eighth session), its field's RMS over all the pairs, beside the fixed
reconstruction's correlation of the same frames.

Reported per density: the particles per frame; the particle route's recall, ghosts (found with no
true particle within 1 voxel per axis, as a share of those found) and position RMS per axis in voxels;
each field's RMS per axis in voxels (over its own filled points), as a share of the peak speed and the
share of its grid points filled; the reconstructions' Q and their volume peaks (``lfpiv evaluate``'s
detection at 0.1 of the brightest voxel) matched within 1 voxel as the particles are; the CPU seconds
of every stage's process (user + system, of the process and its children, from ``os.wait4``) and its
peak RSS. Issue 48's one-camera goals (A1 at 0.5 PPM): recall >= 90%, ghosts <= 5% of the particles
found, position RMS <= 0.1, 0.1, 0.3 voxel; the field <= 0.1, 0.1, 0.3 voxel and better than
correlation's (here: below the fixed reconstruction's correlation on every axis; the shares of the peak
speed are printed beside). The figures are read from the run stores by :mod:`lfpiv.jobs.evaluate`, the
code ``lfpiv evaluate`` prints them with; ``--from-json FILE`` prints an earlier run's tables again.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_particles, evaluate_run, evaluate_vector_fields  # noqa: E402

RIG = ROOT / "examples" / "one_camera_off_focus.toml"
#: issue 48's one-camera goals: positions and field RMS per axis (voxels), recall and ghosts.
GOAL_RMS = np.array([0.1, 0.1, 0.3])
GOAL_RECALL, GOAL_GHOSTS = 0.9, 0.05
WINDOWS, OVERLAP = "64x64x16,32x32x16", "0.75"


def lfpiv(stages: dict, name: str, *argv: object) -> str:
    """Run ``lfpiv ARGV`` as a child process; record its CPU seconds, wall seconds and peak RSS under
    ``stages[name]``; return its stdout. A failure stops the benchmark with the command's stderr."""
    cmd = [sys.executable, "-m", "lfpiv", *map(str, argv)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=err, env=env, text=True)
        _, status, ru = os.wait4(p.pid, 0)  # the child's own resource usage, its reaped children included
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        text, errors = out.read(), err.read()
    if p.returncode:
        sys.exit(f"lfpiv {' '.join(map(str, argv))} failed (exit {p.returncode}):\n{errors[-3000:]}")
    stages[name] = {"cpu_s": ru.ru_utime + ru.ru_stime, "wall_s": wall, "rss_gib": ru.ru_maxrss / 2**20}
    return text


def field(run: Path) -> dict:
    """A run's vectors against the truth: RMS per axis (voxels), % of the peak speed, share filled."""
    store = RunStore.open(run)
    ev = evaluate_vector_fields(store)
    assert not isinstance(ev, str), ev
    u = np.stack([store.read_vectors(p)["u"] for p in ev.pairs])
    return {"rms": [float(v) for v in ev.rms_voxels], "of_peak": float(ev.errors.of_peak),
            "filled": float(np.isfinite(u).mean()), "grid": list(ev.counts), "pairs": len(ev.pairs)}


def positions(matches: list, voxel: np.ndarray) -> dict:
    """Recall, ghosts and RMS per axis (voxels) of several frames' one-to-one matches, pooled."""
    n_true = sum(m.n_true for m in matches)
    n_det = sum(m.n_detected for m in matches)
    err = np.concatenate([m.error_mm for m in matches])
    rms = np.sqrt(np.mean(err**2, axis=0)) / voxel if len(err) else np.full(3, np.nan)
    return {"recall": sum(m.n_matched for m in matches) / max(n_true, 1),
            "ghosts": sum(m.ghosts for m in matches) / max(n_det, 1),
            "rms": [float(v) for v in rms], "found": n_det / len(matches)}


def voxel_route(run: Path) -> dict:
    """Q and the volume peaks' recall, ghosts and RMS (matched within 1 voxel per axis) of a run's volumes."""
    store = RunStore.open(run)
    evals = evaluate_run(store, match_voxels=1.0)
    voxel = np.asarray(store.volume_grid().voxel_mm)
    return {"q": float(np.mean([e.q for e in evals])), "peaks": positions([e.match for e in evals], voxel)}


def one(ppm: float, seed: int, work: Path) -> dict:
    """The whole comparison at one density and seed; the figures and every stage's cost."""
    stages: dict = {}
    base = work / f"a1_{ppm:g}_{seed}.zarr"
    lfpiv(stages, "synth", "synth", "--rig", RIG, "--out", base, "--flow", "A1", "--omega", "4.449",
          "--displacement-px", "10", "--ppm", ppm, "--seed", seed, "--pairs", "1", "--quiet")
    truth = RunStore.open(base).truth()["particles"]
    res: dict = {"ppm": ppm, "seed": seed, "particles": float(np.mean([len(f) for pair in truth for f in pair]))}
    for proto, extra in (("default", ()), ("fixed", ("--protocol", "fixed", "--iterations", "100"))):
        run = work / f"{base.stem}_{proto}.zarr"
        shutil.copytree(base, run)
        lfpiv(stages, f"reconstruct {proto}", "reconstruct", run, *extra, "--quiet")
        if proto == "fixed":  # the particle route's copy: its volumes are the tracking's predictor
            part = work / f"{base.stem}_particles.zarr"
            shutil.copytree(run, part)
        lfpiv(stages, f"correlate {proto}", "correlate", run, "--windows", WINDOWS, "--overlap", OVERLAP, "--quiet")
        lfpiv(stages, f"evaluate {proto}", "evaluate", run)
        res[f"voxels {proto}"] = {**voxel_route(run), "field": field(run)}
    lfpiv(stages, "particles", "particles", part, "--quiet")
    lfpiv(stages, "track", "track", part, "--predictor", "volumes", "--search-voxels", "2,2,2", "--quiet")
    lfpiv(stages, "evaluate particles", "evaluate", part)
    store = RunStore.open(part)
    pe = evaluate_particles(store, match_voxels=1.0)
    res["particle route"] = {**positions([e.match for e in pe], pe[0].voxel_mm), "field": field(part)}
    res["stages"] = stages
    return res


def time_resolved(ppm: float, seed: int, pairs: int, work: Path) -> dict:
    """A time-resolved series at one density: particles, tracks along the pairs, the field's RMS."""
    stages: dict = {}
    run = work / f"a1tr_{ppm:g}_{seed}.zarr"
    lfpiv(stages, "synth", "synth", "--rig", RIG, "--out", run, "--flow", "A1", "--omega", "4.449",
          "--displacement-px", "10", "--ppm", ppm, "--seed", seed, "--pairs", pairs, "--time-resolved", "--quiet")
    vox = work / f"{run.stem}_fixed.zarr"
    shutil.copytree(run, vox)
    # frame by frame, and along the pairs with the defaults before the fourteenth session, as recorded
    lfpiv(stages, "particles", "particles", run, "--pair-by-pair", "--quiet")
    lfpiv(stages, "track --along-pairs", "track", run, "--along-pairs", "--search-voxels", "6,2,2", "--no-relink",
          "--pool-pairs", "0", "--field", "fit", "--quiet")
    lfpiv(stages, "evaluate", "evaluate", run)
    store = RunStore.open(run)
    pe = evaluate_particles(store, match_voxels=1.0)
    lfpiv(stages, "reconstruct fixed", "reconstruct", vox, "--protocol", "fixed", "--iterations", "100", "--quiet")
    lfpiv(stages, "correlate fixed", "correlate", vox, "--windows", WINDOWS, "--overlap", OVERLAP, "--quiet")
    return {"ppm": ppm, "seed": seed, "pairs": pairs, **positions([e.match for e in pe], pe[0].voxel_mm),
            "field": field(run), "voxels fixed": {"field": field(vox)}, "stages": stages}


def goals(r: dict, corr: dict | None = None) -> str:
    """Which of issue 48's one-camera goals a route meets: R recall, G ghosts, P positions, F field
    within 0.1, 0.1, 0.3 voxel, C the field better than ``corr``'s on every axis (lower case: missed)."""
    out = ""
    if "recall" in r:
        out += "R" if r["recall"] >= GOAL_RECALL else "r"
        out += "G" if r["ghosts"] <= GOAL_GHOSTS else "g"
        out += "P" if np.all(np.asarray(r["rms"]) <= GOAL_RMS) else "p"
    f = np.asarray(r["field"]["rms"])
    out += "F" if np.all(f <= GOAL_RMS) else "f"
    if corr is not None:
        out += "C" if np.all(f < np.asarray(corr["field"]["rms"])) else "c"
    return out


def meets_all(r: dict, corr: dict | None = None) -> bool:
    return goals(r, corr).isupper()


def _v(xs) -> str:
    return ", ".join(f"{x:.3f}" for x in xs)


def tables(results: list[dict], tr: list[dict]) -> str:
    """The markdown tables of the results."""
    lines = ["Particle route (`particles`, `track --predictor volumes --search-voxels 2,2,2`, fit on 16x16x8 bins):",
             "", "| PPM | seed | particles / frame | recall | ghosts | position RMS x, y, z (voxel) | "
             "field RMS x, y, z (voxel) | % of peak | filled | goals |", "| --- " * 10 + "|"]
    for r in results:
        p, corr = r["particle route"], r["voxels fixed"]
        lines.append(f"| {r['ppm']:g} | {r['seed']} | {r['particles']:.0f} | {p['recall']:.3f} | "
                     f"{100 * p['ghosts']:.1f}% | {_v(p['rms'])} | {_v(p['field']['rms'])} | "
                     f"{100 * p['field']['of_peak']:.1f} | {100 * p['field']['filled']:.0f}% | {goals(p, corr)} |")
    lines += ["", "Voxel route (`reconstruct`, `correlate --windows 64x64x16,32x32x16 --overlap 0.75`; the "
              "volume peaks matched within 1 voxel):", "",
              "| PPM | seed | reconstruct | Q | peaks recall | peaks ghosts | peaks RMS x, y, z (voxel) | "
              "field RMS x, y, z (voxel) | % of peak | goals (peaks, field) |", "| --- " * 10 + "|"]
    for r in results:
        for proto in ("default", "fixed"):
            v = r[f"voxels {proto}"]
            pk = v["peaks"]
            lines.append(f"| {r['ppm']:g} | {r['seed']} | {proto} | {v['q']:.3f} | {pk['recall']:.3f} | "
                         f"{100 * pk['ghosts']:.1f}% | {_v(pk['rms'])} | {_v(v['field']['rms'])} | "
                         f"{100 * v['field']['of_peak']:.1f} | {goals({**pk, 'field': v['field']})} |")
    names = list(results[0]["stages"]) if results else []
    if names:
        lines += ["", "CPU seconds of each stage's process (peak RSS, GiB):", "",
                  "| PPM | seed | " + " | ".join(names) + " |", "| --- " * (len(names) + 2) + "|"]
        for r in results:
            s = r["stages"]
            lines.append(f"| {r['ppm']:g} | {r['seed']} | "
                         + " | ".join(f"{s[n]['cpu_s']:.1f} ({s[n]['rss_gib']:.2f})" for n in names) + " |")
    if results:
        lines += route_cpu(results)
    if tr:
        lines += ["", "Time-resolved (`synth --time-resolved`, `particles`, `track --along-pairs --search-voxels "
                  "6,2,2`), all pairs:", "",
                  "| PPM | seed | pairs | recall | ghosts | position RMS x, y, z | field RMS x, y, z | % of peak | "
                  "filled | goals | correlation (fixed 100): RMS x, y, z, % | CPU s particles, track |",
                  "| --- " * 12 + "|"]
        for r in tr:
            s = r["stages"]
            corr = r.get("voxels fixed")
            cf = f"{_v(corr['field']['rms'])}, {100 * corr['field']['of_peak']:.1f}" if corr else ""
            lines.append(f"| {r['ppm']:g} | {r['seed']} | {r['pairs']} | {r['recall']:.3f} | "
                         f"{100 * r['ghosts']:.1f}% | {_v(r['rms'])} | {_v(r['field']['rms'])} | "
                         f"{100 * r['field']['of_peak']:.1f} | {100 * r['field']['filled']:.0f}% | {goals(r, corr)} | "
                         f"{cf} | {s['particles']['cpu_s']:.0f}, {s['track --along-pairs']['cpu_s']:.1f} |")
    lines += ["", "Goals: R recall >= 0.9, G ghosts <= 5%, P positions <= 0.1, 0.1, 0.3 voxel, F field <= 0.1, "
              "0.1, 0.3 voxel, C field below the fixed reconstruction's correlation on every axis; lower case: "
              "missed."]
    if results:
        lines += ["", limits(results)]
    return "\n".join(lines)


def limits(results: list[dict]) -> str:
    """For each goal of each route, the densities where it is met on every seed run."""
    ppms = sorted({r["ppm"] for r in results})

    def where(route: str, letter: str) -> str:
        def ok(r: dict) -> bool:
            if route == "particle route":
                return letter in goals(r[route], r["voxels fixed"])
            return letter in goals({**r[route]["peaks"], "field": r[route]["field"]})

        met = [p for p in ppms if all(ok(r) for r in results if r["ppm"] == p)]
        return ", ".join(f"{p:g}" for p in met) + " PPM" if met else "none"

    names = (("R", "recall"), ("G", "ghosts"), ("P", "positions"), ("F", "field"))
    parts = ["particle route: " + ", ".join(f"{name} at {where('particle route', k)}" for k, name in
                                             (*names, ("C", "field better than correlation's")))]
    parts += [f"DRT-MART ({proto}) peaks and correlation: " + ", ".join(f"{name} at {where(f'voxels {proto}', k)}"
                                                                      for k, name in names)
              for proto in ("default", "fixed")]
    return "Where each goal is met on every seed (of " + ", ".join(f"{p:g}" for p in ppms) + " PPM): " + \
        "; ".join(parts) + "."


def route_cpu(results: list[dict]) -> list[str]:
    """CPU seconds of each route, its stages summed (the particle route's predictor volumes apart)."""
    lines = ["", "CPU seconds a route (one pair):", "",
             "| PPM | seed | particles + track | its predictor (reconstruct fixed) | reconstruct + correlate, "
             "default | reconstruct + correlate, fixed 100 |", "| --- " * 6 + "|"]
    for r in results:
        s = {k: v["cpu_s"] for k, v in r["stages"].items()}
        lines.append(f"| {r['ppm']:g} | {r['seed']} | {s['particles'] + s['track']:.1f} | {s['reconstruct fixed']:.1f}"
                     f" | {s['reconstruct default'] + s['correlate default']:.1f} | "
                     f"{s['reconstruct fixed'] + s['correlate fixed']:.1f} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ppms", default="0.1,0.25,0.5,1,2", help="densities, particles per microlens")
    ap.add_argument("--seeds", default="14", help="seeds, comma-separated")
    ap.add_argument("--time-resolved", default="", metavar="PPMS",
                    help="also a time-resolved series at each of these densities, tracked along the pairs")
    ap.add_argument("--tr-pairs", type=int, default=3, help="the time-resolved series' pairs")
    ap.add_argument("--work", default=None, help="keep the run stores in this folder (default: a temporary one)")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--from-json", default=None, metavar="FILE",
                    help="print the tables of an earlier --json; run nothing")
    args = ap.parse_args(argv)
    if args.from_json:
        d = json.loads(Path(args.from_json).read_text())
        print(tables(d["results"], d["time_resolved"]))
        return
    ppms = [float(p) for p in args.ppms.split(",") if p]
    tr_ppms = [float(p) for p in args.time_resolved.split(",") if p]
    seeds = [int(s) for s in args.seeds.split(",")]
    results, tr = [], []
    with tempfile.TemporaryDirectory(prefix="density_") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for ppm in ppms:
            for seed in seeds:
                results.append(one(ppm, seed, work))
                r = results[-1]
                print(f"{ppm:g} PPM seed {seed}: particles {goals(r['particle route'], r['voxels fixed'])} "
                      f"{_v(r['particle route']['rms'])} field {_v(r['particle route']['field']['rms'])}; "
                      f"correlation {_v(r['voxels fixed']['field']['rms'])}", file=sys.stderr, flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps({"results": results, "time_resolved": tr}, indent=1))
        for ppm in tr_ppms:
            for seed in seeds:
                tr.append(time_resolved(ppm, seed, args.tr_pairs, work))
                print(f"{ppm:g} PPM seed {seed}, time-resolved: {goals(tr[-1])} {_v(tr[-1]['rms'])} "
                      f"field {_v(tr[-1]['field']['rms'])}", file=sys.stderr, flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps({"results": results, "time_resolved": tr}, indent=1))
    print(tables(results, tr))


if __name__ == "__main__":
    main()
