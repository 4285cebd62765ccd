"""The monitor window: a pyqtgraph ``QMainWindow`` showing what the live pipeline makes of the newest pair.

Panels: each camera's raw light-field image (frame A); maximum-intensity projections of volume
A along z and y and the chosen slice; the in-plane vectors of the vector plane nearest the slice
drawn over its out-of-plane vorticity. A status line gives pairs per second processed and
recorded, frames recorded and dropped, ring overruns, pairs skipped by the live path, the
trigger-to-display latency and, on CUDA, the GPU memory in use. On the particle route
(:data:`realtime.settings.LIVE_ROUTES`) "volume A" is frame A's particles drawn into the live
grid, the vectors are the tracks' field in bins, and the status line adds the particles of
frames A and B and the tracks kept. Beside them, the checks before
recording for each camera (:func:`realtime.view.camera_checks`): its seeding density, saturated
share and micro-image fill against the chapter's ranges, its histogram with full scale marked
and the plane through the middle of the volume refocused from its raw frame, computed every
:data:`CHECK_EVERY_S` seconds on a thread of their own. Controls: start/stop the live
view, arm/disarm (through :class:`realtime.monitor.Controls`), record on/off, the slice axis and
index, the DRT-MART iterations and relaxation.

The pipeline's thread never touches Qt: a subscriber keeps the newest result and emits a queued
signal; the GUI thread draws the newest result when it gets to it (older ones are dropped, never
queued up), so the window stays responsive however slow the pipeline is, and the pipeline never
waits for drawing. Images are set with ``autoLevels=False`` (levels from a strided sample) in
row-major order.

Importing this module imports Qt (:func:`realtime.monitor.require_qt`, which raises
:class:`~realtime.monitor.GuiUnavailable` without the ``gui`` extra): make windows through
:func:`realtime.monitor.MonitorWindow`, which imports it only then.
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from lfcore.files import replace_file
from realtime.monitor import Controls, require_qt
from realtime.pipeline import AXES, LivePipeline, LiveResult, plausible_latency
from realtime.view import IN_PLANE, camera_checks

pg, QtCore, _, QtWidgets = require_qt()

__all__ = ["CHECK_EVERY_S", "MonitorWindow"]

#: Seconds between two runs of the camera checks on the newest raw frames.
CHECK_EVERY_S = 2.0


def _levels(img: np.ndarray, lo_pct: float = 1.0, hi_pct: float = 99.9) -> tuple[float, float]:
    """Display levels from a strided sample (cheap on 2048 x 2048 frames)."""
    step = max(1, int(math.sqrt(img.size / 65536)))
    sample = img[::step, ::step]
    finite = sample[np.isfinite(sample)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [lo_pct, hi_pct])
    return float(lo), float(hi if hi > lo else lo + 1.0)


def _gpu_memory(device: str | None) -> str:
    if not device or not device.startswith("cuda"):
        return ""
    try:
        from lfcore.device import warp

        d = warp().get_device(device)
        used = (d.total_memory - d.free_memory) / 2**30
        return f"  |  GPU {used:.1f}/{d.total_memory / 2**30:.0f} GiB"
    except Exception:  # noqa: BLE001 - the status line must never fail
        return ""


class _Bridge(QtCore.QObject):
    """Carries "a result is pending" from the pipeline's thread to the GUI thread (a queued signal)."""

    ready = QtCore.Signal()
    checks_ready = QtCore.Signal()


class MonitorWindow(QtWidgets.QMainWindow):
    """The monitor window for ``pipeline``, with optional acquisition ``controls``.

    Create a ``QApplication`` first (``pyqtgraph.mkQApp()``).

    Parameters
    ----------
    pipeline
        The live pipeline whose results are drawn (subscribed to here, unsubscribed on close).
    controls
        What the arm and record controls act on; None: those controls are disabled.
    title
        The window's title.

    Attributes
    ----------
    displayed
        Results drawn.
    last_result
        The last result drawn, or None.
    display_latency_s
        Trigger-to-display latency of the last result drawn (NaN if unknown).
    """

    def __init__(self, pipeline: LivePipeline, controls: Controls | None = None, *,
                 title: str = "lfpiv monitor") -> None:
        super().__init__()
        self.pipeline = pipeline
        self.controls = controls
        self.displayed = 0
        self.last_result: LiveResult | None = None
        self.display_latency_s = float("nan")
        self._pending: LiveResult | None = None
        self._pending_lock = threading.Lock()
        self._shown_times: list[float] = []
        self.setWindowTitle(title)
        self.resize(1800, 950)
        pg.setConfigOptions(antialias=False, imageAxisOrder="row-major")

        central = QtWidgets.QWidget()
        layout = QtWidgets.QVBoxLayout(central)
        self.view = pg.GraphicsLayoutWidget()
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.view, stretch=3)
        self._checks_box = self._checks_column(pipeline.cameras)
        top.addWidget(self._checks_box, stretch=1)
        layout.addLayout(top, stretch=1)
        self.status = QtWidgets.QLabel("waiting for the first pair ...")
        self.status.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        layout.addWidget(self.status)
        layout.addLayout(self._controls_row())
        self.setCentralWidget(central)

        grey = pg.colormap.get("CET-L1")
        hot = pg.colormap.get("magma")
        self.plots: dict[str, Any] = {}
        self.images: dict[str, Any] = {}
        for k, cam in enumerate(pipeline.cameras):
            self._panel(f"raw:{cam}", f"{cam}: raw frame A", 0, k, grey, "column (px)", "row (px)", True)
        self._what = "particles A" if pipeline.route == "particles" else "volume A"
        self._panel("mip:z", f"{self._what}: maximum over z", 1, 0, hot, "x (mm)", "y (mm)", False)
        self._panel("mip:y", f"{self._what}: maximum over y", 1, 1, hot, "x (mm)", "z (mm)", False)
        self._panel("slice", f"{self._what}: slice", 2, 0, hot, "x (mm)", "y (mm)", False)
        vp = self._panel("vectors", "vectors over vorticity", 2, 1, pg.colormap.get("CET-D1"), "x (mm)", "y (mm)",
                         False)
        self.arrows = pg.PlotDataItem(pen=pg.mkPen("w", width=1.5), connect="pairs")
        self.heads = pg.ScatterPlotItem(size=4, pen=None, brush=pg.mkBrush("w"))
        vp.addItem(self.arrows)
        vp.addItem(self.heads)

        self._bridge = _Bridge()
        self._bridge.ready.connect(self._draw_pending, QtCore.Qt.ConnectionType.QueuedConnection)
        self._bridge.checks_ready.connect(self._draw_checks, QtCore.Qt.ConnectionType.QueuedConnection)
        self._checker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lfpiv-checks")
        self._checks_busy = False
        self._closing = False
        self._checks_due = 0.0
        self._checks_pending: dict[str, Any] | None = None
        self.last_checks: dict[str, Any] = {}
        self._unsubscribe = pipeline.subscribe(self._on_result)
        self._timer = QtCore.QTimer(self)
        self._timer.timeout.connect(self.refresh_status)
        self._timer.start(200)

    def _panel(self, name: str, title: str, row: int, col: int, cmap, xlabel: str, ylabel: str, invert: bool):
        """A plot with one image item at (``row``, ``col``) of the layout, kept by ``name``."""
        p = self.view.addPlot(row=row, col=col, title=title)
        p.setAspectLocked(False)
        p.setLabel("bottom", xlabel)
        p.setLabel("left", ylabel)
        p.invertY(invert)
        for side in ("bottom", "left"):
            p.getAxis(side).enableAutoSIPrefix(False)
        img = pg.ImageItem(axisOrder="row-major")
        img.setColorMap(cmap)
        p.addItem(img)
        self.plots[name], self.images[name] = p, img
        return p

    def _checks_column(self, cameras: list[str]):
        """The checks before recording: per camera a line of verdicts, its histogram and a refocused plane."""
        box = QtWidgets.QWidget()
        col = QtWidgets.QVBoxLayout(box)
        col.setContentsMargins(0, 0, 0, 0)
        self.check_labels: dict[str, Any] = {}
        self.check_plots: dict[str, Any] = {}
        self.check_items: dict[str, Any] = {}
        self.checks_view = pg.GraphicsLayoutWidget()
        for k, cam in enumerate(cameras):
            label = QtWidgets.QLabel(f"{cam}: checks before recording (waiting for a frame)")
            label.setWordWrap(True)
            label.setTextFormat(QtCore.Qt.TextFormat.RichText)
            col.addWidget(label)
            self.check_labels[cam] = label
            h = self.checks_view.addPlot(row=2 * k, col=0, title=f"{cam}: histogram")
            h.setLabel("bottom", "counts")
            h.setLogMode(y=True)
            bars = pg.PlotDataItem(stepMode="center", fillLevel=0, brush=(80, 140, 220, 160), pen="w")
            full = pg.InfiniteLine(angle=90, pen=pg.mkPen("r", style=QtCore.Qt.PenStyle.DashLine))
            h.addItem(bars)
            h.addItem(full)
            p = self.checks_view.addPlot(row=2 * k + 1, col=0, title=f"{cam}: refocused plane")
            p.invertY(True)
            p.setAspectLocked(True)
            img = pg.ImageItem(axisOrder="row-major")
            img.setColorMap(pg.colormap.get("CET-L1"))
            p.addItem(img)
            self.check_plots[f"hist:{cam}"], self.check_plots[f"plane:{cam}"] = h, p
            self.check_items[f"hist:{cam}"], self.check_items[f"full:{cam}"] = bars, full
            self.check_items[f"plane:{cam}"] = img
        col.addWidget(self.checks_view, stretch=1)
        return box

    def run_checks(self, raw: dict[str, np.ndarray], *, wait: bool = False) -> None:
        """Check ``raw`` (camera -> frame A) on the checks' thread and draw the result when it comes
        (``wait``: here and now, for scripts and tests)."""
        if wait:
            self.show_checks(camera_checks(self.pipeline.rig, raw))
            return
        if self._checks_busy or self._closing:  # one check at a time; none once the window closed
            return
        self._checks_busy = True
        frames = {k: np.array(v, copy=True) for k, v in raw.items()}

        def work() -> None:
            try:
                result = camera_checks(self.pipeline.rig, frames)
            except Exception as exc:  # noqa: BLE001 - a frame the checks cannot read must not stop the monitor
                result = {"error": str(exc)}
            with self._pending_lock:
                self._checks_pending = result
            if self._closing:
                return
            try:
                self._bridge.checks_ready.emit()
            except RuntimeError:  # the window closed meanwhile
                pass

        self._checker.submit(work)

    def _draw_checks(self) -> None:
        with self._pending_lock:
            checks, self._checks_pending = self._checks_pending, None
        self._checks_busy = False
        if checks is None or self._checks_box is None:  # nothing, or the panel is gone (the window closed)
            return
        if "error" in checks:
            for label in self.check_labels.values():
                label.setText(f"checks failed: {checks['error']}")
            return
        self.show_checks(checks)

    def show_checks(self, checks: dict[str, Any]) -> None:
        """Draw the checks of each camera (:class:`lfcore.camera_checks.CameraCheck`; GUI thread)."""
        for cam, c in checks.items():
            label = self.check_labels.get(cam)
            if label is None:
                continue
            lines = [f'<span style="color:{"#3c3" if ok else "#e33"}">{"ok" if ok else "FIX"}</span> {text}'
                     for text, ok in c.verdicts()]
            label.setText(f"<b>{cam}</b>: " + "<br>".join(lines))
            self.check_items[f"hist:{cam}"].setData(c.bin_edges, np.maximum(c.histogram, 1).astype(float))
            self.check_items[f"full:{cam}"].setValue(c.full_scale)
            self.check_items[f"plane:{cam}"].setImage(c.preview, autoLevels=False, levels=_levels(c.preview))
            self.check_plots[f"plane:{cam}"].setTitle(f"{cam}: {c.preview_label}")
        self.last_checks = dict(checks)

    def release_checks(self) -> None:
        """Stop the checks' thread and have Qt delete the checks panel (once the window is done with:
        its pyqtgraph items must go while the application exists)."""
        self._closing = True
        self._checker.shutdown(wait=True, cancel_futures=True)
        if self._checks_box is not None:
            self._checks_box.setParent(None)
            self._checks_box.deleteLater()
            self._checks_box = None

    def check_rects(self) -> dict[str, tuple[int, int, int, int]]:
        """Where each checks panel's data area lies in a :meth:`screenshot`: (x, y, width, height) px."""
        return self._rects(self.checks_view, self.check_plots)

    # --- controls -------------------------------------------------------------------------
    def _controls_row(self):
        row = QtWidgets.QHBoxLayout()
        self.live_button = QtWidgets.QPushButton("stop live view")
        self.live_button.clicked.connect(self._toggle_live)
        self.arm_button = QtWidgets.QPushButton("arm")
        self.arm_button.clicked.connect(self._toggle_arm)
        self.arm_button.setEnabled(self.controls is not None)
        self.record_box = QtWidgets.QCheckBox("record")
        self.record_box.setChecked(bool(self.controls is not None and self.controls.record))
        self.record_box.setEnabled(self.controls is not None)
        self.record_box.toggled.connect(self._set_record)
        s = self.pipeline.settings
        self.axis_box = QtWidgets.QComboBox()
        self.axis_box.addItems(list(AXES))
        self.axis_box.setCurrentText(s.slice_axis)
        self.axis_box.currentTextChanged.connect(self._axis_changed)
        self.slice_spin = QtWidgets.QSpinBox()
        self.iter_spin = QtWidgets.QSpinBox()
        self.iter_spin.setRange(0, 1000)
        self.iter_spin.setValue(s.iterations)
        self.iter_spin.valueChanged.connect(lambda v: self._update(iterations=int(v)))
        self.relax_spin = QtWidgets.QDoubleSpinBox()
        self.relax_spin.setRange(0.05, 2.0)
        self.relax_spin.setSingleStep(0.1)
        self.relax_spin.setValue(s.relaxation)
        self.relax_spin.valueChanged.connect(lambda v: self._update(relaxation=float(v)))
        if self.pipeline.route == "particles":  # the voxel route's MART settings: nothing to change here
            for spin in (self.iter_spin, self.relax_spin):
                spin.setEnabled(False)
                spin.setToolTip("the voxel route's (lfpiv monitor --route voxels)")
        self._axis_changed(s.slice_axis, keep_index=s.slice_index)
        self.slice_spin.valueChanged.connect(lambda v: self._update(slice_index=int(v)))
        for w in (self.live_button, self.arm_button, self.record_box, QtWidgets.QLabel("slice axis"),
                  self.axis_box, QtWidgets.QLabel("index"), self.slice_spin, QtWidgets.QLabel("iterations"),
                  self.iter_spin, QtWidgets.QLabel("relaxation"), self.relax_spin):
            row.addWidget(w)
        row.addStretch(1)
        return row

    def _update(self, **changes) -> None:
        try:
            self.pipeline.update(**changes)
        except ValueError as exc:
            self.status.setText(f"setting refused: {exc}")

    def _axis_changed(self, axis: str, keep_index: int | None = None) -> None:
        n = self.pipeline.grid.shape["zyx".index(axis)]
        index = n // 2 if keep_index is None else int(np.clip(keep_index, 0, n - 1))
        self.slice_spin.blockSignals(True)
        self.slice_spin.setRange(0, n - 1)
        self.slice_spin.setValue(index)
        self.slice_spin.blockSignals(False)
        self._update(slice_axis=axis, slice_index=index)

    def _toggle_live(self) -> None:
        paused = not self.pipeline.paused
        self.pipeline.pause(paused)
        self.live_button.setText("start live view" if paused else "stop live view")

    def _toggle_arm(self) -> None:
        if self.controls is None:
            return
        if self.controls.armed:
            self.controls.disarm()
        else:
            self.controls.arm()
        self.refresh_status()

    def _set_record(self, on: bool) -> None:
        if self.controls is not None:
            self.controls.set_record(bool(on))

    # --- results ----------------------------------------------------------------------------
    def _on_result(self, result: LiveResult) -> None:
        # The pipeline's thread: keep the newest, wake the GUI thread once.
        with self._pending_lock:
            wake = self._pending is None
            self._pending = result
        if wake:
            self._bridge.ready.emit()

    @property
    def drawing_pending(self) -> bool:
        """True while a result waits to be drawn."""
        with self._pending_lock:
            return self._pending is not None

    def _draw_pending(self) -> None:
        with self._pending_lock:
            r, self._pending = self._pending, None
        if r is not None:
            self.show_result(r)

    def show_result(self, r: LiveResult) -> None:
        """Draw one result (GUI thread)."""
        for cam, img in r.raw.items():
            item = self.images.get(f"raw:{cam}")
            if item is not None:
                item.setImage(img, autoLevels=False, levels=_levels(img))
        ex = r.extent_mm
        for name, data, normal in (("mip:z", r.mip["z"], "z"), ("mip:y", r.mip["y"], "y"),
                                   ("slice", r.slice_image, r.slice_axis)):
            h, v = IN_PLANE[normal]
            self._set_world_image(self.images[name], data, ex[h], ex[v], _levels(data, 0.0, 99.95))
        h, v = IN_PLANE[r.slice_axis]
        self.plots["slice"].setTitle(f"{self._what}: slice {r.slice_axis} = {r.slice_index}")
        self.plots["slice"].setLabel("bottom", f"{h} (mm)")
        self.plots["slice"].setLabel("left", f"{v} (mm)")
        self._draw_vectors(r)
        now_s = time.monotonic()
        if r.raw and now_s >= self._checks_due:
            self._checks_due = now_s + CHECK_EVERY_S
            self.run_checks(r.raw)
        self.last_result = r
        self.displayed += 1
        now = time.monotonic()
        self._shown_times = [*self._shown_times[-9:], now]
        latency = (time.time_ns() - r.trigger_ns) * 1e-9  # trigger to display
        self.display_latency_s = latency if r.trigger_ns > 0 and plausible_latency(latency) else float("nan")
        self.refresh_status()

    def _set_world_image(self, item, data, hx: tuple[float, float], vy: tuple[float, float], levels) -> None:
        item.setImage(data, autoLevels=False, levels=levels)
        rows, cols = data.shape
        dx = (hx[1] - hx[0]) / max(cols - 1, 1)
        dy = (vy[1] - vy[0]) / max(rows - 1, 1)
        item.setRect(QtCore.QRectF(hx[0] - 0.5 * dx, vy[0] - 0.5 * dy, cols * dx or 1.0, rows * dy or 1.0))

    def _draw_vectors(self, r: LiveResult) -> None:
        vs = r.vectors
        h, v = IN_PLANE[vs.axis]
        w = np.nan_to_num(vs.normal_vorticity)
        lim = float(np.max(np.abs(w))) or 1.0
        hx = (float(vs.h_mm[0]), float(vs.h_mm[-1]))
        vy = (float(vs.v_mm[0]), float(vs.v_mm[-1]))
        if len(vs.h_mm) < 2:
            hx = (hx[0] - 0.5, hx[0] + 0.5)
        if len(vs.v_mm) < 2:
            vy = (vy[0] - 0.5, vy[0] + 0.5)
        self._set_world_image(self.images["vectors"], w, hx, vy, (-lim, lim))
        hh, vv = np.meshgrid(vs.h_mm, vs.v_mm)
        uv = np.nan_to_num(vs.uv)
        speed = float(np.max(np.hypot(uv[..., 0], uv[..., 1])))
        spacing = min(np.diff(vs.h_mm).min() if len(vs.h_mm) > 1 else 1.0,
                      np.diff(vs.v_mm).min() if len(vs.v_mm) > 1 else 1.0)
        scale = 1.5 * spacing / speed if speed > 0 else 0.0
        tips_h = hh + scale * uv[..., 0]
        tips_v = vv + scale * uv[..., 1]
        xs = np.stack([hh.ravel(), tips_h.ravel()], axis=1).ravel()
        ys = np.stack([vv.ravel(), tips_v.ravel()], axis=1).ravel()
        self.arrows.setData(xs, ys)
        self.heads.setData(tips_h.ravel(), tips_v.ravel())
        self.plots["vectors"].setTitle(f"in-plane vectors at {vs.axis} = {vs.position_mm:.3f} mm over "
                                       f"vorticity w_{vs.axis} (+-{lim:.3g} 1/s)")
        self.plots["vectors"].setLabel("bottom", f"{h} (mm)")
        self.plots["vectors"].setLabel("left", f"{v} (mm)")

    # --- status -----------------------------------------------------------------------------
    def status_numbers(self) -> dict[str, float]:
        """The numbers of the status line (for scripts and tests)."""
        st = self.pipeline.stats()
        t = self._shown_times
        shown_hz = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
        out: dict[str, float] = {"processed": st.processed, "skipped": st.skipped, "discarded": st.discarded,
                                 "processed_hz": st.rate_hz, "displayed": self.displayed,
                                 "displayed_hz": shown_hz, "latency_s": self.display_latency_s}
        if self.controls is not None:
            out.update(self.controls.status())
        return out

    def refresh_status(self) -> None:
        n = self.status_numbers()
        st = self.pipeline.stats()
        parts = []
        if self.controls is not None:
            state = "ARMED" if self.controls.armed else "disarmed"
            rec = "recording" if self.controls.record else "not recording"
            parts.append(f"{state}, {rec}: {int(n.get('committed_pairs', 0))} pairs "
                         f"({n.get('pair_rate_hz', 0.0):.1f} pairs/s), frames {int(n.get('frames_recorded', 0))}, "
                         f"drops {int(n.get('frames_dropped', 0))}, overruns {int(n.get('overruns', 0))}")
        lat = n["latency_s"]
        # a rate needs two processed pairs: before that it is unknown, not zero
        rate = f"{st.rate_hz:.1f} pairs/s" if st.rate_hz > 0 else "rate n/a"
        # which plan runs (lfpiv monitor --protocol): the method and how frame B starts
        plan = f", plan {st.plan}" if st.plan else ""
        parts.append(f"live ({st.state}{plan}): pair {st.last_pair}, processed {st.processed} "
                     f"({rate}), skipped {st.skipped}, discarded {st.discarded}, latency "
                     + (f"{lat:.2f} s" if math.isfinite(lat) else "n/a")
                     # what applied the last pair's operator (stored weights or matrix-free)
                     + (f", projector {st.projector}" if st.projector else "")
                     # the particle route: what its last pair found and tracked
                     + (f", particles A/B {st.particles[0]}/{st.particles[1]}, tracks {st.tracks}"
                        if st.particles is not None else ""))
        text = "  |  ".join(parts) + _gpu_memory(self.pipeline.device)
        if st.error:
            text += f"  |  error: {st.error}"
        self.status.setText(text)
        if self.controls is not None:
            self.arm_button.setText("disarm" if self.controls.armed else "arm")

    # --- screenshots and closing ----------------------------------------------------------
    def panel_rects(self) -> dict[str, tuple[int, int, int, int]]:
        """Where each panel's data area lies in a :meth:`screenshot`: (x, y, width, height) px."""
        return self._rects(self.view, self.plots)

    def _rects(self, view, plots: dict[str, Any]) -> dict[str, tuple[int, int, int, int]]:
        out = {}
        for name, p in plots.items():
            vb = p.getViewBox()
            scene_rect = vb.sceneBoundingRect()
            poly = view.mapFromScene(scene_rect)
            r = poly.boundingRect()
            top_left = view.mapTo(self, r.topLeft())
            out[name] = (top_left.x(), top_left.y(), r.width(), r.height())
        return out

    def screenshot(self, path: str | Path) -> Path:
        """Save the window as a PNG (works offscreen), whole or not at all
        (:func:`lfcore.files.replace_file`: an earlier file stays until the new one is complete).

        Raises
        ------
        OSError
            The file cannot be written (naming ``path`` and the cause: a full disk, a
            read-only folder, ...).
        """
        path = Path(path)
        QtWidgets.QApplication.processEvents()
        buf = QtCore.QBuffer()
        buf.open(QtCore.QIODevice.OpenModeFlag.WriteOnly)
        if not self.grab().save(buf, "PNG"):
            raise OSError(f"the window could not be encoded as PNG for {path}")
        return replace_file(path, bytes(buf.data()))

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt's name
        self._timer.stop()
        self._unsubscribe()
        # a check still running ends before the window's objects go: its signal into a deleted bridge,
        # or its thread alive at the interpreter's exit, crashed the process (segfault)
        self._closing = True
        self._checker.shutdown(wait=True, cancel_futures=True)
        if self.controls is not None and self.controls.armed:
            self.controls.disarm()
        super().closeEvent(event)

