"""The MART iteration kernels against NumPy on random sparse weights, on every device Warp finds.

Known truth: the forward projection is proj_i = sum_j w_ij E_j and the simultaneous update is
E_j exp(mu sum_i w_ij ln(max(I_i, floor) / proj_i)), both written out in NumPy. Every launch
form is checked: the projection with a thread per voxel taking four entries a step (the CPU's),
with one lane per voxel and with a warp per voxel (the GPU's), the update with a thread per voxel
(four entries a step) and with a block per voxel; rows of every length modulo four, and empty.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcore.device import warp
from lfcore.projector import LANES

FLOOR = 0.05
MU = 0.8


@pytest.fixture
def sparse():
    rng = np.random.default_rng(3)
    n, n_pix = 600, 4000
    counts = rng.integers(0, 3 * LANES + 7, n)  # rows shorter and longer than a warp, some empty
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    pix = rng.integers(0, n_pix, offsets[-1]).astype(np.int32)
    w = rng.random(offsets[-1]).astype(np.float32) / 50
    e = rng.random(n).astype(np.float32)
    e[::17] = 0.0  # dead voxels
    image = (rng.random(n_pix) * 2).astype(np.float32)
    return offsets, pix, w, e, image, n_pix


def _reference(offsets, pix, w, e, image, n_pix):
    rows = np.repeat(np.arange(e.size), np.diff(offsets))
    proj = np.bincount(pix, weights=w.astype(np.float64) * e[rows], minlength=n_pix)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(proj > 0, np.log(np.maximum(image, FLOOR) / proj), 0.0)
    s = np.bincount(rows, weights=w * ratio[pix], minlength=e.size)
    step = np.clip(MU * s, -np.log(1000.0), np.log(1000.0))
    return proj, e * np.exp(step)


@pytest.mark.parametrize("lanes", [1, LANES])
def test_forward_projection_in_both_launch_forms(sparse, device, lanes):
    from lfcore._kernels import mart as km

    wp = warp()
    offsets, pix, w, e, image, n_pix = sparse
    proj_ref, _ = _reference(*sparse)
    a = [wp.array(x, device=device) for x in (offsets, pix, w, e)]
    out = wp.zeros(n_pix, dtype=float, device=device)
    # a second chunk starting at voxel 200 (the kernel's ``first``)
    for lo, hi in ((0, 200), (200, e.size)):
        wp.launch(km.project, dim=(hi - lo, lanes), device=device,
                  inputs=[wp.array(offsets[lo:hi + 1], device=device), a[1], a[2], lo, lanes, a[3], out])
    np.testing.assert_allclose(out.numpy(), proj_ref, rtol=1e-5, atol=1e-7)


def test_forward_projection_four_entries_a_step(sparse, device):
    from lfcore._kernels import mart as km

    wp = warp()
    offsets, pix, w, e, image, n_pix = sparse
    assert set(np.diff(offsets) % 4) == {0, 1, 2, 3} and (np.diff(offsets) == 0).any()
    proj_ref, _ = _reference(*sparse)
    a = [wp.array(x, device=device) for x in (pix, w, e)]
    out = wp.zeros(n_pix, dtype=float, device=device)
    for lo, hi in ((0, 200), (200, e.size)):
        wp.launch(km.project_rows, dim=hi - lo, device=device,
                  inputs=[wp.array(offsets[lo:hi + 1], device=device), a[0], a[1], lo, a[2], out])
    np.testing.assert_allclose(out.numpy(), proj_ref, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("tiled", [False, True])
def test_simultaneous_update_in_both_launch_forms(sparse, device, tiled):
    from lfcore._kernels import mart as km

    wp = warp()
    offsets, pix, w, e, image, n_pix = sparse
    proj_ref, e_ref = _reference(*sparse)
    proj = wp.array(proj_ref.astype(np.float32), device=device)
    ratio = wp.empty(n_pix, dtype=float, device=device)
    wp.launch(km.log_ratio, dim=n_pix, inputs=[wp.array(image, device=device), proj, FLOOR, ratio], device=device)
    e_out = wp.array(e, device=device)
    args = [wp.array(offsets, device=device), wp.array(pix, device=device), wp.array(w, device=device), 0, ratio,
            MU, e_out]
    if tiled:
        wp.launch_tiled(km.smart_update_tiled, dim=[e.size], inputs=args, block_dim=LANES, device=device)
    else:
        wp.launch(km.smart_update, dim=e.size, inputs=args, device=device)
    got = e_out.numpy()
    np.testing.assert_allclose(got, e_ref, rtol=2e-5, atol=1e-7)
    assert np.all(got[::17] == 0.0)  # a dead voxel stays dead
