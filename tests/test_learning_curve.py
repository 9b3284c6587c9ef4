"""twist-eval --snapshots: a distillation run's learning curve, every snapshot, the teacher and
the zero floor on the same held-out episodes, checked against independent evaluations."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import run_command
from twist_models.distillation import distil_preset
from twist_pipeline.distil import distil
from twist_pipeline.evaluation import EvalConfig, run_evaluation
from twist_pipeline.learning_curve import CurveError, evaluate_snapshots, snapshots

CONFIG = EvalConfig(task="cartpole-balance", episodes=2, max_steps=15)


@pytest.fixture(scope="module")
def run(collected_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("curve") / "student"
    distil(collected_tiny, out, distil_preset("tiny", steps=8, snapshot_every=4))
    return out


def test_the_curve_holds_each_snapshot_and_the_references_as_evaluated_alone(
        run: Path, tmp_path: Path) -> None:
    curve = evaluate_snapshots(run, CONFIG, tmp_path / "curve", batch=2, agreement_episodes=0)
    assert list(curve["agent"]) == ["oracle", "zero", "u00000004", "u00000008"]
    students = curve.set_index("agent").loc[["u00000004", "u00000008"]]
    assert list(students["updates"]) == [4, 8] and list(students["progress"]) == [4, 8]
    # Each row equals an evaluation of that agent alone on the same episodes: the zero
    # floor's return is a fixed policy's, known without any model.
    alone = run_evaluation({"zero": "zero", "snapshot": run / "agent-00000004.pt"}, CONFIG,
                           [0], tmp_path / "alone", batch=2)["agents"]
    by_agent = curve.set_index("agent")["mean"]
    assert by_agent["zero"] == pytest.approx(alone["zero"]["mean"])
    assert by_agent["u00000004"] == pytest.approx(alone["snapshot"]["mean"])
    episodes = pd.read_csv(tmp_path / "curve" / "episodes.csv")
    paired = (episodes[episodes.agent == "u00000008"]["return"].to_numpy()
              - episodes[episodes.agent == "oracle"]["return"].to_numpy())
    assert students.loc["u00000008", "paired_vs_oracle"] == pytest.approx(paired.mean())
    assert pd.read_csv(tmp_path / "curve" / "curve.csv").equals(curve)
    assert (tmp_path / "curve" / "curve.png").stat().st_size > 0


def test_closed_loop_agreement_is_measured_once_per_snapshot(run: Path, tmp_path: Path) -> None:
    curve = evaluate_snapshots(run, CONFIG, tmp_path / "curve", agreement_episodes=2)
    students = curve.set_index("agent").loc[["u00000004", "u00000008"]]
    assert students["closed_loop_h_explained"].le(1.0).all()
    assert students["closed_loop_action_corr"].between(-1.0, 1.0).all()
    assert curve.set_index("agent").loc[["oracle", "zero"], "closed_loop_h_explained"].isna().all()
    kept = pd.read_csv(tmp_path / "curve" / "agreement.csv")
    assert list(kept["agent"]) == ["u00000004", "u00000008"] and (kept["episodes"] == 2).all()
    # Seeded by the evaluation's episodes: measured again, the same figures.
    from twist_pipeline.acting import load_agent
    from twist_pipeline.learning_curve import closed_loop_agreement, run_teacher

    again = closed_loop_agreement(load_agent(run / "agent-00000008.pt"),
                                  load_agent(run_teacher(run)), CONFIG, 2)
    assert again["closed_loop_h_explained"] == pytest.approx(
        students.loc["u00000008", "closed_loop_h_explained"])
    # Resumed, the kept figures are read, not measured again.
    kept.loc[0, "closed_loop_h_explained"] = -123.0
    kept.to_csv(tmp_path / "curve" / "agreement.csv", index=False)
    resumed = evaluate_snapshots(run, CONFIG, tmp_path / "curve", resume=True,
                                 agreement_episodes=2)
    assert resumed.set_index("agent").loc["u00000004", "closed_loop_h_explained"] == -123.0


def test_a_resumed_curve_evaluates_only_new_snapshots(run: Path, collected_tiny: Path,
                                                      tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "student"
    shutil.copytree(run, copy)
    evaluate_snapshots(copy, CONFIG, tmp_path / "curve", agreement_episodes=0)
    before = pd.read_csv(tmp_path / "curve" / "episodes.csv")
    distil(collected_tiny, copy, distil_preset("tiny", steps=12, snapshot_every=4), resume=True)
    curve = evaluate_snapshots(copy, CONFIG, tmp_path / "curve", resume=True,
                               agreement_episodes=0)
    after = pd.read_csv(tmp_path / "curve" / "episodes.csv")
    assert list(curve["agent"])[-1] == "u00000012"
    assert len(after) == len(before) + 2 and after.iloc[:len(before)].equals(before)


def test_a_run_without_snapshots_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(CurveError, match="holds no agent snapshot"):
        snapshots(tmp_path)
    result = run_command("eval", "--snapshots", str(tmp_path), "--out", str(tmp_path / "curve"))
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "holds no agent snapshot" in result.stderr and not (tmp_path / "curve").exists()
