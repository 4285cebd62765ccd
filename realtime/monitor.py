"""The live monitor: a pyqtgraph window showing what the live pipeline makes of the newest pair.

Panels: each camera's raw light-field image (frame A); maximum-intensity projections of volume
A along z and y and the chosen slice; the in-plane vectors of the vector plane nearest the slice
drawn over its out-of-plane vorticity. A status line gives pairs per second processed and
recorded, frames recorded and dropped, ring overruns, pairs skipped by the live path, the
trigger-to-display latency and, on CUDA, the GPU memory in use. Controls: start/stop the live
view, arm/disarm (through :class:`Controls`, which the application implements), record on/off,
the slice axis and index, the DRT-MART iterations and relaxation.

The pipeline's thread never touches Qt: a subscriber keeps the newest result and emits a queued
signal; the GUI thread draws the newest result when it gets to it (older ones are dropped, never
queued up), so the window stays responsive however slow the pipeline is, and the pipeline never
waits for drawing. Images are set with ``autoLevels=False`` (levels from a strided sample) in
row-major order.

Qt is imported lazily: ``import realtime.monitor`` works without the ``gui`` extra, and
:func:`require_qt` raises :class:`GuiUnavailable` naming ``pip install 'lfpiv[gui]'``.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from realtime.pipeline import AXES, LivePipeline, LiveResult, plausible_latency

__all__ = ["Controls", "GuiUnavailable", "MonitorWindow", "WindowOutcome", "drops_none_references", "require_qt",
           "run_monitor_window"]

INSTALL_HINT = "pip install 'lfpiv[gui]'"
_HANDLER_INSTALLED = False
_BINDING_FAULT: str | None = None  # once checked: "" for a sound binding, else why the monitor refuses it


class GuiUnavailable(RuntimeError):
    """pyqtgraph or its Qt binding is missing, or Qt cannot start (the message says which)."""


def drops_none_references(QtCore: Any, calls: int = 256) -> bool:  # noqa: N803 - Qt's module name
    """True if the Qt binding gives back ``None`` without a reference from methods that return nothing.

    Up to Python 3.11 ``None`` is reference-counted like any object, and an extension that returns
    it without adding a reference takes one away from every other holder; at zero the interpreter
    aborts ("Fatal Python error: none_dealloc"). PySide6 6.12.0 does so on every call of a C++
    method returning ``void`` (``QLabel.setText``, ``ImageItem.setImage`` through pyqtgraph, the
    event loop's ``processEvents``), which ended ``lfpiv monitor`` after about a thousand pairs.
    From Python 3.12 on ``None`` is immortal and such a binding does no harm.

    Parameters
    ----------
    QtCore
        The binding's ``QtCore`` module.
    calls
        Calls of ``QObject.setObjectName`` (a ``void`` method) made to find out; a faulty binding
        takes ``calls`` references from ``None`` (harmless at a few hundred), a sound one none.
    """
    if sys.version_info >= (3, 12):
        return False  # None is immortal: its count never reaches zero
    obj = QtCore.QObject()
    set_name = obj.setObjectName
    collecting = gc.isenabled()
    gc.disable()  # a collection meanwhile could free objects that refer to None
    try:
        before = sys.getrefcount(None)
        for _ in range(calls):
            set_name("")
        drift = sys.getrefcount(None) - before
    finally:
        if collecting:
            gc.enable()
    # Half the calls leaves room for other threads holding or letting go of a few references meanwhile.
    return drift <= -(calls // 2)


def require_qt() -> tuple[Any, Any, Any, Any]:
    """Import pyqtgraph and the Qt binding: (pg, QtCore, QtGui, QtWidgets).

    Raises
    ------
    GuiUnavailable
        Without the ``gui`` extra, or with a Qt binding that loses references to ``None``
        (:func:`drops_none_references`), with the command that installs the tested one.
    """
    os.environ.setdefault("PYQTGRAPH_QT_LIB", "PySide6")  # the binding the gui extra pins and tests
    try:
        import pyqtgraph as pg
        from pyqtgraph.Qt import QtCore, QtGui, QtWidgets
    except ImportError as exc:
        raise GuiUnavailable(f"the monitor needs pyqtgraph and PySide6 ({exc.name or exc} is missing); "
                             f"install them with: {INSTALL_HINT}") from None
    global _BINDING_FAULT, _HANDLER_INSTALLED
    if _BINDING_FAULT is None:
        _BINDING_FAULT = ""
        if drops_none_references(QtCore):
            lib = pg.Qt.QT_LIB
            version = getattr(sys.modules.get(lib), "__version__", "")
            _BINDING_FAULT = (f"the Qt binding {lib} {version} loses a reference to None on every call (a refcount "
                              f"bug of that build on Python {sys.version_info[0]}.{sys.version_info[1]}) and would "
                              f"abort the monitor mid-run; install the tested one with: {INSTALL_HINT}")
    if _BINDING_FAULT:
        raise GuiUnavailable(_BINDING_FAULT)
    if not _HANDLER_INSTALLED:
        _HANDLER_INSTALLED = True
        previous = None

        def handler(kind, context, message: str) -> None:
            # The offscreen platform warns about every top-level window; nothing to act on.
            if "propagateSizeHints" in message:
                return
            if previous is not None:
                previous(kind, context, message)
            else:
                sys.stderr.write(message + "\n")

        previous = QtCore.qInstallMessageHandler(handler)
    return pg, QtCore, QtGui, QtWidgets


class Controls(Protocol):
    """What the monitor's acquisition controls act on (the application implements it)."""

    @property
    def armed(self) -> bool:
        """True while a recording is armed (the laser fires)."""
        ...

    @property
    def record(self) -> bool:
        """True if the next recording is written to the run store."""
        ...

    def arm(self) -> None:
        """Start a recording and arm the laser."""
        ...

    def disarm(self) -> None:
        """Disarm the laser and end the recording (what was recorded is kept)."""
        ...

    def set_record(self, on: bool) -> None:
        """Record the next arming's pairs to the run store, or only show them."""
        ...

    def status(self) -> dict[str, float]:
        """Numbers for the status line: ``committed_pairs``, ``pair_rate_hz``, ``frames_recorded``,
        ``frames_dropped``, ``overruns``."""
        ...

    def wait(self, timeout_s: float = 60.0) -> bool:
        """Wait for the recording to end; True if none is running."""
        ...


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


def _build_window_class():  # noqa: C901 - one Qt class, built once Qt is importable
    pg, QtCore, QtGui, QtWidgets = require_qt()

    class _Bridge(QtCore.QObject):
        ready = QtCore.Signal()

    class _MonitorWindow(QtWidgets.QMainWindow):
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
            self.resize(1400, 950)
            pg.setConfigOptions(antialias=False, imageAxisOrder="row-major")

            central = QtWidgets.QWidget()
            layout = QtWidgets.QVBoxLayout(central)
            self.view = pg.GraphicsLayoutWidget()
            layout.addWidget(self.view, stretch=1)
            self.status = QtWidgets.QLabel("waiting for the first pair ...")
            self.status.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
            layout.addWidget(self.status)
            layout.addLayout(self._controls_row())
            self.setCentralWidget(central)

            grey = pg.colormap.get("CET-L1")
            hot = pg.colormap.get("magma")
            self.plots: dict[str, Any] = {}
            self.images: dict[str, Any] = {}

            def panel(name: str, title: str, row: int, col: int, cmap, xlabel: str, ylabel: str, invert: bool):
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

            for k, cam in enumerate(pipeline.cameras):
                panel(f"raw:{cam}", f"{cam}: raw frame A", 0, k, grey, "column (px)", "row (px)", True)
            panel("mip:z", "volume A: maximum over z", 1, 0, hot, "x (mm)", "y (mm)", False)
            panel("mip:y", "volume A: maximum over y", 1, 1, hot, "x (mm)", "z (mm)", False)
            panel("slice", "volume A: slice", 2, 0, hot, "x (mm)", "y (mm)", False)
            vp = panel("vectors", "vectors over vorticity", 2, 1, pg.colormap.get("CET-D1"), "x (mm)", "y (mm)",
                       False)
            self.arrows = pg.PlotDataItem(pen=pg.mkPen("w", width=1.5), connect="pairs")
            self.heads = pg.ScatterPlotItem(size=4, pen=None, brush=pg.mkBrush("w"))
            vp.addItem(self.arrows)
            vp.addItem(self.heads)

            self._bridge = _Bridge()
            self._bridge.ready.connect(self._draw_pending, QtCore.Qt.ConnectionType.QueuedConnection)
            self._unsubscribe = pipeline.subscribe(self._on_result)
            self._timer = QtCore.QTimer(self)
            self._timer.timeout.connect(self.refresh_status)
            self._timer.start(200)

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
            axes_of = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}
            for name, data, normal in (("mip:z", r.mip["z"], "z"), ("mip:y", r.mip["y"], "y"),
                                       ("slice", r.slice_image, r.slice_axis)):
                h, v = axes_of[normal]
                self._set_world_image(self.images[name], data, ex[h], ex[v], _levels(data, 0.0, 99.95))
            h, v = axes_of[r.slice_axis]
            self.plots["slice"].setTitle(f"volume A: slice {r.slice_axis} = {r.slice_index}")
            self.plots["slice"].setLabel("bottom", f"{h} (mm)")
            self.plots["slice"].setLabel("left", f"{v} (mm)")
            self._draw_vectors(r)
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
            h, v = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}[vs.axis]
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
            parts.append(f"live ({st.state}): pair {st.last_pair}, processed {st.processed} "
                         f"({rate}), skipped {st.skipped}, discarded {st.discarded}, latency "
                         + (f"{lat:.2f} s" if math.isfinite(lat) else "n/a")
                         # what applied the last pair's operator (stored weights or matrix-free)
                         + (f", projector {st.projector}" if st.projector else ""))
            text = "  |  ".join(parts) + _gpu_memory(self.pipeline.device)
            if st.error:
                text += f"  |  error: {st.error}"
            self.status.setText(text)
            if self.controls is not None:
                self.arm_button.setText("disarm" if self.controls.armed else "arm")

        # --- screenshots and closing ----------------------------------------------------------
        def panel_rects(self) -> dict[str, tuple[int, int, int, int]]:
            """Where each panel's data area lies in a :meth:`screenshot`: (x, y, width, height) px."""
            out = {}
            for name, p in self.plots.items():
                vb = p.getViewBox()
                scene_rect = vb.sceneBoundingRect()
                poly = self.view.mapFromScene(scene_rect)
                r = poly.boundingRect()
                top_left = self.view.mapTo(self, r.topLeft())
                out[name] = (top_left.x(), top_left.y(), r.width(), r.height())
            return out

        def screenshot(self, path: str | Path) -> Path:
            """Save the window as a PNG (works offscreen)."""
            path = Path(path)
            QtWidgets.QApplication.processEvents()
            if not self.grab().save(str(path)):
                raise OSError(f"could not write the screenshot {path}")
            return path

        def closeEvent(self, event) -> None:  # noqa: N802 - Qt's name
            self._timer.stop()
            self._unsubscribe()
            if self.controls is not None and self.controls.armed:
                self.controls.disarm()
            super().closeEvent(event)

    return _MonitorWindow


_WINDOW_CLASS = None


def MonitorWindow(pipeline: LivePipeline, controls: Controls | None = None, *, title: str = "lfpiv monitor"):  # noqa: N802
    """The monitor window (a ``QMainWindow``) for ``pipeline``, with optional acquisition ``controls``.

    Create a ``QApplication`` first (``pyqtgraph.mkQApp()``). Attributes of interest:
    ``displayed`` (results drawn), ``last_result``, ``status_numbers()``, ``panel_rects()``,
    ``screenshot(path)``.

    Raises
    ------
    GuiUnavailable
        Without pyqtgraph and PySide6.
    """
    global _WINDOW_CLASS
    if _WINDOW_CLASS is None:
        _WINDOW_CLASS = _build_window_class()
    return _WINDOW_CLASS(pipeline, controls, title=title)


@dataclass(frozen=True)
class WindowOutcome:
    """How a monitor session ended (:func:`run_monitor_window`).

    Attributes
    ----------
    numbers
        The status line's numbers when the window closed (``MonitorWindow.status_numbers``).
    screenshot
        The screenshot written, or None.
    screenshot_error
        Why the screenshot could not be written, or None.
    interrupted
        True if Ctrl-C, SIGTERM or SIGHUP closed the window.
    stop_s
        Seconds from the window closing to the recording and live path stopped.
    """

    numbers: dict[str, float]
    screenshot: Path | None
    screenshot_error: OSError | None
    interrupted: bool
    stop_s: float


def run_monitor_window(pipeline: LivePipeline, controls: Controls, *, title: str, screenshot: str | Path | None = None,
                       after: int = 3, say: Callable[[str], None] = lambda text: None) -> WindowOutcome:
    """Show the monitor, arm, and run Qt's event loop until the window closes.

    The pipeline is started and ``controls`` armed once the window shows. Ctrl-C, SIGTERM and
    SIGHUP disarm the laser at once (:func:`acquisition.pulse_generator.signals_call`) and close
    the window as its close button does. With ``screenshot`` (offscreen too) the window is
    saved after ``after`` pairs were shown, or once the recording ended and the live path
    caught up, and the loop ends when the recording has. Whatever ends the loop, the recording
    is disarmed and waited for, and the pipeline stopped.

    Raises
    ------
    GuiUnavailable
        Without pyqtgraph and PySide6.
    """
    import signal

    from acquisition.pulse_generator import signals_call

    pg, QtCore, _, _ = require_qt()
    shot: dict[str, Any] = {"path": None, "error": None}
    interrupted: list[str] = []

    def interrupt(*_: object) -> None:
        # Only noted here: tick() closes the window from the event loop. A signal handler
        # runs between any two bytecodes of the main thread, possibly inside a paint
        # event, where destroying the widgets being painted is unsafe.
        interrupted.append("signal")

    app = pg.mkQApp("lfpiv monitor")
    win = MonitorWindow(pipeline, controls, title=title)
    win.show()
    pipeline.start()
    controls.arm()
    previous_int = signal.signal(signal.SIGINT, interrupt)
    try:
        # a kill or a closed terminal: the laser off at once, then the window closes as on Ctrl-C
        with signals_call(interrupt):

            def tick() -> None:
                if interrupted:
                    win.close()
                    app.quit()
                    return
                # Offscreen mode: the screenshot after `after` pairs were shown (or once the
                # recording ended and the live path has caught up), then quit when the
                # recording has ended.
                if screenshot is None:
                    return
                st = pipeline.stats()
                caught_up = (not controls.armed and st.state in ("waiting", "stopped")
                             and st.last_pair >= controls.status()["committed_pairs"] - 1)
                if shot["path"] is None and (win.displayed >= after or (caught_up and not win.drawing_pending)):
                    win.refresh_status()
                    try:
                        shot["path"] = win.screenshot(screenshot)
                    except OSError as exc:  # the monitor stops: the run it recorded is kept
                        shot["path"], shot["error"] = Path(screenshot), exc
                        controls.disarm()
                    if win.displayed < after:
                        say(f"the recording ended after {win.displayed} pair(s) were shown, fewer than --after "
                            f"{after}")
                if shot["path"] is not None and not controls.armed:
                    app.quit()

            timer = QtCore.QTimer()
            timer.timeout.connect(tick)
            timer.start(50)
            app.exec()
            timer.stop()
            if win.isVisible():
                win.close()
            t0 = time.monotonic()
            controls.disarm()
            controls.wait(120.0)
            pipeline.stop()
            numbers = win.status_numbers()
            stop_s = time.monotonic() - t0
    finally:
        signal.signal(signal.SIGINT, previous_int)
    return WindowOutcome(numbers=numbers, screenshot=shot["path"] if shot["error"] is None else None,
                         screenshot_error=shot["error"], interrupted=bool(interrupted), stop_s=stop_s)
