"""Docstrings and ``#:`` comments as Markdown, for the generated pages and the API reference.

The code's docstrings are numpydoc with Sphinx roles (``:class:`Rig```, ``:meth:`~RunStore.open```)
and reST literal blocks (``Layout::``). MkDocs renders Markdown, where a role would show as
``:class:`` before the name: here each role becomes the code span of its name, and a paragraph
ending in ``::`` ends in ``:`` (its indented block is a code block in Markdown too).
"""

from __future__ import annotations

import re

__all__ = ["doc_comment", "plain", "rst_to_markdown"]

#: A Sphinx role: ``:class:`~pkg.Name``` or ``:py:meth:`Name.method```.
_ROLE = re.compile(r":(?:py:)?(?:class|meth|func|mod|attr|data|exc|obj|const|term|ref|doc):`~?([^`]+)`")


def rst_to_markdown(text: str) -> str:
    """``text`` (a docstring or comment written for Sphinx) as Markdown.

    Parameters
    ----------
    text
        reST-flavoured text: Sphinx roles, double-backtick literals, ``::`` literal blocks.

    Returns
    -------
    str
        The same text with each role the code span of its target as written (only the last
        name where the target starts with a tilde, as Sphinx shows it) and a trailing ``::`` a
        single colon.
    """

    def role(m: re.Match[str]) -> str:
        target = m.group(1)
        if m.group(0).split("`")[1].startswith("~"):
            target = target.rsplit(".", 1)[-1]
        return f"`{target}`"

    text = _ROLE.sub(role, text)
    # "Layout::" introduces a literal block: in Markdown the indented block already is one
    return re.sub(r"(?m)(\S)::$", r"\1:", text)


def doc_comment(lines: list[str], lineno: int) -> str:
    """The ``#:`` comment lines just above line ``lineno`` (1-based), joined, or "".

    Sphinx's convention for documenting an attribute or a field: each line of the comment
    starts with ``#:`` and the comment ends on the line before the attribute.
    """
    out: list[str] = []
    k = lineno - 2
    while k >= 0 and lines[k].lstrip().startswith("#:"):
        out.insert(0, lines[k].lstrip()[2:].strip())
        k -= 1
    return " ".join(s for s in out if s)


def plain(text: str) -> str:
    """``text`` (help or prose with no Markdown in mind) safe in a Markdown table cell: one
    line, ``*``, ``<`` and ``>`` escaped outside code spans, ``|`` escaped everywhere."""
    parts = " ".join(text.split()).split("`")
    for k in range(0, len(parts), 2):  # outside the code spans
        parts[k] = parts[k].replace("*", "\\*").replace("<", "&lt;").replace(">", "&gt;")
    return "`".join(parts).replace("|", "\\|")
