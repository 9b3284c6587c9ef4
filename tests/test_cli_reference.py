"""docs/cli.md's option tables are generated from the commands themselves and must be current."""

from pathlib import Path

import tomllib

from twist_cli.reference import COMMANDS, WIDTH, _item, options_markdown, render

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
        assert f"- `{option} " in table or f"- `{option}`:" in table
    group = options_markdown("twist-data")
    assert "**`twist-data verify`**" in group and "**`twist-data salvage`**" in group


def test_an_option_wraps_into_one_list_item_of_short_lines() -> None:
    words = ["word"] * 60 + ["-", "1.", "#", ",".join(["choice"] * 40)]
    item = _item("- `--flag <str>`:", " ".join(words))
    lines = item.splitlines()
    assert len(lines) > 3 and lines[0].startswith("- `--flag <str>`: word")
    # Continuations are indented, never open a list, heading or numbered item of their own,
    # and a comma-separated word longer than a line breaks after its commas.
    assert all(line.startswith("  ") and line.split()[0] not in ("-", "1.", "#")
               for line in lines[1:])
    assert all(len(line) <= WIDTH for line in lines if "-" not in line.split())
    assert " ".join(item.split()).replace(", ", ",") == " ".join(
        ["- `--flag <str>`:", *words])


def test_the_reference_has_no_line_over_200_characters() -> None:
    for name in COMMANDS:
        long = [line for line in options_markdown(name).splitlines() if len(line) > 200]
        assert not long, f"{name}: {long[0][:80]}…"
