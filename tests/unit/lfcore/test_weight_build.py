"""The fast DRT weight builds give the operator of the direct build, on every device Warp finds.

The direct build is the two-pass trace with the library's segmented sort. The single-pass build
(slots of a guessed capacity, per-voxel sort and merge) and the cross-frame
:class:`~lfcore.weight_cache.WeightCache` must give the same voxels, the same pixels per voxel
and the same weights (to 1e-6 relative), including when a voxel overflows its slot, when the
build is split into chunks, and when the cache's budget is exhausted.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcore import projector as projector_module
from lfcore import weight_build as build_module
from lfcore.particles import seed_particles
from lfcore.projector import LightFieldProjector
from lfcore.reconstruct import ReconSettings, estimate_background, preprocess, reconstruct
from lfcore.render import LightFieldRenderer
from lfcore.rig import Rig
from lfcore.volume import VolumeGrid
from lfcore.weight_cache import WeightCache


@pytest.fixture(scope="module")
def small_dual_rig(tiny_rig) -> Rig:
    """Two cameras at 90 degrees around a small box (27 x 23 x 7 voxels)."""
    d = tiny_rig.to_dict()
    d["volume"].update(size_mm=[0.3, 0.25, 0.4], pvr=[2.0, 2.0, 10.0])
    d["camera"].append(dict(d["camera"][0], name="cam1", rotation_deg=[0.0, 90.0, 0.0]))
    return Rig.from_dict(d)


def _same(a, b) -> None:
    """Two Weights hold the same operator: same voxels, pixels and weights (1e-6 relative)."""
    assert np.array_equal(a.voxels.numpy(), b.voxels.numpy())
    assert a.nnz == b.nnz
    oa, pa, wa = a.to_numpy()
    ob, pb, wb = b.to_numpy()
    assert np.array_equal(oa, ob)
    assert np.array_equal(pa, pb)
    np.testing.assert_allclose(wb, wa, rtol=1e-6, atol=0.0)


def _images(rig, grid, device, n=12, seed=3):
    pts = seed_particles(rig.volume, n, np.random.default_rng(seed))
    cfg = rig.render.model_copy(update={"rays_per_particle": 4000})
    return [LightFieldRenderer(c, cfg, wavelength_nm=rig.laser.wavelength_nm, device=device).frame(
                pts, 50_000.0, seed=1 + i)
            for i, c in enumerate(rig.camera)]


def _lit(images, settings):
    out = []
    for img in images:
        level, sigma = estimate_background(img)
        out.append(preprocess(img, level, sigma, settings.threshold_sigma)[1])
    return out


def test_single_pass_build_matches_the_two_pass_build(small_dual_rig, device, monkeypatch):
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    vox = proj.wp.array(np.arange(0, grid.n_voxels, 5, dtype=np.int32), device=device)
    direct = proj.weights(vox, method="drt", build="two-pass")
    assert direct.nnz > 0
    _same(direct, proj.weights(vox, method="drt", build="single-pass"))
    # both merges of the two-pass build, for DRT and the MART baseline's weights
    _same(direct, proj.weights(vox, method="drt", build="two-pass", sort="library"))
    _same(direct, proj.weights(vox, method="drt", build="two-pass", sort="per-voxel"))
    los = proj.weights(vox, method="los", sort="library")
    assert los.nnz > 0
    _same(los, proj.weights(vox, method="los", sort="per-voxel"))
    # a tiny capacity sample (voxels overflow their slots) and small chunks: still the same
    monkeypatch.setattr(build_module, "CAPACITY_SAMPLE", 1)
    monkeypatch.setattr(build_module, "SINGLE_PASS_ENTRIES", 5000)
    fast = proj.weights(vox, method="drt", build="single-pass")
    assert len(fast.chunks) == 1  # the build's many small chunks joined: fewer launches an iteration
    _same(direct, fast)
    # joined up to the chunk size, and not at all where the copy would not fit the budget
    monkeypatch.setitem(build_module.CHUNK_ENTRIES, "cpu" if device == "cpu" else "cuda", direct.nnz // 3)
    fast = proj.weights(vox, method="drt", build="single-pass")
    assert 3 <= len(fast.chunks) < 10 and max(c.nnz for c in fast.chunks) <= direct.nnz // 3
    _same(direct, fast)
    tight = proj.weights(vox, method="drt", build="single-pass",
                         budget_bytes=build_module.BYTES_PER_WEIGHT * direct.nnz)
    assert len(tight.chunks) >= 10
    _same(direct, tight)
    _same(direct, proj.weights(vox, method="drt"))  # the device's default build
    empty = proj.weights(proj.wp.zeros(0, dtype=proj.wp.int32, device=device), method="drt", build="single-pass")
    assert empty.nnz == 0 and empty.n_voxels == 0
    with pytest.raises(ValueError, match="build"):
        proj.weights(vox, method="drt", build="fast")
    with pytest.raises(ValueError, match="unknown sort"):
        proj.weights(vox, method="drt", sort="quick")


def test_cache_gives_the_direct_operator_frame_after_frame(small_dual_rig, device):
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    settings = ReconSettings()
    cache = WeightCache(proj)
    seen = 0
    for seed in (3, 4, 3):  # the third frame repeats the first: nothing new to trace
        lit = _lit(_images(small_dual_rig, grid, device, seed=seed), settings)
        voxels = proj.eliminate(lit, min_seen=settings.min_seen, max_dark=settings.max_dark)
        assert voxels.shape[0] > 0
        direct = proj.weights(voxels, method="drt", build="two-pass")
        cached = cache.weights(voxels)
        _same(direct, cached)
        assert cache.n_cached >= seen
        seen = cache.n_cached
        assert cache.nbytes >= cached.nnz * 8
    # prefill stores the rest; rows of a mixed request are still the direct ones
    every = np.arange(0, grid.n_voxels, 3, dtype=np.int32)
    assert cache.prefill(voxels=every) + seen >= len(every)
    vox = proj.wp.array(every, device=device)
    _same(proj.weights(vox, method="drt", build="two-pass"), cache.weights(vox))


def _rows_by_voxel(weights) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    offsets, pix, w = weights.to_numpy()
    return {int(v): (pix[offsets[k]:offsets[k + 1]], w[offsets[k]:offsets[k + 1]])
            for k, v in enumerate(weights.voxels.numpy())}


def _same_rows(a, b) -> None:
    """The same operator with the voxels in any order."""
    ra, rb = _rows_by_voxel(a), _rows_by_voxel(b)
    assert ra.keys() == rb.keys() and a.nnz == b.nnz
    for v, (pa, wa) in ra.items():
        assert np.array_equal(pa, rb[v][0])
        np.testing.assert_allclose(rb[v][1], wa, rtol=1e-6, atol=0.0)


def test_cache_over_budget_keeps_the_newest_frame(small_dual_rig, device, monkeypatch):
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    every = np.arange(0, grid.n_voxels, 9, dtype=np.int32)
    vox = proj.wp.array(every, device=device)
    direct = proj.weights(vox, method="drt", build="two-pass")
    cache = WeightCache(proj, budget_bytes=8 * direct.nnz * 9 // 10)
    first = proj.wp.array(every[: every.size // 2], device=device)
    _same(proj.weights(first, method="drt", build="two-pass"), cache.weights(first))  # fits: stored
    assert cache.n_cached == first.shape[0]
    # the second half does not fit next to the first: the request's stored rows are copied
    # out, its new rows follow as built, and the pool is refilled with the request alone
    late = proj.wp.array(every[every.size // 4:], device=device)
    got = cache.weights(late)
    _same_rows(proj.weights(late, method="drt", build="two-pass"), got)
    stored = every[every.size // 4: every.size // 2]  # the part of the request already stored comes first
    assert np.array_equal(got.voxels.numpy()[: stored.size], stored)
    assert cache.n_cached == late.shape[0] and cache.nbytes <= cache.budget_bytes
    _same(proj.weights(late, method="drt", build="two-pass"), cache.weights(late))  # now stored, in request order
    # the caller's host copy of the indices serves in place of their copy from the device
    _same(proj.weights(late, method="drt", build="two-pass"), cache.weights(late, host=every[every.size // 4:]))
    # a request larger than the whole budget is served as built and leaves the pool empty
    _same_rows(direct, cache.weights(vox))
    assert cache.n_cached == 0
    # output chunks stay below the length limit of one array
    monkeypatch.setitem(build_module.CHUNK_ENTRIES, device.split(":")[0], direct.nnz // 5)
    monkeypatch.setattr("lfcore.weight_cache.CHUNK_ENTRIES", build_module.CHUNK_ENTRIES)
    small = WeightCache(proj)
    small.weights(vox)
    chunked = small.weights(vox)
    assert len(chunked.chunks) >= 5 and all(c.nnz <= direct.nnz // 5 for c in chunked.chunks)
    _same(direct, chunked)


@pytest.mark.parametrize(("method", "kind"), [("drt-mart", "drt"), ("mlos-mart", "los")])
def test_reconstruct_with_a_cache_gives_the_same_volume(small_dual_rig, device, method, kind):
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    images = _images(small_dual_rig, grid, device)
    settings = ReconSettings(method=method, iterations=10)
    plain = reconstruct(proj, images, settings)
    other = WeightCache(proj, method="los" if kind == "drt" else "drt")
    res = reconstruct(proj, images, settings, cache=other)  # a cache of the other weights is not used
    assert other.n_cached == 0 and res.nnz == plain.nnz
    cache = WeightCache(proj, method=kind)
    for _ in range(2):  # filling the cache, then reading it
        res = reconstruct(proj, images, settings, cache=cache)
        assert res.active_voxels == plain.active_voxels and res.nnz == plain.nnz
        np.testing.assert_allclose(res.volume, plain.volume, rtol=1e-4, atol=1e-6 * float(plain.volume.max()))
    with pytest.raises(ValueError, match="another projector"):
        reconstruct(LightFieldProjector(small_dual_rig.camera, grid, device=device), images, settings, cache=cache)


def test_elimination_with_stored_checks_keeps_the_same_voxels(small_dual_rig, device):
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    settings = ReconSettings()
    lit = _lit(_images(small_dual_rig, grid, device, n=30), settings)
    for min_seen, max_dark in ((settings.min_seen, settings.max_dark), (0.5, 0.2)):
        ref = proj.eliminate(lit, min_seen=min_seen, max_dark=max_dark).numpy()
        assert 0 < ref.size < grid.n_voxels
        for n_checks in (3, None, 0):
            nbytes = proj.precompute_checks(n_checks=n_checks)
            expect = 0 if n_checks == 0 else 20 * grid.n_voxels * 2 * (n_checks or proj.max_checks)
            assert nbytes == expect
            assert np.array_equal(proj.eliminate(lit, min_seen=min_seen, max_dark=max_dark).numpy(), ref)
    # a budget too small for every check stores fewer; one too small for any stores none
    assert proj.precompute_checks(n_checks=None, budget_bytes=20 * grid.n_voxels * 2 * 5) == 20 * grid.n_voxels * 2 * 5
    assert proj.precompute_checks(n_checks=None, budget_bytes=10) == 0


@pytest.mark.parametrize("prefilter", [1, 4, 1000])
def test_elimination_in_two_passes_keeps_what_one_full_pass_keeps(small_dual_rig, device, monkeypatch, prefilter):
    """The grid pass with a few checks, then every check on its candidates, against every check at once."""
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    settings = ReconSettings()
    lit = _lit(_images(small_dual_rig, grid, device, n=30), settings)
    wp = proj.wp
    flat = wp.array(np.concatenate([m.ravel() for m in lit]).astype(np.uint8), device=device)
    monkeypatch.setattr(projector_module, "PREFILTER_CHECKS", prefilter)
    for min_seen, max_dark in ((settings.min_seen, settings.max_dark), (0.5, 0.2), (0.9, 0.0)):
        mask = wp.zeros(grid.n_voxels, dtype=wp.int32, device=device)
        wp.launch(proj._kw.eliminate, dim=grid.n_voxels, device=device,
                  inputs=[proj._grid, proj.views, 2, proj.sub_a, proj.check_order, flat, min_seen, max_dark,
                          proj._checks, proj._n_checks, wp.empty(0, dtype=wp.int32, device=device), 2**30, 0, mask])
        one_pass = np.flatnonzero(mask.numpy())
        assert 0 < one_pass.size < grid.n_voxels
        assert np.array_equal(proj.eliminate(lit, min_seen=min_seen, max_dark=max_dark).numpy(), one_pass)
        assert np.array_equal(proj.eliminate(flat, min_seen=min_seen, max_dark=max_dark).numpy(), one_pass)


def _clipped_reference(rect, normals, h):
    """Area, centroid and extent of a rectangle clipped to the cell {p: n . p <= h} (Sutherland-Hodgman)."""
    x0, x1, y0, y1 = rect
    poly = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    for nx, ny in normals:
        out = []
        for i, p in enumerate(poly):
            q = poly[(i + 1) % len(poly)]
            sp, sq = nx * p[0] + ny * p[1] - h, nx * q[0] + ny * q[1] - h
            if sp <= 0:
                out.append(p)
            if (sp <= 0) != (sq <= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        poly = out
        if not poly:
            return 0.0, 0.0, 0.0, 0.0, 0.0
    xy = np.array(poly)
    x, y = xy[:, 0], xy[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cr = x * yn - xn * y
    a = cr.sum()
    if a <= 1e-20:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    return 0.5 * a, ((x + xn) * cr).sum() / (3 * a), ((y + yn) * cr).sum() / (3 * a), np.ptp(x), np.ptp(y)


@pytest.mark.parametrize(("edges", "rotation_deg"), [(4, 0.0), (4, 17.0), (6, 0.0), (6, 8.0)])
def test_cell_overlap_is_the_clipped_rectangle(device, edges, rotation_deg):
    """The register-only overlap of a footprint and a lenslet cell (DRT's w1) against polygon
    clipping: random rectangles inside, across and outside the cell, and rectangles whose edges
    lie exactly on an unrotated cell's edges (each side counted once)."""
    import math

    import warp as wp

    from lfcore._kernels import weights as kw

    pitch = 0.055
    h = 0.5 * pitch
    step = 360.0 / edges
    ang = [math.radians(i * step + rotation_deg) for i in range(edges)]
    normals = [(math.cos(a), math.sin(a)) for a in ang]
    view = kw.View()
    view.cam.pitch = pitch
    view.n_edges = edges
    view.edge_nx = kw.vec6(*[n[0] for n in normals], *[0.0] * (6 - edges))
    view.edge_ny = kw.vec6(*[n[1] for n in normals], *[0.0] * (6 - edges))
    rng = np.random.default_rng(4)
    centre = rng.uniform(-1.2 * pitch, 1.2 * pitch, (400, 2))
    half = rng.uniform(0.02 * pitch, 0.7 * pitch, (400, 2))
    rects = np.concatenate([centre - half, centre + half], axis=1)[:, [0, 2, 1, 3]]
    if rotation_deg == 0.0 and edges == 4:  # edges on the cell's edges, from inside and from outside
        rects = np.concatenate([rects, [[-h, h, -h, h], [-0.3 * h, h, -0.2 * h, 0.5 * h], [h, 2 * h, -h, h],
                                        [-h, 0.4 * h, -h, -0.1 * h]]])
    if rotation_deg == 0.0 and edges == 6:
        rects = np.concatenate([rects, [[-0.2 * h, h, -0.4 * h, 0.3 * h], [h, 1.5 * h, -0.1 * h, 0.1 * h]]])
    cx, cy = 1.234, -0.567  # a cell away from the optical axis: the kernel works relative to it

    @wp.kernel
    def overlaps(view: kw.View, r: wp.array(dtype=wp.vec4), out: wp.array(dtype=wp.vec4), ext: wp.array(dtype=wp.vec2)):
        i = wp.tid()
        o = kw.cell_overlap(view, cx, cy, cx + r[i][0], cx + r[i][1], cy + r[i][2], cy + r[i][3])
        out[i] = wp.vec4(o.area, o.cx - cx, o.cy - cy, 0.0)
        ext[i] = wp.vec2(o.wx, o.wy)

    r = wp.array(rects.astype(np.float32), dtype=wp.vec4, device=device)
    out = wp.zeros(len(rects), dtype=wp.vec4, device=device)
    ext = wp.zeros(len(rects), dtype=wp.vec2, device=device)
    wp.launch(overlaps, dim=len(rects), inputs=[view, r, out, ext], device=device)
    got, got_ext = out.numpy(), ext.numpy()
    ref = np.array([_clipped_reference(tuple(map(float, q)), normals, h) for q in rects.astype(np.float32)])
    cell = pitch**2 if edges == 4 else math.sqrt(3) / 2 * pitch**2
    assert np.abs(got[:, 0] - ref[:, 0]).max() < 1e-5 * cell
    some = ref[:, 0] > 1e-4 * cell
    rect_area = (rects[:, 1] - rects[:, 0]) * (rects[:, 3] - rects[:, 2])
    clipped = some & (ref[:, 0] < 0.99 * np.minimum(rect_area, cell))
    assert clipped.sum() > 100 and (ref[:, 0] == 0).sum() > 10  # most cross the cell's edge, some miss it
    # float32 centroids of slivers lose digits (as the clipping's did): tighter where the overlap is larger
    big = ref[:, 0] > 0.01 * cell
    assert np.abs(got[big, 1:3] - ref[big, 1:3]).max() < 1e-5 * pitch
    assert np.abs(got[some, 1:3] - ref[some, 1:3]).max() < 2e-4 * pitch
    assert np.abs(got_ext[some] - ref[some, 3:5]).max() < 1e-5 * pitch


def test_cache_rejects_an_unknown_method(small_dual_rig):
    proj = LightFieldProjector(small_dual_rig.camera[:1], VolumeGrid.from_rig(small_dual_rig), device="cpu")
    with pytest.raises(ValueError, match="unknown weight method 'mart'"):
        WeightCache(proj, method="mart", checks=0)


def test_elimination_off_the_sensor_edges_keeps_what_the_traced_table_keeps(tiny_rig, device):
    """A box wider than the field of view: footprints off the sensor and partly off it.

    Traced checks settle a footprint by its first lit point when it surely lies on the sensor
    (and use one lenslet for a footprint inside one cell); the table stores every point of every
    check, traced without those shortcuts, so the two must keep the same voxels.
    """
    d = tiny_rig.to_dict()
    d["volume"].update(size_mm=[1.6, 1.4, 1.6], pvr=[4.0, 4.0, 20.0])
    rig = Rig.from_dict(d)
    grid = VolumeGrid.from_rig(rig)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    settings = ReconSettings()
    lit = _lit(_images(rig, grid, device, n=40), settings)
    for min_seen, max_dark in ((settings.min_seen, settings.max_dark), (0.9, 0.2), (0.2, 0.0)):
        proj.precompute_checks(n_checks=0)
        traced = proj.eliminate(lit, min_seen=min_seen, max_dark=max_dark).numpy()
        proj.precompute_checks(n_checks=None)
        assert np.array_equal(proj.eliminate(lit, min_seen=min_seen, max_dark=max_dark).numpy(), traced)
        assert 0 < traced.size < grid.n_voxels
    # the test means something only if some voxels are seen through few sub-apertures
    everything = np.ones((rig.camera[0].sensor_px[1], rig.camera[0].sensor_px[0]), bool)
    proj.precompute_checks(n_checks=0)
    strict = proj.eliminate([everything], min_seen=0.99, max_dark=0.0).numpy().size
    assert strict < proj.eliminate([everything], min_seen=0.01, max_dark=0.0).numpy().size


def test_elimination_reuses_its_scratch_and_returns_arrays_of_its_own(small_dual_rig, device):
    """Frames with many, few, then many lit pixels through one projector keep the voxels a fresh
    projector keeps, and a result is not overwritten by the next call."""
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    settings = ReconSettings()
    lits = [_lit(_images(small_dual_rig, grid, device, n=n, seed=seed), settings) for n, seed in ((30, 3), (4, 4))]
    fresh = [LightFieldProjector(small_dual_rig.camera, grid, device=device).eliminate(lit, min_seen=settings.min_seen,
                                                                             max_dark=settings.max_dark).numpy()
             for lit in lits]
    assert 0 < fresh[1].size < fresh[0].size < grid.n_voxels
    got = [proj.eliminate(lits[k], min_seen=settings.min_seen, max_dark=settings.max_dark) for k in (0, 1, 0)]
    for k, voxels in zip((0, 1, 0), got, strict=True):
        assert np.array_equal(voxels.numpy(), fresh[k])


@pytest.mark.parametrize(("edges", "rotation_deg"), [(4, 0.0), (4, 17.0), (6, 0.0), (6, 8.0)])
def test_edge_spans_computed_once_give_the_per_cell_clipping_to_the_bit(device, edges, rotation_deg):
    """The DRT trace clips the cell's edges to each other once per voxel and camera (kw.edge_spans)
    instead of once per cell: the overlaps (area, centroid, extent) of rectangles with cells around
    the footprint are those of the clipping done cell by cell as before, to the bit."""
    import math

    import warp as wp

    from lfcore._kernels import weights as kw

    @wp.func
    def per_cell(view: kw.View, cx: float, cy: float, x0: float, x1: float, y0: float, y1: float) -> kw.Overlap:
        # the edges' spans as cell_overlap computed them for every cell before edge_spans
        h = 0.5 * view.cam.pitch
        spans = kw.EdgeSpans()
        for e in range(view.n_edges):
            nx = view.edge_nx[e]
            ny = view.edge_ny[e]
            dx = -ny
            dy = nx
            t0 = float(-1.0e30)  # noqa: UP018 (a Warp variable the loop changes)
            t1 = float(1.0e30)  # noqa: UP018
            for f in range(view.n_edges):
                den = view.edge_nx[f] * dx + view.edge_ny[f] * dy
                if f != e and wp.abs(den) > 1.0e-6:
                    t = (h - h * (view.edge_nx[f] * nx + view.edge_ny[f] * ny)) / den
                    if den > 0.0:
                        t1 = wp.min(t1, t)
                    else:
                        t0 = wp.max(t0, t)
            spans.t0[e] = t0
            spans.t1[e] = t1
        return kw.spans_overlap(view, spans, cx, cy, x0, x1, y0, y1)

    pitch = 0.077
    ang = [math.radians(i * 360.0 / edges + rotation_deg) for i in range(edges)]
    view = kw.View()
    view.cam.pitch = pitch
    view.n_edges = edges
    view.edge_nx = kw.vec6(*[math.cos(a) for a in ang], *[0.0] * (6 - edges))
    view.edge_ny = kw.vec6(*[math.sin(a) for a in ang], *[0.0] * (6 - edges))
    rng = np.random.default_rng(7)
    centre = rng.uniform(-1.5 * pitch, 1.5 * pitch, (300, 2)) + np.array([2.1, -0.7])
    half = rng.uniform(0.02 * pitch, 1.2 * pitch, (300, 2))
    rects = np.concatenate([centre - half, centre + half], axis=1)[:, [0, 2, 1, 3]].astype(np.float32)
    cells = np.array([(2.1 + i * pitch, -0.7 + j * pitch) for i in (-1, 0, 1) for j in (-1, 0, 1)], np.float32)

    @wp.kernel
    def both(view: kw.View, r: wp.array(dtype=wp.vec4), cells: wp.array(dtype=wp.vec2),
             once: wp.array2d(dtype=float), each: wp.array2d(dtype=float)):
        i = wp.tid()
        spans = kw.edge_spans(view)  # once, for every cell below
        for k in range(cells.shape[0]):
            c = cells[k]
            a = kw.spans_overlap(view, spans, c[0], c[1], r[i][0], r[i][1], r[i][2], r[i][3])
            b = per_cell(view, c[0], c[1], r[i][0], r[i][1], r[i][2], r[i][3])
            once[i, 5 * k + 0] = a.area
            once[i, 5 * k + 1] = a.cx
            once[i, 5 * k + 2] = a.cy
            once[i, 5 * k + 3] = a.wx
            once[i, 5 * k + 4] = a.wy
            each[i, 5 * k + 0] = b.area
            each[i, 5 * k + 1] = b.cx
            each[i, 5 * k + 2] = b.cy
            each[i, 5 * k + 3] = b.wx
            each[i, 5 * k + 4] = b.wy

    n = len(rects)
    once = wp.zeros((n, 5 * len(cells)), dtype=float, device=device)
    each = wp.zeros((n, 5 * len(cells)), dtype=float, device=device)
    wp.launch(both, dim=n, inputs=[view, wp.array(rects, dtype=wp.vec4, device=device),
                                   wp.array(cells, dtype=wp.vec2, device=device), once, each], device=device)
    got, ref = once.numpy(), each.numpy()
    assert (ref[:, 0::5] > 0).sum() > 500 and (ref[:, 0::5] == 0).sum() > 500  # cells met and missed
    assert np.array_equal(got, ref)
    # and cell_overlap itself is the same function
    direct = wp.zeros((n, 5 * len(cells)), dtype=float, device=device)

    @wp.kernel
    def plain(view: kw.View, r: wp.array(dtype=wp.vec4), cells: wp.array(dtype=wp.vec2), out: wp.array2d(dtype=float)):
        i = wp.tid()
        for k in range(cells.shape[0]):
            c = cells[k]
            a = kw.cell_overlap(view, c[0], c[1], r[i][0], r[i][1], r[i][2], r[i][3])
            out[i, 5 * k + 0] = a.area
            out[i, 5 * k + 1] = a.cx
            out[i, 5 * k + 2] = a.cy
            out[i, 5 * k + 3] = a.wx
            out[i, 5 * k + 4] = a.wy

    wp.launch(plain, dim=n, inputs=[view, wp.array(rects, dtype=wp.vec4, device=device),
                                    wp.array(cells, dtype=wp.vec2, device=device), direct], device=device)
    assert np.array_equal(direct.numpy(), ref)


def test_line_of_sight_single_pass_gives_the_two_pass_weights_to_the_bit(small_dual_rig, device, monkeypatch):
    """The MART baseline's weights traced once into slots (counted, summed, then divided and packed) are
    the two-pass build's (counted first, then written divided) to the bit: with slots that hold every
    voxel, with a tiny capacity sample (voxels overflow and their chunk is written again) and small
    chunks; a budget that may not hold them all leaves the choice to the two-pass build."""
    grid = VolumeGrid.from_rig(small_dual_rig)
    proj = LightFieldProjector(small_dual_rig.camera, grid, device=device)
    vox = proj.wp.array(np.arange(0, grid.n_voxels, 3, dtype=np.int32), device=device)
    two = proj.weights(vox, method="los", build="two-pass")
    assert two.nnz > 0

    def bitwise(a, b):
        assert np.array_equal(a.voxels.numpy(), b.voxels.numpy()) and a.nnz == b.nnz
        assert all(np.array_equal(x, y) for x, y in zip(a.to_numpy(), b.to_numpy(), strict=True))

    modes = []
    trace = proj.builder.trace_los
    monkeypatch.setattr(proj.builder, "trace_los", lambda *a, **k: modes.append(a[1]) or trace(*a, **k))
    one = proj.weights(vox, method="los", build="single-pass")
    assert 4 in modes and 1 not in modes  # one trace of every voxel, none overflowed
    bitwise(two, one)
    bitwise(two, proj.weights(vox, method="los", build="single-pass", storage="stored"))
    modes.clear()
    tight = proj.weights(vox, method="los", build="single-pass", storage="auto",
                         budget_bytes=build_module.BYTES_PER_WEIGHT * two.nnz + 64 * grid.n_voxels)
    assert 4 not in modes and 0 in modes  # counted first by the two-pass build, which stores what fits
    bitwise(two, tight)
    # the capacity sampled from the first voxel alone, the one with the fewest weights (that of others
    # then overflow their slots), and small chunks
    per_voxel = np.diff(two.to_numpy()[0])
    order = np.argsort(per_voxel, kind="stable")
    assert per_voxel[order[-1]] > 1.25 * per_voxel[order[0]] + 32
    ordered = proj.wp.array(vox.numpy()[order], device=device)
    two = proj.weights(ordered, method="los", build="two-pass")
    modes.clear()
    monkeypatch.setattr(build_module, "CAPACITY_SAMPLE", 1)
    monkeypatch.setattr(build_module, "SINGLE_PASS_ENTRIES", 2000)
    small = proj.weights(ordered, method="los", build="single-pass")
    assert 1 in modes and 4 in modes  # overflowed slots written again at exact offsets
    bitwise(two, small)


def _every_third_voxels_two_pass(rig, device: str):
    """The CPU's packed-build tests' start: the rig's projector, every third voxel of its box, and their
    line-of-sight weights by the two-pass build (the reference); skipped on a GPU, whose build joins its
    chunks by copies."""
    if device != "cpu":
        pytest.skip("the CPU's build (a GPU's joins its chunks by copies)")
    grid = VolumeGrid.from_rig(rig)
    proj = LightFieldProjector(rig.camera, grid, device=device)
    vox = proj.wp.array(np.arange(0, grid.n_voxels, 3, dtype=np.int32), device=device)
    return proj, vox, proj.weights(vox, method="los", build="two-pass")


def test_line_of_sight_chunks_packed_into_one_array_are_the_same_weights(small_dual_rig, device, monkeypatch):
    """The single-pass line-of-sight build's small chunks packed straight into one array on the CPU (sized
    from the capacity sample's mean) give the two-pass build's weights to the bit as one chunk, with nothing
    copied to join them; where that array is too short (a margin below the mean), what it holds is one chunk
    and the rest are packed and joined as before: the same weights again."""
    proj, vox, two = _every_third_voxels_two_pass(small_dual_rig, device)
    want = two.to_numpy()
    monkeypatch.setattr(build_module, "SINGLE_PASS_ENTRIES", 20_000)  # many chunks
    joined = []
    join = build_module.WeightBuilder._joined
    monkeypatch.setattr(build_module.WeightBuilder, "_joined",
                        lambda self, group, *a: joined.append(len(group)) or join(self, group, *a))
    packed = proj.weights(vox, method="los", build="single-pass")
    assert len(packed.chunks) == 1 and not any(k > 1 for k in joined)  # no copy made to join them
    assert packed.nnz == two.nnz and all(np.array_equal(x, y) for x, y in zip(packed.to_numpy(), want, strict=True))
    monkeypatch.setattr(build_module, "LOS_PACKED_MARGIN", 0.3)  # the array holds about a third of them
    short = proj.weights(vox, method="los", build="single-pass")
    assert any(k > 1 for k in joined)  # the chunks after it packed and joined as before
    assert short.nnz == two.nnz and all(np.array_equal(x, y) for x, y in zip(short.to_numpy(), want, strict=True))
    # the weights iterate as the two-pass build's
    e = proj.wp.array(np.linspace(0.5, 2.0, two.n_voxels).astype(np.float32), device=device)
    for got in (packed, short):
        assert np.allclose(proj.bind(got).forward(e).numpy(), proj.bind(two).forward(e).numpy(), rtol=1e-6, atol=0)


def test_a_packed_array_too_short_for_the_first_chunk_leaves_no_empty_chunk(small_dual_rig, device, monkeypatch):
    """Where the capacity sample's mean puts the packed array below even the first chunk's entries, nothing is
    packed and the chunks go as before: no chunk of no voxels, the same weights as the two-pass build."""
    proj, vox, two = _every_third_voxels_two_pass(small_dual_rig, device)
    monkeypatch.setattr(build_module, "SINGLE_PASS_ENTRIES", 20_000)  # many chunks
    monkeypatch.setattr(build_module, "LOS_PACKED_MARGIN", 1e-6)  # the array holds one slot's entries
    # no room to join the chunks (a budget near full): each stays as it was made
    monkeypatch.setattr(build_module.WeightBuilder, "_joined", lambda self, group, *a: group)
    got = proj.weights(vox, method="los", build="single-pass")
    assert all(c.n > 0 for c in got.chunks), [(c.first, c.n) for c in got.chunks]
    assert got.nnz == two.nnz and all(np.array_equal(x, y) for x, y in zip(got.to_numpy(), two.to_numpy(),
                                                                           strict=True))
