"""The operator figures ``volumes/`` records (:func:`lfpiv.jobs.reconstruct.operator_figures`),
from known frames: the largest operator, the mean time per iteration, what ran."""

from __future__ import annotations

import numpy as np
import pytest

from lfpiv.jobs.reconstruct import ReconResult, operator_figures


def _frame(projector: str, nbytes: int, iterate_s: float, iterations: int = 10) -> ReconResult:
    return ReconResult(volume=np.zeros((0, 0, 0), np.float32), active_voxels=1, active_fraction=0.1, nnz=0,
                       weight_bytes=nbytes, weights_s=0.0, iterate_s=iterate_s, iterations=iterations,
                       projector=projector)


def test_figures_of_frames() -> None:
    fig = operator_figures([_frame("stored", 100, 0.01), _frame("stored", 300, 0.03)])
    assert fig == {"projector": "stored", "bytes": 300, "ms_per_iteration": pytest.approx(2.0), "frames": 2}


def test_figures_added_to_those_recorded_before() -> None:
    before = operator_figures([_frame("stored", 100, 0.01), _frame("stored", 300, 0.03)])  # 1 and 3 ms
    fig = operator_figures([_frame("matrix-free", 200, 0.5)], before)  # 50 ms
    assert fig["frames"] == 3 and fig["bytes"] == 300
    assert fig["ms_per_iteration"] == pytest.approx((1 + 3 + 50) / 3, abs=1e-3)
    assert fig["projector"] == "matrix-free, stored"  # auto used each for some frames
    # added to again: the projectors are not repeated
    assert operator_figures([_frame("stored", 10, 0.0)], fig)["projector"] == "matrix-free, stored"


def test_no_iterations_and_nothing_before() -> None:
    fig = operator_figures([_frame("stored", 5, 0.0, iterations=0)], None)
    assert fig == {"projector": "stored", "bytes": 5, "ms_per_iteration": 0.0, "frames": 1}
    assert operator_figures([], {})["frames"] == 0
