"""The simulated tasks of TWIST: registered dm_control-style tasks with privileged state and
physics state.

A task is a registered :class:`TaskSpec`: the six DMC tasks of the paper are registered here,
by dm_control suite domain and task (names ``<domain>-<task>`` with the paper's short names:
``cup-catch`` is dm_control's ``ball_in_cup``/``catch``); a user registers their own from
their own module with :func:`register_task`, giving a factory of a dm_control
``control.Environment`` (any MJCF scene and a ``base.Task`` with its observation and reward).
Every stage finds a task by name through :func:`task_spec`, which first imports the modules
named in ``TWIST_TASK_MODULES`` and the ``twist.tasks`` entry points, so that a user's task is
known in every process, the renderer's workers included. :class:`TaskEnv` adds action repeat,
the flattened privileged state vector s_t, and a physics vector that restores the exact
simulated instant; see ``datasets.md`` for the layouts per task.
"""

from __future__ import annotations

import copy
import functools
import importlib
import logging
import os
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from twist_data.errors import ConfigError
from twist_sim.errors import PhysicsStateError, TaskRegistrationError, UnknownTaskError
from twist_sim.randomisation import COLOUR_GROUPS, Dynamics

log = logging.getLogger(__name__)

#: What a task's name looks like: lower-case words joined by one hyphen (``cup-catch``).
TASK_NAME = re.compile(r"^[a-z0-9_]+-[a-z0-9_]+$")
#: Environment variable: comma-separated modules that register tasks when imported.
TASK_MODULES_VARIABLE = "TWIST_TASK_MODULES"
#: Entry-point group of installed packages' task modules (each entry point is imported).
TASK_ENTRY_POINTS = "twist.tasks"
#: The kinds of model element ``TaskSpec.model_fields`` may name, by a field's prefix.
_OBJECT_KINDS = {"site": "mjOBJ_SITE", "geom": "mjOBJ_GEOM", "body": "mjOBJ_BODY"}


@dataclass(frozen=True)
class TaskSpec:
    """One twist task: where its dm_control environment comes from and what DR may touch."""

    name: str
    """Stable twist name, ``<words>-<words>``, e.g. ``cup-catch``."""
    domain: str = ""
    """dm_control suite domain, e.g. ``ball_in_cup`` (a suite task; empty with
    ``environment``)."""
    task: str = ""
    """dm_control suite task, e.g. ``catch``."""
    environment: Callable[[], Any] | None = field(default=None, compare=False)
    """A factory of the task's dm_control ``control.Environment`` (a user's task; None for a
    suite task). It is called once per process; every episode's environment is a copy, seeded
    through its task's ``random``."""
    camera: int = 0
    """Camera id rendered (DreamerV2 uses camera 0 for the suite tasks)."""
    model_fields: tuple[tuple[str, str], ...] = ()
    """Model entries the task changes per episode and that show in renders, as (field, element):
    appended to the physics vector so that restoring it reproduces the picture."""
    mirror: tuple[float, ...] = ()
    """The sign each component of the state vector takes when the rendered view is mirrored
    left to right: the camera sits in a vertical plane of the world's (x = 0 facing along y
    for the suite's camera 0, y = 0 facing along -x for the panda tasks'), so the mirror is
    the reflection through that plane, a symmetry of the task's dynamics. A read-out may average over it
    (``ReadOutStage.mirror``); empty where not declared."""
    success: Callable[[np.ndarray], bool] | None = field(default=None, compare=False)
    """Whether an episode that ends in this privileged state [S] succeeded (the manipulation
    tasks: the block on the goal, or lifted); evaluation reports the rate beside the return.
    None: the task's return is its only measure."""
    revision: int = 1
    """Raised whenever the task's dynamics, reward or state change so that data recorded
    before would differ: every D records it (``extra["task_revision"]``) and a collection
    refuses to add to a D of another revision, whose steps would mix two tasks."""

    def __post_init__(self) -> None:
        if not TASK_NAME.match(self.name):
            raise TaskRegistrationError(f"a task's name is lower-case words joined by one "
                                        f"hyphen, like 'cup-catch'; got {self.name!r}")
        if self.revision < 1:
            raise TaskRegistrationError(f"task {self.name!r} needs a revision >= 1, got "
                                        f"{self.revision}")
        if (self.environment is None) == bool(self.domain and self.task):
            return
        raise TaskRegistrationError(
            f"task {self.name!r} needs either an environment factory or a dm_control suite "
            f"domain and task, not {'both' if self.environment is not None else 'neither'}")

    @property
    def source(self) -> str:
        """Where the task's environment comes from, in words."""
        if self.environment is None:
            return f"dm_control {self.domain}/{self.task}"
        factory = self.environment
        return f"{getattr(factory, '__module__', '?')}.{getattr(factory, '__qualname__', '?')}"


_REGISTERED: dict[str, TaskSpec] = {}
#: Called with each task :func:`register_task` adds (:func:`on_register`).
_LISTENERS: list[Callable[[TaskSpec], Any]] = []
#: Every registered task by name, a read-only view that follows :func:`register_task`.
TASKS: Mapping[str, TaskSpec] = MappingProxyType(_REGISTERED)

def _panda(lift: bool) -> Any:
    from twist_sim.panda import environment

    return environment(lift)


def _panda_success(lift: bool, state: np.ndarray) -> bool:
    from twist_sim.panda import succeeded

    return succeeded(lift, state)


# The six tasks of the paper's Table I, and its two manipulation tasks.
for _spec in (
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
        # The paper's manipulation tasks (twist_sim.panda); the goal marker moves per episode.
        # Their camera looks along -x from the plane y = 0: the mirror is y -> -y.
        # position (fingertips x y z, block x y z, goal x y), velocity (fingertips, block).
        TaskSpec("panda-push", environment=functools.partial(_panda, False),
                 model_fields=(("site_pos", "goal"),),
                 mirror=(1, -1, 1, 1, -1, 1, 1, -1, 1, -1, 1, 1, -1, 1),
                 success=functools.partial(_panda_success, False)),
        # position (fingertips x y z, opening, block x y z), velocity (the same seven).
        TaskSpec("panda-lift", environment=functools.partial(_panda, True),
                 mirror=(1, -1, 1, 1, 1, -1, 1, 1, -1, 1, 1, 1, -1, 1),
                 success=functools.partial(_panda_success, True),
                 revision=2)):  # 2: a grasp needs the fingers on the block's sides
    _REGISTERED[_spec.name] = _spec

DEFAULT_TASK = "cartpole-balance"
#: Simulator steps per agent step of DreamerV2 and TWIST on every DMC task.
DEFAULT_ACTION_REPEAT = 2


def register_task(spec: TaskSpec) -> TaskSpec:
    """Register a task under ``spec.name`` for every command and the Gymnasium ids; returns
    ``spec``. The environment is built once to check it: a state layout (a non-empty mapping
    of observations), actions within [-1, 1], a rendered camera and model fields that exist,
    a state mirror of the state's length, and at least one material DR recolours. A name taken
    already, or a spec that fails a check, is refused in one sentence and nothing registers."""
    if spec.name in _REGISTERED:
        raise TaskRegistrationError(f"a task named {spec.name!r} is registered already "
                                    f"({_REGISTERED[spec.name].source})")
    _check_task(spec)
    _REGISTERED[spec.name] = spec
    for listener in _LISTENERS:
        listener(spec)
    return spec


def on_register(listener: Callable[[TaskSpec], Any]) -> None:
    """Call ``listener`` with every task registered from now on (the Gymnasium environments
    register its ids)."""
    _LISTENERS.append(listener)


def _check_task(spec: TaskSpec) -> None:
    import mujoco

    try:
        env = spec.environment()
    except Exception as exc:  # a user's factory: any failure is the task's
        raise TaskRegistrationError(f"task {spec.name!r}: its environment factory failed: "
                                    f"{type(exc).__name__}: {exc}") from None
    def refuse(problem: str) -> TaskRegistrationError:
        return TaskRegistrationError(f"task {spec.name!r} {problem}")

    for attribute in ("physics", "task", "reset", "step", "action_spec", "control_timestep"):
        if not hasattr(env, attribute):
            raise refuse(f"needs a dm_control control.Environment, got {type(env).__name__} "
                         f"(no {attribute!r})")
    observation = env.task.get_observation(env.physics)
    if not isinstance(observation, Mapping) or not observation:
        raise refuse("declares no state layout: its task's get_observation must return a "
                     f"non-empty mapping of named arrays, got {observation!r}")
    state_dim = sum(int(np.asarray(value).size) for value in observation.values())
    if spec.mirror and len(spec.mirror) != state_dim:
        raise refuse(f"declares a mirror of {len(spec.mirror)} signs for a state of "
                     f"{state_dim} components")
    action = env.action_spec()
    low, high = np.broadcast_to(action.minimum, action.shape), np.broadcast_to(action.maximum,
                                                                               action.shape)
    if len(action.shape) != 1 or not (np.all(low >= -1) and np.all(high <= 1)):
        raise refuse(f"must take a vector of actions within [-1, 1] (an actor's tanh range), "
                     f"got shape {action.shape} within [{low.min()}, {high.max()}]")
    model = env.physics.model.ptr
    if not 0 <= spec.camera < model.ncam:
        raise refuse(f"renders camera {spec.camera}, but its model has {model.ncam} cameras")
    for field_name, element in spec.model_fields:
        if _model_field_index(model, field_name, element) is None:
            raise refuse(f"names model field {field_name}[{element}], which its model lacks")
    if all(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name) < 0
           for name in COLOUR_GROUPS):
        raise refuse(f"has no material domain randomisation recolours: name at least one of "
                     f"its materials {', '.join(COLOUR_GROUPS)}")


_LOADED_MODULES = False


def load_task_modules() -> None:
    """Import the modules named in ``TWIST_TASK_MODULES`` and the ``twist.tasks`` entry points,
    once per process: they register their tasks as they import."""
    global _LOADED_MODULES
    if _LOADED_MODULES:
        return
    _LOADED_MODULES = True
    from importlib.metadata import entry_points

    names = [n.strip() for n in os.environ.get(TASK_MODULES_VARIABLE, "").split(",") if n.strip()]
    for name in names:
        if name in sys.modules:
            continue
        try:
            importlib.import_module(name)
        except ImportError as exc:
            raise TaskRegistrationError(f"task module {name!r} named in "
                                        f"{TASK_MODULES_VARIABLE} does not import: {exc}") from None
    for entry in entry_points(group=TASK_ENTRY_POINTS):
        entry.load()


def physics_signature(model) -> int:
    """mj_getState signature of the physics vector: time, qpos, qvel, act and plugin state,
    and a mocap body's pose where the model has one (a task driven through a mocap body:
    MuJoCo keeps its pose apart from the full physics state; the built-in tasks have none)."""
    import mujoco

    signature = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    if model.nmocap:
        signature |= int(mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT)
    return signature


def state_mirror(name: str) -> tuple[float, ...]:
    """The signs of task ``name``'s state components in the mirrored view
    (:attr:`TaskSpec.mirror`, the synthetic cartpole's included); empty where none is
    declared."""
    from twist_data.synth import SYNTH_MIRROR, SYNTH_TASK

    if name == SYNTH_TASK:
        return SYNTH_MIRROR
    try:
        return tuple(float(v) for v in task_spec(name).mirror)
    except UnknownTaskError:
        return ()


def task_spec(name: str) -> TaskSpec:
    """The spec of task ``name`` (the task modules imported first); an unknown name raises
    listing the registered ones."""
    if name not in _REGISTERED:
        load_task_modules()
    try:
        return _REGISTERED[name]
    except KeyError:
        raise UnknownTaskError(
            f"unknown task {name!r}; registered tasks are: {', '.join(sorted(_REGISTERED))}"
        ) from None


#: One never-stepped environment per task, copied for every further environment of that task.
_PRISTINE: dict[str, Any] = {}


def load_environment(spec: TaskSpec, seed: int = 0):
    """The task's dm_control environment (a suite task's without its model-compiler
    deprecation chatter).

    The first call per task builds it (a suite task compiles its XML, ~0.1 s); later calls
    deep-copy a never-stepped environment (~0.02 s), which a batched evaluation's N episode
    slots pay N times. The copy has its own model and data and gets the task's
    RandomState(``seed``), as ``suite.load`` would give it: a copy equals a fresh load
    (tested)."""
    env = _PRISTINE.get(spec.name)
    if env is None:
        absl = logging.getLogger("absl")
        level = absl.level
        # cheetah.xml uses a deprecated compiler attribute; MuJoCo warns on every load.
        absl.setLevel(logging.ERROR)
        try:
            if spec.environment is not None:
                env = spec.environment()
            else:
                from dm_control import suite

                env = suite.load(spec.domain, spec.task, task_kwargs={"random": 0})
        finally:
            absl.setLevel(level)
        _PRISTINE[spec.name] = env
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
        self._env = load_environment(self.spec, seed)
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

        self._core_dim = mujoco.mj_stateSize(self.model, physics_signature(self.model))
        self._rows = model_rows(self.model, self.spec)
        # Asked on every step; dm_control builds a new spec per call (~0.2 ms).
        action_spec = self._env.action_spec()
        self._action_dim = int(action_spec.shape[0])
        self._action_low = np.broadcast_to(action_spec.minimum, action_spec.shape) - 1e-6
        self._action_high = np.broadcast_to(action_spec.maximum, action_spec.shape) + 1e-6
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
        if not (np.all(action >= self._action_low) and np.all(action <= self._action_high)):
            raise ConfigError(f"{self.name}'s actions lie within [{self._action_low.min():.3g}, "
                              f"{self._action_high.max():.3g}]; got {action.tolist()}")
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

    sig = physics_signature(model)
    core = np.empty(mujoco.mj_stateSize(model, sig), np.float64)
    mujoco.mj_getState(model, data, core, sig)
    return np.concatenate([core, *[np.asarray(v, np.float64).ravel() for v in model_values]])


def restore_physics(model, data, physics: np.ndarray, rows: list[np.ndarray], task: str) -> None:
    """Write a physics vector into ``model``/``data`` (and the task's model ``rows``, from
    :func:`model_rows`) and recompute positions (``mj_forward``)."""
    import mujoco

    sig = physics_signature(model)
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
    return [getattr(model, field_name)[_model_field_index(model, field_name, element)]
            for field_name, element in spec.model_fields]


def _model_field_index(model, field_name: str, element: str) -> int | None:
    """The row of model field ``field_name`` (e.g. ``site_pos``) that element ``element`` owns,
    or None when the model has no such field or element."""
    import mujoco

    kind = _OBJECT_KINDS.get(field_name.split("_")[0])
    if kind is None or not hasattr(model, field_name):
        return None
    index = mujoco.mj_name2id(model, getattr(mujoco.mjtObj, kind), element)
    return None if index < 0 else index
