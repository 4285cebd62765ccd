"""The live monitor: its :class:`Controls` protocol, Qt's lazy import and the window's event loop.

The window itself (:class:`realtime.window.MonitorWindow`: raw images, projections and a slice
of volume A, the in-plane vectors over their vorticity, a status line and the controls) is a Qt
class in a module of its own; :func:`MonitorWindow` makes one. :func:`run_monitor_window` shows
it, arms the acquisition and runs Qt's event loop until the window closes.

Qt is imported lazily: ``import realtime.monitor`` works without the ``gui`` extra, and
:func:`require_qt` raises :class:`GuiUnavailable` naming ``pip install 'lfpiv[gui]'``.
"""

from __future__ import annotations

import gc
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from realtime.pipeline import LivePipeline

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


def MonitorWindow(pipeline: LivePipeline, controls: Controls | None = None, *,  # noqa: N802 - made like a class
                  title: str = "lfpiv monitor"):
    """The monitor window (:class:`realtime.window.MonitorWindow`, a ``QMainWindow``) for ``pipeline``,
    with optional acquisition ``controls``.

    Create a ``QApplication`` first (``pyqtgraph.mkQApp()``). Attributes of interest:
    ``displayed`` (results drawn), ``last_result``, ``status_numbers()``, ``panel_rects()``,
    ``screenshot(path)``. Qt is imported here, the first time a window is made.

    Raises
    ------
    GuiUnavailable
        Without pyqtgraph and PySide6.
    """
    require_qt()  # the one-line refusal before the window's module imports Qt
    from realtime.window import MonitorWindow as Window

    return Window(pipeline, controls, title=title)


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
    caught up, and the loop ends when the recording has; offscreen without ``screenshot`` the
    loop ends once the recording has and the live path caught up. Whatever ends the loop, the recording
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
    offscreen = app.platformName() in ("offscreen", "minimal")
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
                # recording has ended. Offscreen without a screenshot (no one can close the
                # window) ends once the recording has and the live path caught up.
                if screenshot is None and not offscreen:
                    return
                st = pipeline.stats()
                caught_up = (not controls.armed and st.state in ("waiting", "stopped")
                             and st.last_pair >= controls.status()["committed_pairs"] - 1)
                if screenshot is None:
                    if caught_up and not win.drawing_pending:
                        app.quit()
                    return
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
            # the checks panel destroyed by Qt now, while the application exists: left to the
            # interpreter's exit, its pyqtgraph items were freed after it (a segfault at every exit)
            win.release_checks()
            QtCore.QCoreApplication.sendPostedEvents(None, QtCore.QEvent.Type.DeferredDelete)
            app.processEvents()
    finally:
        signal.signal(signal.SIGINT, previous_int)
    return WindowOutcome(numbers=numbers, screenshot=shot["path"] if shot["error"] is None else None,
                         screenshot_error=shot["error"], interrupted=bool(interrupted), stop_s=stop_s)
