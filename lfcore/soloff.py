"""The Soloff polynomial mapping of a camera: world points to pixels by a fitted polynomial.

Soloff, Adrian and Liu (1997) map each world point X = (x, y, z) to a camera's image by a
polynomial cubic in x and y and quadratic in z, the mapping DaVis calls "polynomial" (third
order, 19 terms for each of column and row):

    1, x, y, z, x^2, xy, y^2, xz, yz, z^2, x^3, x^2 y, x y^2, y^3, x^2 z, xyz, y^2 z, x z^2, y z^2

It needs no optical model, so it absorbs lens distortion, a Scheimpflug adapter's tilt and the
refraction of a tank window alike; fitted to the dots of calibration planes at three depths or
more (fewer: the terms in z^2 are left out, and with a single plane every term in z). World
coordinates are taken relative to a centre and divided by a scale per axis (both stored), so the
coefficients of a 1 m field and of a 10 mm one are equally well conditioned.

Pure: arrays in, arrays out; :meth:`SoloffMap.fit` is linear least squares.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SOLOFF_TERMS", "SoloffMap"]

#: The exponents (x, y, z) of each term, in the order of the coefficients.
SOLOFF_TERMS = np.array([
    (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (2, 0, 0), (1, 1, 0), (0, 2, 0), (1, 0, 1), (0, 1, 1), (0, 0, 2),
    (3, 0, 0), (2, 1, 0), (1, 2, 0), (0, 3, 0), (2, 0, 1), (1, 1, 1), (0, 2, 1), (1, 0, 2), (0, 1, 2),
], dtype=np.int64)


def _basis(u: np.ndarray, z_order: int) -> np.ndarray:
    """(..., terms) values of the terms with z exponent at most ``z_order`` at normalised points."""
    keep = SOLOFF_TERMS[:, 2] <= z_order
    e = SOLOFF_TERMS[keep]
    return np.prod(u[..., None, :] ** e, axis=-1)


@dataclass(frozen=True)
class SoloffMap:
    """One camera's third-order Soloff mapping.

    Attributes
    ----------
    coefficients
        (2, terms) float64: the column and the row polynomial, terms in the order of
        :data:`SOLOFF_TERMS` (those with z exponent at most ``z_order``).
    centre_mm
        (3,) world point the coordinates are taken from, mm.
    scale_mm
        (3,) what each axis is divided by, mm.
    z_order
        Highest power of z: 2, or less when the planes were too few to fit it.
    """

    coefficients: np.ndarray
    centre_mm: np.ndarray
    scale_mm: np.ndarray
    z_order: int = 2

    @classmethod
    def fit(cls, points_mm: np.ndarray, pixels: np.ndarray) -> SoloffMap:
        """The least-squares mapping of world points onto their pixel positions.

        Parameters
        ----------
        points_mm
            (n, 3) world points (x, y, z), mm: the named dots of every plane.
        pixels
            (n, 2) continuous (column, row) pixel positions of the same points.

        Raises
        ------
        ValueError
            Fewer points than terms, or points that do not span two axes.
        """
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if len(pts) != len(px):
            raise ValueError(f"{len(pts)} points but {len(px)} pixel positions")
        depths = len(np.unique(np.round(pts[:, 2], 6)))
        z_order = min(2, depths - 1)
        n_terms = int(np.sum(SOLOFF_TERMS[:, 2] <= z_order))
        if len(pts) < 2 * n_terms:
            raise ValueError(f"{len(pts)} dots cannot fit the {n_terms} terms of a Soloff polynomial; take more "
                             "dots or planes")
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        scale = 0.5 * (pts.max(axis=0) - pts.min(axis=0))
        if np.sum(scale[:2] > 0) < 2:
            raise ValueError("the dots do not span both x and y; a Soloff polynomial cannot be fitted")
        scale = np.where(scale > 0, scale, 1.0)
        a = _basis((pts - centre) / scale, z_order)
        coef, *_ = np.linalg.lstsq(a, px, rcond=None)
        return cls(coef.T.copy(), centre, scale, z_order)

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        """(..., 2) continuous (column, row) pixel positions of (..., 3) world points, mm."""
        u = (np.asarray(points_mm, dtype=np.float64) - self.centre_mm) / self.scale_mm
        return _basis(u, self.z_order) @ self.coefficients.T

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible form (for the calibration store)."""
        return {"coefficients": self.coefficients.tolist(), "centre_mm": self.centre_mm.tolist(),
                "scale_mm": self.scale_mm.tolist(), "z_order": int(self.z_order),
                "terms": [f"x^{a} y^{b} z^{c}" for a, b, c in SOLOFF_TERMS[SOLOFF_TERMS[:, 2] <= self.z_order]],
                "description": "column and row = sum of coefficient * term of (X - centre_mm) / scale_mm, X world mm "
                               "(Soloff et al. 1997: cubic in x and y, quadratic in z)"}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SoloffMap:
        """Inverse of :meth:`to_dict`."""
        return cls(np.asarray(data["coefficients"], dtype=np.float64), np.asarray(data["centre_mm"], dtype=np.float64),
                   np.asarray(data["scale_mm"], dtype=np.float64), int(data.get("z_order", 2)))
