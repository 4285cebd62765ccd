"""The README is the door, and the guide's references are made from the code (docs/gen).

The whole guide is built with warnings as errors by ``make docs`` (in ``make test`` and CI);
these checks need no MkDocs: the README's commands, length and links, and that the generated
rig-file and command references list every key and every option the code has.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from pathlib import Path

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"


def _generator(name: str):
    """A module of docs/gen (they import each other by name, as MkDocs' hook loads them)."""
    gen = str(ROOT / "docs" / "gen")
    if gen not in sys.path:
        sys.path.insert(0, gen)
    return importlib.import_module(name)


def test_readme_starts_with_the_demo_and_the_tests():
    lines = README.read_text(encoding="utf-8").splitlines()
    first = lines[lines.index("```sh") + 1:lines.index("```sh") + 3]
    assert lines.index("```sh") < 4
    assert first[0].split("#")[0].strip() == "make demo"
    assert first[1].split("#")[0].strip() == "make test"


def test_readme_is_short_and_every_link_resolves_inside_the_repository():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links
    for target in links:
        assert "://" not in target, f"README links outside the repository: {target}"
        path = (ROOT / target.split("#")[0]).resolve()
        assert path.is_relative_to(ROOT) and path.exists(), f"README link does not resolve: {target}"


def test_rig_file_reference_lists_every_key_of_every_table():
    from lfcore.rig import Camera, PinholeCamera, Rig

    page = _generator("rig_reference").rig_reference()
    tables = {key: field.annotation for key, field in Rig.model_fields.items()
              if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)}
    assert all(f"| `{key}` |" in page for key in set(Rig.model_fields) - set(tables) - {"camera"})
    assert "## `[[camera]]`" in page
    for key, model in tables.items():
        assert f"## `[{key}]`" in page
        assert all(f"| `{k}` |" in page for k in model.model_fields), model.__name__
    for model in (Camera, PinholeCamera):
        assert all(f"| `{k}` |" in page for k in model.model_fields), model.__name__


def test_command_reference_lists_every_command_and_option():
    from lfpiv import cli

    page = _generator("cli_reference").command_reference()
    for parser in cli._subparsers(cli._build_parser()):
        assert f"`{parser.prog}`" in page
        for action in parser._actions:
            if action.help != argparse.SUPPRESS:
                assert all(f"`{option}`" in page for option in action.option_strings), (parser.prog, action.dest)
