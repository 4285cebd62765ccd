"""Live: the pipeline that reconstructs and correlates the newest recorded pair, and the
pyqtgraph monitor window that shows it (Qt is imported only when a window is made)."""

__all__ = [
    "monitor",   # the monitor window, its Controls protocol and its event loop
    "pipeline",  # the live pipeline: ring buffer to volumes, vectors and vorticity
]
