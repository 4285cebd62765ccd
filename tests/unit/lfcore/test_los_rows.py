"""The line-of-sight kernel's pixel search misses no pixel: its rows are those of every pixel of the sensor
tested one by one.

:func:`lfcore._kernels.weights.los_weights` searches only a box of lenslets around the voxel and, under each,
only the pixels of the lenslet's own micro-image within the line-of-sight disc (the aperture and
ownership tests in the cheaper order). A brute-force kernel here tests every pixel of every camera by the
same definition (its own lenslet, its aperture point inside the aperture, its line of sight within the
cylinder and sphere's reach); a voxel's row must hold the same pixels with the same weights.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from lfcore._kernels import weights as kw
from lfcore.projector import LightFieldProjector
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from tests.conftest import tiny_variant


@wp.kernel
def every_pixel(grid: kw.Grid, views: wp.array(dtype=kw.View), n_views: int, voxels: wp.array(dtype=wp.int32),
                overlap: wp.array(dtype=float), min_weight: float, out: wp.array2d(dtype=float)):
    """out[t, q]: voxel ``voxels[t]``'s line-of-sight weight (not yet divided by its sum) at global pixel q."""
    t, q = wp.tid()
    pw = kw.voxel_centre(grid, voxels[t])
    for iv in range(n_views):
        view = views[iv]
        cam = view.cam
        local = q - view.pix_offset
        if local < 0 or local >= cam.nrows * cam.ncols:
            continue
        r = local // cam.ncols
        cc = local - r * cam.ncols
        p = kw.view_point(view, pw)
        if (cam.so - p[2]) * cam.inv_f <= 1.0:
            continue
        dz = p[2]
        if wp.abs(dz) < 1.0e-6:
            dz = float(1.0e-6)  # noqa: UP018 (a Warp kernel: the float32 it declares)
        m = view.magnification
        ratio = cam.si / cam.f_ml
        sx = (0.5 * float(cam.ncols) - (float(cc) + 0.5)) * cam.pixel
        sy = (float(r) + 0.5 - 0.5 * float(cam.nrows)) * cam.pixel
        c = kw.lenslet_centre(cam, sx, sy)
        ax = c[0] + (c[0] - sx) * ratio
        ay = c[1] + (c[1] - sy) * ratio
        if ax * ax + ay * ay > cam.aperture_r * cam.aperture_r:
            continue
        xfx = c[0] / m
        xfy = c[1] / m
        ex = xfx - p[0] + (ax - xfx) * dz / cam.so
        ey = xfy - p[1] + (ay - xfy) * dz / cam.so
        wt = kw.tabulated_overlap(view, overlap, wp.sqrt(ex * ex + ey * ey))
        if wt > min_weight:
            out[t, q] = wt


def _rigs(tiny_rig) -> list[Rig]:
    """The tiny rig's hexagonal camera, a square rotated MLA with its aperture smaller than the lenslets'
    micro-images, and two cameras at 90 degrees; voxels in and out of the focal plane (the box 0.4 mm deep)."""
    dual = tiny_rig.to_dict()
    dual["volume"].update(size_mm=[0.3, 0.25, 0.4], pvr=[2.0, 2.0, 10.0])
    dual["camera"].append(dict(dual["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
    square = tiny_variant(tiny_rig, mla_grid="square", mla_rotation_deg=7.0, f_number=2.5)
    return [tiny_rig, square, Rig.from_dict(dual)]


@pytest.mark.parametrize("which", [0, 1, 2])
def test_line_of_sight_rows_hold_every_pixel_that_sees_the_voxel(tiny_rig, device, which):
    rig = _rigs(tiny_rig)[which]
    grid = VolumeGrid.from_rig(rig)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    n = grid.n_voxels
    picked = np.unique(np.linspace(0, n - 1, 40).astype(np.int32))
    vox = wp.array(picked, dtype=wp.int32, device=device)
    offsets, pix, w = proj.weights(vox, method="los").to_numpy()
    assert offsets[-1] > 0
    out = wp.zeros((picked.size, proj.n_pixels), dtype=float, device=device)
    wp.launch(every_pixel, dim=(picked.size, proj.n_pixels), device=device,
              inputs=[proj._grid, proj.views, len(proj.cameras), vox, proj._overlap, 1e-6, out])
    brute = out.numpy()
    for t in range(picked.size):
        row = brute[t]
        seen = np.flatnonzero(row)
        got = pix[offsets[t]:offsets[t + 1]]
        assert np.array_equal(np.sort(got), seen), f"voxel {picked[t]}"
        if seen.size:
            order = np.argsort(got, kind="stable")
            np.testing.assert_allclose(w[offsets[t]:offsets[t + 1]][order], row[seen] / row[seen].sum(),
                                       rtol=1e-5)
