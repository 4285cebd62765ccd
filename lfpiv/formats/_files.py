"""How every writer of :mod:`lfpiv.formats` replaces a file: whole, or not at all
(:func:`lfcore.files.replacing`, which every file lfpiv writes goes through)."""

from __future__ import annotations

from lfcore.files import replacing

__all__ = ["replacing"]
