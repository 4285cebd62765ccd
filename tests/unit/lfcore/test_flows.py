"""Test flows against their analytic properties, and the advection against exact paths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcore.flows import (
    FLOW_NAMES,
    OSCILLATORY_CASES,
    Oscillatory,
    advect,
    flow_for_displacement,
    flow_from_params,
    peak_speed,
    standard_flow,
)
from lfcore.rig import VolumeConfig

VOLUME = VolumeConfig(centre_mm=(1.0, -2.0, 0.5), size_mm=(18.0, 18.0, 12.0))


def _gd(u):
    """Gudermannian function."""
    return 2.0 * np.arctan(np.tanh(0.5 * u))


@pytest.mark.parametrize("case", OSCILLATORY_CASES)
@pytest.mark.parametrize("omega", [0.25, 1.0])
def test_table_4_1_paths_are_exact(case, omega):
    # Velocity A cos(phi) along e with phi = k.(x - c): d(phi)/dt = (k.e) A cos(phi), solved by
    # phi(t) = gd((k.e) A t + gd^-1(phi0)); if k.e = 0 the particle moves in a straight line.
    flow = standard_flow(case, VOLUME, omega=omega).scaled(0.8)  # 0.8 m/s peak
    assert isinstance(flow, Oscillatory)
    e = np.eye(3)[0 if case[0] == "A" else 2]
    k = flow.wave_vector
    amp = 1e3 * flow.amplitude_m_s  # mm/s
    dt = 0.4 / (amp * max(np.linalg.norm(k), 1e-9))  # a large step: 0.4 rad of phase
    rng = np.random.default_rng(3)
    p0 = np.asarray(VOLUME.centre_mm) + rng.uniform(-0.5, 0.5, (200, 3)) * VOLUME.size_mm
    phi0 = (p0 - VOLUME.centre_mm) @ k
    p0 = p0[np.abs(np.cos(phi0)) > 0.2]  # stay clear of the turning points of gd^-1
    phi0 = (p0 - VOLUME.centre_mm) @ k
    ke = float(k @ e)
    if abs(ke) < 1e-12:
        expected = p0 + amp * np.cos(phi0)[:, None] * dt * e
    else:
        branch = np.floor((phi0 + 0.5 * np.pi) / np.pi)  # which half-period the phase is in
        local = phi0 - branch * np.pi
        sign = np.where(np.mod(branch, 2) == 0, 1.0, -1.0)  # cos changes sign every half period
        phi1 = _gd(sign * ke * amp * dt + np.arctanh(np.sin(local))) + branch * np.pi
        expected = p0 + ((phi1 - phi0) / ke)[:, None] * e
    got = advect(flow, p0, 0.0, dt)
    assert np.abs(got - p0).max() > 0.2 / np.linalg.norm(k)  # far: a good part of a wavelength
    assert np.abs(got - expected).max() < 1e-5


def test_wave_vectors_follow_table_4_1():
    L = VOLUME.size_mm[0]
    k = {c: standard_flow(c, VOLUME, omega=0.5).wave_vector for c in OSCILLATORY_CASES}
    assert np.allclose(k["A1"], [2 * math.pi / (0.5 * L), 0, 0])
    # L_xy = sqrt(2) L and k_x = k_y = 2 pi / (sqrt(2) omega L_xy)
    d = 2 * math.pi / (math.sqrt(2) * 0.5 * math.sqrt(2) * L)
    assert np.allclose(k["A2"], [d, d, 0]) and np.allclose(k["B3"], [d, 0, d])
    assert np.allclose(k["B4"], [0, 0, 2 * math.pi / (0.5 * L)])
    v = standard_flow("B2", VOLUME).velocity(np.array([VOLUME.centre_mm]))
    assert np.allclose(v, [[0, 0, 1.0]])  # type B moves along z only


def _divergence(flow, pts, t=0.0, h=1e-4):
    return sum((flow.velocity(pts + h * np.eye(3)[i], t_s=t)[:, i] - flow.velocity(pts - h * np.eye(3)[i], t_s=t)[:, i])
               / (2 * h) for i in range(3))


@pytest.mark.parametrize("name", ["vortex-ring", "jet", "A4", "B1", "B2"])
def test_flows_are_divergence_free(name):
    flow = standard_flow(name, VOLUME, omega=0.5)
    pts = np.asarray(VOLUME.centre_mm) + np.random.default_rng(4).uniform(-0.5, 0.5, (300, 3)) * VOLUME.size_mm
    scale = np.linalg.norm(flow.velocity(pts, t_s=0.05), axis=1).max() / (0.3 * min(VOLUME.size_mm[::2]))
    assert np.abs(_divergence(flow, pts, 0.05)).max() < 1e-5 * scale


def test_table_4_1_gradient_cases_compress():
    # A1's u varies along x itself: du/dx = -A k sin(k x), the chapter's gradient test
    flow = standard_flow("A1", VOLUME)
    p = np.array([[VOLUME.centre_mm[0] + 2.0, 0.0, 0.0]])
    k = flow.wave_vector[0]
    assert _divergence(flow, p)[0] == pytest.approx(-1e-3 * 1e3 * k * np.sin(2.0 * k), rel=1e-5)


def test_vortex_ring_centre_speed_and_translation():
    ring = standard_flow("vortex-ring", VOLUME)
    r, a, gamma = ring.radius_mm, ring.core_mm, ring.circulation_mm2_s
    # On the axis, u = Gamma R^2 / (2 rho^3) with rho^2 = z^2 + R^2 + a^2 (smoothed core)
    z = np.array([0.0, 1.0, -2.5])
    pts = np.asarray(VOLUME.centre_mm) + z[:, None] * np.array([0.0, 1.0, 0.0])
    expected = gamma * r**2 / (2 * (z**2 + r**2 + a**2) ** 1.5) * 1e-3
    v = ring.velocity(pts)
    assert np.allclose(v[:, 1], expected, rtol=1e-6) and np.allclose(v[:, [0, 2]], 0.0, atol=1e-12)
    # it moves along +y at Saffman's speed, and the field moves with it
    u = ring.translation_m_s
    assert u == pytest.approx(1e-3 * gamma / (4 * math.pi * r) * (math.log(8 * r / a) - 0.558))
    moved = ring.velocity(pts + [0.0, 1e3 * u * 0.3, 0.0], t_s=0.3)
    assert np.allclose(moved, v)


def test_a_phase_locked_ring_is_at_the_same_place_at_every_pair():
    # 10 px in 2 ms on 5.5 um pixels, pairs at 10 Hz: one ring would travel on by about 50 dt
    # of its own displacement between pairs, out of a millimetre-sized volume
    single = flow_for_displacement("vortex-ring", VOLUME, 0.0055, 2e-3)
    locked = flow_for_displacement("vortex-ring", VOLUME, 0.0055, 2e-3, period_s=0.1)
    assert single.period_s is None and locked.period_s == 0.1
    assert locked.circulation_mm2_s == single.circulation_mm2_s
    pts = np.asarray(VOLUME.centre_mm) + np.random.default_rng(2).uniform(-0.3, 0.3, (50, 3)) * VOLUME.size_mm
    for k in (1, 3, 7, 123):  # pair k's first pulse (at k / rate, as the sim times it), and its middle
        for t in (0.0, 1e-3):
            got = locked.velocity(pts, t_s=k / 10.0 + t)
            assert np.allclose(got, single.velocity(pts, t_s=t), rtol=1e-6, atol=1e-12), (k, t)
    travel = 1e3 * single.translation_m_s * 0.1  # mm between pairs
    assert np.allclose(single.centre_at(0.1) - single.centre_at(0.0), [0.0, travel, 0.0])
    # the period is kept in the truth's parameters, and only the ring has one
    assert flow_from_params(locked.params()) == locked
    assert flow_for_displacement("jet", VOLUME, 0.0055, 2e-3, period_s=0.1) == \
        flow_for_displacement("jet", VOLUME, 0.0055, 2e-3)
    with pytest.raises(ValueError, match="longer than dt"):
        flow_for_displacement("vortex-ring", VOLUME, 0.0055, 2e-3, period_s=1e-3)


def test_advection_converges():
    ring = standard_flow("vortex-ring", VOLUME).scaled(20.0)
    p0 = np.asarray(VOLUME.centre_mm) + np.random.default_rng(5).uniform(-0.4, 0.4, (100, 3)) * VOLUME.size_mm
    fine = advect(ring, p0, 0.0, 0.0005, rtol=1e-12)
    assert np.abs(advect(ring, p0, 0.0, 0.0005) - fine).max() < 1e-6
    assert np.abs(fine - p0).max() > 1.0  # mm: far more than a PIV displacement


def test_scaling_sets_the_peak_speed():
    for name in FLOW_NAMES:
        f = standard_flow(name, VOLUME)
        assert peak_speed(f.scaled(0.37 / peak_speed(f, VOLUME)), VOLUME) == pytest.approx(0.37)


def test_bad_flow_requests():
    with pytest.raises(ValueError, match="unknown flow 'vortex'"):
        standard_flow("vortex", VOLUME)
    with pytest.raises(ValueError, match="omega must be positive"):
        standard_flow("A1", VOLUME, omega=0.0)
