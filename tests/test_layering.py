"""The layers of the code: twist_data knows nothing of the models, building blocks nothing of
the pipeline's stages, and no library module anything of the console commands. Checked on
every import statement, function-level ones included."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).glob("*.py"))


LAYERS = [
    ("twist_data", ("twist_models", "twist_cli")),
    ("twist_models", ("twist_models.stages", "twist_cli")),
    ("twist_models/stages", ("twist_cli",)),
]


@pytest.mark.parametrize(("folder", "forbidden"), LAYERS, ids=[f for f, _ in LAYERS])
def test_no_module_imports_a_higher_layer(folder: str, forbidden: tuple[str, ...]) -> None:
    offending = [f"{path.name} imports {name}" for path in modules(folder)
                 for name in sorted(imported_modules(path))
                 if any(name == f or name.startswith(f + ".") for f in forbidden)]
    assert not offending, offending


def test_evaluation_does_not_import_the_collector() -> None:
    names = imported_modules(ROOT / "twist_models" / "stages" / "evaluation.py")
    assert not any(n.startswith("twist_models.stages.collect") for n in names)


def test_the_check_sees_function_level_imports(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from twist_models.stages import collect\n")
    assert "twist_models.stages.collect" in imported_modules(source)
