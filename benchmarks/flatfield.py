"""The flat field's worth: Q and the end-to-end vector error of a rig with a strong camera response,
its frames uncorrected and corrected by the calibration's dark and white images, beside the same
rig with a clean response (issue 49's goal: corrected within 2% of clean).

Run from the repository root (a few minutes on a 2-core CPU)::

    python benchmarks/flatfield.py
    python benchmarks/flatfield.py --rig examples/demo.toml --pairs 2 --falloff 0.4 --dust 5

The same particles and flow (one seed) are rendered three times by ``lfpiv synth``: with the rig's
``[render]`` as it is (clean), and with main-lens fall-off (``--falloff`` at the corners),
micro-image vignetting (``--micro``), ``--dust`` dust shadows and a dark offset with fixed-pattern
noise. The response rig is reconstructed as recorded (one background level per camera) and with
``--flat-field`` from ``lfpiv calibrate mla --dark-frames`` (the simulated lab's white diffuser and
darkness through the same response); every run is correlated and evaluated against its truth by
the commands a user runs. Q is the mean over the reconstructed frames; the vector error is the RMS
error vector's magnitude over the peak speed (``lfpiv evaluate``'s).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfpiv.jobs.demo import demo_windows  # noqa: E402
from lfpiv.jobs.evaluate import evaluate_run, evaluate_vector_fields  # noqa: E402
from lfpiv.runs import open_run  # noqa: E402


def lfpiv(*args: str, cwd: Path) -> float:
    """Run an lfpiv command; its seconds."""
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-m", "lfpiv", *args], cwd=cwd, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"lfpiv {' '.join(args)} failed:\n{res.stderr}")
    return time.perf_counter() - t0


def figures(run: Path) -> tuple[float, float]:
    """(mean Q over the frames, vector error over the peak speed) of an evaluated synthetic run."""
    store = open_run(run)
    q = float(np.mean([e.q for e in evaluate_run(store)]))
    vec = evaluate_vector_fields(store)
    if isinstance(vec, str) or vec.errors is None:
        raise SystemExit(f"{run}: no vector errors ({vec})")
    return q, vec.errors.of_peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(ROOT / "examples" / "demo.toml"))
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--ppm", type=float, default=0.3)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--falloff", type=float, default=0.4, help="main-lens fall-off at the corners (default 0.4)")
    ap.add_argument("--micro", type=float, default=0.3, help="micro-image vignetting at the rims (default 0.3)")
    ap.add_argument("--dust", type=int, default=5, help="dust shadows (default 5)")
    ap.add_argument("--dust-radius", type=float, default=8.0, help="dust shadow radius, pixels (default 8)")
    ap.add_argument("--dust-opacity", type=float, default=0.7, help="light a dust shadow takes (default 0.7)")
    ap.add_argument("--fpn", type=float, default=5.0, help="dark fixed-pattern noise, counts (default 5)")
    ap.add_argument("--keep", default=None, help="folder to keep the runs in (default: a temporary one)")
    args = ap.parse_args()
    text = Path(args.rig).read_text()
    response = (f"lens_falloff = {args.falloff}\nmicro_vignetting = {args.micro}\ndust_spots = {args.dust}\n"
                f"dust_radius_px = {args.dust_radius}\ndust_opacity = {args.dust_opacity}\n"
                f"dark_fpn_counts = {args.fpn}\n")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        (work / "clean.toml").write_text(text)
        (work / "response.toml").write_text(text.replace("[render]\n", "[render]\n" + response))
        synth = ("--pairs", str(args.pairs), "--ppm", str(args.ppm), "--seed", "7", "--quiet", "--overwrite")
        recon = ("--iterations", str(args.iterations), "--quiet")
        rows, seconds = {}, {}
        for name, rig in (("clean", "clean.toml"), ("response", "response.toml")):
            seconds[name] = lfpiv("synth", "--rig", rig, "--out", f"{name}.zarr", *synth, cwd=work)
        cal = lfpiv("calibrate", "mla", "--rig", "response.toml", "--out", "cal.zarr", "--dark-frames", "4",
                    "--sim-vignetting", "0", "--sim-dead", "0", "--quiet", cwd=work)
        # the corrected run: a copy of the response run's frames, reconstructed with the flat field
        subprocess.run(["cp", "-r", str(work / "response.zarr"), str(work / "corrected.zarr")], check=True)
        for name, extra in (("clean", ()), ("response", ()), ("corrected", ("--flat-field", "cal.zarr"))):
            t = lfpiv("reconstruct", f"{name}.zarr", *recon, *extra, cwd=work)
            t += lfpiv("correlate", f"{name}.zarr", "--windows", demo_windows(str(work / f"{name}.zarr")), "--quiet",
                       cwd=work)
            seconds[name] = seconds.get(name, 0.0) + t
            rows[name] = figures(work / f"{name}.zarr")
    q0, v0 = rows["clean"]
    print(f"rig {Path(args.rig).name}, {args.pairs} pair(s) at {args.ppm} PPM, {args.iterations} iterations; response: "
          f"fall-off {args.falloff:.0%} at the corners, micro-image vignetting {args.micro:.0%}, {args.dust} dust "
          f"shadows ({args.dust_radius:g} px, {args.dust_opacity:.0%} opaque),"
          f" dark fixed pattern {args.fpn:g} counts; calibrate mla {cal:.1f} s")
    print("| images | Q | Q vs clean | vector error (of peak) | vector error vs clean | s |")
    print("| --- | --- | --- | --- | --- | --- |")
    labels = {"clean": "clean rig", "response": "response, uncorrected", "corrected": "response, flat-field corrected"}
    for name, (q, v) in rows.items():
        print(f"| {labels[name]} | {q:.3f} | {(q - q0) / q0:+.1%} | {v:.2%} | {(v - v0) / v0:+.1%} | "
              f"{seconds[name]:.1f} |")
    qc, vc = rows["corrected"]
    ok = qc >= 0.98 * q0 and vc <= 1.02 * v0
    print(f"goal (corrected no more than 2% worse than clean, in Q and in vector error): {'met' if ok else 'NOT met'}; "
          f"Q {(qc - q0) / q0:+.1%}, vector error {(vc - v0) / v0:+.1%}")


if __name__ == "__main__":
    main()
