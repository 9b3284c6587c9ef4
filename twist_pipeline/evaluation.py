"""Evaluate agents in the simulator under a domain-randomisation setting (``twist-eval``).

An agent is anything with ``uses_images``, ``reset()`` and ``act(step, image)``: the teacher
acting on privileged state (the *oracle*), a distilled student bundle acting on one rendered
view, or a scripted policy. Every agent evaluated with the same config and seed meets the same
episodes: initial states, dynamics and DR parameters all derive from (seed, episode), so
returns can be compared episode by episode.

Held-out evaluation follows the paper: the DR parameters (background, colours, light, camera)
are drawn **once per episode** and held for all its steps, whatever the preset's own
``resample`` says.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from twist_data.errors import ConfigError, TwistError
from twist_data.export import episode_strip, write_video
from twist_data.seeding import evaluation_episode_seed
from twist_data.staging import require_writable
from twist_models.config import require_positive, to_json
from twist_models.device import resolve_device
from twist_models.networks import single_threaded
from twist_models.rssm import require_posterior_read
from twist_pipeline.acting import EvalAgent, agent_kind, load_agent
from twist_pipeline.curves import plot_returns
from twist_pipeline.runlog import append_csv, refuse_resume, resume_conflicts
from twist_pipeline.statistics import PairedDifference, paired_difference, stratified_bootstrap
from twist_sim.backgrounds import background_files
from twist_sim.errors import BackgroundError
from twist_sim.randomisation import DR_PRESETS, DRConfig, dr_preset
from twist_sim.tasks import DEFAULT_ACTION_REPEAT, DEFAULT_TASK, Step, task_spec
from twist_sim.vector_env import EnvWorkers, LocalEnvs


class EvalError(TwistError):
    """An evaluation cannot run (agent, task or setting)."""


#: The most episodes of one evaluation seed: 1,000 times the paper's 100.
MAX_EPISODES = 100_000


@dataclass(frozen=True)
class EvalConfig:
    """Where and how long agents are evaluated."""

    task: str = DEFAULT_TASK
    """DMC task."""
    dr: str = "heldout"
    """DR preset of the scenes (``heldout``: backgrounds never seen in training)."""
    backgrounds: str | None = None
    """Folder of user images/videos replacing the preset's background bank."""
    episodes: int = 100
    """Episodes per seed (the paper: 100)."""
    image_size: int = 64
    """Rendered view side in pixels (the student's input size)."""
    supersample: int | None = None
    """Render at this multiple and area-downsample (anti-aliasing); None: as each image
    agent's training data was rendered (its bundle records it), 1 where unknown."""
    action_repeat: int = DEFAULT_ACTION_REPEAT
    """Simulator steps per agent step (the agents' own: :func:`check_compatible` refuses
    others)."""
    max_steps: int | None = None
    """Agent steps per episode; None: the task's limit."""
    posterior: str = "sample"
    """How image agents take z from their posterior when acting (one of
    :data:`~twist_models.rssm.POSTERIOR_READS`): ``sample`` as DreamerV2 and the paper,
    ``mode``, or ``mean`` (the class probabilities; see docs/findings.md)."""

    def __post_init__(self) -> None:
        task_spec(self.task)
        require_posterior_read(self.posterior)
        if self.dr not in DR_PRESETS:
            raise ConfigError(f"unknown DR preset {self.dr!r}; valid: {', '.join(DR_PRESETS)}")
        if not 1 <= self.episodes <= MAX_EPISODES:
            raise ConfigError(f"episodes must lie in [1, {MAX_EPISODES:,}] per seed, got "
                              f"{self.episodes}; more seeds give more episodes")
        require_positive(self, "image_size", "action_repeat")
        if self.supersample is not None:
            require_positive(self, "supersample")
        if self.max_steps is not None and self.max_steps < 1:
            raise ConfigError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.backgrounds is not None:  # an empty folder too, before any episode starts
            try:
                background_files(self.backgrounds)
            except BackgroundError as exc:
                raise ConfigError(str(exc)) from None

    def dr_config(self) -> DRConfig:
        """The preset (with user backgrounds), drawn once per episode."""
        return dataclasses.replace(dr_preset(self.dr, self.backgrounds), resample="episode")


def check_compatible(agent: EvalAgent, config: EvalConfig, name: str = "the agent") -> None:
    """Refuse an agent trained for another task, image size or action repeat than the
    evaluation's (a policy trained at repeat 4 acting every 2 frames is another controller)."""
    task = getattr(agent, "task", None)
    if task is not None and task != config.task:
        raise EvalError(f"{name} was trained on {task!r} but the evaluation task is "
                        f"{config.task!r}")
    size = getattr(agent, "image_size", None)
    if agent.uses_images and size is not None and size != config.image_size:
        raise EvalError(f"{name} reads {size}px images but the evaluation renders "
                        f"{config.image_size}px")
    posterior = getattr(agent, "posterior", None)
    if agent.uses_images and posterior is not None and posterior != config.posterior:
        raise EvalError(f"{name} reads its posterior as {posterior!r} but the evaluation "
                        f"says {config.posterior!r}")
    repeat = getattr(agent, "action_repeat", None)
    if repeat is not None and repeat != config.action_repeat:
        raise EvalError(f"{name} was trained at action repeat {repeat} but the evaluation "
                        f"uses {config.action_repeat}")


def agents_setting(agents: Mapping[str, EvalAgent], setting: str) -> Any:
    """The value of ``setting`` (``task``, ``action_repeat``) that the agents were trained
    with (None if none says); agents that disagree raise EvalError naming two of them."""
    known = [(name, getattr(a, setting, None)) for name, a in agents.items()]
    known = [(name, value) for name, value in known if value is not None]
    if not known:
        return None
    first, value = known[0]
    for name, other in known[1:]:
        if other != value:
            raise EvalError(f"agents {first!r} and {name!r} were trained with different "
                            f"{setting} ({value!r} and {other!r}); evaluate them separately")
    return value


@dataclass(frozen=True)
class EpisodeResult:
    """One evaluated episode."""

    seed: int
    episode: int
    episode_seed: int
    episode_return: float
    steps: int
    trajectory: dict[str, np.ndarray] | None = None
    """With ``trajectories``: ``state`` [T+1, S] at every agent step, ``action`` [T, A] and
    ``reward`` [T] after it."""
    success: bool | None = None
    """Whether the episode's last state meets the task's success (``TaskSpec.success``);
    None for a task without one."""


def evaluation_envs(agent: EvalAgent, config: EvalConfig, batch: int = 1, workers: int = 1,
                    record: bool = False) -> LocalEnvs | EnvWorkers:
    """The environments :func:`evaluate` steps ``agent``'s episodes in, ``batch`` at a time in
    this process or in ``workers`` processes; close them (or use ``with``) when done. Made
    once and passed to several :func:`evaluate` calls (``envs=``), they spare each call their
    set-up: a simulator per slot, a renderer and, with workers, the processes' start. Each
    episode is seeded on its own, so one set serves every seed."""
    if batch < 1 or workers < 1:
        raise ConfigError(f"batch and workers must be >= 1, got {batch} and {workers}")
    # An agent without act_batch keeps one episode's state: its episodes run one at a time.
    width = (min(batch, config.episodes) if batch > 1 and getattr(agent, "batchable", False)
             else 1)
    envs = dict(slots=width, render=agent.uses_images or record, **_env_settings(agent, config))
    return (EnvWorkers(workers=workers, **envs) if workers > 1 and width > 1
            else LocalEnvs(**envs))


def _env_settings(agent: EvalAgent, config: EvalConfig) -> dict[str, Any]:
    """What an evaluation's environments are made with, but their number and views."""
    return dict(task=config.task, dr=config.dr_config(), image_size=config.image_size,
                supersample=config.supersample or getattr(agent, "supersample", None) or 1,
                action_repeat=config.action_repeat, max_steps=config.max_steps)


def evaluate(agent: EvalAgent, config: EvalConfig, seed: int = 0,
             on_episode: Callable[[EpisodeResult], None] | None = None,
             record: Callable[[int, np.ndarray], None] | None = None,
             skip: frozenset[int] = frozenset(), batch: int = 1,
             trajectories: bool = False, workers: int = 1,
             envs: LocalEnvs | EnvWorkers | None = None) -> list[EpisodeResult]:
    """Run ``config.episodes`` episodes of ``agent``, but those in ``skip``;
    ``record(episode, frame)`` receives the rendered view of every step (for videos) when
    given; with ``trajectories`` each result carries its episode's states, actions and
    rewards (where the agent went, to set beside the states its training data holds). Each
    episode depends only on (seed, its index), so a skipped episode changes none of the
    others.

    ``batch`` > 1 steps that many episodes together, with one batched call of an agent that
    has ``act_batch`` (one call per episode otherwise). Each episode keeps its own torch
    random stream, seeded by its episode seed, from which its sampling draws are taken in the
    order a lone episode takes them: every episode meets the same scene, initial state and
    draws for every ``batch``, and follows the lone episode's trajectory until the rounding
    of batched matrix products (a batch of N sums in another order than N batches of 1)
    tips a sampled class, after which the two differ as two draws would (returns agree to
    ~1e-9 over a few steps; over 250 some episodes part). ``batch=1`` is the reference.

    ``workers`` > 1 simulates and renders a batch's environments in that many worker
    processes (:class:`~twist_sim.vector_env.EnvWorkers`), with the same episodes as in
    this process. ``envs``: environments from :func:`evaluation_envs` made for the same
    agent, config, ``batch`` and ``workers``, to use (and leave open) instead of making them."""
    check_compatible(agent, config)
    if batch < 1 or workers < 1:
        raise ConfigError(f"batch and workers must be >= 1, got {batch} and {workers}")
    todo = [i for i in range(config.episodes) if i not in skip]
    batched = batch > 1 and getattr(agent, "batchable", False)
    width = max(1, min(batch, len(todo))) if batched else 1
    views = agent.uses_images or record is not None
    owned = envs is None
    if envs is None:
        envs = evaluation_envs(agent, config, batch, workers, record is not None)
    elif envs.slots < width or (views and not envs.render) or (
            envs.settings != _env_settings(agent, config)):
        raise ConfigError(f"the environments given ({envs.slots} slots, "
                          f"{'with' if envs.render else 'without'} views, {envs.settings}) "
                          f"are not those this evaluation needs ({width} slots"
                          f"{', with views' if views else ''}, {_env_settings(agent, config)})")
    results = []
    with (envs if owned else contextlib.nullcontext()), single_threaded(), \
            torch.random.fork_rng(devices=range(torch.cuda.device_count())):
        for lo in range(0, len(todo), width):
            group = todo[lo:lo + width]
            for result in _run_group(agent, envs, seed, group, record, batched, trajectories):
                results.append(result)
                if on_episode is not None:
                    on_episode(result)
    return results


def _run_group(agent: EvalAgent, envs: LocalEnvs | EnvWorkers, seed: int, episodes: list[int],
               record: Callable[[int, np.ndarray], None] | None, batched: bool,
               trajectories: bool = False) -> list[EpisodeResult]:
    """``episodes`` stepped together until each ends: one episode per slot of ``envs`` (its
    environment, DR sampler and view), each with its own random stream. Alone (not
    ``batched``: one slot), the agent draws from torch's stream seeded by the episode seed;
    batched, each slot's draws come from a generator seeded the same way (the same
    numbers)."""
    n = len(episodes)
    seeds = [evaluation_episode_seed(seed, i) for i in episodes]
    observed = envs.reset(seeds)
    steps = [step for step, _ in observed]
    images = [image for _, image in observed]
    if batched:
        agent.reset_batch(n)
        streams = [torch.Generator().manual_seed(s) for s in seeds]
    else:
        agent.reset()
        torch.manual_seed(seeds[0])  # the agents sample their latents: re-runs match
    totals, counts = [0.0] * n, [0] * n
    done = [False] * n
    visited: list[list[np.ndarray]] = [[s.state] for s in steps]
    acted: list[list[tuple[np.ndarray, float]]] = [[] for _ in steps]
    while True:
        for slot in range(n):
            if done[slot]:
                continue
            if record is not None:
                record(episodes[slot], images[slot])
            done[slot] = steps[slot].is_last
        live = [slot for slot in range(n) if not done[slot]]
        if not live:
            break
        if batched:
            actions = _act_batch(agent, steps, images, streams)
        else:
            with torch.no_grad():
                actions = [np.asarray(agent.act(steps[0], images[0]), np.float32)]
        clipped = [np.clip(actions[slot], -1.0, 1.0) for slot in live]
        for slot, action, (step, image) in zip(live, clipped, envs.step(live, clipped),
                                               strict=True):
            steps[slot], images[slot] = step, image
            totals[slot] += step.reward
            counts[slot] += 1
            if trajectories:
                visited[slot].append(step.state)
                acted[slot].append((action, step.reward))
    success = task_spec(envs.settings["task"]).success
    return [EpisodeResult(seed, i, s, totals[k], counts[k],
                          _trajectory(visited[k], acted[k]) if trajectories else None,
                          None if success is None else bool(success(steps[k].state)))
            for k, (i, s) in enumerate(zip(episodes, seeds, strict=True))]


def _trajectory(states: list[np.ndarray], acted: list[tuple[np.ndarray, float]]
                ) -> dict[str, np.ndarray]:
    return {"state": np.stack(states).astype(np.float32),
            "action": np.array([a for a, _ in acted], np.float32).reshape(len(acted), -1),
            "reward": np.array([r for _, r in acted], np.float32)}


def _act_batch(agent: EvalAgent, steps: list[Step], images: list[np.ndarray | None],
               streams: list[torch.Generator]) -> np.ndarray:
    """One batched call for every slot (a finished one on its last step and image, its action
    ignored, so the batch keeps its shape), each slot's draws taken from its own stream in
    the shape one lone step draws -> actions [N, A]."""
    shape = agent.draw_shape
    uniform = None if shape is None else torch.cat(
        [torch.rand(*shape, generator=stream) for stream in streams])
    stacked = None if images[0] is None else np.stack(images)
    with torch.no_grad():
        return np.asarray(agent.act_batch(steps, stacked, uniform), np.float32)


# -- a whole evaluation: several agents, seeds, files ---------------------------------------------
EPISODE_COLUMNS = ("agent", "kind", "seed", "episode", "episode_seed", "return", "steps",
                   "success")
TRAJECTORIES = "trajectories"


def trajectory_name(agent: str, seed: int, episode: int) -> str:
    """The file under ``trajectories/`` that holds one evaluated episode."""
    return f"{agent}-seed{seed}-episode{episode}.npz"


def run_evaluation(agents: Mapping[str, str | os.PathLike[str] | EvalAgent],
                   config: EvalConfig,
                   seeds: Sequence[int], out: str | os.PathLike[str], videos: int = 0,
                   device: str = "cpu",
                   on_episode: Callable[[str, EpisodeResult], None] | None = None,
                   against: str | None = None, resume: bool = False,
                   on_progress: Callable[[int, int], None] | None = None, batch: int = 1,
                   trajectories: bool = False, workers: int = 1) -> dict[str, Any]:
    """Evaluate every ``name: checkpoint`` (or loaded agent) on the same episodes for each seed and write
    ``episodes.csv``, ``summary.json``, ``returns.png`` and ``videos`` mp4s per agent to
    ``out``. Returns the summary: per agent the mean and std over seeds of the per-seed mean
    return, and, when an oracle (a teacher checkpoint) is among the agents, every agent's
    oracle-normalised IQM with a 95% bootstrap interval stratified by seed; with ``against``
    (one of the agents' names), every other agent's paired difference from it, episode by
    episode.

    Each episode is appended to ``episodes.csv`` as it finishes. An ``out`` that holds an
    evaluation is refused unless ``resume``: then the episodes it holds (agent, seed, episode)
    are kept and not run again, provided its ``eval-config.json`` matches ``config`` in every
    field but ``episodes`` (agents and seeds may be added). ``on_progress(done, total)``
    follows the episodes asked for, those found done included. ``batch``: episodes stepped
    together, ``workers``: processes they are simulated in (:func:`evaluate`).
    ``trajectories``: each episode's states, actions and rewards go to
    ``trajectories/NAME-seedS-episodeE.npz`` as it finishes."""
    if not agents:
        raise EvalError("no agents to evaluate")
    if not seeds:
        raise EvalError("no seeds to evaluate")
    if batch < 1 or workers < 1:
        raise ConfigError(f"batch and workers must be >= 1, got {batch} and {workers}")
    if videos < 0:
        raise ConfigError(f"the episodes to film per agent and seed (--video) must be >= 0, "
                          f"got {videos}")
    if against is not None and against not in agents:
        raise EvalError(f"the agent to pair against, {against!r}, is not among the agents "
                        f"({', '.join(agents)})")
    resolve_device(device)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise EvalError(f"output {str(out)!r} exists and is not a folder")
    require_writable(out, "output folder")
    done = _episodes_done(out, config, resume)
    loaded = {name: load_agent(a, device, config.task, config.posterior)
              if isinstance(a, str | os.PathLike)
              else a for name, a in agents.items()}
    for name, agent in loaded.items():
        check_compatible(agent, config, f"agent {name!r}")
    out.mkdir(parents=True, exist_ok=True)
    stored = json.loads((out / EVAL_CONFIG).read_text()) if (out / EVAL_CONFIG).exists() else {}
    (out / EVAL_CONFIG).write_text(json.dumps({"eval": to_json(config), "kinds": {
        **stored.get("kinds", {}), **{n: agent_kind(a) for n, a in loaded.items()}}}, indent=2))
    total = len(loaded) * len(seeds) * config.episodes
    count = sum(1 for a, s_, e in done if a in loaded and s_ in seeds and e < config.episodes)
    if on_progress is not None:
        on_progress(count, total)
    for name, agent in loaded.items():
        kind = agent_kind(agent)
        # One set of environments serves all of an agent's seeds: set up (and, with workers,
        # started) once.
        envs: LocalEnvs | EnvWorkers | None = None
        with contextlib.ExitStack() as stack:
            for seed in seeds:
                skip = frozenset(e for a, s_, e in done if a == name and s_ == seed)
                if all(i in skip for i in range(config.episodes)):
                    continue
                if envs is None:
                    envs = stack.enter_context(
                        evaluation_envs(agent, config, batch, workers, record=videos > 0))
                frames: dict[int, list[np.ndarray]] = {}
                record = functools.partial(_keep_frame, frames, videos) if videos else None

                def finished(result: EpisodeResult, name: str = name, kind: str = kind) -> None:
                    append_csv(out / "episodes.csv", {
                        "agent": name, "kind": kind, "seed": result.seed,
                        "episode": result.episode, "episode_seed": result.episode_seed,
                        "return": result.episode_return, "steps": result.steps,
                        "success": "" if result.success is None else int(result.success)},
                               EPISODE_COLUMNS)
                    if result.trajectory is not None:
                        (out / TRAJECTORIES).mkdir(exist_ok=True)
                        np.savez(out / TRAJECTORIES / trajectory_name(name, result.seed, result.episode),
                                 **result.trajectory)
                    if on_episode is not None:
                        on_episode(name, result)
                    nonlocal count
                    count += 1
                    if on_progress is not None:
                        on_progress(count, total)

                evaluate(agent, config, seed, finished, record, skip, batch, trajectories, workers,
                         envs)
                for episode, clip in frames.items():
                    write_video(episode_strip(np.stack(clip)[:, None]),
                                out / f"{name}-seed{seed}-episode{episode}.mp4")
    table = pd.read_csv(out / "episodes.csv").drop_duplicates(["agent", "seed", "episode"])
    table = _asked_for(table, list(agents), list(seeds), config.episodes)
    summary = {**summarise(table, config, against), "batch": batch}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    plot_returns(table, out / "returns.png", f"{config.task}, DR {config.dr}")
    return summary


def _asked_for(table: pd.DataFrame, agents: list[str], seeds: list[int], episodes: int
               ) -> pd.DataFrame:
    """The rows of ``agents`` x ``seeds`` x episodes < ``episodes``, ordered by agent and seed
    as asked and then by episode: a resumed evaluation's rows, appended in another order, then
    sum to the uninterrupted one's summary exactly."""
    agent_rank = {a: i for i, a in enumerate(agents)}
    seed_rank = {s: i for i, s in enumerate(seeds)}
    table = table[table["agent"].isin(agent_rank) & table["seed"].isin(seed_rank)
                  & (table["episode"] < episodes)]
    order = np.lexsort((table["episode"].to_numpy(), table["seed"].map(seed_rank).to_numpy(),
                        table["agent"].map(agent_rank).to_numpy()))
    return table.iloc[order].reset_index(drop=True)


#: What an evaluation folder records of its config, to refuse resuming it with another.
EVAL_CONFIG = "eval-config.json"


def _episodes_done(out: Path, config: EvalConfig, resume: bool) -> set[tuple[str, int, int]]:
    """(agent, seed, episode) of every episode ``out`` holds; refuses a folder that holds an
    evaluation unless ``resume``, and one whose stored config differs from ``config`` in any
    field but ``episodes``."""
    episodes = out / "episodes.csv"
    if not episodes.exists():
        return set()
    if not resume:
        raise EvalError(f"{str(out)!r} already holds an evaluation (episodes.csv); pass "
                        "--resume to continue it, or another --out")
    if (out / EVAL_CONFIG).exists():
        before = json.loads((out / EVAL_CONFIG).read_text())["eval"]
        refuse_resume(resume_conflicts(before, config, ("episodes",)), EvalError,
                      "--episodes, --agent and --seeds")
    text = episodes.read_bytes()
    if text and not text.endswith(b"\n"):  # a row cut short by a kill: the episode reruns
        episodes.write_bytes(text[:text.rfind(b"\n") + 1])
    table = pd.read_csv(episodes).dropna(subset=["return"])
    return {(str(a), int(s), int(e))
            for a, s, e in zip(table["agent"], table["seed"], table["episode"], strict=True)}


def _keep_frame(frames: dict[int, list[np.ndarray]], videos: int, episode: int,
                frame: np.ndarray) -> None:
    if episode < videos:
        frames.setdefault(episode, []).append(frame)


def summarise(table: pd.DataFrame, config: EvalConfig, against: str | None = None
              ) -> dict[str, Any]:
    """Per-agent statistics of an ``episodes.csv`` table (see :func:`run_evaluation`)."""
    oracles = table[table["kind"] == "oracle"]
    oracle_mean = float(oracles["return"].mean()) if len(oracles) else None
    agents = {}
    for name, rows in table.groupby("agent", sort=False):
        per_seed = rows.groupby("seed")["return"].mean()
        entry: dict[str, Any] = {
            "kind": rows["kind"].iloc[0], "episodes": len(rows), "seeds": len(per_seed),
            "mean": float(per_seed.mean()),
            "std_over_seeds": float(per_seed.std(ddof=0)),
            "std_over_episodes": float(rows["return"].std(ddof=0))}
        if "success" in rows and rows["success"].notna().any():
            entry["success_rate"] = float(rows["success"].dropna().mean())
        # As the report's aggregate: a non-positive oracle mean gives no ratio to normalise by.
        if oracle_mean is not None and oracle_mean > 0:
            strata = [g["return"].to_numpy() / oracle_mean for _, g in rows.groupby("seed")]
            interval = stratified_bootstrap(strata)
            entry["normalised_iqm"] = interval.estimate
            entry["normalised_iqm_ci95"] = [interval.low, interval.high]
        if against is not None and name != against:
            entry["paired"] = {"against": against,
                               **paired_episodes(table, name, against).as_dict()}
        agents[name] = entry
    return {"task": config.task, "dr": config.dr, "backgrounds": config.backgrounds,
            "episodes_per_seed": config.episodes, "oracle_mean": oracle_mean, "agents": agents}


def paired_episodes(table: pd.DataFrame, agent: str, against: str,
                    on: Sequence[str] = ("seed", "episode")) -> PairedDifference:
    """``agent``'s returns minus ``against``'s over the episodes both met, matched on ``on``
    (columns of an ``episodes.csv``-shaped ``table``)."""
    keys = list(on)
    pairs = table.loc[table["agent"] == agent, [*keys, "return"]].merge(
        table.loc[table["agent"] == against, [*keys, "return"]], on=keys,
        suffixes=("", "_against"))
    if pairs.empty:
        raise EvalError(f"agents {agent!r} and {against!r} share no episodes to pair")
    return paired_difference(pairs["return"].to_numpy(), pairs["return_against"].to_numpy())
