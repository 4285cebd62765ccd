"""MkDocs hooks (``mkdocs.yml``, ``hooks``): the pages made from the code at every build.

- ``reference/rig-file.md`` from the rig model (:mod:`rig_reference`),
- ``reference/commands.md`` from the argument parsers (:mod:`cli_reference`),
- ``reference/examples.md`` from ``examples/*.toml``,
- ``reference/api/*.md``, one page per package listing every public module for mkdocstrings,
- ``benchmarks.md`` from ``benchmarks/RESULTS.md``, which stays beside the benchmarks.

None of these is written into ``docs/``: they exist only in the build, so they cannot go stale.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path[:0] = [str(HERE), str(ROOT)]

from cli_reference import command_reference  # noqa: E402
from rig_reference import rig_reference  # noqa: E402

#: API pages: (page, title, the packages documented there). A package's public modules are
#: documented on its page unless a page of their own is listed; lfpiv.commands is the command
#: reference's, and modules whose name starts with "_" are private.
API_PAGES = (
    ("lfpiv", "lfpiv: the application and `import lfpiv`", "lfpiv"),
    ("lfpiv.jobs", "lfpiv.jobs: what each command does", "lfpiv.jobs"),
    ("lfpiv.formats", "lfpiv.formats: other tools' files", "lfpiv.formats"),
    ("lfpiv.studies", "lfpiv.studies: the chapter's studies", "lfpiv.studies"),
    ("lfcore", "lfcore: pure computation", "lfcore"),
    ("acquisition", "acquisition: devices and recording", "acquisition"),
    ("calibration", "calibration", "calibration"),
    ("realtime", "realtime: the live path", "realtime"),
    ("sim", "sim: the simulated lab", "sim"),
)
_SKIP = {"lfpiv.commands", "lfpiv.__main__"}


def _modules(package: str) -> list[str]:
    """``package`` and its public modules, depth first, each before its own modules."""
    path = ROOT.joinpath(*package.split("."))
    out = [package]
    for child in sorted(path.iterdir()):
        name = child.stem if child.suffix == ".py" else child.name
        dotted = f"{package}.{name}"
        if name.startswith("_") or dotted in _SKIP or any(dotted == p for _, _, p in API_PAGES):
            continue
        if child.is_dir() and (child / "__init__.py").exists():
            out += _modules(dotted)
        elif child.suffix == ".py":
            out.append(dotted)
    return out


def _api_page(title: str, package: str) -> str:
    out = [f"# {title}", ""]
    for module in _modules(package):
        out += [f"::: {module}", ""]
    return "\n".join(out)


def _examples() -> str:
    out = ["# Example rigs", "",
           "The rig files in the repository's `examples/` folder, as they are. Every key is explained in the "
           "[rig-file reference](rig-file.md); `lfpiv synth --rig examples/NAME.toml ...` runs any of them on "
           "simulated images.", ""]
    for path in sorted((ROOT / "examples").glob("*.toml")):
        out += [f"## `examples/{path.name}`", "", "```toml", path.read_text(encoding="utf-8").rstrip(), "```", ""]
    return "\n".join(out)


def generated_pages() -> dict[str, str]:
    """Every generated page: its path under docs/ and its Markdown."""
    pages = {
        "reference/rig-file.md": rig_reference(),
        "reference/commands.md": command_reference(),
        "reference/examples.md": _examples(),
        "benchmarks.md": (ROOT / "benchmarks" / "RESULTS.md").read_text(encoding="utf-8"),
    }
    for page, title, package in API_PAGES:
        pages[f"reference/api/{page}.md"] = _api_page(title, package)
    return pages


def on_files(files: Files, config: MkDocsConfig) -> Files:
    for path, content in generated_pages().items():
        files.append(File.generated(config, path, content=content))
    return files
