"""Errors the ``lfpiv`` command reports as one line on stderr with exit code 2."""

from __future__ import annotations


class UsageError(Exception):
    """Bad input from the user: the message names the problem and the fix."""
