"""The calibration target: a board of dots on a square grid, moved by the stage along world z.

The board defines the world frame of a calibration (the board positions from the stage
readback define it): dot ``(i, j)`` of the board lies at

    P(i, j, s) = centre_mm + (s - stage_centre_mm) z + spacing_mm (i e1 + j e2)

for stage readback ``s`` (mm), with ``e1``, ``e2`` the board's in-plane axes. An untilted board
has e1 = world x, e2 = world y and its normal along world z (facing a camera of identity pose).
A dual-camera rig with a second camera rotated about world y tilts the board about world y by
``tilt_deg`` (45 degrees puts the normal half way between two optical axes 90 degrees apart),
so both cameras see it; the stage still moves it along world z.

Dot ``(0, 0)`` is the marker: ``marker_scale`` times the radius of the others, as commercial
targets carry, so a camera that sees only part of the board can still tell which dot is which.
A two-level plate (``level_step_mm`` > 0) has the dots of odd columns ``i`` on a second level,
that much behind the first along the board's normal.

Pure geometry: numbers in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["DotBoard"]


@dataclass(frozen=True)
class DotBoard:
    """A dot calibration board and how the stage moves it.

    Parameters
    ----------
    spacing_mm
        Distance between neighbouring dot centres on the board, mm.
    radius_fraction
        Dot radius as a fraction of ``spacing_mm``.
    marker_scale
        Radius of the marker dot (0, 0) relative to the others (1: no marker).
    tilt_deg
        Rotation of the board about world y, degrees (0: normal along world +z).
    centre_mm
        World (x, y, z) of dot (0, 0) when the stage reads ``stage_centre_mm``.
    stage_centre_mm
        Stage position at which the board's origin is at ``centre_mm``, mm.
    level_step_mm
        Two-level plates: depth of the second level (the odd columns) behind the first, mm (0:
        one level).
    """

    spacing_mm: float = 3.0
    radius_fraction: float = 0.15
    marker_scale: float = 1.6
    tilt_deg: float = 0.0
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    stage_centre_mm: float = 0.0
    level_step_mm: float = 0.0

    def __post_init__(self) -> None:
        if not (self.spacing_mm > 0 and math.isfinite(self.spacing_mm)):
            raise ValueError(f"spacing_mm must be positive, got {self.spacing_mm}")
        if not 0 < self.radius_fraction * max(1.0, self.marker_scale) < 0.5:
            raise ValueError("dots (and the marker) must be smaller than half the spacing: "
                             f"radius_fraction {self.radius_fraction}, marker_scale {self.marker_scale}")
        if not -80.0 <= self.tilt_deg <= 80.0:
            raise ValueError(f"tilt_deg must be within +-80 degrees, got {self.tilt_deg}")
        if not (0.0 <= self.level_step_mm < 10 * self.spacing_mm):
            raise ValueError(f"level_step_mm must be 0 (one level) or a depth below ten dot pitches, got "
                             f"{self.level_step_mm}")
        object.__setattr__(self, "centre_mm", tuple(float(v) for v in self.centre_mm))

    @property
    def radius_mm(self) -> float:
        """Radius of an ordinary dot, mm."""
        return self.radius_fraction * self.spacing_mm

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) rows e1, e2 (in-plane) and the normal n, unit world vectors."""
        t = math.radians(self.tilt_deg)
        return np.array([[math.cos(t), 0.0, -math.sin(t)], [0.0, 1.0, 0.0], [math.sin(t), 0.0, math.cos(t)]])

    def indices(self, half: int) -> np.ndarray:
        """(n, 2) int64 dot indices (i, j) with |i|, |j| <= ``half``, i fastest."""
        g = np.arange(-half, half + 1)
        j, i = np.meshgrid(g, g, indexing="ij")
        return np.stack([i.ravel(), j.ravel()], axis=-1).astype(np.int64)

    def dot_centres(self, indices: np.ndarray, stage_mm: float | np.ndarray) -> np.ndarray:
        """World positions of dots ``indices`` (n, 2) at stage readback ``stage_mm``.

        Parameters
        ----------
        indices
            (n, 2) integer dot indices (i, j).
        stage_mm
            Stage readback, mm: a scalar or (n,) (one per dot).

        Returns
        -------
        numpy.ndarray
            (n, 3) world (x, y, z), mm.
        """
        ij = np.asarray(indices, dtype=np.float64).reshape(-1, 2)
        e1, e2, normal = self.axes
        s = np.broadcast_to(np.asarray(stage_mm, dtype=np.float64), (len(ij),))
        out = np.asarray(self.centre_mm) + self.spacing_mm * (ij[:, :1] * e1 + ij[:, 1:] * e2)
        if self.level_step_mm:  # the second level of a two-level plate lies behind the first
            out -= self.level_step_mm * (np.mod(ij[:, :1], 2) == 1) * normal
        out[:, 2] += s - self.stage_centre_mm
        return out

    def half_extent(self, reach_mm: float) -> int:
        """Dots per side (from the origin) that cover ``reach_mm`` of board in every direction."""
        return int(math.ceil(reach_mm / self.spacing_mm))

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible attributes (for the calibration store)."""
        d = asdict(self)
        d["centre_mm"] = list(self.centre_mm)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DotBoard:
        """Inverse of :meth:`to_dict`."""
        d = dict(data)
        d["centre_mm"] = tuple(d.get("centre_mm", (0.0, 0.0, 0.0)))
        return cls(**d)

    @classmethod
    def for_cameras(cls, optical_axes: np.ndarray, **kw: Any) -> DotBoard:
        """A board tilted about world y so its normal bisects the cameras' optical axes.

        Parameters
        ----------
        optical_axes
            (cameras, 3) unit world directions from the focal plane toward each camera.
        **kw
            Other fields of :class:`DotBoard`.
        """
        n = np.asarray(optical_axes, dtype=np.float64).reshape(-1, 3).mean(axis=0)
        tilt = math.degrees(math.atan2(n[0], n[2])) if np.hypot(n[0], n[2]) > 1e-9 else 0.0
        return cls(tilt_deg=round(tilt, 9), **kw)
