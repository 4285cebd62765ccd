"""From one camera's target-plane images to its fitted model.

The volumetric calibration's fit, step by step: find the dots of every plane taken
(:func:`calibration.dots.detect_dots`, once), name them on the board with the nominal camera
(:func:`calibration.dots.match_dots` against :func:`lfcore.chief_ray.project`), fit the model
(:func:`calibration.fit.fit_camera`), name the dots again with the fitted model (a nominal
model can be a few dots off at the edges of the field of view) and fit again. Pure: images,
stage positions, the microlens grid and the board in; the fit out.

A pinhole (Tomo-PIV) camera takes the same steps with its own pieces: its dots are blobs
(:func:`calibration.pinhole.detect_blobs`, no microlens grid), predicted by the pinhole model
(:func:`lfcore.pinhole.project`), and fitted by :func:`calibration.pinhole.fit_pinhole` (the
pinhole model with distortion, and the Soloff polynomial).
"""

from __future__ import annotations

import math

import numpy as np

from calibration.dots import DotError, Dots, detect_dots, lenslet_cells, match_dots, view_geometry
from calibration.fit import CameraFit, FitError, PlaneDots, fit_camera
from calibration.mla_grid import MlaGrid
from calibration.pinhole import detect_blobs, fit_pinhole
from lfcore import pinhole
from lfcore.chief_ray import project
from lfcore.rig import AnyCamera, is_pinhole
from lfcore.target import DotBoard

__all__ = ["find_plane_dots", "fit_from_planes", "name_plane_dots", "predicted_px"]


def predicted_px(model: AnyCamera, points_mm: np.ndarray) -> np.ndarray:
    """(..., 2) where ``model`` images (..., 3) world points: the chief-ray view of a light-field
    camera (:func:`lfcore.chief_ray.project`), the pinhole image of a pinhole one."""
    return pinhole.project(model, points_mm) if is_pinhole(model) else project(model, points_mm)


def find_plane_dots(frames, stage_mm: np.ndarray, grid: MlaGrid | None, *, camera: str) -> list[tuple[int, Dots]]:
    """The dots of every plane taken, found once (naming them needs a model).

    Parameters
    ----------
    frames
        (planes, rows, columns) images of the target, one per plane (a NumPy or zarr array).
    stage_mm
        (planes,) stage readback of each plane, mm; NaN for a plane not taken.
    grid
        The camera's microlens grid (from its white image); None for a pinhole camera, whose
        dots are blobs (:func:`calibration.pinhole.detect_blobs`).
    camera
        The camera's name, for the messages.

    Raises
    ------
    FitError
        A plane whose dots cannot be found, naming the camera and the plane.
    """
    cells = lenslet_cells(grid) if grid is not None else None
    out = []
    for p in np.flatnonzero(np.isfinite(stage_mm)):
        try:
            frame = frames[int(p)]
            out.append((int(p), detect_dots(frame, grid, cells=cells) if grid is not None else detect_blobs(frame)))
        except DotError as exc:
            raise FitError(f"camera '{camera}', plane {p + 1} of {len(stage_mm)}: {exc}") from None
    return out


def name_plane_dots(model: AnyCamera, board: DotBoard, detected: list[tuple[int, Dots]], stage_mm: np.ndarray, *,
                    min_dots: int, camera: str) -> list[PlaneDots]:
    """Name the dots of every plane on the board, where ``model`` predicts them.

    Parameters
    ----------
    model
        The camera model that predicts where each dot of the board appears.
    board
        The dot board (its world frame follows the stage readback).
    detected
        The dots of each plane, from :func:`find_plane_dots`.
    stage_mm
        (planes,) stage readback of each plane, mm.
    min_dots
        Fewest named dots accepted in a plane.
    camera
        The camera's name, for the messages.

    Raises
    ------
    FitError
        A plane with fewer than ``min_dots`` named dots, naming the camera and the plane.
    """
    reach = 0.75 * math.hypot(*model.field_of_view_mm) / math.cos(math.radians(board.tilt_deg)) + board.spacing_mm
    ij = board.indices(board.half_extent(reach + abs(float(np.nanmax(np.abs(stage_mm - board.stage_centre_mm))))))
    out = []
    for p, dots in detected:
        if not len(dots):
            # nothing lit enough to be a dot: most often a plane beyond the depth of field, where
            # each dot's light spreads over so many lenslets that it sinks into the noise
            depth = float(np.dot(board.dot_centres(np.zeros((1, 2)), stage_mm[p])[0] - np.asarray(model.focus_mm),
                                 model.optical_axis))
            raise FitError(f"camera '{camera}', plane {p + 1} of {len(stage_mm)} (stage {stage_mm[p]:.4f} mm): no "
                           f"dot seen; the plane is {abs(depth):.2f} mm {'in front of' if depth > 0 else 'behind'} "
                           "the camera's focus, likely beyond its depth of field: take planes nearer the focus (a "
                           "smaller --step-mm or fewer --planes), or check the target's lighting")
        found, which = match_dots(dots, predicted_px(model, board.dot_centres(ij, stage_mm[p])), ij)
        if len(found) < min_dots:
            raise FitError(f"camera '{camera}', plane {p + 1} of {len(stage_mm)} (stage {stage_mm[p]:.4f} mm): "
                           f"{len(found)} dot(s) found and named (of {len(dots)} seen), need at least "
                           f"{min_dots}; check the target's lighting, focus and the board settings")
        out.append(PlaneDots(p, float(stage_mm[p]), which, dots.views_px[found]))
    return out


def fit_from_planes(nominal: AnyCamera, board: DotBoard, frames, stage_mm: np.ndarray, grid: MlaGrid | None, *,
                    wavelength_nm: float, fit_distortion: bool = False, min_dots: int = 2) -> CameraFit:
    """Find, name and fit, then name again with the fitted model and refit (module docstring).

    Parameters
    ----------
    nominal
        The camera as the rig file describes it (the starting model).
    board
        The dot board.
    frames, stage_mm
        As :func:`find_plane_dots`.
    grid
        The camera's microlens grid (None for a pinhole camera).
    wavelength_nm
        The light the target was imaged in (the views' diffraction).
    fit_distortion
        Also fit a radial distortion k1 (a pinhole camera always fits k1, k2, p1 and p2).
    min_dots
        Fewest named dots accepted in a plane.

    Raises
    ------
    FitError
        Dots that cannot be found or named, too few of them, or a fit that fails, in one line
        naming the camera.
    """
    detected = find_plane_dots(frames, stage_mm, None if is_pinhole(nominal) else grid, camera=nominal.name)
    planes = name_plane_dots(nominal, board, detected, stage_mm, min_dots=min_dots, camera=nominal.name)
    if is_pinhole(nominal):
        fit = fit_pinhole(nominal, board, planes, n_planes=len(stage_mm))
        planes = name_plane_dots(fit.camera, board, detected, stage_mm, min_dots=min_dots, camera=nominal.name)
        return fit_pinhole(nominal, board, planes, n_planes=len(stage_mm))
    opts = {"n_planes": len(stage_mm), "fit_distortion": fit_distortion, "wavelength_nm": wavelength_nm,
            "views": view_geometry(nominal, wavelength_nm)}
    fit = fit_camera(nominal, board, planes, grid, **opts)
    planes = name_plane_dots(fit.camera, board, detected, stage_mm, min_dots=min_dots, camera=nominal.name)
    return fit_camera(nominal, board, planes, grid, **opts)
