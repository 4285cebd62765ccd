"""Microlens calibration of a large sensor: white image, grid detection, lenslet cells, dot finding.

Run from the repository root::

    python benchmarks/calibrate.py                  # the two-camera example's 6600 x 4400 camera
    python benchmarks/calibrate.py --px 2048 2048   # a smaller sensor of the same optics

Each stage is timed once on the CPU (these are NumPy/SciPy stages, threaded where SciPy
releases the GIL) and printed with its cost per megapixel. The baseline, measured in
the same run on the same image, is one Gaussian filter of the whole image (sigma 1 px, SciPy),
the cheapest full-image pass any of these stages makes; each stage is printed as a multiple of
it. The grid's accuracy against the true micro-image centres is printed too.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calibration.dots import detect_dots, lenslet_cells  # noqa: E402
from calibration.mla_grid import detect_grid  # noqa: E402
from lfcore.white import WhiteImageConfig, micro_image_centres, white_image  # noqa: E402
from lfpiv.rigfile import load_rig  # noqa: E402


def _timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(ROOT / "examples" / "two_cameras.toml"))
    ap.add_argument("--px", type=int, nargs=2, metavar=("COLUMNS", "ROWS"), help="sensor size (default: the rig's)")
    args = ap.parse_args(argv)
    rig = load_rig(args.rig)
    cam = rig.camera[0]
    if args.px:
        cam = cam.model_copy(update={"sensor_px": tuple(args.px)})
    mp = cam.sensor_px[0] * cam.sensor_px[1] / 1e6
    print(f"camera {cam.sensor_px[0]} x {cam.sensor_px[1]} ({mp:.1f} MP), {cam.pixels_per_lenslet:.1f} px per "
          f"lenslet, {cam.mla_grid} grid; {os.cpu_count()} CPU cores")
    white, t_white = _timed(white_image, cam, rig.render, WhiteImageConfig(vignetting=0.3, dead_lenslets=3),
                            rig.laser.wavelength_nm)
    img = white.astype(np.float64)
    _, t_base = _timed(ndimage.gaussian_filter, img, 1.0)
    grid, t_grid = _timed(detect_grid, img)
    cells, t_cells = _timed(lenslet_cells, grid)
    # A frame of light spread over every lenslet (the white image again) exercises the sums,
    # the segmentation and the centroids at full size.
    _, t_dots = _timed(detect_dots, white, grid, cells=cells)
    d, _ = cKDTree(micro_image_centres(cam)).query(grid.centres_px[grid.inliers])
    print(f"baseline: one Gaussian filter of the image {t_base * 1e3:.0f} ms")
    for name, t in (("white image (simulated)", t_white), ("detect_grid", t_grid), ("lenslet cells", t_cells),
                    ("detect_dots (with cells)", t_dots)):
        print(f"{name:26s} {t:8.2f} s  {t / mp:6.2f} s/MP  {t / t_base:7.0f} x baseline")
    print(f"grid: {grid.n_lenslets} lenslets, pitch {grid.pitch_px:.4f} px, RMS {grid.rms_px:.4f} px; "
          f"against the true centres {np.sqrt(np.mean(d**2)):.4f} px RMS")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
