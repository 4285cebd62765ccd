"""Finding the calibration target's dots in a light-field frame (calibration.dots).

Frames are built lenslet by lenslet from a white image: every micro-image is filled with a
chosen lenslet brightness, with noise per lenslet as a Monte-Carlo render (or a dim target)
gives, so the truth is which dots there are and where their light is centred.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.dots import _climb, _regions, detect_dots, lenslet_cells, lenslet_sums
from calibration.mla_grid import detect_grid
from lfcore.white import WhiteImageConfig, white_image, white_irradiance
from tests.conftest import tiny_variant


@pytest.fixture(scope="module")
def lattice(tiny_rig):
    cam = tiny_variant(tiny_rig, sensor_px=[640, 480]).camera[0]  # about 64 x 48 lenslets
    grid = detect_grid(white_image(cam, render=tiny_rig.render, config=WhiteImageConfig(seed=3)))
    disc = white_irradiance(cam, config=WhiteImageConfig(level_counts=1.0))
    return grid, disc, lenslet_cells(grid)


def _frame(lattice, brightness, noise=0.3, seed=0):
    """Each micro-image lit by ``brightness(node_xy)`` (counts at a disc's centre) times 1 + noise * N(0, 1)."""
    grid, disc, cells = lattice
    rng = np.random.default_rng(seed)
    nodes = grid.lattice_px()
    level = brightness(nodes) * (1.0 + noise * rng.standard_normal(len(nodes)))
    img = np.full(disc.size, 100.0)
    img[cells.pixels] += disc.ravel()[cells.pixels] * level[cells.lenslet]
    img += rng.normal(0.0, 3.0, img.size)
    return np.clip(img, 0, None).reshape(disc.shape), nodes


def _disc(centre, radius_px, level):
    return lambda xy: level * (np.hypot(*(xy - centre).T) <= radius_px)


def _blob(centre, sigma_px, level):
    return lambda xy: level * np.exp(-0.5 * np.sum((xy - centre) ** 2, axis=1) / sigma_px**2)


def test_a_dot_many_lenslets_wide_is_one_dot_despite_noise(lattice):
    # Two flat-topped dots 12 lenslets across, with 30% noise per lenslet: many shallow maxima
    # on each top, which must not split it.
    a, b = np.array([170.0, 240.0]), np.array([440.0, 240.0])
    frame, _ = _frame(lattice, lambda xy: _disc(a, 60, 3000)(xy) + _disc(b, 60, 3000)(xy))
    dots = detect_dots(frame, lattice[0], cells=lattice[2])
    assert len(dots) == 2
    found = dots.centres_px[np.argsort(dots.centres_px[:, 0])]
    assert np.allclose(found, [a, b], atol=2.0)  # a fifth of a lenslet
    assert np.all(dots.lenslets > 80)
    # the noise is real: taking every maximum apart from 2.5 pitches splits the tops
    assert len(detect_dots(frame, lattice[0], cells=lattice[2], min_prominence=0.0)) > 4


def test_two_overlapping_dots_part_at_the_valley_and_a_faint_fragment_is_left_out(lattice):
    a, b, speck = np.array([250.0, 240.0]), np.array([330.0, 240.0]), np.array([500.0, 120.0])
    frame, _ = _frame(lattice, lambda xy: (_blob(a, 15, 4000)(xy) + _blob(b, 15, 4000)(xy)
                                            + _blob(speck, 6, 1500)(xy)), noise=0.05)
    dots = detect_dots(frame, lattice[0], cells=lattice[2])
    assert len(dots) == 2  # the speck holds 4% of a dot's light: the tip of a defocused dot
    found = dots.centres_px[np.argsort(dots.centres_px[:, 0])]
    assert np.allclose(found, [a, b], atol=3.0)
    assert dots.flux[0] == pytest.approx(dots.flux[1], rel=0.05)
    assert len(detect_dots(frame, lattice[0], cells=lattice[2], min_flux_fraction=0.0)) == 3


@pytest.mark.parametrize("min_prominence, merged", [(0.35, True), (0.2, False)])
def test_a_maximum_joins_a_brighter_one_unless_it_stands_above_their_saddle(min_prominence, merged):
    # peaks 10 and 8 joined at a saddle of 6: the lower one rises 2 above it, a quarter of its height
    sm = np.array([[1.0, 5.0, 10.0, 6.0, 8.0, 3.0]])
    lit, adj = np.ones_like(sm, dtype=bool), np.ones((3, 3), dtype=bool)
    top = _climb(sm, lit, adj)
    assert top.tolist() == [2, 2, 2, 2, 4, 4]  # the saddle climbs to its brighter side
    assert _regions(sm, lit, adj, top, min_prominence)[[2, 4]].tolist() == ([2, 2] if merged else [2, 4])


def test_at_a_saddle_of_three_a_low_maximum_joins_the_highest_not_the_nearest():
    # three arms (4-neighbour lattice) with peaks 10, 9 and 5 meeting at one lenslet of 4.5:
    # 9 stands 4.5 above it (half its height) and stays a dot; 5 joins the peak of 10
    sm = np.zeros((5, 5))
    sm[0, 2], sm[1, 2], sm[2, 0], sm[2, 1], sm[2, 3], sm[2, 4], sm[2, 2] = 10, 7, 9, 6, 4.8, 5, 4.5
    lit, adj = sm > 0, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)
    top = _climb(sm, lit, adj)
    assert _regions(sm, lit, adj, top, 0.35)[[2, 10, 14]].tolist() == [2, 10, 2]


def test_camera_frames_give_the_sums_and_noise_of_float_frames(lattice):
    # uint16 frames take the background and its noise from a histogram, other frames from
    # numpy.median: the two must agree exactly
    frame, _ = _frame(lattice, _disc(np.array([300.0, 200.0]), 40, 3000))
    counts = np.round(frame).astype(np.uint16)
    cam = lenslet_sums(counts, lattice[0], lattice[2])
    flt = lenslet_sums(counts.astype(np.float64), lattice[0], lattice[2])
    assert cam[1] == flt[1] > 0
    np.testing.assert_allclose(cam[0], flt[0], rtol=0, atol=1e-9 * np.abs(flt[0]).max())
    # the halves of each axis add up to the whole
    np.testing.assert_allclose(cam[0][:, 1] + cam[0][:, 2], cam[0][:, 0], atol=1e-6)


@pytest.mark.parametrize("n", [1, 2, 7, 10, 1001, 4096])
def test_the_histogram_median_and_noise_are_numpys(n):
    from calibration.dots import _background

    img = np.random.default_rng(n).poisson(60.0, (1, n)).astype(np.uint16)
    f = img.astype(np.float64)
    bg = np.median(f)
    assert _background(img) == pytest.approx((bg, 1.4826 * np.median(bg - f[f <= bg])), abs=1e-12)


def test_a_dot_is_centred_on_all_its_light_including_the_rim_below_the_threshold(lattice):
    # A defocused dot on a tilted board blurs more on its far side: a faint rim there, below
    # the threshold, holds light the centroid needs. Bright dots over a quarter of the frame
    # raise its median pixel above the background, which, summed over the dot's rim, biased the
    # centroid as much again.
    grid, disc, cells = lattice
    nodes = grid.lattice_px()
    a = np.array([250.0, 240.0])

    def dot(xy):
        d = xy - a
        outer = np.where(d[:, 0] > 0, 110.0, 50.0)  # the rim reaches 80 px on +x, 20 px on -x
        return 40.0 * np.clip((outer - np.hypot(*d.T)) / (outer - 30.0), 0.0, 1.0)

    w = dot(nodes)
    truth = (w[:, None] * nodes).sum(axis=0) / w.sum()
    level = w + 40.0 * (nodes[:, 0] < 130)  # the bright block (cut by the frame's edge: no dot)
    errors = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        img = np.full(disc.size, 100.0)
        img[cells.pixels] += disc.ravel()[cells.pixels] * level[cells.lenslet]
        img = (img + rng.normal(0.0, 3.0, img.size)).reshape(disc.shape)
        row = []
        for kw in ({}, {"window_margin": None, "refine_background": False}, {"window_margin": None},
                   {"refine_background": False}):
            dots = detect_dots(img, grid, cells=cells, **kw)
            assert len(dots) == 1
            row.append(dots.centres_px[0] - truth)
        errors.append(row)
    e = np.array(errors)  # (seeds, variants, 2)
    # centred on a disc about it: the pixel noise of the disc's dark lenslets (about 0.1 px), no bias
    assert np.all(np.hypot(e[:, 0, 0], e[:, 0, 1]) < 0.25) and abs(e[:, 0, 0].mean()) < 0.1
    # over the lit lenslets only, the rim is lost (toward -x) and the background error weighs too
    assert np.all(e[:, 1, 0] < -1.0) and np.all(e[:, 2, 0] < -0.3)
    # the disc is centred on the dot, so the background's error barely moves it
    assert np.all(np.hypot(e[:, 3, 0], e[:, 3, 1]) < 0.25)


@pytest.mark.parametrize(("f_number", "shortfall"), [(2.0, 0.04), (4.0, 0.01)])
def test_the_views_parallax_is_what_view_geometry_predicts_for_the_rendered_camera(f_number, shortfall):
    # Micro-images that touch (f-number matched, f/2 at M = -1) share their rims: the half views
    # of rendered point sources, spread over a whole period of the micro-images' drift on the
    # pixel grid, show the parallax of view_geometry's pupils, 4-6 % under the half disc's
    # 4 R / (3 pi). At f/4 the micro-images are half as wide and apart: no light crosses, and
    # only the pixels and the diffraction blur smooth the split between halves (2 % less).
    from calibration.dots import view_geometry, view_pupils_mm
    from lfcore.chief_ray import project
    from lfcore.render import LightFieldRenderer
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / "two_cameras.toml")
    cam = rig.camera[0].model_copy(update={"sensor_px": (1400, 1300), "f_number": f_number})  # 7.7 mm: a period
    grid = detect_grid(white_image(cam, render=rig.render, config=WhiteImageConfig(seed=1)))
    geo = view_geometry(cam, rig.laser.wavelength_nm)
    xs = np.linspace(-3.0, 3.0, 5)
    pts = np.array([[x, y, z] for x in xs for y, z in ((-2.0, -2.0), (1.5, 2.0))])  # 1.4 mm apart at least
    rend = LightFieldRenderer(cam, rig.render.model_copy(update={"rays_per_particle": 400_000,
                                                                 "particle_diameter_um": 0.0}),
                              wavelength_nm=rig.laser.wavelength_nm)
    sums, _ = lenslet_sums(rend.irradiance(pts, 1e6, seed=2), grid)
    nodes = grid.lattice_px()
    found, model, naive = [], [], []
    for p in pts:
        chief = project(cam, p)
        near = np.hypot(*(nodes - chief).T) < 100.0  # the blur disc is 45 px across
        s = sums[near]
        found.append((s[:, :, None] * nodes[near][:, None, :]).sum(axis=0) / s.sum(axis=0)[:, None])
        model.append(np.stack([project(cam, p, pupil_mm=tuple(a)) for a in geo.pupils_mm]) + geo.offsets_px)
        naive.append(np.stack([project(cam, p, pupil_mm=tuple(a)) for a in view_pupils_mm(cam.aperture_mm)]))
    found, model, naive = (np.array(v)[:, 1:] - np.array(v)[:, :1] for v in (found, model, naive))  # parallax

    def ratio(a, b):
        return float(np.sum(a * b) / np.sum(b * b))

    print("parallax found / model", ratio(found, model), "found / half disc", ratio(found, naive))
    assert ratio(found, model) == pytest.approx(1.0, abs=0.01)
    assert ratio(found, naive) < 1.0 - shortfall
    if f_number == 4.0:
        np.testing.assert_allclose(geo.offsets_px, 0.0, atol=0.005)
