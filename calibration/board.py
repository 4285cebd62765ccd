"""The dot board the volumetric calibration assumes unless told (:func:`default_board`).

A dot is found from the lenslets its light falls on, so neighbouring dots closer than
:data:`MIN_DOT_LENSLETS` lenslets (in the object space of the coarsest camera) share lenslets and
cannot be told apart; and the fit needs a grid of dots in every camera's view, at least
:data:`MIN_DOTS_ACROSS` across the narrowest field of view.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lfcore.rig import Rig
from lfcore.target import DotBoard

__all__ = ["MIN_DOTS_ACROSS", "MIN_DOT_LENSLETS", "default_board"]

#: Fewest lenslets (in the volume, through the main lens) between neighbouring dots of a board.
MIN_DOT_LENSLETS = 2
#: Fewest dots across the narrowest camera's field of view.
MIN_DOTS_ACROSS = 2


def default_board(rig: Rig, spacing_mm: float | None = None, tilt_deg: float | None = None) -> DotBoard:
    """The board the volumetric run assumes unless told.

    3 mm spacing (a quarter of the volume's smaller transverse size for small rigs), centred on
    the volume, tilted about world y so its normal bisects the cameras' optical axes (0 for one
    camera, 45 degrees for two at 90), with a marker dot (1.6 times larger) at its origin for two
    or more cameras; one camera names its dots from the nominal model alone (no marker).

    Parameters
    ----------
    rig
        The rig (cameras, volume).
    spacing_mm
        Dot pitch, mm (None: the default above).
    tilt_deg
        Tilt about world y, degrees (None: the bisecting tilt).

    Raises
    ------
    ValueError
        A spacing below :data:`MIN_DOT_LENSLETS` lenslets of the coarsest camera, or one that
        leaves fewer than :data:`MIN_DOTS_ACROSS` dots across the narrowest field of view.
    """
    vol = rig.volume
    if spacing_mm is None:
        spacing_mm = min(3.0, 0.25 * min(vol.size_mm[0], vol.size_mm[1]))
    least = max(MIN_DOT_LENSLETS * c.mla_pitch_mm / abs(c.magnification) for c in rig.camera)
    if spacing_mm < least:
        raise ValueError(f"dots {spacing_mm:g} mm apart are closer than {MIN_DOT_LENSLETS} lenslets of the cameras "
                         f"({least:.3g} mm in the volume), where they cannot be told apart; use a spacing of at least "
                         f"{least:.2g} mm")
    most = min(min(c.field_of_view_mm) for c in rig.camera) / MIN_DOTS_ACROSS
    if spacing_mm > most:
        raise ValueError(f"dots {spacing_mm:g} mm apart leave fewer than {MIN_DOTS_ACROSS} across the narrowest "
                         f"camera's field of view ({MIN_DOTS_ACROSS * most:.3g} mm); use a spacing of at most "
                         f"{most:.2g} mm")
    board = DotBoard.for_cameras(np.array([c.optical_axis for c in rig.camera]), spacing_mm=spacing_mm,
                                 centre_mm=vol.centre_mm, marker_scale=1.6 if len(rig.camera) > 1 else 1.0)
    return board if tilt_deg is None else dataclasses.replace(board, tilt_deg=tilt_deg)
