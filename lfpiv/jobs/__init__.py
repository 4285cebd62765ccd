"""What each ``lfpiv`` command does, one module per command, named after it.

``lfpiv/commands/X.py`` parses the command line and prints; ``lfpiv/jobs/X.py`` does the job
(the same functions serve Python users: see :mod:`lfpiv`); the computation itself is in the
package that owns it (``lfcore``, ``calibration``, ``acquisition``, ``realtime``).
"""

__all__ = ["acquire", "calibrate", "check", "correlate", "demo", "devices", "evaluate", "export", "import_", "info",
           "monitor", "reconstruct", "synth"]
