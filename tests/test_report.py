"""The reproduction report: statistics of Table I against hand-computed values, the whole
pipeline at the tiny scale (every agent trained as its column says), resumption without
repeated work, and the CLI's refusals."""

from __future__ import annotations

import dataclasses
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twist_data.errors import ConfigError
from twist_data.reader import open_dataset
from twist_models.config import json_leaves, to_json
from twist_pipeline.report import (
    AGENTS,
    EPISODE_RESULT_COLUMNS,
    RESULT_COLUMNS,
    ReportConfig,
    ReportError,
    aggregate,
    build_report,
    markdown_table,
    paired_with,
    plot_iqm,
    run_reproduction,
    run_scores,
)
from twist_sim.errors import UnknownTaskError


def _results(scores: dict[tuple[str, str], list[float]]) -> pd.DataFrame:
    rows = [(task, seed, agent, score, 10) for (task, agent), values in scores.items()
            for seed, score in enumerate(values)]
    return pd.DataFrame(rows, columns=RESULT_COLUMNS)


def test_table_statistics_match_hand_computed_values() -> None:
    results = _results({
        ("cartpole-balance", "oracle"): [900.0, 1000.0, 1100.0],  # mean 1000
        ("cartpole-balance", "twist"): [800.0, 900.0, 1000.0],
        ("cup-catch", "oracle"): [500.0, 500.0, 500.0],
        ("cup-catch", "twist"): [100.0, 400.0, 500.0],
    })
    summary = aggregate(results)
    twist = summary["per_task"]["cartpole-balance"]["twist"]
    assert twist["mean"] == pytest.approx(900.0)
    assert twist["std"] == pytest.approx(np.sqrt(20000 / 3))  # population std over seeds
    # Normalised run scores: 0.8, 0.9, 1.0 (cartpole) and 0.2, 0.8, 1.0 (cup); the IQM of six
    # trims one from each end: mean(0.8, 0.8, 0.9, 1.0) = 0.875.
    iqm = summary["normalised_iqm"]["twist"]
    assert iqm["iqm"] == pytest.approx(0.875)
    assert iqm["ci95"][0] <= 0.875 <= iqm["ci95"][1]
    assert iqm["runs"] == 6 and iqm["tasks"] == 2
    # The oracle normalised by its own task mean: 0.9, 1.0, 1.1, 1, 1, 1 -> IQM 1.
    assert summary["normalised_iqm"]["oracle"]["iqm"] == pytest.approx(1.0)
    # P(TWIST run > oracle run), per task over the 3 x 3 pairs, ties half: cartpole 0.8, 0.9,
    # 1.0 against 0.9, 1.0, 1.1 -> 0.9 ties once (.5), 1.0 beats 0.9 and ties 1.0 (1.5): 2/9;
    # cup 0.2, 0.8, 1.0 against 1, 1, 1 -> three ties of 1.0: 1.5/9. Mean: 3.5/18.
    improvement = summary["improvement"]["oracle"]
    assert improvement["probability"] == pytest.approx(3.5 / 18)
    assert improvement["tasks"] == 2 and "twist" not in summary["improvement"]

    table = markdown_table(summary)
    assert "| cartpole-balance (ours) | 1000.0 ± 81.6 | 900.0 ± 81.6 |" in table
    assert "| cartpole-balance (paper, `paper` scale) | 992.9 | 954.5 |" in table
    assert "| TWIST | 0.875 [" in table
    assert "| Oracle (teacher on states) | 0.19 [" in table


def test_agents_are_paired_with_twist_episode_by_episode_within_each_task() -> None:
    # cartpole: TWIST scores 100, 200 on seed 0's episodes 0, 1 and 300 on seed 1's episode 0;
    # Dreamer 90, 230, 280, so its differences are -10, +30, -20. cup-catch has no TWIST run.
    rows = [("cartpole-balance", 0, "twist", 0, 100.0), ("cartpole-balance", 0, "twist", 1, 200.0),
            ("cartpole-balance", 1, "twist", 0, 300.0), ("cartpole-balance", 1, "dreamer-dr", 0, 280.0),
            ("cartpole-balance", 0, "dreamer-dr", 1, 230.0), ("cartpole-balance", 0, "dreamer-dr", 0, 90.0),
            ("cup-catch", 0, "dreamer-dr", 0, 5.0)]
    episodes = pd.DataFrame(rows, columns=EPISODE_RESULT_COLUMNS)
    paired = paired_with(episodes)
    assert set(paired) == {"cartpole-balance"}
    dreamer = paired["cartpole-balance"]["dreamer-dr"]
    assert dreamer["mean"] == pytest.approx(0.0) and (dreamer["better"], dreamer["pairs"]) == (1, 3)
    # sample std of (-10, 30, -20) is sqrt(700), so the standard error is sqrt(700 / 3)
    assert dreamer["standard_error"] == pytest.approx(np.sqrt(700 / 3))
    scores = run_scores(episodes)
    twist = scores[(scores.agent == "twist") & (scores.seed == 0)]
    assert float(twist["score"].iloc[0]) == 150.0 and int(twist["episodes"].iloc[0]) == 2

    summary = aggregate(scores[scores.task == "cartpole-balance"].assign(
        agent=lambda d: d.agent.replace({"dreamer-dr": "oracle"})))
    summary["paired"] = {"cartpole-balance": {"oracle": dreamer}}
    table = markdown_table(summary)
    # t(0.975, 2 dof) = 4.302653, times the standard error: 65.7
    assert ("| cartpole-balance | Oracle (teacher on states) | +0.0 ± 15.3 (1/3) "
            "| [-65.7, +65.7] |") in table


def test_aggregate_refuses_a_task_without_oracle() -> None:
    with pytest.raises(ReportError, match="'cup-catch' has no oracle"):
        aggregate(_results({("cup-catch", "twist"): [1.0]}))
    with pytest.raises(ReportError, match="no evaluation results"):
        aggregate(pd.DataFrame(columns=RESULT_COLUMNS))


def test_a_task_whose_oracle_scored_zero_keeps_raw_scores_but_leaves_the_iqm(
        tmp_path: Path) -> None:
    results = _results({
        ("cartpole-balance", "oracle"): [800.0, 1000.0],  # mean 900
        ("cartpole-balance", "twist"): [450.0, 900.0],     # normalised 0.5, 1.0
        ("cup-catch", "oracle"): [0.0, 0.0],               # a teacher that never caught
        ("cup-catch", "twist"): [20.0, 40.0],
    })
    summary = aggregate(results)
    assert summary["unnormalised_tasks"] == ["cup-catch"]
    assert summary["per_task"]["cup-catch"]["twist"]["mean"] == pytest.approx(30.0)
    twist = summary["normalised_iqm"]["twist"]
    # Only cartpole's two runs: the IQM of two values trims nothing, mean(0.5, 1.0).
    assert twist["runs"] == 2 and twist["tasks"] == 1
    assert twist["iqm"] == pytest.approx(0.75)
    assert np.isfinite(twist["ci95"]).all()
    table = markdown_table(summary)
    assert "| cup-catch (ours) | 0.0 ± 0.0 | 30.0 ± 10.0 |" in table
    assert "oracle's mean score is not positive: cup-catch." in table

    # With no task normalisable there is no IQM row, and the plot still gets written.
    only_cup = aggregate(results[results["task"] == "cup-catch"])
    assert only_cup["normalised_iqm"] == {}
    assert "| TWIST | " not in markdown_table(only_cup)
    assert plot_iqm(only_cup, tmp_path / "iqm.png").stat().st_size > 0


def test_config_names_the_bad_value() -> None:
    with pytest.raises(UnknownTaskError, match="'walker-fly'"):
        ReportConfig(tasks=("walker-fly",))
    with pytest.raises(ConfigError, match="unknown agent 'sac'"):
        ReportConfig(agents=("twist", "sac"))
    with pytest.raises(ConfigError, match="eval_episodes must be > 0, got 0"):
        ReportConfig(eval_episodes=0)
    assert ReportConfig(agents=("twist",)).agents == ("oracle", "twist")


def test_frames_override_sets_how_long_the_teacher_learns() -> None:
    quick = ReportConfig(preset="quick").collect_config("cup-catch", 2)
    assert (quick.task, quick.seed, quick.frames) == ("cup-catch", 2, 300_000)
    longer = ReportConfig(preset="quick", frames=200_000).collect_config("cup-catch", 0)
    assert (longer.learn_frames, longer.frames) == (200_000, 300_000)
    beyond = ReportConfig(preset="quick", frames=400_000).collect_config("cup-catch", 0)
    assert (beyond.learn_frames, beyond.frames) == (400_000, 400_000)
    tiny = ReportConfig(preset="tiny", frames=300).collect_config("cartpole-balance", 0)
    assert (tiny.learn_frames, tiny.frames) == (None, 300)


def test_tiny_pipeline_trains_every_column_and_resumes_without_repeating(tmp_path: Path) -> None:
    config = ReportConfig(tasks=("cartpole-balance",), seeds=(3,), preset="tiny",
                          eval_episodes=1, eval_max_steps=10)
    first = run_reproduction(tmp_path, dataclasses.replace(config, agents=("twist",),
                                                           factor_drs=("heldout-light",)))
    assert set(first["per_task"]["cartpole-balance"]) == {"oracle", "twist"}
    root = tmp_path / "cartpole-balance" / "seed-3"
    # Every agent also met the same episode under the factor preset.
    lit = pd.read_csv(root / "eval-heldout-light" / "episodes.csv")
    base = pd.read_csv(root / "eval" / "episodes.csv")
    assert sorted(lit["agent"]) == ["oracle", "twist"]
    assert list(lit["episode_seed"]) == list(base["episode_seed"])
    assert {(f["agent"], f["dr"]) for f in first["factors"]} == {
        (a, d) for a in ("oracle", "twist") for d in ("heldout", "heldout-light")}
    assert "| cartpole-balance | TWIST | " in (tmp_path / "report.md").read_text()
    twist_stamp = (root / "twist" / "agent.pt").stat().st_mtime_ns
    summary = run_reproduction(tmp_path, config)  # the other columns join the same runs
    assert (root / "twist" / "agent.pt").stat().st_mtime_ns == twist_stamp
    assert set(summary["per_task"]["cartpole-balance"]) == set(AGENTS)

    # Each column is the run its heading names.
    def stored(name: str) -> dict:
        return json.loads((root / name / "config.json").read_text())

    assert stored("twist")["distil"]["imagined"] and stored("twist")["distil"]["seed"] == 3
    assert stored("twist")["distil"]["copy_dynamics"]
    assert not stored("twist-scratch")["distil"]["copy_dynamics"]
    assert not stored("twist-no-imagined")["distil"]["imagined"]
    assert stored("twist-no-noise")["distil"]["action_noise"] == 0.0
    assert stored("twist")["distil"]["weights"]["action"] == 0.0
    assert stored("twist-action")["distil"]["weights"]["action"] > 0.0
    assert stored("twist")["distil"]["recipe"] == "paper"
    dense = stored("twist-dense")["distil"]
    assert dense["recipe"] == "dense" and dense["frame_steps"] > 0
    assert dense["weights"]["state"] > 0 and dense["weights"]["frame_post"] > 0
    for name, field, off in (("twist-dense-no-stage", "frame_steps", 0),
                             ("twist-dense-no-state", "weights.state", 0.0),
                             ("twist-dense-no-frame-kl", "weights.frame_post", 0.0),
                             ("twist-dense-no-norm", "encoder_norm", "none")):
        ablated = json_leaves(stored(name)["distil"])
        assert ablated[field] == off and ablated["recipe"] == "dense"
        assert {k: v for k, v in ablated.items() if k != field} == {
            k: v for k, v in json_leaves(dense).items() if k != field}
    student_steps = stored("twist")["distil"]["steps"]
    readout = stored("twist-readout")["distil"]
    assert readout["recipe"] == "readout" and readout["readout"] and readout["frame_steps"] > 0
    assert readout["steps"] == 0
    for name, changed in (("twist-readout-eq34", {"steps": student_steps}),
                          ("twist-readout-no-stage", {"frame_steps": 0, "steps": student_steps}),
                          ("twist-readout-no-norm", {"encoder_norm": "none"}),
                          ("twist-readout-no-mirror", {"readout_stage.mirror": "none"}),
                          ("twist-readout-no-lean", {"readout_stage.lean": 1.0})):
        ablated = json_leaves(stored(name)["distil"])
        assert ablated["recipe"] == "readout"
        assert ablated == {**json_leaves(readout), **changed}, name
    for name, kind in (("dreamer-dr", "dreamer"), ("dreamer-no-dr", "dreamer"),
                       ("state-recon", "state-recon")):
        baseline = stored(name)["baseline"]
        assert (baseline["kind"], baseline["steps"]) == (kind, student_steps)
    clean = open_dataset(root / "dataset-clean")
    source = open_dataset(root / "dataset")
    assert clean.spec.views == 1 and clean.n_episodes == source.n_episodes
    np.testing.assert_array_equal(clean.episode(0).action, source.episode(0).action)

    # The table's figures are the evaluation's.
    episodes = pd.read_csv(root / "eval" / "episodes.csv")
    oracle = episodes.loc[episodes["agent"] == "oracle", "return"].mean()
    assert summary["per_task"]["cartpole-balance"]["oracle"]["mean"] == pytest.approx(oracle)
    assert (tmp_path / "iqm.png").stat().st_size > 0
    assert (tmp_path / "profiles.png").stat().st_size > 0
    assert "TWIST w/o action noise" in (tmp_path / "report.md").read_text()
    twist_return = episodes.loc[episodes["agent"] == "twist", "return"].iloc[0]
    paired_oracle = summary["paired"]["cartpole-balance"]["oracle"]
    assert paired_oracle["mean"] == pytest.approx(oracle - twist_return)
    assert paired_oracle["pairs"] == 1 and paired_oracle["standard_error"] is None

    # A second run finds every stage done and only re-aggregates.
    stamps = {p: p.stat().st_mtime_ns for p in root.rglob("*.pt")}
    stamps[root / "eval" / "episodes.csv"] = (root / "eval" / "episodes.csv").stat().st_mtime_ns
    assert run_reproduction(tmp_path, config) == summary
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert build_report(tmp_path, config) == summary


def test_the_factor_table_pools_each_tasks_seeds_and_pairs_within_them(tmp_path: Path) -> None:
    # Two seeds of one task: twist loses 100 and 300 under the moved camera on the same
    # episodes; the oracle loses nothing.
    returns = {("heldout", 0): {"oracle": [900, 910], "twist": [800, 600]},
               ("heldout", 1): {"oracle": [920, 930], "twist": [700, 900]},
               ("heldout-camera", 0): {"oracle": [900, 910], "twist": [700, 300]},
               ("heldout-camera", 1): {"oracle": [920, 930], "twist": [600, 800]}}
    for (dr, seed), by_agent in returns.items():
        folder = tmp_path / "cartpole-balance" / f"seed-{seed}" / (
            "eval" if dr == "heldout" else f"eval-{dr}")
        folder.mkdir(parents=True)
        pd.DataFrame([{"agent": agent, "kind": "student", "seed": seed, "episode": e,
                       "episode_seed": 100 * seed + e, "return": r, "steps": 10}
                      for agent, values in by_agent.items() for e, r in enumerate(values)]
                     ).to_csv(folder / "episodes.csv", index=False)
    config = ReportConfig(tasks=("cartpole-balance",), seeds=(0, 1), eval_episodes=2,
                          factor_drs=("heldout-camera",))
    summary = build_report(tmp_path, config)
    factors = pd.read_csv(tmp_path / "factors.csv").set_index(["agent", "dr"])
    twist = factors.loc[("twist", "heldout-camera")]
    differences = [-100, -300, -100, -100]
    assert twist["paired"] == pytest.approx(np.mean(differences))
    assert twist["paired_sem"] == pytest.approx(np.std(differences, ddof=1) / 2)
    assert twist["ratio"] == pytest.approx(2400 / 3000) and twist["episodes"] == 4
    assert factors.loc[("oracle", "heldout-camera"), "paired"] == 0.0
    assert len(summary["factors"]) == 4
    assert "| cartpole-balance | TWIST | 750.0 | 600.0: 0.80, -150.0 ± 50.0 (0/4) |" in (
        tmp_path / "report.md").read_text()
    with pytest.raises(ConfigError, match="must differ from the others and from eval_dr"):
        ReportConfig(factor_drs=("heldout-camera", "heldout"))
    with pytest.raises(ConfigError, match="unknown DR preset 'tilted'"):
        ReportConfig(factor_drs=("tilted",))


def test_cli_refuses_bad_input_without_traceback(tmp_path: Path) -> None:
    # One subprocess (the others' errors are library errors tested above): the CLI's error
    # boundary turns them into one line and exit code 2.
    result = subprocess.run([sys.executable, "-m", "twist_cli.report", "--out", str(tmp_path),
                             "--seeds", "0,x"], capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert "--seeds must be a comma-separated list, got '0,x'" in result.stderr
    assert "Traceback" not in result.stderr and not any(tmp_path.iterdir())


def test_every_student_column_is_an_agent_with_a_valid_recipe() -> None:
    from twist_models.distillation import DISTIL_PRESETS, distil_preset
    from twist_pipeline.report import AGENTS, STUDENT_VARIANTS

    assert set(STUDENT_VARIANTS) <= set(AGENTS)
    for name, (recipe, changes) in STUDENT_VARIANTS.items():
        # The report gives every column the preset's window updates unless it says otherwise.
        base = distil_preset("tiny", recipe, steps=DISTIL_PRESETS["tiny"].steps)
        config = distil_preset("tiny", recipe, **{"steps": base.steps, **changes})
        # Each ablation changes exactly what it names, and changes something.
        now, before = json_leaves(to_json(config)), json_leaves(to_json(base))
        assert {k for k in changes if now[k] != before[k]} == set(changes), name


def test_an_out_that_is_a_file_is_refused_before_any_stage_logs(tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture
                                                                ) -> None:
    from twist_pipeline.report import ReportConfig, run_reproduction

    target = tmp_path / "report.md"
    target.write_text("mine")
    with caplog.at_level(logging.INFO), pytest.raises(ConfigError, match=r"report folder "
                                                      r".*report\.md' is a file; name a folder"):
        run_reproduction(target, ReportConfig(tasks=("cartpole-balance",), seeds=(0,)))
    assert not caplog.records and target.read_text() == "mine"
    assert [p.name for p in tmp_path.iterdir()] == ["report.md"]
