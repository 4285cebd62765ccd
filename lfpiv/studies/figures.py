"""Drawing the studies' figures: one PNG per study, its panels laid out as the chapter's."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["METHOD_COLOURS", "label", "log_x", "pdf", "panels", "save"]

#: One colour per reconstruction method in every figure.
METHOD_COLOURS = {"drt-mart": "tab:blue", "mart": "tab:red", "mlos-mart": "tab:green", "truth": "0.3"}


def panels(rows: int, cols: int, *, width: float = 4.6, height: float = 3.6, title: str = ""):
    """A figure of ``rows`` x ``cols`` panels (always a 2-D array of axes)."""
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False)
    if title:
        fig.suptitle(title)
    return fig, axes


def save(fig, path: Path) -> None:
    """Lay out, write the PNG (whole or not at all) and free the figure."""
    from lfpiv.plots import save_figure

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)


def pdf(values: Sequence[float], edges: np.ndarray) -> np.ndarray:
    """Probability density of ``values`` (NaN left out) over the bins ``edges``; zeros without values."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return np.zeros(len(edges) - 1)
    h, _ = np.histogram(np.clip(v, edges[0], edges[-1]), bins=edges, density=True)
    return h


def log_x(ax) -> None:
    """A logarithmic x axis labelled in plain numbers (5, 20, 100 rather than powers of ten)."""
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())


def label(ax, letter: str, text: str) -> None:
    """The chapter's panel caption: bold letter, then the text."""
    ax.set_title(f"({letter}) {text}", loc="left", fontsize=10)
