"""Every benchmark and experiment script still imports against the library and has a
documented entry point, so that none rots while the library changes."""

from pathlib import Path

import pytest

from tests.conftest import load_script

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = sorted([*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "experiments").glob("*.py")])


def test_the_folders_hold_scripts() -> None:
    assert {p.parent.name for p in SCRIPTS} == {"benchmarks", "experiments"}


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_script_imports_and_documents_its_command(script: Path) -> None:
    module = load_script(script)
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"
    doc = module.__doc__ or ""
    assert doc.strip(), f"{script.name} has no docstring"
    assert f"{script.parent.name}/{script.name}" in doc, (
        f"{script.name}'s docstring does not show the command that runs it")
