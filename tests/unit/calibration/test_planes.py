"""calibration.planes: a plane whose dots cannot be seen says how far from focus it lies."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.board import default_board
from calibration.dots import VIEW_PUPILS, Dots
from calibration.fit import FitError
from calibration.planes import name_plane_dots


def test_a_plane_with_no_dot_names_its_distance_from_focus(tiny_rig):
    cam = tiny_rig.camera[0]
    board = default_board(tiny_rig)
    stage = np.array([24.0, 25.0, 25.7])
    board = type(board)(**{**board.__dict__, "stage_centre_mm": 25.0})
    none = Dots(np.zeros((0, len(VIEW_PUPILS), 2)), np.zeros(0), np.zeros(0, int))
    with pytest.raises(FitError) as info:
        name_plane_dots(cam, board, [(2, none)], stage, min_dots=2, camera="cam0")
    msg = str(info.value)
    assert "plane 3 of 3 (stage 25.7000 mm): no dot seen" in msg and "0.70 mm in front of the camera's focus" in msg
    assert "\n" not in msg
