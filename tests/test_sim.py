"""Simulated tasks: privileged state, physics state, dynamics randomisation."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import mask_overlap
from twist_data.errors import ConfigError
from twist_sim.errors import PhysicsStateError, UnknownTaskError
from twist_sim.randomisation import Dynamics
from twist_sim.tasks import TASKS, TaskEnv, task_spec

# Observation sizes of the DMC tasks as DreamerV2/DrQ report them for state-based agents.
KNOWN_STATE_DIMS = {"cup-catch": 8, "cartpole-balance": 5, "cheetah-run": 17, "hopper-stand": 15,
                    "walker-walk": 24, "finger-turn_easy": 12,
                    # fingertips, block and goal (x, y) or opening, with their velocities
                    "panda-push": 14, "panda-lift": 14}


@pytest.mark.parametrize("task", sorted(TASKS))
def test_state_and_physics_dimensions(task: str) -> None:
    env = TaskEnv(task, max_steps=3)
    step = env.reset(seed=0)
    assert step.state.shape == (KNOWN_STATE_DIMS[task],) == (env.state_dim,)
    assert step.state.dtype == np.float32
    spec_dims = sum(int(np.prod(s.shape)) for s in env._env.observation_spec().values())
    assert env.state_dim == spec_dims
    m = env.model
    # finger's target site position and size; panda-push's goal position
    extra = {"finger-turn_easy": 6, "panda-push": 3}.get(task, 0)
    mocap = 7 * m.nmocap  # the manipulation tasks' gripper target, position and quaternion
    assert step.physics.shape == (1 + m.nq + m.nv + m.na + mocap + extra,) == (env.physics_dim,)
    assert sum(n for _, n in env.physics_layout) == env.physics_dim
    assert env.action_dim == env._env.action_spec().shape[0]


def test_unknown_task_lists_valid_names() -> None:
    with pytest.raises(UnknownTaskError, match="registered tasks are: cartpole-balance, cheetah-run"):
        TaskEnv("cartpole-swingup")


def test_episode_flags_rewards_and_action_repeat() -> None:
    env, single = TaskEnv("cartpole-balance", action_repeat=2), TaskEnv("cartpole-balance",
                                                                       action_repeat=1)
    first = env.reset(seed=4)
    single.reset(seed=4)
    assert first.is_first and not first.is_last and first.reward == 0.0
    action = np.array([0.3])
    step = env.step(action)
    rewards = [single.step(action).reward for _ in range(2)]
    # Two simulator steps per agent step: same state as two single steps, rewards summed.
    np.testing.assert_array_equal(step.physics, single.physics_state())
    assert step.reward == pytest.approx(sum(rewards))
    assert step.physics[0] == pytest.approx(2 * 0.01)  # time advanced by two control steps
    n = 1
    while not step.is_last:
        step = env.step(action)
        n += 1
    # 1000 control steps at repeat 2: 500 agent steps after the reset step (501 rows).
    assert n == 500 and step.discount == 1.0 and not step.is_terminal  # a time limit
    with pytest.raises(ConfigError, match="reset"):
        env.step(action)


def test_determinism_under_a_seed() -> None:
    runs = []
    for _ in range(2):
        env = TaskEnv("walker-walk", max_steps=10)
        steps = [env.reset(seed=11)]
        rng = np.random.default_rng(0)
        while not steps[-1].is_last:
            steps.append(env.step(rng.uniform(-1, 1, env.action_dim)))
        runs.append(np.stack([s.physics for s in steps]))
    np.testing.assert_array_equal(runs[0], runs[1])
    other = TaskEnv("walker-walk").reset(seed=12)
    assert not np.array_equal(other.physics, runs[0][0])


def test_restoring_physics_reproduces_the_future() -> None:
    env = TaskEnv("finger-turn_easy")
    env.reset(seed=1)
    for _ in range(5):
        env.step(np.array([0.5, -0.5]))
    saved = env.physics_state()
    later = [env.step(np.array([0.2, 0.1])).physics for _ in range(3)]
    fresh = TaskEnv("finger-turn_easy")
    fresh.reset(seed=99)  # a different target and pose
    fresh.set_physics_state(saved)
    np.testing.assert_array_equal(fresh.physics_state(), saved)
    replay = [fresh.step(np.array([0.2, 0.1])).physics for _ in range(3)]
    np.testing.assert_array_equal(np.stack(replay), np.stack(later))


def test_wrong_physics_length_is_refused() -> None:
    env = TaskEnv("cheetah-run")
    with pytest.raises(PhysicsStateError, match=r"length 19, got shape \(5,\)"):
        env.set_physics_state(np.zeros(5))


def test_dynamics_scales_apply_per_episode() -> None:
    env = TaskEnv("hopper-stand")
    friction, mass = env.model.geom_friction[:, 0].copy(), env.model.body_mass.copy()
    env.reset(dynamics=Dynamics(friction_scale=2.0, mass_scale=0.5))
    np.testing.assert_allclose(env.model.geom_friction[:, 0], friction * 2.0)
    np.testing.assert_allclose(env.model.body_mass, mass * 0.5)
    env.reset()  # nominal again, not compounded
    np.testing.assert_allclose(env.model.geom_friction[:, 0], friction)
    np.testing.assert_allclose(env.model.body_mass, mass)
    with pytest.raises(ConfigError, match="mass_scale"):
        Dynamics(mass_scale=0.0)


@pytest.mark.parametrize("task", ["cartpole-balance", "cup-catch"])
def test_a_copied_environment_steps_as_a_freshly_compiled_one(task: str) -> None:
    """Environments after a task's first are copies of a cached one; each must be its own
    simulator and behave exactly as dm_control's own ``suite.load`` with the same seed."""
    from dm_control import suite

    first = TaskEnv(task, seed=0)
    env = TaskEnv(task, seed=7)
    spec = task_spec(task)
    fresh = suite.load(spec.domain, spec.task, task_kwargs={"random": 7})
    assert env.physics.model.ptr is not first.physics.model.ptr
    first.reset(dynamics=Dynamics(mass_scale=2.0))  # must not leak into the copy
    ours, theirs = env._env.reset(), fresh.reset()
    action = np.full(env.action_dim, 0.4)
    for _ in range(6):
        ours, theirs = env._env.step(action), fresh.step(action)
        for key, value in theirs.observation.items():
            np.testing.assert_array_equal(ours.observation[key], value)
        assert ours.reward == theirs.reward


#: Per task, a pose far from symmetric (qpos) and which joints move along the world's x axis
#: or turn about its y axis, what a reflection x -> -x negates (from the MJCF: cartpole's
#: slider and hinge; ball_in_cup's cup and ball x slides, not their z slides).
REFLECTED = {"cartpole-balance": ([0.6, 0.4], [0, 1]),
             "cup-catch": ([0.15, 0.05, 0.3, -0.1], [0, 2])}


def _body_mask(view: np.ndarray) -> np.ndarray:
    """Pixels of the bodies' nominal orange-red, which the nominal scene's blue-grey sky and
    floor never show."""
    r, g, b = (view[..., c].astype(int) for c in range(3))
    return (r > g + 40) & (r > b + 40)


@pytest.mark.parametrize("task", sorted(REFLECTED))
def test_a_tasks_mirror_signs_are_those_of_the_reflected_world(task: str) -> None:
    """TaskSpec.mirror must be the state of the reflected physics, and camera 0 must show the
    reflected world as the mirror image of the original (the bodies; the sky's noise and the
    lights' shading are not symmetric)."""
    from twist_sim.randomisation import dr_preset
    from twist_sim.render import DRRenderer
    from twist_sim.tasks import state_mirror

    pose, joints = REFLECTED[task]
    env = TaskEnv(task, seed=3)
    env.reset(seed=3)
    nq = env.model.nq
    physics = env.physics_state()
    physics[1:1 + nq] = pose
    physics[1 + nq:1 + 2 * nq] = np.linspace(0.5, -0.3, nq)  # velocities
    reflected = physics.copy()
    reflected[[1 + j for j in joints]] *= -1
    reflected[[1 + nq + j for j in joints]] *= -1
    env.set_physics_state(physics)
    state = env.flat_state()
    env.set_physics_state(reflected)
    np.testing.assert_allclose(env.flat_state(), np.array(state_mirror(task)) * state,
                               atol=1e-6)
    with DRRenderer(task, dr_preset("none"), 64, 1) as renderer:
        params = renderer.sampler(0).sample()
        original, of_reflected = (_body_mask(renderer.render(p, params)[0])
                                  for p in (physics, reflected))

    assert original.sum() > 20  # the bodies are seen
    assert mask_overlap(original[:, ::-1], of_reflected) > 0.8
    assert mask_overlap(original, of_reflected) < 0.5
