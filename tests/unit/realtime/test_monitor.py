"""The monitor window offscreen: results are drawn from the pipeline's thread via a queued signal,
and the controls reach the pipeline and the acquisition."""

from __future__ import annotations

import os
import time

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pyqtgraph")

from realtime.monitor import MonitorWindow, require_qt  # noqa: E402
from realtime.pipeline import LivePipeline  # noqa: E402
from tests.helpers import filled_ring as _ring  # noqa: E402


class FakeControls:
    def __init__(self) -> None:
        self.armed = False
        self.record = True
        self.calls: list[str] = []

    def arm(self) -> None:
        self.armed = True
        self.calls.append("arm")

    def disarm(self) -> None:
        self.armed = False
        self.calls.append("disarm")

    def set_record(self, on: bool) -> None:
        self.record = on
        self.calls.append(f"record {on}")

    def status(self) -> dict[str, float]:
        return {"committed_pairs": 7, "pair_rate_hz": 10.0, "frames_recorded": 27, "frames_dropped": 1,
                "overruns": 0}


def test_window_draws_results_and_controls_act(tiny_rig, tmp_path) -> None:
    pg, _, _, _ = require_qt()
    app = pg.mkQApp()
    pipe = LivePipeline(tiny_rig, _ring(3), device="cpu")
    ctl = FakeControls()
    win = MonitorWindow(pipe, ctl)
    win.show()
    with pipe:
        end = time.monotonic() + 60
        while win.displayed < 1 and time.monotonic() < end:
            app.processEvents()
            time.sleep(0.01)
    assert win.displayed == 1 and win.last_result.pair == 2 and not win.drawing_pending
    assert win.images["raw:cam0"].image.shape == (160, 192)
    win.refresh_status()
    text = win.status.text()
    assert "disarmed, recording: 7 pairs" in text and "frames 27, drops 1, overruns 0" in text
    assert "processed 1" in text and "skipped 2" in text
    # the tiny rig's weights fit: the live path's auto projector stores them
    assert f"projector {win.last_result.projector}" in text and win.last_result.projector == "stored"
    # acquisition controls
    win.arm_button.click()
    assert ctl.calls == ["arm"] and win.arm_button.text() == "disarm"
    win.arm_button.click()
    assert ctl.calls == ["arm", "disarm"] and win.arm_button.text() == "arm"
    win.record_box.setChecked(False)
    assert ctl.record is False
    # reconstruction and slice controls reach the pipeline's settings
    win.iter_spin.setValue(7)
    win.relax_spin.setValue(1.5)
    win.axis_box.setCurrentText("x")
    assert win.slice_spin.maximum() == pipe.grid.shape[2] - 1 and win.slice_spin.value() == pipe.grid.shape[2] // 2
    win.slice_spin.setValue(3)
    s = pipe.settings
    assert (s.iterations, s.relaxation, s.slice_axis, s.slice_index) == (7, 1.5, "x", 3)
    # live view on and off
    win.live_button.click()
    assert pipe.paused and win.live_button.text() == "start live view"
    win.live_button.click()
    assert not pipe.paused
    path = win.screenshot(tmp_path / "w.png")
    assert path.read_bytes()[:4] == b"\x89PNG"
    ctl.armed = True
    win.close()  # closing an armed monitor disarms
    assert ctl.calls[-1] == "disarm"


def test_window_on_the_particle_route_draws_particles_and_says_what_it_found(tiny_rig) -> None:
    pg, _, _, _ = require_qt()
    app = pg.mkQApp()
    pipe = LivePipeline(tiny_rig, _ring(1), device="cpu", route="particles")
    win = MonitorWindow(pipe, FakeControls())
    win.show()
    # the MART settings are the voxel route's: shown, not changeable
    assert not win.iter_spin.isEnabled() and not win.relax_spin.isEnabled()
    with pipe:
        end = time.monotonic() + 120
        while win.displayed < 1 and time.monotonic() < end:
            app.processEvents()
            time.sleep(0.01)
    assert win.displayed == 1
    r = win.last_result
    assert r.route == "particles" and r.particles is not None and r.tracks is not None
    assert win.plots["slice"].titleLabel.text.startswith("particles A: slice z")
    win.refresh_status()
    text = win.status.text()
    assert f"particles A/B {r.particles[0]}/{r.particles[1]}, tracks {r.tracks}" in text and "projector" not in text
    win.close()
