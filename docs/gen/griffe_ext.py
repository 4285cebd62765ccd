"""A Griffe extension for the API reference: the code's Sphinx conventions read as Markdown.

Loaded by mkdocstrings (``mkdocs.yml``, ``extensions``). Every docstring's Sphinx roles become
code spans (:func:`markup.rst_to_markdown`), and an attribute without a docstring takes its
``#:`` comment, the convention the code documents module constants and rig-file keys with.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import griffe

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markup import doc_comment, rst_to_markdown  # noqa: E402


class SphinxToMarkdown(griffe.Extension):
    """Sphinx roles to Markdown; ``#:`` comments to attribute docstrings."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.is_alias:
            return
        if obj.docstring is None and obj.is_attribute and obj.lineno is not None:
            try:
                lines = obj.lines_collection[obj.filepath]
            except (KeyError, TypeError, ValueError):  # no source (or a namespace package's paths)
                lines = []
            text = doc_comment(list(lines), obj.lineno)
            if text:
                obj.docstring = griffe.Docstring(text, parent=obj)
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
