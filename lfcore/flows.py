"""Analytic test flows and particle advection.

Positions are in mm and times in s; velocities are returned in m/s, so a particle moves
1000 * v * dt mm. Every flow is a frozen dataclass whose :meth:`Flow.params` is what a run
store records as the truth.

Flows
-----
``uniform``
    One constant velocity everywhere.
``A1``-``A4``, ``B1``-``B4``
    The oscillatory cases of the chapter's Table 4.1: u (type A) or w (type B) equal to
    ``amplitude * cos(k . (x - centre))``, with the wave vector along x (1), the x-y diagonal
    (2), the x-z diagonal (3) or z (4), and a wavelength of ``omega * L`` along that direction,
    where L is the volume's x extent (the chapter's 1820-pixel image width) and sqrt(2) L on
    the diagonals. Smaller omega means steeper velocity gradients.
``vortex-ring``
    A laminar vortex ring with a smoothed core, moving along its axis at its self-induced
    speed (Saffman's formula for a Gaussian core).
``jet``
    A round jet: a hyperbolic-tangent axial velocity profile plus a periodic train of
    shear-layer roll-up rings convected at 0.6 of the centreline velocity.

The vortex ring and the jet are divergence-free by construction (axisymmetric Stokes stream
functions). Table 4.1 is a test of velocity gradients rather than a physical flow: only A4,
B1 and B2, whose velocity does not vary along its own direction, are divergence-free.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipe, ellipk

from lfcore._deprecation import keyword_options
from lfcore.rig import VolumeConfig

__all__ = [
    "FLOW_NAMES",
    "Flow",
    "Oscillatory",
    "RoundJet",
    "Uniform",
    "VortexRing",
    "advect",
    "default_displacement_px",
    "flow_for_displacement",
    "peak_speed",
    "standard_flow",
]

OSCILLATORY_CASES = ("A1", "A2", "A3", "A4", "B1", "B2", "B3", "B4")
FLOW_NAMES = ("uniform", *OSCILLATORY_CASES, "vortex-ring", "jet")


class Flow:
    """Base of the analytic flows: a velocity field v(x, t)."""

    name: ClassVar[str] = ""

    @keyword_options("t_s", since="0.1.0")
    def velocity(self, points_mm: np.ndarray, *, t_s: float = 0.0) -> np.ndarray:
        """Velocity at world points.

        Parameters
        ----------
        points_mm
            (n, 3) world positions in mm, (x, y, z).
        t_s
            Time in s.

        Returns
        -------
        numpy.ndarray
            (n, 3) velocity (u, v, w) in m/s.
        """
        raise NotImplementedError

    def scaled(self, factor: float) -> Flow:
        """The same flow with every velocity multiplied by ``factor``."""
        raise NotImplementedError

    def params(self) -> dict[str, Any]:
        """JSON-compatible description: ``name`` plus the flow's parameters."""
        return {"name": self.name, **_jsonable(asdict(self))}


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


@dataclass(frozen=True)
class Uniform(Flow):
    velocity_m_s: tuple[float, float, float]
    name: ClassVar[str] = "uniform"

    @keyword_options("t_s", since="0.1.0")
    def velocity(self, points_mm: np.ndarray, *, t_s: float = 0.0) -> np.ndarray:
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        return np.broadcast_to(np.asarray(self.velocity_m_s), pts.shape).copy()

    def scaled(self, factor: float) -> Uniform:
        return replace(self, velocity_m_s=tuple(factor * v for v in self.velocity_m_s))


@dataclass(frozen=True)
class Oscillatory(Flow):
    """Table 4.1: ``u`` (type A) or ``w`` (type B) = amplitude * cos(k . (x - centre))."""

    case: str
    omega: float
    amplitude_m_s: float
    length_mm: float
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: ClassVar[str] = "oscillatory"

    def __post_init__(self) -> None:
        if self.case not in OSCILLATORY_CASES:
            raise ValueError(f"unknown oscillatory case '{self.case}'; choose one of {', '.join(OSCILLATORY_CASES)}")
        if not (self.omega > 0 and self.length_mm > 0):
            raise ValueError("omega and length_mm must be positive")

    @property
    def wave_vector(self) -> np.ndarray:
        """k in rad/mm: wavelength omega * L along x or z, omega * sqrt(2) L on a diagonal."""
        k1 = 2.0 * math.pi / (self.omega * self.length_mm)
        kd = 2.0 * math.pi / (2.0 * self.omega * self.length_mm)  # 2 pi / (sqrt2 omega L_xy)
        return np.array({"1": (k1, 0.0, 0.0), "2": (kd, kd, 0.0),
                         "3": (kd, 0.0, kd), "4": (0.0, 0.0, k1)}[self.case[1]])

    @keyword_options("t_s", since="0.1.0")
    def velocity(self, points_mm: np.ndarray, *, t_s: float = 0.0) -> np.ndarray:
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        out = np.zeros_like(pts)
        phase = (pts - np.asarray(self.centre_mm)) @ self.wave_vector
        out[:, 0 if self.case[0] == "A" else 2] = self.amplitude_m_s * np.cos(phase)
        return out

    def scaled(self, factor: float) -> Oscillatory:
        return replace(self, amplitude_m_s=factor * self.amplitude_m_s)

    def params(self) -> dict[str, Any]:
        return {**super().params(), "name": self.case}


def _ring_velocity(pts: np.ndarray, centre: np.ndarray, axis: np.ndarray, radius: float,
                   core: float, circulation: float) -> np.ndarray:
    """Velocity (mm/s) of a circular vortex ring with a smoothed core.

    Stokes stream function of a ring filament, psi = Gamma/(2 pi) rho [(1 - m/2) K(m) - E(m)]
    with rho^2 = z^2 + (r + R)^2 + a^2 and m = 4 r R / rho^2 (the core radius a removes the
    filament's singularity); u_z = (1/r) dpsi/dr, u_r = -(1/r) dpsi/dz, differentiated
    analytically, so the field is exactly divergence-free.
    """
    d = pts - centre
    z = d @ axis
    rvec = d - z[:, None] * axis
    r_true = np.linalg.norm(rvec, axis=1)
    r = np.maximum(r_true, 1e-9 * radius)
    rho2 = z**2 + (r + radius) ** 2 + core**2
    rho = np.sqrt(rho2)
    m = 4.0 * r * radius / rho2
    k, e = ellipk(m), ellipe(m)
    f = (1.0 - 0.5 * m) * k - e
    small = m < 1e-3
    ms = np.where(small, 0.5, m)  # keep the exact branch away from its 0/0 at m = 0
    dk = (e - (1.0 - ms) * k) / (2.0 * ms * (1.0 - ms))
    de = (e - k) / (2.0 * ms)
    fp = np.where(small, math.pi * m / 16.0 + 9.0 * math.pi * m**2 / 128.0,
                  -0.5 * k + (1.0 - 0.5 * ms) * dk - de)
    f = np.where(small, math.pi * m**2 / 32.0 + 3.0 * math.pi * m**3 / 128.0, f)
    m_r = 4.0 * radius / rho2 - 8.0 * r * radius * (r + radius) / rho2**2
    m_z = -8.0 * r * radius * z / rho2**2
    c = circulation / (2.0 * math.pi)
    psi_r = c * ((r + radius) / rho * f + rho * fp * m_r)
    psi_z = c * (z / rho * f + rho * fp * m_z)
    u_axial = psi_r / r
    u_radial = -psi_z / r
    e_r = np.where(r_true[:, None] > 0, rvec / np.maximum(r_true, 1e-300)[:, None], 0.0)
    return u_axial[:, None] * axis + u_radial[:, None] * e_r


def _unit(v: tuple[float, float, float]) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


@dataclass(frozen=True)
class VortexRing(Flow):
    """A laminar vortex ring translating along ``axis`` at its self-induced speed.

    ``period_s``: a new ring leaves ``centre_mm`` every ``period_s`` seconds, as from a ring
    generator fired with the laser: with the laser's pair period every pair sees the ring at
    the same phase (phase-locked PIV). None: one ring, which travels on (at the usual speeds
    it leaves a millimetre-sized volume between one pair and the next).
    """

    centre_mm: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius_mm: float
    core_mm: float
    circulation_mm2_s: float
    period_s: float | None = None
    name: ClassVar[str] = "vortex-ring"

    @property
    def translation_m_s(self) -> float:
        """Saffman's speed of a thin ring with a Gaussian core: G/(4 pi R) (ln(8R/a) - 0.558)."""
        r, a = self.radius_mm, self.core_mm
        return 1e-3 * self.circulation_mm2_s / (4 * math.pi * r) * (math.log(8 * r / a) - 0.558)

    def centre_at(self, t_s: float) -> np.ndarray:
        """Centre (mm) of the ring at time ``t_s``."""
        age = t_s
        if self.period_s:
            # pair k fires at k / rate: k * (1 / rate) must count as whole periods, where
            # t % period would give 0.7 % 0.1 = 0.09999... (the ring at the end of its travel)
            age = max(0.0, t_s - self.period_s * math.floor(t_s / self.period_s + 1e-9))
        return np.asarray(self.centre_mm) + 1e3 * self.translation_m_s * age * _unit(self.axis)

    @keyword_options("t_s", since="0.1.0")
    def velocity(self, points_mm: np.ndarray, *, t_s: float = 0.0) -> np.ndarray:
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        v = _ring_velocity(pts, self.centre_at(t_s), _unit(self.axis), self.radius_mm,
                           self.core_mm, self.circulation_mm2_s)
        return 1e-3 * v

    def scaled(self, factor: float) -> VortexRing:
        return replace(self, circulation_mm2_s=factor * self.circulation_mm2_s)


@dataclass(frozen=True)
class RoundJet(Flow):
    """A round jet along ``axis`` with shear-layer roll-up rings.

    Axial velocity U0/2 (1 - tanh((r - R) / (2 theta))) plus vortex rings of radius R, spaced
    ``wavelength_mm`` apart and convected at 0.6 U0, each of circulation 0.5 U0 wavelength.
    The ring train is periodic over ``n_rings`` wavelengths centred on ``centre_mm``.
    """

    centre_mm: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius_mm: float
    centreline_m_s: float
    theta_mm: float
    wavelength_mm: float
    core_mm: float
    n_rings: int = 8
    name: ClassVar[str] = "jet"

    @keyword_options("t_s", since="0.1.0")
    def velocity(self, points_mm: np.ndarray, *, t_s: float = 0.0) -> np.ndarray:
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        axis = _unit(self.axis)
        centre = np.asarray(self.centre_mm)
        d = pts - centre
        z = d @ axis
        r = np.linalg.norm(d - z[:, None] * axis, axis=1)
        u0 = 1e3 * self.centreline_m_s  # mm/s
        v = (0.5 * u0 * (1.0 - np.tanh((r - self.radius_mm) / (2.0 * self.theta_mm))))[:, None] * axis
        lam = self.wavelength_mm
        span = self.n_rings * lam
        shift = 0.6 * u0 * t_s
        gamma = 0.5 * u0 * lam
        for k in range(self.n_rings):
            pos = (k * lam + shift) % span - 0.5 * span  # axial position, wrapped into the span
            v += _ring_velocity(pts, centre + pos * axis, axis, self.radius_mm, self.core_mm, gamma)
        return 1e-3 * v

    def scaled(self, factor: float) -> RoundJet:
        return replace(self, centreline_m_s=factor * self.centreline_m_s)


def standard_flow(name: str, volume: VolumeConfig, *, omega: float = 1.0) -> Flow:
    """The named test flow laid out in ``volume``, at an arbitrary velocity scale.

    Use :func:`peak_speed` and :meth:`Flow.scaled` to set its speed. Vortex rings and jets have
    their axis along world y (up), centred in the volume; their radius is set by the smaller
    of the volume's x and z extents, so that both an identity-pose camera and one rotated
    about y see them side-on.

    Raises
    ------
    ValueError
        For an unknown name or a non-positive omega.
    """
    c = tuple(float(v) for v in volume.centre_mm)
    sx, _, sz = volume.size_mm
    if name == "uniform":
        return Uniform(velocity_m_s=tuple(float(v) for v in _unit((0.8, 0.5, 0.33))))
    if name in OSCILLATORY_CASES:
        if not omega > 0:
            raise ValueError(f"omega must be positive, got {omega}")
        return Oscillatory(case=name, omega=float(omega), amplitude_m_s=1.0, length_mm=float(sx), centre_mm=c)
    if name == "vortex-ring":
        radius = 0.3 * min(sx, sz)
        return VortexRing(centre_mm=c, axis=(0.0, 1.0, 0.0), radius_mm=radius, core_mm=0.25 * radius,
                          circulation_mm2_s=1e3 * radius)
    if name == "jet":
        radius = 0.3 * min(sx, sz)
        return RoundJet(centre_mm=c, axis=(0.0, 1.0, 0.0), radius_mm=radius, centreline_m_s=1.0,
                        theta_mm=0.1 * radius, wavelength_mm=1.2 * radius, core_mm=0.25 * radius)
    raise ValueError(f"unknown flow '{name}'; choose one of {', '.join(FLOW_NAMES)}")


def default_displacement_px(name: str) -> float:
    """Peak particle displacement over dt, in object-side pixels, when the user gives none.

    25 for the chapter's Table 4.1 cases (its amplitude), 10 for the others.
    """
    return 25.0 if name in OSCILLATORY_CASES else 10.0


def flow_for_displacement(name: str, volume: VolumeConfig, object_pixel_mm: float, dt_s: float, *,
                          displacement_px: float | None = None, omega: float = 1.0,
                          period_s: float | None = None) -> Flow:
    """The named test flow, scaled so its fastest particle moves ``displacement_px`` in ``dt_s``.

    Parameters
    ----------
    name, volume, omega
        As for :func:`standard_flow`.
    period_s
        For the vortex ring: a new ring every ``period_s`` (pass the laser's pair period,
        ``1 / rate_hz``, so that every pair of a run sees it in the volume; see
        :class:`VortexRing`). The other flows ignore it.
    object_pixel_mm
        Object-side pixel size (pixel pitch / |M|) of the camera the displacement refers to.
    dt_s
        Time between the frames of a pair, seconds.
    displacement_px
        Peak displacement in object-side pixels; :func:`default_displacement_px` if None.

    Raises
    ------
    ValueError
        For an unknown flow, a non-positive displacement or dt, or a displacement beyond the
        volume's extent.
    """
    disp = default_displacement_px(name) if displacement_px is None else float(displacement_px)
    if not (np.isfinite(disp) and disp > 0):
        raise ValueError(f"the displacement must be positive, got {disp}")
    # a particle moving further than the volume is long between the frames of a pair leaves it:
    # nothing to correlate, and advecting the flows at such speeds takes minutes
    most = max(volume.size_mm) / object_pixel_mm
    if disp > most:
        raise ValueError(f"a displacement of {disp:g} px is more than the volume's extent ({most:.0f} px of "
                         f"{object_pixel_mm * 1e3:.3g} um): every particle would leave it between frames A and B; "
                         "give at most a few tens of pixels (PIV windows follow a quarter of their size)")
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt must be positive, got {dt_s}")
    field = standard_flow(name, volume, omega=omega)
    if period_s is not None and not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"the ring period must be positive, got {period_s}")
    target = disp * object_pixel_mm * 1e-3 / dt_s  # m/s
    field = field.scaled(target / peak_speed(field, volume))
    if isinstance(field, VortexRing) and period_s is not None:
        if period_s <= dt_s:
            raise ValueError(f"the ring period {period_s:g} s must be longer than dt = {dt_s:g} s")
        field = replace(field, period_s=float(period_s))
    return field


def peak_speed(flow: Flow, volume: VolumeConfig, *, t_s: float = 0.0, n: int = 24) -> float:
    """Largest speed (m/s) of ``flow`` on an n^3 grid spanning ``volume`` at time ``t_s``."""
    axes = [c + s * np.linspace(-0.5, 0.5, n) for c, s in zip(volume.centre_mm, volume.size_mm, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return float(np.linalg.norm(flow.velocity(grid, t_s=t_s), axis=1).max())


def advect(flow: Flow, points_mm: np.ndarray, t0_s: float, dt_s: float, *, rtol: float = 1e-9) -> np.ndarray:
    """Move particles with the flow from ``t0_s`` to ``t0_s + dt_s``.

    Integrates dx/dt = 1000 v(x, t) (mm/s) with scipy's adaptive 8th-order Dormand-Prince
    method under error control, so even curved paths through strong gradients are followed
    to ``rtol``.

    Parameters
    ----------
    flow
        The velocity field.
    points_mm
        (n, 3) world positions in mm at ``t0_s``.
    t0_s, dt_s
        Start time and interval in s.
    rtol
        Relative tolerance; the absolute tolerance is ``rtol`` times the largest coordinate.

    Returns
    -------
    numpy.ndarray
        (n, 3) positions in mm at ``t0_s + dt_s``.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0 or dt_s == 0:
        return pts.copy()

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        return 1e3 * flow.velocity(y.reshape(-1, 3), t_s=t).ravel()

    atol = rtol * max(1.0, float(np.abs(pts).max()))
    sol = solve_ivp(rhs, (t0_s, t0_s + dt_s), pts.ravel(), method="DOP853", rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"particle advection failed: {sol.message}")
    return sol.y[:, -1].reshape(-1, 3)


def flow_from_params(params: dict[str, Any]) -> Flow:
    """The flow that :meth:`Flow.params` described (as a run store's ``truth`` attrs keep it).

    Raises
    ------
    ValueError
        For an unknown flow name or parameters that do not fit it.
    """
    p = {k: (tuple(v) if isinstance(v, list) else v) for k, v in params.items()}
    name = p.pop("name", None)
    classes: dict[str, type[Flow]] = {"uniform": Uniform, "vortex-ring": VortexRing, "jet": RoundJet}
    if name in OSCILLATORY_CASES:
        p["case"] = name
        cls: type[Flow] = Oscillatory
    elif name in classes:
        cls = classes[name]
    else:
        raise ValueError(f"unknown flow '{name}'; choose one of {', '.join(FLOW_NAMES)}")
    try:
        return cls(**p)
    except TypeError as exc:
        raise ValueError(f"parameters of flow '{name}' do not fit: {exc}") from None
