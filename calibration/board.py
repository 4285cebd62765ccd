"""The dot board the volumetric calibration assumes unless told (:func:`default_board`).

A dot is found from the lenslets its light falls on, so neighbouring dots closer than
:data:`MIN_DOT_LENSLETS` lenslets (in the object space of the coarsest camera) share lenslets and
cannot be told apart; a pinhole camera's dots are blobs of pixels, told apart from
:data:`MIN_DOT_PIXELS` pixels; and the fit needs a grid of dots in every camera's view, at least
:data:`MIN_DOTS_ACROSS` across the narrowest field of view.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lfcore.rig import Rig, is_pinhole
from lfcore.target import DotBoard

__all__ = ["MIN_DOTS_ACROSS", "MIN_DOT_LENSLETS", "MIN_DOT_PIXELS", "default_board"]

#: Fewest lenslets (in the volume, through the main lens) between neighbouring dots of a board.
MIN_DOT_LENSLETS = 2
#: Fewest pixels (in the volume) between neighbouring dots of a board, for a pinhole camera: a dot
#: a third of the spacing across, blurred by about 3 px, still stands apart from its neighbours.
MIN_DOT_PIXELS = 8
#: Fewest dots across the narrowest camera's field of view.
MIN_DOTS_ACROSS = 2


def default_board(rig: Rig, spacing_mm: float | None = None, tilt_deg: float | None = None) -> DotBoard:
    """The board of the volumetric calibration: the rig's ``[target]`` where it describes the plate,
    else the default board.

    The default board has a 3 mm spacing (a quarter of the volume's smaller transverse size for
    small rigs) and dots 0.3 spacings across, is centred on the volume, tilted about world y so
    its normal bisects the cameras' optical axes (0 for one camera, 45 degrees for two at 90), and
    has a marker dot (1.6 times larger) at its origin for two or more cameras; one camera names
    its dots from the nominal model alone (no marker).

    Parameters
    ----------
    rig
        The rig (cameras, volume, ``[target]``).
    spacing_mm
        Dot pitch, mm (None: ``target.dot_pitch_mm``, else the default above).
    tilt_deg
        Tilt about world y, degrees (None: ``target.tilt_deg``, else the bisecting tilt).

    Raises
    ------
    ValueError
        A spacing below :data:`MIN_DOT_LENSLETS` lenslets of the coarsest camera, or one that
        leaves fewer than :data:`MIN_DOTS_ACROSS` dots across the narrowest field of view.
    """
    vol, plate = rig.volume, rig.target
    if spacing_mm is None:
        spacing_mm = plate.dot_pitch_mm or min(3.0, 0.25 * min(vol.size_mm[0], vol.size_mm[1]))
    if tilt_deg is None:
        tilt_deg = plate.tilt_deg
    least, unit = max((MIN_DOT_PIXELS * c.object_pixel_mm, f"{MIN_DOT_PIXELS} pixels") if is_pinhole(c) else
                      (MIN_DOT_LENSLETS * c.mla_pitch_mm / abs(c.magnification), f"{MIN_DOT_LENSLETS} lenslets")
                      for c in rig.camera)
    if spacing_mm < least:
        raise ValueError(f"dots {spacing_mm:g} mm apart are closer than {unit} of the cameras "
                         f"({least:.3g} mm in the volume), where they cannot be told apart; use a spacing of at least "
                         f"{least:.2g} mm")
    most = min(min(c.field_of_view_mm) for c in rig.camera) / MIN_DOTS_ACROSS
    if spacing_mm > most:
        raise ValueError(f"dots {spacing_mm:g} mm apart leave fewer than {MIN_DOTS_ACROSS} across the narrowest "
                         f"camera's field of view ({MIN_DOTS_ACROSS * most:.3g} mm); use a spacing of at most "
                         f"{most:.2g} mm")
    shape: dict[str, float] = {"marker_scale": 1.6 if len(rig.camera) > 1 else 1.0}
    if plate.dot_diameter_mm is not None:
        shape["radius_fraction"] = 0.5 * plate.dot_diameter_mm / spacing_mm
    if plate.marker_diameter_mm is not None:  # 0: the plate has no marker dot
        dot = plate.dot_diameter_mm or 2 * DotBoard.radius_fraction * spacing_mm
        shape["marker_scale"] = max(1.0, plate.marker_diameter_mm / dot)
    try:
        board = DotBoard.for_cameras(np.array([c.optical_axis for c in rig.camera]), spacing_mm=spacing_mm,
                                     centre_mm=vol.centre_mm, level_step_mm=plate.level_step_mm, **shape)
    except ValueError as exc:
        raise ValueError(f"[target]: {exc}") from None
    return board if tilt_deg is None else dataclasses.replace(board, tilt_deg=tilt_deg)
