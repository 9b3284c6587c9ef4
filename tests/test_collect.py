"""twist-collect: an online teacher run writes a verified dataset, survives SIGKILL, refuses
bad output folders. Every run uses the ``tiny`` preset (seconds, learns nothing)."""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch
import zarr

from tests.conftest import board_events, run_command
from twist_data.errors import ConfigError
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.schema import ATTRS_KEY
from twist_data.seeding import derived_seed
from twist_data.verify import verify_dataset
from twist_data.writer import ShardWriter
from twist_models.checkpoint import read_checkpoint
from twist_models.config import teacher_preset
from twist_models.teacher import BEST_TEACHER, FINAL_TEACHER, Teacher, find_teacher, load_teacher
from twist_pipeline.acting import RandomPushes, load_agent
from twist_pipeline.collect import (
    COLLECT_PRESETS,
    CollectConfig,
    CollectError,
    CollectSummary,
    TeacherEvalConfig,
    collect_preset,
    shard_seed,
)
from twist_pipeline.collect import collect as collect_default
from twist_pipeline.runlog import recorded_config
from twist_sim import tasks
from twist_sim.errors import UnknownTaskError
from twist_sim.randomisation import Dynamics
from twist_sim.tasks import TaskEnv

pytestmark = pytest.mark.usefixtures("gl")
COLLECT = [sys.executable, "-m", "twist_cli.collect"]


def collect(out: Path, config: CollectConfig, **kwargs: Any) -> CollectSummary:
    """:func:`twist_pipeline.collect.collect` rendering in this process: the same pixels as the
    default render process (tests/test_render.py), without starting an interpreter for each
    run; the tests that run the command (and the first below) keep the render process."""
    return collect_default(out, config, **{"render_process": False, **kwargs})


def _resimulate(task: str, dataset, index: int) -> tuple[np.ndarray, np.ndarray]:
    """States and physics of episode ``index`` re-simulated from its seed, dynamics and actions."""
    info, episode = dataset.episode_info(index), dataset.episode(index)
    env = TaskEnv(task, action_repeat=dataset.spec.action_repeat, max_steps=len(episode) - 1)
    dynamics = Dynamics(friction_scale=float(info.dr["friction_scale"]),
                        mass_scale=float(info.dr["mass_scale"]))
    steps = [env.reset(seed=info.seed, dynamics=dynamics)]
    steps += [env.step(a) for a in episode.action[1:]]
    return np.stack([s.state for s in steps]), np.stack([s.physics for s in steps])


def test_tiny_run_writes_a_verified_dataset_that_resimulates(tmp_path: Path) -> None:
    config = collect_preset("tiny")
    summary = collect_default(tmp_path, config)
    assert summary.frames >= config.frames and summary.episodes == summary.frames // 100
    assert verify_dataset(tmp_path).ok
    dataset = open_dataset(tmp_path)
    assert dataset.spec.views == 2 and dataset.spec.task == config.task
    seed = shard_seed(config.seed, "collect-000")
    for index in range(dataset.n_episodes):
        info = dataset.episode_info(index)
        assert info.seed == derived_seed(seed, index)  # one episode per index: none lost
        assert info.env_step == index * 100
        # Prefill (100 frames = the first episode) is random; then the teacher acts.
        assert (info.policy, info.teacher_step >= 0) == (
            ("random", False) if index == 0 else ("teacher", True))
        states, physics = _resimulate(config.task, dataset, index)
        episode = dataset.episode(index)
        np.testing.assert_array_equal(states, episode.state)
        np.testing.assert_array_equal(physics, episode.physics)
    runs = tmp_path / "collect" / "collect-000"
    metrics = pd.read_csv(runs / "metrics.csv")
    assert list(metrics["episodes"]) == list(range(1, dataset.n_episodes + 1))
    assert metrics["model_loss"].notna().sum() >= dataset.n_episodes - 1
    assert len(pd.read_csv(runs / "eval.csv")) == config.frames // config.evaluation.every
    teacher, checkpoint = load_teacher(find_teacher(tmp_path), dataset.spec.state_dim)
    assert checkpoint.counters["frames"] == summary.frames
    assert int(teacher.step) == config.updates_due(summary.frames) == summary.updates
    # best.pt is the teacher of the first best evaluation in eval.csv: the final teacher's
    # weights exactly when that evaluation was the last one, older weights otherwise.
    evals = pd.read_csv(runs / "eval.csv")
    best_row = evals.loc[evals["return_mean"].idxmax()]
    best = read_checkpoint(runs / BEST_TEACHER, kind="teacher")
    assert best.counters["frames"] == best_row["frames"]
    assert best.extra["eval_return"] == pytest.approx(best_row["return_mean"])
    same = all(torch.equal(value, checkpoint.weights[key]) for key, value in best.weights.items())
    assert same == (best_row["frames"] == summary.frames)
    # The floor beside every evaluation: the same evaluation episodes with every action 0.
    env = TaskEnv(config.task, config.action_repeat, max_steps=config.max_steps)
    floor = []
    for index in range(config.evaluation.episodes):
        step, total = env.reset(seed=derived_seed(seed, 1 << 30, index)), 0.0
        while not step.is_last:
            step = env.step(np.zeros(env.action_dim, np.float32))
            total += step.reward
        floor.append(total)
    assert summary.zero_action_return == pytest.approx(np.mean(floor))
    assert evals["zero_action_return"].tolist() == [summary.zero_action_return] * len(evals)
    scalars, images = board_events(runs)
    assert scalars["eval/return"] == [
        (f, pytest.approx(r)) for f, r in zip(evals["frames"], evals["return_mean"], strict=True)]
    assert [s for s, _ in images["eval/learning-curve"]] == list(evals["frames"])
    # Every teacher checkpoint names its task and action repeat: twist-eval needs no --task.
    for name in (FINAL_TEACHER, BEST_TEACHER, "latest.pt"):
        oracle = load_agent(runs / name)
        assert (oracle.task, oracle.action_repeat) == (config.task, config.action_repeat), name
    # The recorded config starts another run as this one was; another kind's is refused.
    assert recorded_config(runs, "collect", CollectConfig) == config
    distil_config = tmp_path / "distil.json"
    distil_config.write_text('{"distil": {"steps": 3}}')
    refused = run_command("collect", "--out", str(tmp_path / "again"), "--config",
                          str(distil_config))
    assert refused.returncode == 2 and refused.stderr.strip() == (
        f"error: config file {str(distil_config)!r} is a distil run's config; this command "
        "starts from a collect run's")
    assert not (tmp_path / "again").exists()


def test_sigkilled_cli_run_resumes_without_duplicates_or_losses(tmp_path: Path) -> None:
    out = tmp_path / "D"
    args = [*COLLECT, "--out", str(out), "--preset", "tiny", "--frames", "800", "--quiet"]
    shard = out / "collect-000.zarr"
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        # Kill once the teacher has learned and committed: >= 2 episodes (the first is prefill).
        while time.monotonic() < deadline:
            if shard.exists() and _committed(shard) >= 2:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the collector committed nothing in 120 s")
        renderers = _children(proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert renderers, "the collector should render in a child process"
    deadline = time.monotonic() + 10  # the render child exits once its pipe closes
    while any(map(_running, renderers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(_running, renderers))
    killed_at = _committed(shard)
    assert verify_dataset(out).ok  # consistent at the instant of the kill
    done = run_command("collect", *args[len(COLLECT):], "--resume")
    assert done.returncode == 0, done.stderr
    assert verify_dataset(out).ok
    dataset = open_dataset(out)
    assert dataset.n_episodes == 8 > killed_at
    seed = shard_seed(0, "collect-000")
    seeds = [dataset.episode_info(i).seed for i in range(dataset.n_episodes)]
    assert seeds == [derived_seed(seed, i) for i in range(8)]
    steps = [dataset.episode_info(i).env_step for i in range(dataset.n_episodes)]
    assert steps == [100 * i for i in range(8)]
    metrics = pd.read_csv(out / "collect" / "collect-000" / "metrics.csv")
    assert metrics["episodes"].is_unique


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's zombie waits for whoever reaps in a container)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def _committed(shard: Path) -> int:
    try:
        return open_dataset(shard).n_episodes
    except Exception:  # the shard is being created
        return 0


@pytest.mark.parametrize("failing", [1, 3])  # before the first commit, and after two
def test_disk_full_drops_the_partial_episode_and_resume_continues(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing: int) -> None:
    config = collect_preset("tiny")
    real_commit = ShardWriter._commit

    def commit_fails(self: ShardWriter, n_episodes: int, n_steps: int) -> None:
        if n_episodes == failing:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_commit(self, n_episodes, n_steps)

    monkeypatch.setattr(ShardWriter, "_commit", commit_fails)
    with pytest.raises(CollectError, match=rf"disk full while writing episode {failing - 1} .* "
                                           rf"{failing - 1} committed"):
        collect(tmp_path, config)
    report = verify_dataset(tmp_path)
    assert report.ok and report.episodes == failing - 1
    assert open_dataset(tmp_path).n_episodes == failing - 1
    monkeypatch.setattr(ShardWriter, "_commit", real_commit)
    summary = collect(tmp_path, config, resume=True)
    assert summary.episodes == 4 and verify_dataset(tmp_path).ok


def test_bad_outputs_are_refused_before_anything_is_written(tmp_path: Path, monkeypatch) -> None:
    with pytest.raises(UnknownTaskError, match="nope"):
        collect_preset("tiny", task="nope")
    config = dataclasses.replace(collect_preset("tiny"), frames=100)
    collect(tmp_path, config)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(CollectError, match="views 2, but this run asks for 3"):
        collect(tmp_path, dataclasses.replace(config, views=3), shard="other")
    with pytest.raises(CollectError, match="task 'cartpole-balance', but this run asks for "
                                           "'cup-catch'"):
        collect(tmp_path, dataclasses.replace(config, task="cup-catch"), shard="other")
    with pytest.raises(CollectError, match="supersample 1, but this run asks for 2"):
        collect(tmp_path, dataclasses.replace(config, supersample=2), shard="other")
    with pytest.raises(CollectError, match="supersample 1, but this run asks for 2"):
        collect(tmp_path, dataclasses.replace(config, supersample=2), resume=True)
    with pytest.raises(CollectError, match=r"already exists .* pass --resume"):
        collect(tmp_path, config)
    with pytest.raises(CollectError, match="seed was 0, now 5"):
        collect(tmp_path, dataclasses.replace(config, seed=5), resume=True)
    # The task changed since D was recorded: its steps would mix two tasks.
    assert open_dataset(tmp_path).spec.extra["task_revision"] == 1
    changed = dataclasses.replace(tasks.TASKS["cartpole-balance"], revision=2)
    with monkeypatch.context() as patch:
        patch.setitem(tasks._REGISTERED, "cartpole-balance", changed)
        for kwargs in ({"resume": True}, {"shard": "other"}):
            with pytest.raises(CollectError, match="holds cartpole-balance revision 1, but "
                                                   "this library's cartpole-balance is revision 2"):
                collect(tmp_path, config, **kwargs)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(CollectError, match=r"a-file/D. cannot be written: .*a-file. is a file, "
                                           r"not a folder"):
        collect(blocker / "D", config)


def test_teacher_settings_by_their_former_names_reach_the_teacher_config() -> None:
    default = collect_preset("tiny").teacher_config(5, 1)
    config = collect_preset("tiny", explore_noise=0.3, actor_entropy=1e-3, imag_starts=7,
                            horizon=50, critic_head="twohot", actor_lr=2e-5, critic_lr=3e-4,
                            slow_target_every=1, discount=0.96,
                            state_noise=0.05, imagination_precision="bfloat16"
                            ).teacher_config(5, 1)
    behaviour = config.actor_critic
    assert (config.explore_noise, behaviour.entropy, behaviour.imag_starts, behaviour.horizon) \
        == (0.3, 1e-3, 7, 50)
    assert (behaviour.critic_head, behaviour.actor_lr, behaviour.critic_lr,
            behaviour.slow_target_every, behaviour.discount) == ("twohot", 2e-5, 3e-4, 1, 0.96)
    assert Teacher(config).actor_critic.critic[-1].out_features == 255
    assert (default.explore_noise, default.actor_critic.entropy) == (0.0, 1e-4)
    assert (behaviour.precision, default.actor_critic.precision) == ("bfloat16", "float32")
    with pytest.raises(ConfigError, match=r"precision must be one of .*'half'"):
        collect_preset("tiny", imagination_precision="half")
    assert config.world_model == dataclasses.replace(default.world_model, state_noise=0.05)
    assert default.world_model.state_noise == 0.0
    # The collect config holds them in its teacher config, their one home.
    assert not {"actor_lr", "explore_noise", "imagination_precision"} & {
        f.name for f in dataclasses.fields(CollectConfig)}
    # DreamerV2's train ratio: nothing before prefill, then pretrain + 1 per train_every steps.
    paper = collect_preset("paper")
    assert paper.updates_due(paper.prefill_frames - 1) == 0
    assert paper.updates_due(paper.prefill_frames + 10 * paper.action_repeat * 5) == 110


def test_world_model_warms_up_alone_before_behaviour_learning(tmp_path: Path) -> None:
    base = collect_preset("tiny", frames=300)
    warmup = base.updates_due(200)  # the actor-critic joins after the second episode's updates
    done = run_command("collect", "--out", str(tmp_path), "--preset", "tiny", "--frames", "300",
                       "--set", f"behaviour_from={warmup}", "--quiet")
    assert done.returncode == 0, done.stderr
    teacher, checkpoint = load_teacher(find_teacher(tmp_path))
    updates = int(teacher.step)
    assert updates == base.updates_due(checkpoint.counters["frames"]) > warmup > 0
    assert int(teacher.actor_critic.updates) == updates - warmup
    metrics = pd.read_csv(tmp_path / "collect" / "collect-000" / "metrics.csv")
    trained = metrics[metrics["updates"] > 0]
    # Rows of warm-up updates have world-model losses but no actor-critic losses.
    assert trained["model_loss"].notna().all()
    assert list(trained["actor_loss"].notna()) == list(trained["updates"] > warmup)


def test_a_finished_run_extends_d_with_its_frozen_teacher(tmp_path: Path) -> None:
    learned = collect_preset("tiny", frames=200)
    collect(tmp_path, learned)
    runs = tmp_path / "collect" / "collect-000"
    before = read_checkpoint(runs / "teacher.pt", kind="teacher")
    evaluations = len(pd.read_csv(runs / "eval.csv"))
    extended = dataclasses.replace(learned, frames=500, learn_frames=200)
    summary = collect(tmp_path, extended, resume=True)
    assert summary.frames == 500 and verify_dataset(tmp_path).ok
    after = read_checkpoint(runs / "teacher.pt", kind="teacher")
    assert summary.updates == learned.updates_due(200) == extended.updates_due(500)
    assert all(torch.equal(value, after.weights[key]) for key, value in before.weights.items())
    dataset = open_dataset(tmp_path)
    tail = [dataset.episode_info(i) for i in range(2, dataset.n_episodes)]
    assert len(tail) == 3
    assert all((i.policy, i.teacher_step) == ("teacher", summary.updates) for i in tail)
    assert len(pd.read_csv(runs / "eval.csv")) == evaluations  # nothing new to evaluate
    # tiny snapshots every 200 frames, but a frozen teacher's would be copies of teacher.pt.
    assert sorted(p.name for p in runs.glob("teacher-*.pt")) == ["teacher-00000200.pt"]
    with pytest.raises(ConfigError, match="learn_frames 100 ends learning before"):
        collect_preset("tiny", learn_frames=100)


def test_supersampled_collection_records_it_and_its_frames_reproduce(tmp_path: Path) -> None:
    from twist_sim.randomisation import VIEW_PARAMS, DRConfig
    from twist_sim.render import DRRenderer
    from twist_sim.rerender import check_reproduction, render_blocks, reproduce_frames

    collect(tmp_path, collect_preset("tiny", frames=100, supersample=2))  # the prefill episode
    dataset = open_dataset(tmp_path)
    assert dataset.spec.supersample == 2
    assert dataset.spec.image_agent_info()["supersample"] == 2
    steps = np.array([0, 25, dataset.n_steps - 1])
    reproduced = reproduce_frames(dataset, steps)
    assert not check_reproduction(dataset, 20)  # every re-render is pixel-identical
    # Supersampling is rendering at twice the side and area-averaging 2x2 pixels.
    block = render_blocks(dataset.spec)[0]
    params = {p.name: dataset.column(f"dr/{p.name}")[steps] for p in VIEW_PARAMS}
    physics = dataset.column("physics")[steps]
    with DRRenderer(dataset.spec.task, DRConfig.from_json(block["config"]), 128, 2) as large:
        for i in range(steps.size):
            frames = large.render(physics[i], {k: v[i] for k, v in params.items()})
            averaged = frames.reshape(2, 64, 2, 64, 2, 3).mean((2, 4))
            assert np.abs(averaged - reproduced[i]).max() <= 1  # rounding
    with pytest.raises(ConfigError, match="supersample must be > 0, got 0"):
        collect_preset("tiny", supersample=0)


def _extended_with(tmp_path: Path, **perturbation: float
                   ) -> tuple[MatchingDataset, MatchingDataset]:
    """A tiny D whose teacher learned for 200 frames and then acted frozen to 500, collected
    twice from the same learned episodes: as is, and with ``perturbation`` of the frozen
    teacher's actions."""
    learned = collect_preset("tiny", frames=200)
    collect(tmp_path / "plain", learned)
    shutil.copytree(tmp_path / "plain", tmp_path / "perturbed")
    extended = dataclasses.replace(learned, frames=500, learn_frames=200)
    collect(tmp_path / "plain", extended, resume=True)
    collect(tmp_path / "perturbed", dataclasses.replace(extended, **perturbation), resume=True)
    return open_dataset(tmp_path / "plain"), open_dataset(tmp_path / "perturbed")


def test_frozen_noise_perturbs_only_the_frozen_teachers_actions(tmp_path: Path) -> None:
    def clipped(dataset: MatchingDataset) -> float:
        frozen = np.concatenate([dataset.episode(i).action[1:] for i in range(2, 5)])
        # A tanh-squashed sample is never exactly +-1; noise clipped to the bounds often is.
        return float(np.mean(np.abs(frozen) == 1.0))

    plain, noisy = _extended_with(tmp_path, frozen_noise=1.0)
    assert clipped(plain) == 0.0 and clipped(noisy) > 0.2
    with pytest.raises(ConfigError, match="frozen_noise changes who acts"):
        collect_preset("tiny", frozen_noise=0.5)


def test_pushes_start_at_the_given_rate_and_hold_one_action() -> None:
    every, longest = 20, 10
    pushes = RandomPushes(every, longest, action_dim=2, seed=3)
    actions = [pushes() for _ in range(100_000)]
    pushed = np.array([a is not None for a in actions])
    # A renewal process: idle spells of mean every - 1 steps (geometric), pushes of mean
    # (longest + 1) / 2 steps.
    mean_push = (longest + 1) / 2
    assert abs(pushed.mean() - mean_push / (every - 1 + mean_push)) < 0.01
    # Each push holds one action (a new push draws another, even straight after one).
    runs, previous = [], None
    for action in actions:
        if action is not None and previous is not None and np.array_equal(action, previous):
            runs[-1] += 1
        elif action is not None:
            runs.append(1)
            assert np.all(np.abs(action) <= 1.0)
        previous = action
    assert min(runs) == 1 and max(runs) == longest
    assert abs(np.mean(runs) - mean_push) < 0.2
    again = RandomPushes(every, longest, action_dim=2, seed=3)
    assert all((a is None and b is None) or np.array_equal(a, b)
               for a, b in zip(actions[:1000], (again() for _ in range(1000)), strict=True))


def test_push_every_shoves_only_the_frozen_teacher(tmp_path: Path) -> None:
    def repeated(dataset: MatchingDataset) -> list[float]:
        """Per episode, the share of steps whose action repeats the previous one exactly."""
        shares = []
        for i in range(dataset.n_episodes):
            action = dataset.episode(i).action[1:, 0]
            shares.append(float(np.mean(action[1:] == action[:-1])))
        return shares

    plain, pushed = _extended_with(tmp_path, push_every=4, push_steps=5)
    # The teacher's sampled actions never repeat exactly; a push holds one action. The first
    # two episodes are the learned ones, shared by both.
    assert max(repeated(plain)) == 0.0 and repeated(pushed)[:2] == [0.0, 0.0]
    assert min(repeated(pushed)[2:]) > 0.1
    with pytest.raises(ConfigError, match="push_every changes who acts"):
        collect_preset("tiny", push_every=10)
    with pytest.raises(ConfigError, match="push_steps must be > 0, got 0"):
        collect_preset("tiny", learn_frames=200, push_every=10, push_steps=0)


def test_a_student_acts_instead_of_the_frozen_teacher_on_its_own_renders(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from twist_models.agent import Agent
    from twist_models.config import student_preset
    from twist_models.student import Student

    learned = collect_preset("tiny", frames=200)
    collect(tmp_path, learned)
    teacher = load_teacher(find_teacher(tmp_path))[0]
    torch.manual_seed(0)
    info = open_dataset(tmp_path).spec.image_agent_info()
    agent = Agent.from_models(Student(student_preset("tiny", teacher.config)), teacher, info)
    bundle = agent.save(tmp_path / "agent.pt")
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    original = Agent.act

    def spy(self, image, state=None, **options):
        action, state = original(self, image, state, **options)
        seen.append((np.asarray(image), action))
        return action, state

    monkeypatch.setattr(Agent, "act", spy)
    shard = zarr.open_group(tmp_path / "collect-000.zarr", mode="r+")
    block = dict(shard.attrs[ATTRS_KEY])  # as a shard written before code 4 existed
    block["policy_codes"] = {k: v for k, v in block["policy_codes"].items() if k != "student"}
    shard.attrs[ATTRS_KEY] = block
    extended = dataclasses.replace(learned, frames=400, learn_frames=200, student=str(bundle))
    collect(tmp_path, extended, resume=True)
    dataset = open_dataset(tmp_path)
    infos = [dataset.episode_info(i) for i in range(dataset.n_episodes)]
    assert [(i.policy, i.teacher_step) for i in infos[2:]] == [("student", -1)] * 2
    stored = zarr.open_group(tmp_path / "collect-000.zarr", mode="r").attrs[ATTRS_KEY]
    assert stored["policy_codes"]["student"] == 4
    assert verify_dataset(tmp_path).ok
    # Every executed action of the two episodes (50 agent steps each) is the agent's, on an
    # image it rendered itself.
    executed = np.concatenate([dataset.episode(i).action[1:] for i in (2, 3)])
    assert len(seen) == 2 * 50 and all(image.shape == (64, 64, 3) for image, _ in seen)
    np.testing.assert_array_equal(executed, [action for _, action in seen])
    assert not np.array_equal(seen[0][0], seen[1][0])  # the pole moves
    with pytest.raises(ConfigError, match="student changes who acts"):
        collect_preset("tiny", student=str(bundle))
    stranger = Agent.from_models(agent.student, teacher, {**info, "task": "cup-catch"})
    for path, message in ((tmp_path / "missing.pt", "does not exist"),
                          (stranger.save(tmp_path / "cup.pt"), "has task 'cup-catch'")):
        with pytest.raises(CollectError, match=message):
            collect(tmp_path, dataclasses.replace(extended, frames=600, student=str(path)),
                    resume=True)
    assert open_dataset(tmp_path).n_episodes == 4  # a refused run writes nothing


def test_freeze_best_lets_the_best_evaluated_teacher_act_once_learning_ends(
        tmp_path: Path) -> None:
    config = collect_preset("tiny", frames=600, learn_frames=300, freeze_best=True,
                            eval_every=100)
    summary = collect(tmp_path, config)
    runs = tmp_path / "collect" / "collect-000"
    evals = pd.read_csv(runs / "eval.csv")
    assert evals["frames"].tolist() == [100, 200, 300]  # a frozen teacher is not re-evaluated
    # The acting teacher is the first best of the evaluations after the prefill (the first
    # one's teacher never acted: frame 100 is where it starts).
    acted = evals[evals["frames"] >= config.prefill_frames]
    best_row = acted.loc[acted["return_mean"].idxmax()]
    # With these seeds the 200-frame teacher beats the last learned one (300), so the check
    # below tells freezing the best from freezing the last.
    assert best_row["frames"] < 300
    final = read_checkpoint(runs / "teacher.pt", kind="teacher")
    best = read_checkpoint(runs / BEST_TEACHER, kind="teacher")
    assert best.counters["frames"] == best_row["frames"] == summary.frozen_from["frames"]
    assert all(torch.equal(value, final.weights[key]) for key, value in best.weights.items())
    frozen = config.updates_due(int(best_row["frames"]))
    assert summary.frozen_from["updates"] == summary.updates == frozen
    dataset = open_dataset(tmp_path)
    steps = [dataset.episode_info(i).teacher_step for i in range(dataset.n_episodes)]
    assert steps[3:] == [frozen] * 3  # the episodes from 300 frames on
    assert steps[1:3] == [config.updates_due(100), config.updates_due(200)]
    with pytest.raises(ConfigError, match="freeze_best needs learn_frames"):
        collect_preset("tiny", freeze_best=True)


def test_learning_stops_at_the_first_evaluation_that_reaches_learn_until_return(
        tmp_path: Path) -> None:
    # Every cartpole return is >= 0, so the first evaluation after the prefill (100 frames)
    # reaches 0: the one at 200 frames. The 100-frame one does not count (no teacher acted).
    config = collect_preset("tiny", frames=400, learn_frames=500, eval_every=100,
                            learn_until_return=0.0)
    first = collect(tmp_path, config)
    assert first.learned_until == 200 and first.updates == config.updates_due(200)
    resumed = collect(tmp_path, dataclasses.replace(config, frames=600), resume=True)
    assert resumed.learned_until == 200 and resumed.updates == first.updates
    runs = tmp_path / "collect" / "collect-000"
    assert pd.read_csv(runs / "eval.csv")["frames"].tolist() == [100, 200]
    dataset = open_dataset(tmp_path)
    steps = [dataset.episode_info(i).teacher_step for i in range(dataset.n_episodes)]
    assert steps[2:] == [config.updates_due(200)] * 4  # the episodes from 200 frames on
    assert steps[1] == config.updates_due(100)
    # A return no evaluation reaches leaves learning to learn_frames.
    never = collect(tmp_path / "never", dataclasses.replace(config, learn_until_return=1e9))
    assert never.learned_until is None and never.updates == config.updates_due(400)
    with pytest.raises(ConfigError, match=r"learn_until_return 990\.0 needs evaluation\.episodes"):
        collect_preset("tiny", learn_until_return=990.0, eval_episodes=0)


def test_a_resumed_run_may_evaluate_at_another_cadence_and_a_finished_one_returns_at_once(
        tmp_path: Path, monkeypatch) -> None:
    import twist_pipeline.collect as collect_module

    config = collect_preset("tiny", frames=300, learn_frames=600, eval_every=100)
    collect(tmp_path, config)
    slower = dataclasses.replace(config, frames=700,
                                 evaluation=TeacherEvalConfig(every=200, episodes=1))
    finished = collect(tmp_path, slower, resume=True)
    # Resumed again with nothing left to do, no simulator starts (it would raise here).
    monkeypatch.setattr(collect_module, "TaskEnv", None)
    assert collect(tmp_path, dataclasses.replace(slower, compile="on"), resume=True) == finished
    assert collect(tmp_path, dataclasses.replace(slower, frames=500), resume=True) == finished
    with pytest.raises(TypeError):  # more frames: the run goes on
        collect(tmp_path, dataclasses.replace(slower, frames=800), resume=True)
    evals = pd.read_csv(tmp_path / "collect" / "collect-000" / "eval.csv")
    # The evaluation due when the run stopped keeps its frame; the new cadence follows it.
    assert evals["frames"].tolist() == [100, 200, 300, 400, 600]
    assert evals["episodes"].tolist() == [config.evaluation.episodes] * 4 + [1]


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path: Path) -> None:
    # The first through a fresh interpreter, as a user runs it; the rest through the same
    # error boundary in this process.
    done = subprocess.run([*COLLECT, "--out", str(tmp_path), "--task", "nope"],
                          capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.startswith("error: unknown task 'nope'") and "Traceback" not in done.stderr
    done = run_command("collect", "--out", str(tmp_path), "--set", "model_lr")
    assert done.returncode == 2 and "--set takes KEY=VALUE" in done.stderr
    assert "'model_lr'" in done.stderr and not any(tmp_path.iterdir())
    for setting, message in (("model_lr=fast", "--set model_lr must be a number, got 'fast'"),
                             ("batch_size=abc", "--set batch_size must be an integer")):
        done = run_command("collect", "--out", str(tmp_path), "--set", setting)
        assert done.returncode == 2 and message in done.stderr, done.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a torch that sees no CUDA GPU")
def test_a_device_this_torch_cannot_use_is_refused_before_anything_is_created(
        tmp_path: Path) -> None:
    done = run_command("collect", "--out", str(tmp_path / "d"), "--preset", "tiny",
                       "--device", "cuda")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().startswith("error: device 'cuda' is not available")
    assert not (tmp_path / "d").exists()


def test_the_teachers_sizes_are_set_through_nested_keys(tmp_path: Path) -> None:
    config = collect_preset("tiny", **{"teacher.world_model.rssm.deter": 48,
                                       "teacher.actor_critic.actor.units": 24})
    preset = teacher_preset("tiny", 5, 1)  # cartpole: 5 state components, 1 action
    expected = dataclasses.replace(preset, world_model=dataclasses.replace(
        preset.world_model, rssm=dataclasses.replace(preset.world_model.rssm, deter=48)),
        actor_critic=dataclasses.replace(preset.actor_critic, actor=dataclasses.replace(
            preset.actor_critic.actor, units=24)))
    assert config.teacher == expected  # the preset's config with the two fields changed
    collect(tmp_path, dataclasses.replace(config, frames=200))
    teacher, _ = load_teacher(find_teacher(tmp_path), 5)
    assert teacher.config.world_model.rssm.deter == 48
    assert teacher.config.actor_critic.actor.units == 24
    # A teacher config of another task's sizes is refused before anything runs.
    other = collect_preset("tiny", task="cup-catch", **{"teacher.world_model.rssm.deter": 48})
    with pytest.raises(ConfigError, match="reads states of 8 and acts in 2 dimensions, but "
                                          "cartpole-balance has 5 and 1"):
        collect(tmp_path / "other", dataclasses.replace(other, task="cartpole-balance"))
    assert not (tmp_path / "other" / "collect-000.zarr").exists()


def test_a_cli_setting_of_null_clears_the_presets_value(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    import twist_cli.collect as collect_cli

    seen: list[CollectConfig] = []

    def capture(out, config, **_):  # the config the CLI would collect with, not a run
        seen.append(config)
        raise KeyboardInterrupt

    monkeypatch.setattr(collect_cli, "collect", capture)
    for setting, expected in (("learn_until_return=null", None), ("learn_frames=50000", 990.0)):
        CliRunner().invoke(collect_cli.app, ["--out", str(tmp_path / "D"), "--preset", "quick",
                                             "--set", setting])
        assert seen[-1].learn_until_return == expected
    assert COLLECT_PRESETS["quick"].learn_until_return == 990.0
    assert seen[-1].learn_frames == 50_000


def test_the_quick_preset_teacher_learns_with_the_cpu_settings() -> None:
    teacher = collect_preset("quick").teacher_config(5, 1)
    behaviour, model = teacher.actor_critic, teacher.world_model
    assert (behaviour.imag_starts, behaviour.actor_lr, behaviour.critic_lr, behaviour.critic_head,
            behaviour.return_norm, behaviour.slow_target_every, behaviour.discount,
            behaviour.precision) == (256, 1e-3, 3e-4, "twohot", True, 50, 0.98, "auto")
    assert (model.model_lr, model.overshoot, model.rssm.deter) == (1e-3, 15, 128)
    # DreamerV2's schedule at quick sizes keeps DreamerV2's learning.
    mixed = collect_preset("paper", model="quick").teacher_config(5, 1)
    assert (mixed.world_model.rssm.deter, mixed.actor_critic.actor_lr,
            mixed.world_model.overshoot) == (128, 8e-5, 0)
    with pytest.raises(ConfigError, match="learning must be one of dreamerv2, cpu, got 'gpu'"):
        collect_preset("quick", learning="gpu")


def test_a_record_with_teacher_settings_by_former_names_loads_and_resumes_as_it_ran() -> None:
    from twist_models.config import from_json, to_json
    from twist_pipeline.collect import TEACHER_ALIASES
    from twist_pipeline.runlog import record_section, resume_conflicts

    ran = collect_preset("tiny", actor_lr=2e-5, overshoot=3)  # what such a run's teacher was
    section = {k: v for k, v in to_json(ran).items() if k != "teacher"}
    section.update({name: None for name in TEACHER_ALIASES}, teacher=None, explore_noise=0.0,
                   actor_lr=2e-5, overshoot=3)
    record = {"collect": section, "teacher": to_json(ran.teacher)}
    loaded = from_json(CollectConfig, record_section(record, "collect", CollectConfig))
    assert loaded == ran and loaded.teacher_config(5, 1).actor_critic.actor_lr == 2e-5
    assert resume_conflicts(record_section(record, "collect", CollectConfig), loaded, ()) == []
    with pytest.raises(ConfigError, match="needs the teacher config its run recorded"):
        CollectConfig.record_section({"collect": section})
