"""``lfpiv monitor`` for a few hundred pairs: the reference count of ``None`` does not fall per pair.

On Python 3.11 ``None`` is reference-counted; an extension that returns it without a reference of
its own takes one away on every call, and the interpreter aborts when the count reaches zero
("Fatal Python error: none_dealloc"), after so many pairs that a lab session would die mid-run.
Here the whole live path runs in this process, as in the lab: the simulated lab triggers two
cameras, the session records every pair, the live pipeline reconstructs and correlates the newest,
and the monitor window (offscreen) draws each result. The count is sampled on the GUI thread after
each drawing, and its trend per recorded pair must be flat.
"""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import theilslopes

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pyqtgraph")

from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.cli import main  # noqa: E402
from tests.helpers import fast_rig_text  # noqa: E402


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="None is immortal from Python 3.12 on")
def test_none_keeps_its_references_over_hundreds_of_live_pairs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys) -> None:
    import realtime.monitor as monitor

    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(fast_rig_text(rate_hz=25.0, cameras=2))
    samples: list[tuple[int, int]] = []  # (committed pairs, sys.getrefcount(None)) after each drawing
    make = monitor.MonitorWindow

    def sampling(*args, **kwargs):
        win = make(*args, **kwargs)
        show = win.show_result

        def show_result(result) -> None:
            show(result)
            # Only live references count: garbage cycles that hold None are freed before each sample
            # (cheap, as everything older than this test is frozen out of the collector).
            gc.collect()
            samples.append((int(win.controls.status()["committed_pairs"]), sys.getrefcount(None)))

        win.show_result = show_result
        return win

    monkeypatch.setattr(monitor, "MonitorWindow", sampling)
    pairs = 300
    out = tmp_path / "live.zarr"
    # The garbage of the tests before this one (in a whole-suite process, cycles that hold tens of
    # thousands of references to None) is freed now, not by a full collection in the middle of the run,
    # where it once read as a fall of 148 references per pair (CI, 2026-12-06).
    gc.collect()
    gc.freeze()
    try:
        rc = main(["monitor", "--rig", str(rig_file), "--pairs", str(pairs), "--out", str(out), "--screenshot",
                   str(tmp_path / "shot.png"), "--after", "1", "--device", "cpu", "--iterations", "2", "--sim-rays",
                   "300", "--sim-pool", "3", "--pvr", "4,4,20", "--quiet"])
    finally:
        gc.unfreeze()
    _, stderr = capsys.readouterr()
    assert rc == 0, stderr
    assert RunStore.open(out).committed_pairs == pairs
    # Past the first drawings (which build caches that keep references), over the rest of the run.
    steady = np.array(samples[len(samples) // 5:], dtype=float)
    assert len(steady) >= 20, f"only {len(samples)} results were drawn"
    span = steady[-1, 0] - steady[0, 0]
    assert span >= pairs / 2
    # The median of the slopes between every two samples (Theil-Sen): a steady loss sets it, a single
    # step (one release of many references at once) does not.
    per_pair = theilslopes(steady[:, 1], steady[:, 0])[0]
    counts = (f"{len(samples)} samples: {steady[0, 1]:.0f} first, {steady[:, 1].min():.0f} lowest, "
              f"{steady[-1, 1]:.0f} last")
    # A binding that loses one reference per void call loses tens per pair here (every drawing
    # makes dozens of such calls, the status line and the event loop more); transient references
    # held by the other threads move single samples by a few hundred at most.
    assert per_pair > -1.0, f"None lost {-per_pair:.1f} references per pair ({counts})"
    assert steady[-1, 1] - steady[0, 1] > -span, f"None's count fell from {steady[0, 1]:.0f} to {steady[-1, 1]:.0f}"
