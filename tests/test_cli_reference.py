"""docs/cli.md's option tables are generated from the commands themselves and must be current."""

from pathlib import Path

import tomllib

from twist_cli.reference import COMMANDS, options_markdown, render

ROOT = Path(__file__).resolve().parent.parent


def test_docs_cli_options_are_current() -> None:
    text = (ROOT / "docs" / "cli.md").read_text()
    assert render(text) == text, "docs/cli.md is stale: run python scripts/cli_reference.py"


def test_every_console_command_is_documented() -> None:
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(COMMANDS)
    text = (ROOT / "docs" / "cli.md").read_text()
    for name in scripts:
        assert f"<!-- options: {name} -->" in text
        assert f"## `{name}`" in text


def test_generated_table_lists_each_option_of_a_command() -> None:
    table = options_markdown("twist-distil")
    for option in ("--dataset", "--recipe", "--resume", "--set"):
        assert f"| `{option} " in table or f"| `{option}` |" in table
    group = options_markdown("twist-data")
    assert "**`twist-data verify`**" in group and "**`twist-data salvage`**" in group
