"""The Qt binding keeps ``None`` alive: calls that return nothing give back a reference of its own.

PySide6 6.12.0 on Python 3.11 returned ``None`` from every ``void`` C++ method without adding a
reference, so each call took one reference away from ``None``; ``lfpiv monitor`` made a few hundred
such calls per second and aborted with "Fatal Python error: none_dealloc" after about a thousand
pairs. These tests reproduce that fault in isolation (they fail on that build) and check that the
monitor refuses such a binding in one line instead of aborting mid-run.
"""

from __future__ import annotations

import ctypes
import gc
import os
import sys

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("PYQTGRAPH_QT_LIB", "PySide6")  # as require_qt: the binding the gui extra pins
pytest.importorskip("pyqtgraph")

import realtime.monitor as monitor  # noqa: E402
from realtime.monitor import GuiUnavailable, drops_none_references, require_qt  # noqa: E402

needs_counted_none = pytest.mark.skipif(sys.version_info >= (3, 12),
                                        reason="None is immortal from Python 3.12 on: its count does not move")


def _none_drift(call, calls: int = 500) -> int:
    """How far ``sys.getrefcount(None)`` moved over ``calls`` calls of ``call`` (after one warm-up)."""
    call()
    gc.collect()
    gc.disable()  # a collection in between would let go of references that are not the call's
    try:
        before = sys.getrefcount(None)
        for _ in range(calls):
            call()
        return sys.getrefcount(None) - before
    finally:
        gc.enable()


@needs_counted_none
def test_void_calls_of_the_qt_binding_leave_none_its_references() -> None:
    # the binding itself, not through require_qt (which refuses a faulty one before any of this)
    import pyqtgraph as pg
    from pyqtgraph.Qt import QtCore, QtWidgets

    app = pg.mkQApp()
    obj = QtCore.QObject()
    timer = QtCore.QTimer()
    label = QtWidgets.QLabel("status")
    image = pg.ImageItem(axisOrder="row-major")
    data = np.arange(64 * 48, dtype=np.float32).reshape(48, 64)
    calls = 500
    # what the monitor calls for every pair it shows, and its event loop many times a second
    for name, call in [("QObject.setObjectName", lambda: obj.setObjectName("x")),
                       ("QObject.parent (no parent)", obj.parent),
                       ("QTimer.setInterval", lambda: timer.setInterval(50)),
                       ("QLabel.setText", lambda: label.setText("pair 1")),
                       ("ImageItem.setImage", lambda: image.setImage(data, autoLevels=False, levels=(0.0, 1.0))),
                       ("QApplication.processEvents", app.processEvents)]:
        drift = _none_drift(call, calls)
        # a faulty binding: exactly -calls (one reference lost per call); a sound one: 0
        assert drift > -calls // 10, f"{name} lost {-drift} references to None in {calls} calls"
    assert drops_none_references(QtCore) is False


class _BorrowedNoneObject:
    """Stands in for a QObject of a faulty binding: ``setObjectName`` takes one reference from None,
    as a C method returning ``Py_None`` without ``Py_INCREF`` does."""

    _decref = ctypes.PYFUNCTYPE(None, ctypes.py_object)(("Py_DecRef", ctypes.pythonapi))
    lost = 0

    def setObjectName(self, name: str) -> None:  # noqa: N802 - Qt's name
        type(self).lost += 1
        self._decref(None)


@needs_counted_none
def test_a_binding_that_loses_references_to_none_is_found() -> None:
    class FakeQtCore:
        QObject = _BorrowedNoneObject

    incref = ctypes.PYFUNCTYPE(None, ctypes.py_object)(("Py_IncRef", ctypes.pythonapi))
    _BorrowedNoneObject.lost = 0
    try:
        assert drops_none_references(FakeQtCore, calls=64) is True
    finally:
        for _ in range(_BorrowedNoneObject.lost):  # give None back what the stand-in took
            incref(None)
    assert _BorrowedNoneObject.lost == 64


def test_the_monitor_refuses_such_a_binding_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(monitor, "_BINDING_FAULT", None)
    monkeypatch.setattr(monitor, "drops_none_references", lambda QtCore: True)
    with pytest.raises(GuiUnavailable) as err:
        require_qt()
    text = str(err.value)
    assert "\n" not in text
    assert "loses a reference to None" in text and "pip install 'lfpiv[gui]'" in text
    with pytest.raises(GuiUnavailable):  # checked once, refused every time
        require_qt()
