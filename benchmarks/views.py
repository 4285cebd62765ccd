"""Perspective views and refocused planes (lfpiv views) against the issue's goals: the views of a
2048 x 2048 frame in at most 2 s, a refocused plane of a 29 MP frame in at most 5 s, on this CPU.

The frames are the one-camera example's optics (hexagonal lenslets 14 pixels across) on a
2048 x 2048 sensor and on a 6600 x 4400 one (29 MP, the chapter's camera); their content does not
change the time (noise). Baselines, in the same run: every view sampled with
``scipy.ndimage.map_coordinates`` (order 1) at its nodes, and every view shifted with
``scipy.ndimage.shift`` (order 1) and averaged.

    python benchmarks/views.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from lfcore.camera_checks import check_image
from lfcore.views import nominal_lattice, refocus, sample_views, view_offsets, view_shifts_px
from lfpiv.rigfile import load_rig

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "one_camera.toml"


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def baseline_views(img, lat):
    offs = view_offsets(lat)
    n1, n2, inside = lat.nodes(img.shape, margin_px=float(np.abs(offs).max()) + 1.5)
    c = lat.centres(n1, n2)[inside]
    return [ndimage.map_coordinates(img, [c[:, 1] + dv - 0.5, c[:, 0] + du - 0.5], order=1) for du, dv in offs]


def baseline_refocus(views, cam, z):
    dn = view_shifts_px(cam, views.offsets_px, z) @ np.linalg.inv(views.lattice.basis_px)
    acc = np.zeros(views.inside.shape, dtype=np.float32)
    for img, (d1, d2) in zip(views.images, dn, strict=True):
        acc += ndimage.shift(img, (-d2, -d1), order=1)
    return acc / len(views.images)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rig = load_rig(EXAMPLE)
    rng = np.random.default_rng(0)
    rows = []
    for cols_px, rows_px in ((2048, 2048), (6600, 4400)):
        cam = rig.camera[0].model_copy(update={"sensor_px": (cols_px, rows_px)})
        img = rng.integers(100, 4000, (rows_px, cols_px)).astype(np.uint16)
        lat = nominal_lattice(cam)
        views = sample_views(img, lat)
        t_views = best_of(lambda: sample_views(img, lat), args.repeat)  # noqa: B023
        t_base = best_of(lambda: baseline_views(img.astype(np.float32), lat), 1)  # noqa: B023
        t_plane = best_of(lambda: refocus(views, cam, 2.0), args.repeat)  # noqa: B023
        t_plane_up = best_of(lambda: refocus(views, cam, 2.0, upsample=2), args.repeat)  # noqa: B023
        t_base_plane = best_of(lambda: baseline_refocus(views, cam, 2.0), 1)  # noqa: B023
        n2, n1 = views.inside.shape
        name = f"{cols_px} x {rows_px} ({cols_px * rows_px / 1e6:.1f} MP), {len(views.offsets_px)} views of {n1} x {n2}"
        rows.append((f"{name}: views", t_views, t_base))
        rows.append((f"{name}: one refocused plane from the views", t_plane, t_base_plane))
        rows.append((f"{name}: one refocused plane, 2 samples per lenslet", t_plane_up, None))
        rows.append((f"{name}: raw frame to one refocused plane (views + plane)", t_views + t_plane,
                     t_base + t_base_plane))
        if cols_px == 2048:
            t_check = best_of(lambda: check_image(img, cam, full_scale=65535, volume=rig.volume), 1)  # noqa: B023
            rows.append((f"{name}: every check before recording (lfcore.camera_checks.check_image)", t_check, None))
    print("| case | lfpiv (s) | baseline (s) | speed-up |")
    print("| --- | --- | --- | --- |")
    for name, t, b in rows:
        print(f"| {name} | {t:.3f} | {'' if b is None else f'{b:.3f}'} | {'' if b is None else f'{b / t:.1f}x'} |")


if __name__ == "__main__":
    main()
