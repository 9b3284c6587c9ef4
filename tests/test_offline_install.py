"""The offline install's pieces: the dependency check that names what a --no-deps install left
out, and the slimming of a bundled wheel."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

from tests.conftest import load_script

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def fake_distribution(site: Path, name: str, requires: list[str]) -> None:
    info = site / f"{name}-1.0.dist-info"
    info.mkdir(parents=True)
    lines = ["Metadata-Version: 2.1", f"Name: {name}", "Version: 1.0",
             *(f"Requires-Dist: {r}" for r in requires)]
    (info / "METADATA").write_text("\n".join(lines) + "\n")


def test_the_check_names_a_missing_package_and_a_rejected_version_only(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    check = load_script(SCRIPTS / "check_requirements.py")
    fake_distribution(tmp_path, "needy", [
        "numpy<1", "absent-package>=2", "needy-dependency",
        "dev-only-package; extra == 'dev'", "windows-only-package; sys_platform == 'win32'"])
    # A dependency's own requirements are followed too.
    fake_distribution(tmp_path, "needy_dependency", ["another-absent-package"])
    monkeypatch.syspath_prepend(str(tmp_path))
    numpy = metadata.version("numpy")
    assert sorted(check.unmet_requirements("needy")) == sorted([
        f"needy: numpy<1 ({numpy} installed)",
        "needy: absent-package>=2 (not installed)",
        "needy-dependency: another-absent-package (not installed)"])
    assert check.main(["check", "needy"]) == 1


def test_the_installed_package_has_everything_it_needs() -> None:
    run = subprocess.run([sys.executable, str(SCRIPTS / "check_requirements.py")],
                         capture_output=True, text=True)
    assert (run.returncode, run.stdout.strip()) == (0, "ok"), run.stdout


def test_a_slimmed_wheel_loses_the_unused_folders_and_their_record_lines(tmp_path: Path) -> None:
    bundle = load_script(SCRIPTS / "offline_bundle.py")
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    kept = {"pkg/__init__.py": b"x = 1\n", "pkg/suite/cartpole.xml": b"<mujoco/>"}
    dropped = {"pkg/locomotion/a.py": b"", "pkg/suite/dog_assets/mesh.stl": b"\0" * 100}
    record = "".join(f"{name},,\n" for name in [*kept, *dropped, "pkg-1.0.dist-info/RECORD"])
    with zipfile.ZipFile(wheel, "w") as archive:
        for name, data in {**kept, **dropped}.items():
            archive.writestr(name, data)
        archive.writestr("pkg-1.0.dist-info/RECORD", record)
    assert bundle.slim_wheel(wheel, ("pkg/locomotion/", "pkg/suite/dog_assets/")) == 2
    with zipfile.ZipFile(wheel) as archive:
        assert sorted(archive.namelist()) == sorted([*kept, "pkg-1.0.dist-info/RECORD"])
        assert {name: archive.read(name) for name in kept} == kept
        assert archive.read("pkg-1.0.dist-info/RECORD").decode().splitlines() == [
            f"{name},," for name in [*kept, "pkg-1.0.dist-info/RECORD"]]
