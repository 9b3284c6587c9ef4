"""The run lifecycle every stage shares (RunFolder): a folder with a run is refused unless
resumed, a resumed run whose config changed is refused naming both values, and the stored
config round-trips; a run recorded by earlier code resumes and evaluates as it did."""

import dataclasses
import json
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twist_data.errors import TwistError
from twist_data.reader import open_dataset
from twist_data.verify import verify_dataset
from twist_pipeline.collect import collect, stored_config
from twist_pipeline.evaluation import EvalConfig, run_evaluation
from twist_pipeline.runlog import RunFolder


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



#: A tiny collection (cartpole-balance, `tiny` preset, 200 frames, 1 view of 16 px) as the code
#: wrote it before its stages moved from ``twist_models.stages`` into ``twist_pipeline``, with
#: the returns that code's ``twist-eval`` gave its teacher (``episodes-recorded.csv``: ``--agent
#: oracle=…/latest.pt --agent zero --dr heldout --episodes 2``).
RECORDED_RUN = Path(__file__).parent / "data" / "tiny-collection-run.tar.gz"


def test_a_run_recorded_before_the_pipeline_moved_resumes_and_evaluates(tmp_path: Path) -> None:
    with tarfile.open(RECORDED_RUN) as archive:
        archive.extractall(tmp_path, filter="data")
    dataset = tmp_path / "dataset"
    run = dataset / "collect" / "collect-000"
    recorded = pd.read_csv(tmp_path / "episodes-recorded.csv")
    config = stored_config(dataset, "collect-000")
    assert (config.task, config.frames, config.views) == ("cartpole-balance", 200, 1)

    # Its teacher evaluates as it did: the same episodes, the same returns.
    run_evaluation({"oracle": run / "latest.pt", "zero": "zero"},
                   EvalConfig(task="cartpole-balance", dr="heldout", episodes=2), seeds=[0],
                   out=tmp_path / "eval")
    evaluated = pd.read_csv(tmp_path / "eval" / "episodes.csv")
    assert list(evaluated["agent"]) == list(recorded["agent"])
    assert list(evaluated["episode_seed"]) == list(recorded["episode_seed"])
    np.testing.assert_allclose(evaluated["return"], recorded["return"], rtol=1e-3)

    # And its collection resumes where it stopped, keeping its episodes and evaluations.
    episodes = open_dataset(dataset).n_episodes
    evaluations = pd.read_csv(run / "eval.csv")
    resumed = collect(dataset, dataclasses.replace(config, frames=400), resume=True)
    assert resumed.frames == 400 and verify_dataset(dataset).ok
    assert open_dataset(dataset).n_episodes == episodes * 2
    after = pd.read_csv(run / "eval.csv")
    assert len(after) > len(evaluations)
    pd.testing.assert_frame_equal(after.iloc[:len(evaluations)], evaluations)
