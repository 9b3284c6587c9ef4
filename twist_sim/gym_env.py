"""twist's tasks and DR scenes as Gymnasium environments (``pip install twist[gym]``).

``gymnasium.make("twist/cartpole-balance-heldout-v0")`` (after ``import twist_sim.gym_env``,
or as ``gymnasium.make("twist_sim.gym_env:twist/cartpole-balance-heldout-v0")``) gives an
environment for every registered task (:data:`~twist_sim.tasks.TASKS`, a user's too) and
DR preset of :data:`~twist_sim.randomisation.DR_PRESETS`: observations are a dict of the rendered
view (``image``, uint8 [H, W, 3]) and/or the privileged state (``state``, float32 [S]);
actions are in [-1, 1].

The scenes are drawn as ``twist-eval`` draws them: the DR parameters and the dynamics once per
episode, episode i after ``reset(seed=s)`` from the seed ``twist-eval --seeds s`` gives its
episode i. So a policy run here for N episodes after ``reset(seed=s)`` meets exactly the
scenes and initial states that ``twist-eval --seeds s --episodes N`` shows its agents, and
its returns can be compared with theirs episode by episode.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import numpy as np

from twist_data.errors import ConfigError, import_extra
from twist_data.seeding import evaluation_episode_seed
from twist_sim.randomisation import DR_PRESETS, dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import (
    DEFAULT_ACTION_REPEAT,
    DEFAULT_TASK,
    TASKS,
    TaskEnv,
    load_task_modules,
    on_register,
)

gymnasium = import_extra("gymnasium", "gym", "the Gymnasium environments need")
spaces = gymnasium.spaces

#: What an observation may hold.
OBSERVATION_KEYS = ("image", "state")
class TwistEnv(gymnasium.Env):
    """One task in one DR preset's scenes, drawn once per episode."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"]}

    def __init__(self, task: str = DEFAULT_TASK, dr: str = "heldout",
                 observe: tuple[str, ...] | str = OBSERVATION_KEYS,
                 backgrounds: str | None = None, image_size: int = 64, supersample: int = 1,
                 action_repeat: int = DEFAULT_ACTION_REPEAT, max_steps: int | None = None,
                 render_mode: str | None = None) -> None:
        observe = (observe,) if isinstance(observe, str) else tuple(observe)
        unknown = [k for k in observe if k not in OBSERVATION_KEYS]
        if not observe or unknown:
            raise ConfigError(f"observe must name some of {', '.join(OBSERVATION_KEYS)}, "
                              f"got {observe!r}")
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.observe, self.render_mode = observe, render_mode
        self.task = TaskEnv(task, action_repeat, max_steps=max_steps)
        self.metadata = {**self.metadata, "render_fps": round(1 / self.task.seconds_per_step)}
        config = dataclasses.replace(dr_preset(dr, backgrounds), resample="episode")
        self._renderer = DRRenderer(task, config, image_size, views=1, supersample=supersample)
        self._sampler = self._renderer.sampler(0)
        self.observation_space = spaces.Dict({
            key: space for key, space in (
                ("image", spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)),
                ("state", spaces.Box(-np.inf, np.inf, (self.task.state_dim,), np.float32)),
            ) if key in observe})
        self.action_space = spaces.Box(-1.0, 1.0, (self.task.action_dim,), np.float32)
        self._seed: int | None = None
        self._episode = -1
        self._step = None
        self._draws: dict[str, np.ndarray] = {}
        self._image: np.ndarray | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._seed, self._episode = int(seed), 0
        else:
            if self._seed is None:  # unseeded: Gymnasium's own random seed
                self._seed = int(self.np_random.integers(2**31))
            self._episode += 1
        this = evaluation_episode_seed(self._seed, self._episode)
        self._step = self.task.reset(seed=this, dynamics=self._sampler.begin_episode(this))
        self._draws = self._sampler.sample()
        return self._observation(), {"episode": self._episode, "episode_seed": this}

    def step(self, action: np.ndarray
             ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._step is None or self._step.is_last:
            raise gymnasium.error.ResetNeeded("call reset() before step() and after an "
                                              "episode ends")
        action = np.clip(np.asarray(action, np.float32), -1.0, 1.0)
        self._step = step = self.task.step(action)
        terminated = bool(step.is_last and step.discount == 0.0)
        truncated = bool(step.is_last and not terminated)
        return self._observation(), float(step.reward), terminated, truncated, {}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._step is None:
            return None
        return self._render()

    def close(self) -> None:
        self._renderer.close()

    def _render(self) -> np.ndarray:
        if self._image is None:
            self._image = self._renderer.render(self._step.physics, self._draws)[0]
        return self._image

    def _observation(self) -> dict[str, np.ndarray]:
        self._image = None
        obs: dict[str, np.ndarray] = {}
        if "image" in self.observe:
            obs["image"] = self._render()
        if "state" in self.observe:
            obs["state"] = np.asarray(self._step.state, np.float32)
        return obs


def environment_id(task: str, dr: str) -> str:
    """The registered id of ``task`` in ``dr``'s scenes."""
    return f"twist/{task}-{dr}-v0"


def register_environments() -> list[str]:
    """Register every task x DR preset with Gymnasium (done on import, and again for each task
    :func:`~twist_sim.tasks.register_task` adds later); returns the ids."""
    load_task_modules()
    ids = []
    for task in TASKS:
        for dr in DR_PRESETS:
            env_id = environment_id(task, dr)
            if env_id not in gymnasium.registry:
                gymnasium.register(env_id, entry_point=TwistEnv,
                                   kwargs={"task": task, "dr": dr})
            ids.append(env_id)
    return ids


register_environments()
on_register(lambda spec: register_environments())
