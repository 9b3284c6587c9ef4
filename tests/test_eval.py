"""twist-eval: statistics against hand-computed values, scripted agents score what the
environment pays, held-out DR is drawn once per episode, bad inputs are refused."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from tests.conftest import reference_python, run_command
from twist_data.errors import ConfigError
from twist_models.agent import Agent
from twist_models.config import AgentConfig, student_preset, teacher_preset
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline.acting import AgentError, ScriptedAgent, load_agent, reference_agent
from twist_pipeline.evaluation import (
    EvalConfig,
    EvalError,
    agents_setting,
    evaluate,
    run_evaluation,
    summarise,
)
from twist_pipeline.statistics import format_paired, iqm, paired_difference, stratified_bootstrap
from twist_sim.tasks import TaskEnv


def test_iqm_of_known_arrays() -> None:
    assert iqm(np.arange(1, 9)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    assert iqm(np.array([0.0, 10, 10, 10, 10, 10, 10, 1000])) == pytest.approx(10.0)
    assert iqm(np.array([[1, 2, 3, 4], [4, 4, 4, 100]]), axis=1) == pytest.approx([2.5, 4.0])


def test_bootstrap_interval_holds_the_estimate_and_shrinks_with_data() -> None:
    rng = np.random.default_rng(0)
    widths = []
    for n in (10, 100, 1000):
        strata = [rng.normal(0.8, 0.2, n), rng.normal(0.5, 0.3, n)]
        interval = stratified_bootstrap(strata, seed=1)
        assert interval.low <= interval.estimate <= interval.high
        assert interval.estimate == pytest.approx(iqm(np.concatenate(strata)))
        widths.append(interval.high - interval.low)
    assert widths[0] > widths[1] > widths[2]
    assert stratified_bootstrap([np.ones(3), np.ones(3)]).high == 1.0  # no spread, no width


def test_bootstrap_keeps_a_stratum_of_one_score_in_every_resample() -> None:
    # A task run on one seed beside a task run on three: the single score is in every
    # resample, so each resampled pooled IQM is the mean of the middle two of
    # {0.5, three draws from {0.8, 0.9, 1.0}}, between 0.8 and 1.0.
    interval = stratified_bootstrap([np.array([0.5]), np.array([0.8, 0.9, 1.0])], seed=2)
    assert interval.estimate == pytest.approx(0.85)
    assert 0.8 <= interval.low <= 0.85 <= interval.high <= 1.0
    assert interval.high > interval.low


def test_paired_difference_of_known_returns() -> None:
    # Differences 2, 0, 6: mean 8/3, sample variance ((2/3)^2 + (8/3)^2 + (10/3)^2) / 2 = 28/3,
    # standard error sqrt(28/9); the 95% interval is mean ± t(0.975, 2 dof) = 4.302653 s.e.
    paired = paired_difference(np.array([3.0, 5, 10]), np.array([1.0, 5, 4]))
    assert paired.mean == pytest.approx(8 / 3)
    assert paired.standard_error == pytest.approx(np.sqrt(28 / 9))
    assert paired.ci95 == pytest.approx((8 / 3 - 4.302653 * np.sqrt(28 / 9),
                                         8 / 3 + 4.302653 * np.sqrt(28 / 9)), rel=1e-5)
    assert (paired.better, paired.pairs) == (2, 3)  # the tie is not better
    assert format_paired(paired.as_dict()) == "+2.7 ± 1.8 (2/3)"
    single = paired_difference(np.array([1.0]), np.array([4.0]))
    assert (single.mean, single.standard_error, single.ci95) == (-3.0, None, None)
    assert format_paired(single.as_dict()) == "-3.0 (0/1)"
    steady = paired_difference(np.array([2.0, 3.0]), np.array([1.0, 2.0]))
    assert (steady.standard_error, steady.ci95) == (0.0, (1.0, 1.0))
    with pytest.raises(ConfigError, match="got 3 and 2"):
        paired_difference(np.ones(3), np.ones(2))


def test_summary_pairs_every_agent_with_the_named_one_episode_by_episode() -> None:
    # Rows in different orders per agent: pairing must follow (seed, episode), not position.
    rows = [("a", 0, 0, 10.0), ("a", 0, 1, 20.0), ("a", 1, 0, 30.0),
            ("b", 1, 0, 36.0), ("b", 0, 1, 21.0), ("b", 0, 0, 7.0)]
    table = pd.DataFrame([{"agent": a, "kind": "student", "seed": s, "episode": e,
                           "episode_seed": 100 * s + e, "return": r, "steps": 5}
                          for a, s, e, r in rows])
    summary = summarise(table, EvalConfig(task="cartpole-balance"), against="a")
    paired = summary["agents"]["b"]["paired"]
    assert paired["against"] == "a" and paired["pairs"] == 3 and paired["better"] == 2
    assert paired["mean"] == pytest.approx((-3 + 1 + 6) / 3)
    assert "paired" not in summary["agents"]["a"]
    assert "paired" not in summarise(table, EvalConfig(task="cartpole-balance"))["agents"]["b"]


def test_pairing_with_an_agent_not_evaluated_is_refused_before_any_episode(tmp_path) -> None:
    with pytest.raises(EvalError, match="'twist', is not among the agents \\(zero\\)"):
        run_evaluation({"zero": "zero"}, EvalConfig(task="cartpole-balance"), [0],
                       tmp_path / "eval", against="twist")
    assert not (tmp_path / "eval").exists()


def _constant(value: float):
    return lambda step: np.full(1, value, np.float32)


def test_scripted_agent_scores_what_the_environment_pays(gl) -> None:
    config = EvalConfig(task="cartpole-balance", dr="none", episodes=2, max_steps=30)
    results = evaluate(ScriptedAgent(_constant(0.4)), config, seed=5)
    assert [r.episode for r in results] == [0, 1] and all(r.steps == 30 for r in results)
    env = TaskEnv("cartpole-balance", max_steps=30)
    for result in results:
        step, total = env.reset(seed=result.episode_seed), 0.0  # `none`: nominal dynamics
        while not step.is_last:
            step = env.step(np.full(1, 0.4, np.float32))
            total += step.reward
        assert result.episode_return == pytest.approx(total, rel=1e-6)
    assert results[0].episode_return != pytest.approx(results[1].episode_return)


def test_heldout_randomisation_is_drawn_once_per_episode(gl, monkeypatch) -> None:
    from twist_sim.render import DRRenderer

    seen: list[dict[str, np.ndarray]] = []
    original = DRRenderer.render_states  # what every render goes through

    def spy(self, physics, params, *args, **kwargs):
        seen.extend({k: v.copy() for k, v in p.items()} for p in params)
        return original(self, physics, params, *args, **kwargs)

    monkeypatch.setattr(DRRenderer, "render_states", spy)
    config = EvalConfig(task="cartpole-balance", dr="heldout", episodes=2, max_steps=6)
    frames: list[int] = []
    evaluate(ScriptedAgent(_constant(0.0)), config, seed=0,
             record=lambda episode, frame: frames.append(episode))
    assert frames == [0] * 7 + [1] * 7 and len(seen) == 14
    first, second = seen[:7], seen[7:]
    for episode in (first, second):
        for params in episode[1:]:
            for key, value in params.items():
                np.testing.assert_array_equal(value, episode[0][key], err_msg=key)
    assert not np.array_equal(first[0]["colour"], second[0]["colour"])


@pytest.fixture(scope="module")
def agents(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny random teacher and a student bundle built from it, for cartpole-balance."""
    root = tmp_path_factory.mktemp("agents")
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset("tiny", 5, 1))
    teacher_path = save_teacher(root / "teacher.pt", teacher,
                                extra={"collect": {"task": "cartpole-balance"}})
    repeat4 = save_teacher(root / "teacher-repeat4.pt", teacher,
                           extra={"collect": {"task": "cartpole-balance", "action_repeat": 4}})
    from twist_models.student import Student

    student = Student(student_preset("tiny", teacher.config))
    bundle = Agent.from_models(student, teacher, {"task": "cartpole-balance", "image_size": 64,
                                                  "action_repeat": 2})
    other = Agent(AgentConfig(student=student.config,
                              actor_critic=teacher.config.actor_critic), {"task": "cup-catch"})
    return {"teacher": teacher_path, "teacher-repeat4": repeat4,
            "agent": bundle.save(root / "agent.pt"),
            "other": other.save(root / "other.pt")}


def test_oracle_and_student_meet_the_same_episodes(gl, agents, tmp_path) -> None:
    config = EvalConfig(task="cartpole-balance", episodes=2, max_steps=10)
    summary = run_evaluation({"oracle": agents["teacher"], "student": agents["agent"]}, config,
                             [0, 1], tmp_path, videos=1)
    table = pd.read_csv(tmp_path / "episodes.csv")
    assert len(table) == 8
    pairs = table.pivot_table(index=["seed", "episode"], columns="agent", values="episode_seed")
    assert (pairs["oracle"] == pairs["student"]).all()
    assert summary["agents"]["oracle"]["normalised_iqm"] == pytest.approx(
        iqm(table.loc[table.agent == "oracle", "return"] / summary["oracle_mean"]))
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert (tmp_path / "student-seed1-episode0.mp4").stat().st_size > 0
    assert (tmp_path / "returns.png").stat().st_size > 0


def test_bad_inputs_are_refused(gl, agents, tmp_path) -> None:
    with pytest.raises(EvalError, match="trained on 'cup-catch' but the evaluation task is"):
        evaluate(load_agent(agents["other"]), EvalConfig(episodes=1, max_steps=2))

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "twist_cli.eval", *args, "--out",
                               str(tmp_path / "out")], capture_output=True, text=True,
                              timeout=300)

    empty = tmp_path / "no-images"
    empty.mkdir()
    (empty / "notes.txt").write_text("not an image")
    for args, message in (
            (["--agent", str(agents["agent"]), "--episodes", "0"],
             "episodes must lie in [1, 100,000] per seed, got 0"),
            (["--agent", str(agents["other"]), "--task", "cartpole-balance"], "'cup-catch'"),
            (["--agent", str(agents["agent"]), "--backgrounds", str(empty), "--episodes", "1"],
             "no-images"),
            (["--agent", str(tmp_path / "missing.pt")], "does not exist"),
            (["--agent", str(agents["agent"]), "--paired-with", "nobody"],
             "'nobody', is not among the agents"),
            (["--agent", str(agents["agent"]), "--posterior", "median"],
             "unknown --posterior 'median'"),
            (["--agent", str(agents["agent"]), "--dr", "heldout,heldout-camera",
              "--paired-with", "x"], "--paired-with, --video and --save-trajectories take one"),
            (["--agent", str(agents["agent"]), "--dr", "heldout,nowhere", "--episodes", "1"],
             "unknown DR preset 'nowhere'")):
        # The first through a fresh interpreter, as a user runs it; the rest through the same
        # error boundary in this process.
        first = message.startswith("episodes must lie")
        result = (cli(*args) if first else
                  run_command("eval", *args, "--out", str(tmp_path / "out")))
        assert result.returncode == 2, (args, result.stderr)
        assert message in result.stderr and "Traceback" not in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_a_student_reading_its_posterior_mode_or_mean_acts_without_chance(gl, agents) -> None:
    # The tiny random student's posterior is nearly uniform, so sampled latents (and with them
    # the actions) differ between two torch streams; the mode and the mean leave nothing to
    # chance.
    bundle = Agent.load(agents["agent"])
    images = np.random.default_rng(0).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8)

    def actions(posterior: str, seed: int) -> np.ndarray:
        torch.manual_seed(seed)
        state, taken = None, []
        for image in images:
            action, state = bundle.act(image, state, posterior=posterior)
            taken.append(action)
        return np.stack(taken)

    assert not np.array_equal(actions("sample", 0), actions("sample", 1))
    for posterior in ("mode", "mean"):
        np.testing.assert_array_equal(actions(posterior, 0), actions(posterior, 1))
    assert not np.allclose(actions("mode", 0), actions("mean", 0))
    with pytest.raises(ConfigError, match="'median'"):
        bundle.act(images[0], posterior="median")
    with pytest.raises(ConfigError, match="'median'"):
        EvalConfig(posterior="median")
    reads_mean = load_agent(agents["agent"], posterior="mean")
    with pytest.raises(EvalError, match="reads its posterior as 'mean' but the evaluation"):
        evaluate(reads_mean, EvalConfig(episodes=1, max_steps=2))
    evaluate(reads_mean, EvalConfig(episodes=1, max_steps=2, posterior="mean"))


def test_agents_act_at_the_action_repeat_they_were_trained_at(gl, agents, tmp_path) -> None:
    oracle = load_agent(agents["teacher-repeat4"])
    assert oracle.action_repeat == 4
    with pytest.raises(EvalError, match="trained at action repeat 4 but the evaluation uses 2"):
        evaluate(oracle, EvalConfig(episodes=1, max_steps=2))
    with pytest.raises(EvalError, match="different action_repeat"):
        agents_setting({"oracle": oracle, "student": load_agent(agents["agent"])},
                       "action_repeat")
    # The CLI takes the agent's repeat: a whole episode of the task's 1,000 frames is 250
    # agent steps at repeat 4 (500 at the default 2).
    result = run_command("eval", "--agent", str(agents["teacher-repeat4"]), "--episodes", "1",
                         "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert pd.read_csv(tmp_path / "episodes.csv")["steps"].tolist() == [250]


def test_an_evaluation_rerun_scores_exactly_the_same(gl, agents) -> None:
    # The teacher samples its latents; whatever the caller's torch stream, the same episodes
    # must give the same returns.
    oracle, config = load_agent(agents["teacher"]), EvalConfig(episodes=2, max_steps=40)
    torch.manual_seed(0)
    first = [r.episode_return for r in evaluate(oracle, config, seed=3)]
    torch.manual_seed(1)
    state = torch.get_rng_state()
    second = [r.episode_return for r in evaluate(oracle, config, seed=3)]
    assert first == second
    assert torch.equal(torch.get_rng_state(), state)  # the caller's stream is untouched


def test_reference_agents_score_what_their_actions_earn(gl, agents, tmp_path) -> None:
    config = EvalConfig(task="cartpole-balance", dr="none", episodes=2, max_steps=25)
    zero = [r.episode_return for r in evaluate(load_agent("zero", task=config.task), config)]
    assert zero == [r.episode_return for r in evaluate(ScriptedAgent(_constant(0.0)), config)]
    random = load_agent("random", task=config.task)
    first = [r.episode_return for r in evaluate(random, config)]
    assert first == [r.episode_return for r in evaluate(random, config)]  # seeded per episode
    assert first != zero
    with pytest.raises(AgentError, match="'zero' needs a task"):
        load_agent("zero")

    # Beside a trained agent the CLI takes the task from it; reference rows are so marked.
    result = run_command("eval", "--agent", f"oracle={agents['teacher']}", "--agent", "zero",
                         "--agent", "noise=random", "--episodes", "1", "--max-steps", "10",
                         "--paired-with", "zero", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    table = pd.read_csv(tmp_path / "episodes.csv")
    assert dict(zip(table["agent"], table["kind"], strict=True)) == {
        "oracle": "oracle", "zero": "reference", "noise": "reference"}
    returns = dict(zip(table["agent"], table["return"], strict=True))
    summary = json.loads((tmp_path / "summary.json").read_text())["agents"]
    assert summary["noise"]["paired"]["mean"] == pytest.approx(returns["noise"] - returns["zero"])
    assert "paired" not in summary["zero"]
    alone = run_command("eval", "--agent", "zero", "--out", str(tmp_path / "alone"))
    assert alone.returncode == 2 and "pass --task" in alone.stderr, alone.stderr


def test_image_agents_see_the_world_rendered_as_their_data_was(gl, agents, tmp_path,
                                                               monkeypatch) -> None:
    from twist_sim.render import DRRenderer

    made: list[int] = []
    original = DRRenderer.__init__

    def spy(self, *args, supersample: int = 1, **kwargs):
        made.append(supersample)
        original(self, *args, supersample=supersample, **kwargs)

    monkeypatch.setattr(DRRenderer, "__init__", spy)
    bundle = Agent.load(agents["agent"])
    bundle.info["supersample"] = 2  # as twist-distil records a supersampled D
    supersampled = load_agent(bundle.save(tmp_path / "ss2.pt"))
    config = EvalConfig(task="cartpole-balance", episodes=1, max_steps=2)
    evaluate(supersampled, config)
    evaluate(load_agent(agents["agent"]), config)  # a bundle that records none: 1
    evaluate(supersampled, EvalConfig(task="cartpole-balance", episodes=1, max_steps=2,
                                      supersample=1))  # an explicit setting wins
    assert made == [2, 1, 1]
    with pytest.raises(ConfigError, match="supersample must be > 0, got 0"):
        EvalConfig(supersample=0)


def test_an_output_that_is_a_file_is_refused_before_any_episode(tmp_path) -> None:
    afile = tmp_path / "afile.txt"
    afile.write_text("kept")
    with pytest.raises(EvalError, match="exists and is not a folder"):
        run_evaluation({"zero": "zero"}, EvalConfig(task="cartpole-balance", episodes=1,
                                                    max_steps=2), [0], afile)
    assert afile.read_text() == "kept"


def test_probability_of_improvement_by_hand() -> None:
    from twist_pipeline.statistics import probability_of_improvement

    # Pairs: 1>0 (1), 1>2 (0), 2>0 (1), 2=2 (1/2): 2.5 / 4.
    one = probability_of_improvement([np.array([1.0, 2.0])], [np.array([0.0, 2.0])])
    assert one.estimate == pytest.approx(0.625)
    assert one.low <= one.estimate <= one.high
    # Strata count equally: 0.625 and 1.0 (every x above every y) average to 0.8125.
    two = probability_of_improvement([np.array([1.0, 2.0]), np.array([5.0])],
                                     [np.array([0.0, 2.0]), np.array([1.0, 2.0, 3.0])])
    assert two.estimate == pytest.approx(0.8125)
    same = probability_of_improvement([np.arange(10.0)], [np.arange(10.0)])
    assert same.estimate == pytest.approx(0.5) and same.low < 0.5 < same.high
    with pytest.raises(ConfigError, match="strata"):
        probability_of_improvement([np.ones(3)], [np.ones(3), np.ones(2)])


def test_performance_profile_by_hand() -> None:
    from twist_pipeline.statistics import performance_profile

    strata = [np.array([0.1, 0.5, 0.9]), np.array([0.2, 0.8])]
    # At 0.5: 1/3 of the first stratum (0.5 itself is not above) and 1/2 of the second.
    profile = performance_profile(strata, np.array([0.0, 0.5, 1.0]))
    assert profile == pytest.approx([1.0, (1 / 3 + 1 / 2) / 2, 0.0])


def test_statistics_equal_rliables(tmp_path) -> None:
    """The IQM, its stratified bootstrap interval, the probability of improvement and its
    interval, and the performance profile, against rliable's own (Agarwal et al., 2021) on the
    same runs: the estimates to rounding, the intervals to the bootstraps' resampling noise."""
    from twist_pipeline.statistics import performance_profile, probability_of_improvement

    python = reference_python()
    rng = np.random.default_rng(7)
    # 4 tasks far apart, 5 runs each: a bootstrap that pooled the tasks would widen the
    # interval well past the tolerance below.
    x = [rng.normal(0.6 + 0.5 * t, 0.2, 5) for t in range(4)]
    y = [rng.normal(0.5 + 0.5 * t, 0.2, 5) for t in range(4)]
    tau = np.linspace(0, 1.2, 7)
    reps = 2_000
    given = tmp_path / "in.json"
    given.write_text(json.dumps({"x": [a.tolist() for a in x], "y": [b.tolist() for b in y],
                                 "tau": tau.tolist(), "reps": reps}))
    script = Path(__file__).with_name("rliable_reference.py")
    result = subprocess.run([str(python), str(script), str(given), str(tmp_path / "out.json")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    theirs = json.loads((tmp_path / "out.json").read_text())
    assert float(iqm(np.concatenate(x))) == pytest.approx(theirs["iqm"], abs=1e-12)
    interval = stratified_bootstrap(x, resamples=reps)
    assert interval.estimate == pytest.approx(theirs["iqm"], abs=1e-12)
    assert [interval.low, interval.high] == pytest.approx(theirs["iqm_ci"], abs=0.02)
    improvement = probability_of_improvement(x, y, resamples=reps)
    assert improvement.estimate == pytest.approx(theirs["improvement"], abs=1e-12)
    assert [improvement.low, improvement.high] == pytest.approx(theirs["improvement_ci"],
                                                                abs=0.02)
    assert performance_profile(x, tau) == pytest.approx(theirs["profile"], abs=1e-12)


POLICY_MODULE = '''
import numpy as np

def push(observation):
    return np.array([0.5], np.float32)

push.observe = ("state",)
push.task = "cartpole-balance"
'''


def test_an_imported_policy_is_evaluated_like_a_scripted_one(gl, tmp_path, monkeypatch) -> None:
    (tmp_path / "my_policies.py").write_text(POLICY_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    config = EvalConfig(task="cartpole-balance", dr="none", episodes=2, max_steps=15)
    policy = load_agent("my_policies:push")
    assert policy.observe == ("state",) and not policy.uses_images
    assert ([r.episode_return for r in evaluate(policy, config)]
            == [r.episode_return for r in evaluate(ScriptedAgent(_constant(0.5)), config)])
    with pytest.raises(AgentError, match="cannot import module 'no_such_module'"):
        load_agent("no_such_module:push")
    with pytest.raises(AgentError, match="has no 'pull'"):
        load_agent("my_policies:pull")

    # From the CLI (in this process, the module on its path as PYTHONPATH would put it): the
    # task comes from the policy, the name from its attribute.
    result = run_command("eval", "--agent", "my_policies:push", "--episodes", "1",
                         "--max-steps", "5", "--out", str(tmp_path / "e"))
    assert result.returncode == 0, result.stderr
    table = pd.read_csv(tmp_path / "e" / "episodes.csv")
    assert list(table["agent"]) == ["push"] and list(table["kind"]) == ["policy"]
    bad = run_command("eval", "--agent", "my_policies:pull", "--out", str(tmp_path / "f"))
    assert bad.returncode == 2 and "has no 'pull'" in bad.stderr
    assert "Traceback" not in bad.stderr and not (tmp_path / "f").exists()


def test_an_interrupted_evaluation_resumes_to_the_uninterrupted_result(tmp_path) -> None:
    config = EvalConfig(task="cartpole-balance", dr="none", episodes=4, max_steps=15)
    agents = {"random": "random", "zero": "zero"}
    whole = run_evaluation(agents, config, [0, 1], tmp_path / "whole")
    # Stopped after two episodes per seed, the last row cut short by the kill.
    part = tmp_path / "part"
    run_evaluation(agents, dataclasses.replace(config, episodes=2), [0, 1], part)
    with (part / "episodes.csv").open("a") as f:
        f.write("zero,reference,1,2,123")
    with pytest.raises(EvalError, match=r"already holds an evaluation .*pass --resume"):
        run_evaluation(agents, config, [0, 1], part)
    with pytest.raises(EvalError, match="dr was 'none', now 'train'"):
        run_evaluation(agents, dataclasses.replace(config, dr="train"), [0, 1], part,
                       resume=True)
    progress: list[tuple[int, int]] = []
    ran: list[tuple[str, int, int]] = []
    resumed = run_evaluation(agents, config, [0, 1], part, resume=True,
                             on_episode=lambda name, r: ran.append((name, r.seed, r.episode)),
                             on_progress=lambda done, total: progress.append((done, total)))
    assert sorted(ran) == [(a, s, e) for a in ("random", "zero") for s in (0, 1) for e in (2, 3)]
    assert progress[0] == (8, 16) and progress[-1] == (16, 16) and len(progress) == 9
    key = ["agent", "seed", "episode"]
    expected = pd.read_csv(tmp_path / "whole" / "episodes.csv").sort_values(key)
    got = pd.read_csv(part / "episodes.csv").sort_values(key)
    pd.testing.assert_frame_equal(got.reset_index(drop=True), expected.reset_index(drop=True))
    assert resumed == whole


def test_twist_eval_refuses_to_overwrite_an_evaluation_in_one_line(tmp_path) -> None:
    args = ["--agent", "zero", "--task", "cartpole-balance", "--dr", "none", "--episodes", "1",
            "--max-steps", "3", "--out", str(tmp_path)]
    assert run_command("eval", *args).returncode == 0
    before = (tmp_path / "episodes.csv").read_text()
    refused = run_command("eval", *args)
    assert refused.returncode == 2 and refused.stderr.strip() == (
        f"error: {str(tmp_path)!r} already holds an evaluation (episodes.csv); pass --resume "
        "to continue it, or another --out")
    assert (tmp_path / "episodes.csv").read_text() == before
    more = run_command("eval", *args, "--resume", "--episodes", "2")
    assert more.returncode == 0, more.stderr
    assert len(pd.read_csv(tmp_path / "episodes.csv")) == 2


def test_episodes_stepped_together_are_the_episodes_run_alone(gl, agents) -> None:
    config = EvalConfig(task="cartpole-balance", episodes=5, max_steps=12)
    for spec in (agents["teacher"], agents["agent"], "random"):
        agent = (reference_agent(spec, "cartpole-balance") if spec == "random"
                 else load_agent(spec))
        runs = {}
        for batch in (1, 3):  # 3: groups of 3 and 2
            frames: dict[int, list[np.ndarray]] = {}
            calls = {"act": 0}
            act = agent.act

            def counted(step, image, act=act, calls=calls):
                calls["act"] += 1
                return act(step, image)

            agent.act = counted
            results = evaluate(agent, config, seed=1, batch=batch,
                               record=lambda e, f, frames=frames: frames.setdefault(e, [])
                               .append(f))
            del agent.act
            runs[batch] = (results, frames, calls["act"])
        (alone, alone_frames, _), (together, together_frames, lone_calls) = runs[1], runs[3]
        # The same episodes: seeds and lengths exactly; returns and frames up to the rounding
        # of batched matrix products (a batch of 3 rounds differently from 3 of 1).
        assert [(r.episode, r.episode_seed, r.steps) for r in together] == [
            (r.episode, r.episode_seed, r.steps) for r in alone], spec
        assert [r.episode_return for r in together] == pytest.approx(
            [r.episode_return for r in alone], rel=1e-6), spec
        assert len({round(r.episode_return, 3) for r in alone}) > 1  # the episodes differ
        for episode, clip in alone_frames.items():
            difference = np.abs(np.stack(clip).astype(int) - np.stack(together_frames[episode]))
            assert difference.max() <= 1, (spec, episode)
        # The trained agents acted through act_batch; the scripted one, one episode at a time.
        assert (lone_calls == 0) == (spec != "random"), spec


def test_worker_processes_give_the_episodes_of_one_process(gl, agents) -> None:
    """``workers``: the same batch simulated and rendered in 2 processes gives exactly the
    episodes, returns and frames of the same batch in this process (the same policy calls on
    the same inputs, so no rounding may differ)."""
    config = EvalConfig(task="cartpole-balance", episodes=5, max_steps=12)
    agent = load_agent(agents["agent"])
    runs = []
    for workers in (1, 2):
        frames: dict[int, list[np.ndarray]] = {}
        results = evaluate(agent, config, seed=2, batch=3, workers=workers,
                           record=lambda e, f, frames=frames: frames.setdefault(e, []).append(f))
        runs.append(([(r.episode, r.episode_seed, r.steps, r.episode_return) for r in results],
                     frames))
    (local, local_frames), (workers, worker_frames) = runs
    assert workers == local
    assert len({r[3] for r in local}) > 1  # the episodes differ
    assert local_frames.keys() == worker_frames.keys()
    for episode, clip in local_frames.items():
        np.testing.assert_array_equal(np.stack(clip), np.stack(worker_frames[episode]))


def test_environments_made_once_serve_every_seed(gl, agents) -> None:
    """``evaluation_envs`` + ``envs=``: one set of environments used for two seeds in turn
    gives the episodes, returns and frames that fresh environments give each seed."""
    from twist_pipeline.evaluation import evaluation_envs

    config = EvalConfig(task="cartpole-balance", episodes=3, max_steps=10)
    agent = load_agent(agents["agent"])

    def run(seed: int, envs=None) -> tuple[list, list[np.ndarray]]:
        frames: list[np.ndarray] = []
        results = evaluate(agent, config, seed=seed, batch=2, envs=envs,
                           record=lambda e, f: frames.append(f))
        return [(r.episode_seed, r.steps, r.episode_return) for r in results], frames

    fresh = [run(seed) for seed in (0, 1)]
    assert fresh[0][0] != fresh[1][0]  # the seeds' episodes differ
    with evaluation_envs(agent, config, batch=2, record=True) as envs:
        shared = [run(seed, envs) for seed in (0, 1)]
        for (episodes, frames), (again, again_frames) in zip(fresh, shared, strict=True):
            assert again == episodes
            np.testing.assert_array_equal(np.stack(again_frames), np.stack(frames))
        with pytest.raises(ConfigError, match="are not those this evaluation needs"):
            evaluate(agent, dataclasses.replace(config, max_steps=5), envs=envs, batch=2)
        with pytest.raises(ConfigError, match="are not those this evaluation needs"):
            evaluate(agent, config, envs=envs, batch=3)
    with evaluation_envs(reference_agent("zero", "cartpole-balance"), config) as blind:
        assert not blind.render
        with pytest.raises(ConfigError, match="with views"):
            evaluate(agent, config, envs=blind)


def test_environment_workers_report_a_bad_background_folder_as_ours(tmp_path) -> None:
    from twist_sim.errors import BackgroundError
    from twist_sim.randomisation import DRConfig
    from twist_sim.vector_env import EnvWorkers

    dr = DRConfig(background="directory", background_dir=str(tmp_path / "missing"))
    with pytest.raises(BackgroundError):
        EnvWorkers("cartpole-balance", slots=2, workers=2, dr=dr)


def test_saved_trajectories_replay_to_the_same_states_and_rewards(tmp_path) -> None:
    # The saved actions, replayed in a fresh environment from the episode's seed, must give
    # back the saved states and rewards, and the rewards must sum to the reported return.
    from twist_data.seeding import evaluation_episode_seed
    from twist_pipeline.evaluation import TRAJECTORIES, trajectory_name

    config = EvalConfig(task="cartpole-balance", dr="none", episodes=2, max_steps=12)
    run_evaluation({"random": "random", "zero": "zero"}, config, [3], tmp_path,
                   trajectories=True)
    table = pd.read_csv(tmp_path / "episodes.csv")
    assert len(list((tmp_path / TRAJECTORIES).iterdir())) == 4
    for _, row in table.iterrows():
        saved = np.load(tmp_path / TRAJECTORIES / trajectory_name(row.agent, 3, row.episode))
        steps = int(row.steps)
        assert saved["state"].shape == (steps + 1, 5)
        assert saved["action"].shape == (steps, 1) and saved["reward"].shape == (steps,)
        assert saved["reward"].sum() == pytest.approx(row["return"], rel=1e-5)
        env = TaskEnv("cartpole-balance", config.action_repeat, max_steps=12)
        states = [env.reset(seed=evaluation_episode_seed(3, int(row.episode))).state]
        rewards = []
        for action in saved["action"]:
            step = env.step(action)
            states.append(step.state)
            rewards.append(step.reward)
        np.testing.assert_allclose(saved["state"], np.stack(states), atol=1e-6)
        np.testing.assert_allclose(saved["reward"], rewards, atol=1e-6)
    assert not table.loc[table.agent == "random", "return"].eq(
        table.loc[table.agent == "zero", "return"].to_numpy()).all()
