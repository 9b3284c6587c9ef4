"""Recording episodes of a simulated task into the dataset format (state, physics, K DR views).

The collector drives :func:`record_episode` with the teacher's policy; tests, demos, contact
sheets and the renderer benchmark drive it with :func:`random_policy`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from twist_data.errors import ConfigError
from twist_data.schema import DatasetSpec, Episode, EpisodeInfo
from twist_data.seeding import derived_seed
from twist_data.writer import ShardWriter
from twist_sim.randomisation import (
    EPISODE_PARAMS,
    VIEW_PARAMS,
    DRConfig,
    DRSampler,
    dynamics_params,
    stack_view_params,
)
from twist_sim.render import DRRenderer, FrameRenderer
from twist_sim.tasks import DEFAULT_ACTION_REPEAT, Step, TaskEnv, task_spec

log = logging.getLogger(__name__)

#: Maps the current step (privileged state, physics, flags) to the next action in [-1, 1].
Policy = Callable[[Step], np.ndarray]


def random_policy(action_dim: int, seed: int = 0) -> Policy:
    """Uniform random actions in [-1, 1] (Dreamer's prefill policy)."""
    rng = np.random.default_rng(seed)

    def act(step: Step) -> np.ndarray:
        return rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)

    return act


def library_versions() -> dict[str, str]:
    """Versions that determine simulation and rendering results, for provenance."""
    import importlib.metadata

    import mujoco

    import twist_data

    # dm_control defines no __version__; its distribution metadata holds the version.
    return {"twist": twist_data.__version__, "mujoco": mujoco.__version__,
            "dm_control": importlib.metadata.version("dm-control")}


def simulated_spec(env: TaskEnv, renderer: FrameRenderer, extra: dict[str, Any] | None = None) -> DatasetSpec:
    """The dataset spec of episodes recorded from ``env`` through ``renderer``."""
    return DatasetSpec(
        views=renderer.views, image_height=renderer.image_size, image_width=renderer.image_size,
        state_dim=env.state_dim, action_dim=env.action_dim, physics_dim=env.physics_dim,
        task=env.name, action_repeat=env.action_repeat, dr_params=VIEW_PARAMS,
        episode_dr_params=EPISODE_PARAMS, state_layout=env.state_layout,
        extra={"render": [renderer.provenance()], "physics_layout": [list(f) for f in env.physics_layout],
               "versions": library_versions(), "task_revision": task_spec(env.name).revision,
               **(extra or {})},
    )


def record_episode(env: TaskEnv, renderer: FrameRenderer, sampler: DRSampler, policy: Policy,
                   seed: int, policy_name: str = "random", teacher_step: int = -1,
                   env_step: int = 0, timings: dict[str, float] | None = None,
                   ) -> tuple[Episode, EpisodeInfo]:
    """Run one episode from ``env.reset(seed)`` and render K randomised views of every step.

    ``timings``, when given, accumulates seconds spent in ``physics``, ``render`` (DR draws
    included; with a render process, submitting and waiting for the last frames) and
    ``policy``.
    """
    clock = timings if timings is not None else {}
    for part in ("physics", "render", "policy"):
        clock.setdefault(part, 0.0)
    tick = time.perf_counter()

    def lap(part: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        clock[part] += now - tick
        tick = now

    dynamics = sampler.begin_episode(seed)
    step = env.reset(seed=seed, dynamics=dynamics)
    steps: list[Step] = []
    actions: list[np.ndarray] = [np.zeros(env.action_dim, np.float32)]
    params: list[dict[str, np.ndarray]] = []
    lap("physics")
    try:
        while True:
            view_params = sampler.sample()
            renderer.submit(step.physics, view_params)
            params.append(view_params)
            steps.append(step)
            lap("render")
            if step.is_last:
                break
            action = np.clip(np.asarray(policy(step), np.float32), -1.0, 1.0)
            actions.append(action)
            lap("policy")
            step = env.step(action)
            lap("physics")
    except BaseException:
        with contextlib.suppress(Exception):  # drop this episode's frames, keep none pending
            renderer.gather()
        raise
    images = renderer.gather()
    lap("render")
    episode = Episode(
        image=images,
        state=np.stack([s.state for s in steps]),
        physics=np.stack([s.physics for s in steps]),
        action=np.stack(actions),
        reward=np.array([s.reward for s in steps], np.float32),
        discount=np.array([s.discount for s in steps], np.float32),
        is_first=np.array([s.is_first for s in steps]),
        is_last=np.array([s.is_last for s in steps]),
        is_terminal=np.array([s.is_terminal for s in steps]),
        dr=stack_view_params(params),
    )
    info = EpisodeInfo(seed=seed, policy=policy_name, teacher_step=teacher_step, env_step=env_step,
                       dr=dynamics_params(dynamics))
    return episode, info


def record_dataset(out: str | os.PathLike[str], task: str, episodes: int, config: DRConfig,
                   views: int = 2, image_size: int = 64,
                   action_repeat: int = DEFAULT_ACTION_REPEAT,
                   max_steps: int | None = None, seed: int = 0, shard: str = "random-000",
                   on_episode: Callable[[int, int], None] | None = None) -> Path:
    """Record ``episodes`` random-policy episodes of ``task`` into a new shard of ``out``.

    Episode i uses seed ``SeedSequence([seed, i])`` for the task's initial state, the policy
    and the randomisation, so the data is a pure function of the arguments.
    """
    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    env = TaskEnv(task, action_repeat=action_repeat, seed=seed, max_steps=max_steps)
    with DRRenderer(task, config, image_size, views) as renderer:
        sampler = renderer.sampler(seed)
        with ShardWriter.create(out, shard, simulated_spec(env, renderer)) as writer:
            frames = 0
            for i in range(episodes):
                episode_seed = derived_seed(seed, i)
                episode, info = record_episode(env, renderer, sampler,
                                               random_policy(env.action_dim, episode_seed),
                                               seed=episode_seed, env_step=frames)
                writer.append(episode, info)
                frames += (len(episode) - 1) * action_repeat
                if on_episode is not None:
                    on_episode(i + 1, episodes)
    log.info("recorded %d random episodes of %s into %s", episodes, task, out)
    return Path(out)
