"""The demo's own steps (``lfpiv demo``): its output folder, its windows and its pictures.

The rest of the demo is ordinary ``lfpiv`` commands (:mod:`lfpiv.commands.demo`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from lfcore.device import resolve_device
from lfcore.runstore import RunStore, RunStoreError
from lfpiv.errors import UsageError
from lfpiv.jobs.correlate import fitting_windows
from lfpiv.plots import plot_raw_images, plot_vectors

__all__ = ["MARKER", "check_device", "demo_windows", "pictures", "prepare_folder"]

#: Marks a folder written by the demo, so that a later demo may replace it (and nothing else).
MARKER = ".lfpiv-demo"


def check_device(device: str) -> None:
    """A one-line error for a compute device this machine lacks (before anything is cleared)."""
    resolve_device(device)


def prepare_folder(out: Path) -> None:
    """Make ``out`` the demo's empty folder: a previous demo's is replaced, any other non-empty
    folder is refused."""
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the demo's output")
    if out.exists() and any(out.iterdir()):
        if not (out / MARKER).exists() and not _legacy_demo(out):
            raise UsageError(f"{out} is not empty and was not written by 'lfpiv demo'; choose another --out")
        shutil.rmtree(out)  # only ever a previous demo's folder
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by 'lfpiv demo'; the next demo replaces this folder\n")


def _legacy_demo(out: Path) -> bool:
    # lfpiv 0.1's demo left only run.zarr (with attrs demo = true) and raw_images.png.
    if {p.name for p in out.iterdir()} - {"run.zarr", "raw_images.png"}:
        return False
    try:
        return RunStore.open(out / "run.zarr").attrs.get("demo") is True
    except RunStoreError:
        return False


def demo_windows(run: str) -> str:
    """``--windows`` for the run's volumes (:func:`lfpiv.jobs.correlate.fitting_windows`)."""
    return ",".join("x".join(map(str, w)) for w in fitting_windows(RunStore.open(run).volume_grid().shape))


def pictures(run: str, out: Path) -> list[Path]:
    """The raw images and the vectors of the run's first pair, as PNG files in ``out``."""
    store = RunStore.open(run)
    return [plot_raw_images(store, out / "raw_images.png"), plot_vectors(store, out / "vectors.png")]
