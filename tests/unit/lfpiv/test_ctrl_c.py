"""``lfpiv``'s Ctrl-C handling (``lfpiv.cli._one_ctrl_c``): a Ctrl-C taken inside a finalizer or a
weakref callback is neither printed with a traceback nor lost: it is raised again a moment later."""

from __future__ import annotations

import gc
import os
import signal
import time
import weakref

import pytest

from lfpiv.cli import _one_ctrl_c


class _Held:
    pass


def test_a_ctrl_c_inside_a_weakref_callback_is_raised_after_it_not_printed(capsys) -> None:
    calls = []

    def callback() -> None:  # a library's cleanup, run by the collector: not a __del__
        calls.append(1)
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handler runs here, inside the callback
            sum(range(10))

    with _one_ctrl_c(grace_s=5.0):
        held = _Held()
        held.me = held  # a cycle: freed by the collector, which calls the callback
        weakref.finalize(held, callback)
        del held
        with pytest.raises(KeyboardInterrupt):
            gc.collect()
            t0 = time.monotonic()
            while time.monotonic() - t0 < 2.0:
                time.sleep(0.005)
    assert calls == [1]
    assert "Exception ignored" not in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
