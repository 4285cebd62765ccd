"""lfpiv: instrument software for light-field particle image velocimetry."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lfpiv")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
