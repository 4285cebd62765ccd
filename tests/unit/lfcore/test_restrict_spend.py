"""The pruning without the whole operator and its copy side by side (issue 47's L budget).

``restrict(rows, spend=True)`` copies the kept rows chunk by chunk, letting each chunk of the whole go
once copied: the rows are the plain restrict's, and beside the whole stands at most one chunk's copy
(:func:`lfcore.reconstruct.restrict_bytes`), where the plain restrict holds the copy of every kept row
beside all of the whole. The iterations hand their operator over (``spend``) to the same volume, and
the depth slabs count the pruning's copy in their accounted peak.
"""

from __future__ import annotations

import weakref

import numpy as np
import pytest

import lfcore.slabs as slabs_module
import lfcore.weight_build as weight_build
from lfcore.plan import projector_for
from lfcore.reconstruct import FrameReconstructor, ReconSettings, preprocess_images, restrict_bytes
from lfcore.slabs import SlabReconstructor, plan_slabs
from lfcore.subsets import SubsetOperator
from tests.helpers import lightfield_scene

#: Raw entries a chunk of stored weights holds at most here (the CPU's default is 2**25): many chunks
#: on the tiny rig, as an L box has many of 2**25.
SMALL_CHUNK = 40_000


@pytest.fixture(scope="module")
def scene(tiny_rig):
    rig = tiny_rig.model_copy(update={"volume": tiny_rig.volume.model_copy(update={"size_mm": (0.5, 0.4, 1.2)})})
    return lightfield_scene(rig)


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(weight_build, "CHUNK_ENTRIES", {"cpu": SMALL_CHUNK, "cuda": SMALL_CHUNK})
    monkeypatch.setattr(weight_build, "SINGLE_PASS_ENTRIES", SMALL_CHUNK // 2)


def _chunk_bytes(c) -> int:
    return 8 * int(c.nnz) + 8 * (int(c.n) + 1)


def _operator(scene, method: str):
    rig, grid, _, _ = scene
    proj = projector_for(rig.camera[:1], grid, device="cpu")
    rng = np.random.default_rng(4)
    vox = proj.wp.array(np.sort(rng.choice(grid.n_voxels, 3000, replace=False)).astype(np.int32), device="cpu")
    return proj, proj.weights(vox, method=method)


@pytest.mark.parametrize("method", ["los", "drt"])
def test_a_spending_restrict_gives_the_rows_of_the_plain_one_and_spends_the_whole(scene, small_chunks, method):
    proj, op = _operator(scene, method)
    assert len(op.chunks) >= 4
    keep = np.sort(np.random.default_rng(5).choice(op.n_voxels, 2000, replace=False)).astype(np.int32)
    rows = proj.wp.array(keep, dtype=proj.wp.int32, device="cpu")
    plain = op.restrict(rows)
    e = proj.wp.array(np.linspace(0.5, 1.5, op.n_voxels).astype(np.float32), device="cpu")
    whole_image = op.forward(e).numpy()
    spent = op.restrict(rows, spend=True)
    for a, b in zip(plain.to_numpy(), spent.to_numpy(), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(spent.voxels.numpy(), op.voxels.numpy()[keep])
    assert spent.nnz == plain.nnz and spent.kind == op.kind
    assert op.spent and op.chunks == []  # its rows went as they were copied
    with pytest.raises(ValueError, match="spent"):
        op.forward(e)
    # the copy projects as the whole did with the other voxels dark
    dark = e.numpy().copy()
    dark[np.setdiff1d(np.arange(op.n_voxels), keep)] = 0.0
    assert whole_image.sum() > 0
    kept_image = spent.forward(proj.wp.array(dark[keep], device="cpu")).numpy()
    assert np.isfinite(kept_image).all() and 0 < kept_image.sum() < whole_image.sum()


def _peak_while_copying(monkeypatch, op, rows, *, spend: bool) -> int:
    """The most bytes of rows alive at once while ``op.restrict(rows, spend=spend)`` copies: the whole's
    chunks not yet let go, and the copies made so far (the one being made included)."""
    old = [weakref.ref(c) for c in op.chunks]
    sizes = [_chunk_bytes(c) for c in op.chunks]
    made, peak = [], [0]
    launch = weight_build.launch_rows

    def counting(kernel, n, inputs, device, *a, **k):
        new_offsets, new_pix = inputs[1].array, inputs[4]
        made.append(8 * int(new_pix.shape[0]) + 8 * int(new_offsets.shape[0]))
        alive = sum(s for r, s in zip(old, sizes, strict=True) if r() is not None)
        peak[0] = max(peak[0], alive + sum(made))
        return launch(kernel, n, inputs, device, *a, **k)

    monkeypatch.setattr(weight_build, "launch_rows", counting)
    op.restrict(rows, spend=spend)
    monkeypatch.setattr(weight_build, "launch_rows", launch)
    assert made
    return peak[0]


def test_a_spending_restrict_holds_one_chunks_copy_beside_the_whole(scene, small_chunks, monkeypatch):
    """Known truth: the bytes of the rows alive never pass the whole's and :func:`restrict_bytes` (one
    chunk's copy); the plain restrict's pass them by the copy of every kept row, as the budget counted
    them before (once)."""
    proj, op = _operator(scene, "drt")
    whole = sum(_chunk_bytes(c) for c in op.chunks)
    keep = np.arange(0, op.n_voxels, 3, dtype=np.int32)[1:]  # two thirds of the rows go
    keep = np.sort(np.concatenate([keep, keep + 1]))  # two thirds kept
    rows = proj.wp.array(keep, dtype=proj.wp.int32, device="cpu")
    one_chunk = max(_chunk_bytes(c) for c in op.chunks)
    assert restrict_bytes(op, spend=True) == one_chunk + 8 * op.n_voxels
    assert restrict_bytes(op) == op.nbytes + 8 * op.n_voxels
    plain_peak = _peak_while_copying(monkeypatch, op, rows, spend=False)
    assert plain_peak > whole + one_chunk  # the whole and the copy of two thirds of it
    spent_peak = _peak_while_copying(monkeypatch, op, rows, spend=True)
    assert spent_peak <= whole + one_chunk
    assert op.spent


def test_split_rows_restrict_alike(scene, small_chunks):
    """Ordered subsets: each subset's rows restricted (and spent) as the whole's."""
    from lfcore.subsets import pixel_subsets, split

    proj, op = _operator(scene, "drt")
    subset_of = proj.wp.array(pixel_subsets(proj.pixel_offsets, proj.cameras, 3), dtype=proj.wp.int32, device="cpu")
    a, b = split(op, subset_of, 3), split(op, subset_of, 3)
    assert isinstance(a, SubsetOperator)
    rows = proj.wp.array(np.arange(0, op.n_voxels, 2, dtype=np.int32), dtype=proj.wp.int32, device="cpu")
    plain, spent = a.restrict(rows), b.restrict(rows, spend=True)
    for p, q in zip(plain.parts, spent.parts, strict=True):
        for x, y in zip(p.to_numpy(), q.to_numpy(), strict=True):
            np.testing.assert_array_equal(x, y)
    for x, y in zip(plain.scales, spent.scales, strict=True):
        np.testing.assert_array_equal(x.numpy(), y.numpy())
    assert all(p.spent and not p.chunks for p in b.parts)


@pytest.mark.parametrize("subsets", [1, 3])
def test_iterations_that_spend_their_operator_reach_the_same_volume(scene, small_chunks, subsets):
    """``iterate(op, spend=True)``: the same intensities, voxels and iterations as without, and the
    operator handed over is spent (its rows gone at the first split or pruning); without ``spend`` it
    is left whole, to be iterated again."""
    rig, grid, _, img = scene
    proj = projector_for(rig.camera[:1], grid, device="cpu")
    s = ReconSettings(iterations=25, projector="stored", prune_every=10, subsets=subsets)
    frames = FrameReconstructor(proj, s)
    signals, lits, _, noise = preprocess_images(proj, [img], s)
    image = proj.wp.array(np.concatenate([x.ravel() for x in signals]), dtype=float, device="cpu")
    vox = frames.eliminate(lits)
    kept, handed = frames.operator(vox), frames.operator(vox)
    assert kept is not handed
    a = frames.iterate(kept, image, noise)
    ea, va = a.e.numpy()[:a.op.n_voxels].copy(), a.op.voxels.numpy().copy()
    again = frames.iterate(kept, image, noise)  # left whole: the same again
    np.testing.assert_array_equal(again.e.numpy()[:again.op.n_voxels], ea)
    b = frames.iterate(handed, image, noise, spend=True)
    assert b.iterations == a.iterations and b.op.n_voxels == a.op.n_voxels < vox.shape[0]
    np.testing.assert_array_equal(b.op.voxels.numpy(), va)
    np.testing.assert_array_equal(b.e.numpy()[:b.op.n_voxels], ea)
    assert handed.spent and not kept.spent


def test_the_slabs_count_the_prunings_copy_in_their_peak(scene, monkeypatch):
    """The accounted peak (``peak_bytes``) holds the pruning's copy (:func:`restrict_bytes`) where the
    iterations prune, and not where they do not."""
    rig, grid, _, img = scene
    proj = projector_for(rig.camera[:1], grid, device="cpu")
    marker = 1 << 50  # far above anything the tiny rig holds
    counted = []

    def marked(op, *, spend=False):
        counted.append(spend)
        return marker

    monkeypatch.setattr(slabs_module, "restrict_bytes", marked)
    peaks = {}
    for prune in (0.01, 0.0):
        s = ReconSettings(iterations=12, projector="stored", prune=prune, prune_every=3, los_iterations=6)
        res = SlabReconstructor(proj, s, slabs=plan_slabs(grid.shape[0], 2), budget_bytes=1 << 31).reconstruct(
            [img], write=lambda *a: None)
        peaks[prune] = res.peak_bytes
    assert peaks[0.01] >= marker > peaks[0.0]
    assert counted and all(counted)  # one chunk's copy: the slabs spend what they prune
