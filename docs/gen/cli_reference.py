"""The command reference, generated from the ``lfpiv`` argument parsers at every docs build.

Each command's page section is its parser as ``lfpiv COMMAND --help`` prints it: the summary,
the description, the usage line and every argument with its help, so the page can never list
an option the command lacks or miss one it has.

Run on its own (``python docs/gen/cli_reference.py``) it prints the page.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markup import plain  # noqa: E402

__all__ = ["command_reference"]

#: Options every command takes, described once at the top rather than under each command.
_COMMON = {"help", "verbose", "log_file"}
_WIDTH = 100


def _formatter(prog: str) -> argparse.HelpFormatter:
    return argparse.HelpFormatter(prog, width=_WIDTH, max_help_position=40)


def _usage(parser: argparse.ArgumentParser) -> str:
    fmt = _formatter(parser.prog)
    actions = [a for a in parser._actions if a.dest not in _COMMON]
    fmt.add_usage(parser.usage, actions, parser._mutually_exclusive_groups, prefix="")
    return fmt.format_help().strip()


def _rows(parser: argparse.ArgumentParser, *, common: bool) -> list[str]:
    fmt = _formatter(parser.prog)
    rows = []
    for action in parser._actions:
        if action.help == argparse.SUPPRESS or isinstance(action, argparse._SubParsersAction):
            continue
        if (action.dest in _COMMON) != common:
            continue
        if action.option_strings:
            name = ", ".join(f"`{o}`" for o in action.option_strings)
            value = fmt._format_args(action, action.dest.upper()) if action.nargs != 0 else ""
        else:
            name = f"`{action.metavar or action.dest}`"
            value = "" if action.nargs in (None, 1) else fmt._format_args(action, action.dest)
        text = fmt._expand_help(action) if action.help else ""
        default = action.default
        if (default not in (None, False, [], argparse.SUPPRESS) and action.option_strings
                and "default" not in text and not isinstance(action, argparse._VersionAction)):
            text += f" (default: {default})"
        rows.append(f"| {name} | {plain(f'`{value}`' if value else '')} | {plain(text)} |")
    return rows


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each subcommand of ``parser``, in the order --help lists them."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # an alias shares its command's parser
                    seen.add(id(sub))
                    out.append((name, helps.get(name, ""), sub))
    return out


def _section(name: str, summary: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    out = [f"{'#' * level} `{parser.prog}`", ""]
    if summary:
        out += [f"*{plain(summary)}*", ""]
    if parser.description:
        out += [plain(parser.description), ""]
    out += ["```text", _usage(parser), "```", ""]
    rows = _rows(parser, common=False)
    if rows:
        out += ["| argument | value | meaning |", "| --- | --- | --- |", *rows, ""]
    if parser.epilog:
        out += [plain(parser.epilog), ""]
    for sub_name, sub_summary, sub in _subcommands(parser):
        out += _section(sub_name, sub_summary, sub, level + 1)
    return out


def command_reference() -> str:
    """The command reference page, Markdown."""
    from lfpiv import cli

    parser = cli._build_parser()
    commands = _subcommands(parser)
    out = [
        "# Command reference",
        "",
        "Generated from the `lfpiv` command's own argument parsers each time the documentation is built: "
        "what follows is what `lfpiv COMMAND --help` prints, for every command and step. How the commands "
        "fit together is in the [tutorial](../tutorial.md) and the guide's pages.",
        "",
        "```text",
        _usage(parser),
        "```",
        "",
        " ".join((parser.description or "").split()),
        "",
        "## Options of every command",
        "",
        "These go before the command or after it (`lfpiv -v reconstruct run.zarr` or "
        "`lfpiv reconstruct run.zarr -v`).",
        "",
        "| argument | value | meaning |",
        "| --- | --- | --- |",
        *_rows(parser, common=True),
        *[r for r in _rows(parser, common=False)],
        "",
        "## Exit codes",
        "",
        "| code | meaning |",
        "| --- | --- |",
        "| 0 | done |",
        f"| {cli.EXIT_USAGE} | bad input: one line on stderr naming the problem and the fix, no traceback |",
        f"| {cli.EXIT_DEVICE} | a device fault, after the laser was disarmed |",
        f"| {cli.EXIT_INTERRUPTED} | interrupted (Ctrl-C, SIGTERM, SIGHUP); an unfinished run is marked aborted |",
        "",
        "## Commands",
        "",
        "| command | what it does |",
        "| --- | --- |",
        *[f"| [`{name}`](#{sub.prog.replace(' ', '-')}) | {plain(summary)} |" for name, summary, sub in commands],
        "",
    ]
    for name, summary, sub in commands:
        out += _section(name, summary, sub, 2)
    return "\n".join(out)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    print(command_reference())
