"""Live: the pipeline that reconstructs and correlates the newest recorded pair (or tracks its
particles: the particle route), and the pyqtgraph monitor window that shows it (Qt is imported
only when a window is made).

``realtime.window`` holds the window's Qt class; it imports Qt, so it is not in ``__all__``:
:func:`realtime.monitor.MonitorWindow` imports it when a window is made."""

__all__ = [
    "monitor",     # the monitor's Controls protocol, Qt's lazy import and the window's event loop
    "pipeline",    # the live pipeline: runs staging, processing and the view, pair after pair
    "processing",  # one pair on the device: preprocess, reconstruct A and B, correlate; or particles and tracks
    "settings",    # the live routes and methods, the run-time settings, the monitoring windows
    "staging",     # the feeder thread, host slots, the ring's seqlock check, device uploads
    "view",        # a processed pair to what the window shows (pure)
]
