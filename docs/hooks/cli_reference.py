"""MkDocs hook: the command-line reference (reference/cli.md), written at build time
from the parser itself, ``dct_hil.cli.build_parser()``: every subcommand and every
nested one (``mapping template``, ...) with its usage and its options, so the page
says what the installed command accepts and is never written by hand."""

from __future__ import annotations

import argparse
import html
import os
import re
import sys
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
PAGE = "reference/cli.md"
WIDTH = 100          # columns of the usage lines (argparse wraps at $COLUMNS)


def _text(s: str) -> str:
    """Help text as Markdown text: nothing in it read as markup."""
    s = html.escape(s, quote=False)
    s = re.sub(r"([\\`*_\[\]|#])", r"\\\1", s)
    return " ".join(s.split())


def _subparsers(parser: argparse.ArgumentParser):
    """(name, help, parser) of each subcommand, in the order they were added."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:          # an alias
                    continue
                seen.add(id(sub))
                yield name, helps.get(name), sub


def _options(parser: argparse.ArgumentParser) -> list[str]:
    fmt = parser._get_formatter()
    lines: list[str] = []
    for group in parser._action_groups:
        actions = [a for a in group._group_actions
                   if a.help is not argparse.SUPPRESS
                   and not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
        if not actions:
            continue
        kind = "argument" if all(not a.option_strings for a in actions) else "option"
        lines += [f"*{_text(group.title or 'options')}*", "", f"| {kind} | meaning |", "|---|---|"]
        for a in actions:
            invocation = fmt._format_action_invocation(a)
            meaning = _text(fmt._expand_help(a)) if a.help else ""
            lines.append(f"| `{invocation}` | {meaning} |")
        lines.append("")
    return lines


def _section(parser: argparse.ArgumentParser, help_: str | None, depth: int) -> list[str]:
    lines = [f"{'#' * depth} {parser.prog}", ""]
    if parser.description:
        lines += [_text(parser.description), ""]
    elif help_:
        lines += [_text(help_[:1].upper() + help_[1:]) + ".", ""]
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    lines += _options(parser)
    subs = list(_subparsers(parser))
    if subs:
        lines += ["| subcommand | what it does |", "|---|---|"]
        for name, h, sub in subs:
            anchor = re.sub(r"[^a-z0-9]+", "-", sub.prog.lower()).strip("-")
            lines.append(f"| [`{name}`](#{anchor}) | {_text(h or '')} |")
        lines.append("")
        for _, h, sub in subs:
            lines += _section(sub, h, min(depth + 1, 4))
    if parser.epilog:
        lines += [_text(parser.epilog), ""]
    return lines


def render() -> str:
    os.environ["COLUMNS"] = str(WIDTH)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    try:
        from dct_hil.cli import build_parser
        parser = build_parser()
    except Exception as e:  # the build fails with the reason in one line
        raise PluginError(f"cli_reference: dct_hil.cli.build_parser() failed: "
                          f"{type(e).__name__}: {e}") from e
    head = [
        "# Command line",
        "",
        "Every subcommand of `dct-hil` with its usage and options, written when the manual "
        "is built from the parser the command itself uses (`dct_hil.cli.build_parser()`); "
        "`dct-hil COMMAND --help` prints the same. What each command does, with examples, "
        "is on the pages of the manual.",
        "",
    ]
    return "\n".join(head + _section(parser, None, 2)) + "\n"


def on_files(files, config):
    files.append(File.generated(config, PAGE, content=render()))
    return files
