"""The simulated tasks of TWIST: dm_control suite tasks with privileged state and physics state.

Task names are ``<domain>-<task>`` with the paper's short names (``cup-catch`` is dm_control's
``ball_in_cup``/``catch``). :class:`TaskEnv` adds action repeat, the flattened privileged state
vector s_t, and a physics vector that restores the exact simulated instant; see ``datasets.md``
for the layouts per task.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from twist_data.errors import ConfigError, PhysicsStateError, UnknownTaskError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TaskSpec:
    """How one twist task maps onto dm_control."""

    name: str
    """Stable twist name, e.g. ``cup-catch``."""
    domain: str
    """dm_control suite domain, e.g. ``ball_in_cup``."""
    task: str
    """dm_control suite task, e.g. ``catch``."""
    camera: int = 0
    """Camera id rendered (DreamerV2 uses camera 0 for these tasks)."""
    model_fields: tuple[tuple[str, str], ...] = ()
    """Model entries the task changes per episode and that show in renders, as (field, element):
    appended to the physics vector so that restoring it reproduces the picture."""
    mirror: tuple[float, ...] = ()
    """The sign each component of the state vector takes when the rendered view is mirrored
    left to right: the camera sits in the world's x = 0 plane facing along y, so the mirror is
    the reflection x -> -x, a symmetry of the task's dynamics. A read-out may average over it
    (``ReadOutStage.mirror``); empty where not declared."""


#: The six tasks of the paper's Table I.
TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        # position (cup x, cup z, ball x, ball z), velocity (the same four).
        TaskSpec("cup-catch", "ball_in_cup", "catch", mirror=(-1, 1, -1, 1, -1, 1, -1, 1)),
        # position (cart x, cos, sin of the pole's angle), velocity (cart, pole).
        TaskSpec("cartpole-balance", "cartpole", "balance", mirror=(-1, 1, -1, -1, -1)),
        TaskSpec("cheetah-run", "cheetah", "run"),
        TaskSpec("hopper-stand", "hopper", "stand"),
        TaskSpec("walker-walk", "walker", "walk"),
        # The turn target is moved and resized per episode in the model, not in qpos.
        TaskSpec("finger-turn_easy", "finger", "turn_easy",
                 model_fields=(("site_pos", "target"), ("site_size", "target"))),
    )
}

DEFAULT_TASK = "cartpole-balance"
#: Simulator steps per agent step of DreamerV2 and TWIST on every DMC task.
DEFAULT_ACTION_REPEAT = 2


def _full_physics() -> int:
    """mj_getState signature of the physics vector: time, qpos, qvel, act, mocap, plugin state."""
    import mujoco

    return int(mujoco.mjtState.mjSTATE_FULLPHYSICS)


def state_mirror(name: str) -> tuple[float, ...]:
    """The signs of task ``name``'s state components in the mirrored view
    (:attr:`TaskSpec.mirror`, the synthetic cartpole's included); empty where none is
    declared."""
    from twist_data.synth import SYNTH_MIRROR, SYNTH_TASK

    if name == SYNTH_TASK:
        return SYNTH_MIRROR
    return tuple(float(v) for v in TASKS[name].mirror) if name in TASKS else ()


def task_spec(name: str) -> TaskSpec:
    """The spec of task ``name``; an unknown name raises listing the valid ones."""
    try:
        return TASKS[name]
    except KeyError:
        raise UnknownTaskError(
            f"unknown task {name!r}; valid tasks are: {', '.join(sorted(TASKS))}"
        ) from None


#: One never-stepped environment per task, copied for every further environment of that task.
_PRISTINE: dict[str, Any] = {}


def load_suite_env(spec: TaskSpec, seed: int = 0):
    """dm_control's environment for ``spec``, without its model-compiler deprecation chatter.

    The first call per task compiles the model from its XML (~0.1 s); later calls deep-copy
    a never-stepped environment (~0.02 s), which a batched evaluation's N episode slots pay
    N times. The copy has its own model and data and gets the task's RandomState(``seed``),
    as ``suite.load`` would give it: a copy equals a fresh load (tested)."""
    env = _PRISTINE.get(spec.name)
    if env is None:
        from dm_control import suite

        absl = logging.getLogger("absl")
        level = absl.level
        # cheetah.xml uses a deprecated compiler attribute; MuJoCo warns on every load.
        absl.setLevel(logging.ERROR)
        try:
            env = _PRISTINE[spec.name] = suite.load(spec.domain, spec.task,
                                                    task_kwargs={"random": 0})
        finally:
            absl.setLevel(level)
    env = copy.deepcopy(env)
    env.task._random = np.random.RandomState(seed)  # what suite.load's ``random`` sets
    return env


@dataclass(frozen=True)
class Step:
    """One agent step in the dataset's time convention (reward and action led *to* this step)."""

    state: np.ndarray
    """[S] float32 privileged state."""
    physics: np.ndarray
    """[P] float64 physics vector."""
    reward: float
    """Sum of rewards over the repeated simulator steps; 0 on the first step."""
    discount: float
    """0 if the episode ended in a true terminal state, else 1."""
    is_first: bool
    is_last: bool
    is_terminal: bool


@dataclass(frozen=True)
class Dynamics:
    """Per-episode dynamics randomisation (multipliers of the model's nominal values)."""

    friction_scale: float = 1.0
    """Multiplier of every geom's sliding friction."""
    mass_scale: float = 1.0
    """Multiplier of every body's mass (and inertia, so shapes keep their density)."""

    def __post_init__(self) -> None:
        for name in ("friction_scale", "mass_scale"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive finite number, got {value}")


class TaskEnv:
    """One dm_control task with action repeat, privileged state and restorable physics state."""

    def __init__(self, task: str = DEFAULT_TASK, action_repeat: int = DEFAULT_ACTION_REPEAT,
                 seed: int = 0, max_steps: int | None = None) -> None:
        """``max_steps`` ends episodes after that many agent steps (a time limit shorter than
        the task's 1000 simulator steps, for tests and quick demos)."""
        if action_repeat < 1:
            raise ConfigError(f"action_repeat must be >= 1, got {action_repeat}")
        if max_steps is not None and max_steps < 1:
            raise ConfigError(f"max_steps must be >= 1, got {max_steps}")
        self.max_steps = max_steps
        self._steps = 0
        self.spec = task_spec(task)
        self._env = load_suite_env(self.spec, seed)
        self.action_repeat = action_repeat
        self.physics = self._env.physics
        self.model = self.physics.model.ptr
        self.data = self.physics.data.ptr
        self._nominal_friction = self.model.geom_friction[:, 0].copy()
        self._nominal_mass = self.model.body_mass.copy()
        self._nominal_inertia = self.model.body_inertia.copy()
        observation = self._env.task.get_observation(self.physics)
        self.state_layout: tuple[tuple[str, int], ...] = tuple(
            (key, int(np.asarray(value).size)) for key, value in observation.items()
        )
        import mujoco

        self._core_dim = mujoco.mj_stateSize(self.model, _full_physics())
        self._rows = model_rows(self.model, self.spec)
        # Asked on every step; dm_control builds a new spec per call (~0.2 ms).
        self._action_dim = int(self._env.action_spec().shape[0])
        self._done = True

    # -- sizes -------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def state_dim(self) -> int:
        return sum(n for _, n in self.state_layout)

    @property
    def action_dim(self) -> int:
        return self._action_dim

    @property
    def seconds_per_step(self) -> float:
        """Simulated seconds per agent step (the task's control step times the repeat)."""
        return float(self._env.control_timestep()) * self.action_repeat

    @property
    def physics_dim(self) -> int:
        return self._core_dim + sum(row.size for row in self._rows)

    @property
    def physics_layout(self) -> tuple[tuple[str, int], ...]:
        """Names and lengths of the fields of the physics vector, in order."""
        m = self.model
        core = (("time", 1), ("qpos", m.nq), ("qvel", m.nv), ("act", m.na),
                ("mocap_pos", 3 * m.nmocap), ("mocap_quat", 4 * m.nmocap))
        core = tuple((n, int(s)) for n, s in core if s)
        known = sum(s for _, s in core)
        if known != self._core_dim:  # plugin state or other fields of newer MuJoCo versions
            core = (*core, ("other", self._core_dim - known))
        extra = tuple((f"{f}[{e}]", row.size) for (f, e), row in
                      zip(self.spec.model_fields, self._rows, strict=True))
        return core + extra

    # -- stepping ----------------------------------------------------------------------------
    def reset(self, seed: int | None = None, dynamics: Dynamics | None = None) -> Step:
        """Start an episode (optionally reseeding the task's initial-state randomness)."""
        dynamics = dynamics or Dynamics()
        self.model.geom_friction[:, 0] = self._nominal_friction * dynamics.friction_scale
        self.model.body_mass[:] = self._nominal_mass * dynamics.mass_scale
        self.model.body_inertia[:] = self._nominal_inertia * dynamics.mass_scale
        if seed is not None:
            # dm_control keeps the task's RandomState privately; replacing it is the only way
            # to make one episode's initial state a function of its own seed.
            self._env.task._random = np.random.RandomState(seed)
        time_step = self._env.reset()
        self._done = False
        self._steps = 0
        return self._make_step(time_step, 0.0, first=True)

    def step(self, action: np.ndarray) -> Step:
        """Apply ``action`` for ``action_repeat`` simulator steps."""
        if self._done:
            raise ConfigError("step() called on a finished episode; call reset() first")
        action = np.asarray(action, np.float64)
        if action.shape != (self.action_dim,):
            raise ConfigError(f"action must have shape ({self.action_dim},), got {action.shape}")
        reward = 0.0
        for _ in range(self.action_repeat):
            time_step = self._env.step(action)
            reward += float(time_step.reward or 0.0)
            if time_step.last():
                break
        self._steps += 1
        return self._make_step(time_step, reward, first=False)

    def _make_step(self, time_step, reward: float, first: bool) -> Step:
        last = bool(time_step.last()) or (self.max_steps is not None
                                           and self._steps >= self.max_steps)
        discount = 1.0 if time_step.discount is None else float(time_step.discount)
        terminal = last and discount == 0.0
        self._done = last
        return Step(state=self.flat_state(time_step.observation), physics=self.physics_state(),
                    reward=reward, discount=0.0 if terminal else 1.0, is_first=first,
                    is_last=last, is_terminal=terminal)

    def flat_state(self, observation: dict | None = None) -> np.ndarray:
        """The privileged state vector (observation fields concatenated in ``state_layout``)."""
        if observation is None:
            observation = self._env.task.get_observation(self.physics)
        return np.concatenate([np.asarray(v, np.float32).ravel() for v in observation.values()])

    # -- physics state -----------------------------------------------------------------------
    def physics_state(self) -> np.ndarray:
        """[P] float64: MuJoCo full physics state plus the task's per-episode model entries."""
        return physics_vector(self.model, self.data, self._rows)

    def set_physics_state(self, physics: np.ndarray) -> None:
        """Restore an instant recorded by :meth:`physics_state` (kinematics recomputed)."""
        restore_physics(self.model, self.data, physics, self._rows, self.spec.name)


def physics_vector(model, data, model_values: list[np.ndarray]) -> np.ndarray:
    """Full physics state of ``data`` followed by the task's per-episode model entries."""
    import mujoco

    sig = _full_physics()
    core = np.empty(mujoco.mj_stateSize(model, sig), np.float64)
    mujoco.mj_getState(model, data, core, sig)
    return np.concatenate([core, *[np.asarray(v, np.float64).ravel() for v in model_values]])


def restore_physics(model, data, physics: np.ndarray, rows: list[np.ndarray], task: str) -> None:
    """Write a physics vector into ``model``/``data`` (and the task's model ``rows``, from
    :func:`model_rows`) and recompute positions (``mj_forward``)."""
    import mujoco

    sig = _full_physics()
    core = mujoco.mj_stateSize(model, sig)
    physics = np.asarray(physics, np.float64)
    expected = core + sum(row.size for row in rows)
    if physics.ndim != 1 or physics.shape[0] != expected:
        raise PhysicsStateError(
            f"physics state for task {task!r} must be a vector of length {expected}, "
            f"got shape {physics.shape}"
        )
    if not np.all(np.isfinite(physics)):
        raise PhysicsStateError(f"physics state for task {task!r} has non-finite values")
    mujoco.mj_setState(model, data, physics[:core], sig)
    offset = core
    for row in rows:
        row[:] = physics[offset:offset + row.size]
        offset += row.size
    mujoco.mj_forward(model, data)


def model_rows(model, spec: TaskSpec) -> list[np.ndarray]:
    """Writable views of the model entries ``spec.model_fields`` names, looked up once."""
    import mujoco

    kinds = {"site": mujoco.mjtObj.mjOBJ_SITE, "geom": mujoco.mjtObj.mjOBJ_GEOM,
             "body": mujoco.mjtObj.mjOBJ_BODY}
    return [getattr(model, field_name)[
                mujoco.mj_name2id(model, kinds[field_name.split("_")[0]], element)]
            for field_name, element in spec.model_fields]
