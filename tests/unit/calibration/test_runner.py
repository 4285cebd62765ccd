"""The volumetric calibration runner over fake devices: every plane once, resume, stage faults."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.runner import StageError, plane_targets, run_planes
from calibration.store import CalibrationStore


class FakeStage:
    def __init__(self, miss_at: float | None = None) -> None:
        self.moves: list[float] = []
        self.miss_at = miss_at
        self.pos = 0.0

    def move_to(self, position_mm: float) -> float:
        self.moves.append(position_mm)
        self.pos = position_mm + (0.05 if self.miss_at is not None and abs(position_mm - self.miss_at) < 1e-9
                                  else 0.0001)
        return self.pos


def _grab_counter(shape=(160, 192)):
    calls = []

    def grab():
        calls.append(1)
        return {"cam0": np.full(shape, len(calls), dtype=np.uint16)}
    return grab, calls


def test_targets_are_centred():
    t = plane_targets(51, 0.5, 12.5)
    assert len(t) == 51 and t[0] == pytest.approx(0.0) and t[25] == pytest.approx(12.5) and t[-1] == 25.0


def test_interrupted_run_resumes_without_repeating_a_plane(tiny_rig, tmp_path):
    targets = plane_targets(7, 0.5, 10.0)
    store = CalibrationStore.create(tmp_path / "c.zarr", tiny_rig)
    stage = FakeStage()
    grab, calls = _grab_counter()

    def interrupt(plane, done, total):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_planes(store, stage, grab, targets, 0.5, progress=interrupt)
    assert len(calls) == 3 and np.array_equal(CalibrationStore.open(tmp_path / "c.zarr").planes_done(),
                                              [True] * 3 + [False] * 4)
    store = CalibrationStore.open_or_create(tmp_path / "c.zarr", tiny_rig)
    res = run_planes(store, stage, grab, targets, 0.5)
    assert res.skipped == (0, 1, 2) and res.taken == (3, 4, 5, 6)
    assert len(calls) == 7 and len(stage.moves) == 7 and np.allclose(stage.moves, targets)
    back = CalibrationStore.open(tmp_path / "c.zarr")
    assert back.planes_done().all()
    assert np.allclose(back.stage_mm("cam0"), targets + 0.0001)
    # plane i holds the i-th image grabbed: none was taken twice or overwritten
    frames = back.plane_frames("cam0")
    assert [int(frames[i][0, 0]) for i in range(7)] == list(range(1, 8))


def test_a_stage_that_misses_its_target_names_the_plane(tiny_rig, tmp_path):
    targets = plane_targets(5, 0.5, 10.0)
    store = CalibrationStore.create(tmp_path / "c.zarr", tiny_rig)
    grab, calls = _grab_counter()
    with pytest.raises(StageError, match=r"plane 4 of 5: the stage stopped at 10.5500 mm, not at its target 10.5000"):
        run_planes(store, FakeStage(miss_at=targets[3]), grab, targets, 0.5)
    assert len(calls) == 3 and store.planes_done().sum() == 3
