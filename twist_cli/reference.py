"""The option tables of ``docs/cli.md``, generated from the commands' own ``--help`` so that the
reference cannot drift from the code: ``python scripts/cli_reference.py`` rewrites them, and a
test fails when the file differs from what this module generates."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import typer

from twist_cli import baseline, collect, data, distil, report
from twist_cli import eval as evaluate

#: Console command name -> its Typer app, in the order of docs/cli.md.
COMMANDS: dict[str, typer.Typer] = {
    "twist-collect": collect.app, "twist-distil": distil.app, "twist-eval": evaluate.app,
    "twist-baseline": baseline.app, "twist-report": report.app, "twist-data": data.app,
}
BEGIN, END = "<!-- options: {name} -->", "<!-- /options -->"
_BLOCK = re.compile(r"<!-- options: (?P<name>[\w -]+) -->\n.*?<!-- /options -->", re.S)


#: Markdown lines stay within this many characters (a list item's text wraps onto indented lines).
WIDTH = 100


def _cell(text: str) -> str:
    return " ".join(text.split())


#: A word that, opening a line, would start a list, heading or quote instead of continuing one.
_BLOCK_START = re.compile(r"^([-+*>#]+|\d+[.)])$")


def _item(head: str, text: str, indent: str = "  ") -> str:
    """``head`` and ``text`` as one Markdown paragraph or list item wrapped at WIDTH (a word
    longer than a line, such as a comma-separated default, breaks after its commas)."""
    lines: list[str] = []
    words = [piece for word in f"{head} {_cell(text)}".split(" ")
             for piece in (re.findall(r"[^,]+,?", word) if len(word) > WIDTH else [word])]
    for word in words:
        if lines and (len(lines[-1]) + 1 + len(word) <= WIDTH or _BLOCK_START.match(word)):
            lines[-1] += " " + word
        else:
            lines.append((indent if lines else "") + word)
    return "\n".join(lines)


# Typer vendors its own click (typer._click, private), so commands and contexts are reached
# through typer.main.get_command and Command.make_context only, never by importing click.
def _context(command: Any, path: str) -> Any:
    return command.make_context(path, [], resilient_parsing=True)


def _rows(command: Any, ctx: Any) -> Iterator[str]:
    for param in command.get_params(ctx):
        record = param.get_help_record(ctx)
        if record is None:
            continue
        names, meaning = record
        yield _item(f"- `{_cell(names)}`:", meaning)


def _table(command: Any, path: str) -> str:
    ctx = _context(command, path)
    rows = "\n".join(_rows(command, ctx))
    usage = " ".join(command.collect_usage_pieces(ctx))
    return f"`{path} {usage}`\n\n{rows}\n"


def options_markdown(name: str) -> str:
    """The option table(s) of console command ``name``: one per subcommand for a group."""
    command = typer.main.get_command(COMMANDS[name])
    if hasattr(command, "list_commands"):
        ctx = _context(command, name)
        parts = []
        for sub in command.list_commands(ctx):
            subcommand = command.get_command(ctx, sub)
            summary = _item(f"**`{name} {sub}`**:", subcommand.get_short_help_str(limit=200), "")
            parts.append(f"{summary}\n\n{_table(subcommand, f'{name} {sub}')}")
        return "\n".join(parts)
    return _table(command, name)


def render(text: str) -> str:
    """``text`` (docs/cli.md) with every options block regenerated."""
    def block(match: re.Match[str]) -> str:
        name = match["name"]
        return f"{BEGIN.format(name=name)}\n{options_markdown(name)}{END}"
    return _BLOCK.sub(block, text)


def update(path: str | Path) -> bool:
    """Regenerate the options blocks of the file at ``path``; whether it changed."""
    path = Path(path)
    before = path.read_text()
    after = render(before)
    if after != before:
        path.write_text(after)
    return after != before
