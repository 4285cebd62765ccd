"""The one error of :mod:`lfpiv.formats`, and how a library's message becomes part of it."""

from __future__ import annotations

__all__ = ["FormatError", "one_line"]


class FormatError(ValueError):
    """A file that cannot be read as what it should be, or data a format cannot hold.

    The message is one line that names the file (or the quantity) and says how to fix it.
    """


def one_line(exc: BaseException | str, limit: int = 160) -> str:
    """A library's error message on one line (whitespace runs made one space), at most ``limit`` characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."
