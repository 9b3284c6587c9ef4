"""The run lifecycle every stage shares (RunFolder): a folder with a run is refused unless
resumed, a resumed run whose config changed is refused naming both values, and the stored
config round-trips."""

import json
from dataclasses import dataclass
from pathlib import Path

import pytest

from twist_data.errors import TwistError
from twist_models.stages.runlog import RunFolder


class StageError(TwistError):
    pass


@dataclass(frozen=True)
class Settings:
    steps: int = 10
    lr: float = 1e-3


def test_lifecycle(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path / "a" / "run", "stage", StageError, "a stage run")
    folder.open(Settings(), resume=False, may_change=("steps",))
    assert folder.path.is_dir() and folder.stored() is None
    folder.write_config(Settings(steps=20), dataset=tmp_path / "d", other=Settings(lr=2.0))
    stored = json.loads((folder.path / "config.json").read_text())
    assert stored == {"stage": {"steps": 20, "lr": 1e-3}, "dataset": str(tmp_path / "d"),
                      "other": {"steps": 10, "lr": 2.0}}
    assert not list(folder.path.glob("*.partial"))
    with pytest.raises(StageError, match="already holds a stage run; pass --resume"):
        folder.open(Settings(steps=20), resume=False, may_change=("steps",))
    folder.open(Settings(steps=99), resume=True, may_change=("steps",))  # steps may change
    with pytest.raises(StageError, match=r"lr was 0\.001, now 0\.5.*only --steps may change"):
        folder.open(Settings(steps=20, lr=0.5), resume=True, may_change=("steps",))
    with pytest.raises(StageError, match="the sizes differ"):
        folder.open(Settings(steps=20), resume=True, may_change=("steps",),
                    also=["the sizes differ"])


def test_a_file_in_the_folders_place_is_refused(tmp_path: Path) -> None:
    (tmp_path / "run").write_text("not a folder")
    with pytest.raises(StageError, match="exists and is not a folder"):
        RunFolder(tmp_path / "run", "stage", StageError, "a run").open(Settings(), False, ())
    assert (tmp_path / "run").read_text() == "not a folder"
