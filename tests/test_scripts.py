"""Every benchmark and research probe still imports against the library and has a
documented entry point, so that none rots while the library changes."""

from pathlib import Path

import pytest

from tests.conftest import load_script

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = sorted([*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "research" / "probes").glob("*.py")])


def test_the_folders_hold_scripts() -> None:
    assert {p.parent.name for p in SCRIPTS} == {"benchmarks", "probes"}


def _command_path(script: Path) -> str:
    return script.relative_to(ROOT).as_posix()


@pytest.mark.parametrize("script", SCRIPTS, ids=_command_path)
def test_script_imports_and_documents_its_command(script: Path) -> None:
    module = load_script(script)
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"
    doc = module.__doc__ or ""
    assert doc.strip(), f"{script.name} has no docstring"
    assert _command_path(script) in doc, (
        f"{script.name}'s docstring does not show the command that runs it")
