"""Regenerate the option tables of docs/cli.md from the commands' own --help."""

from pathlib import Path

from twist_cli.reference import update

if __name__ == "__main__":
    path = Path(__file__).resolve().parent.parent / "docs" / "cli.md"
    print(f"{path}: {'updated' if update(path) else 'already current'}")
