"""The manipulation tasks: the gripper moves as its action says, a scripted grasp lifts the block
and holds it, fingers pressed onto its top earn no grasp, a scripted push puts it on the goal,
a hand pressed onto the block neither sinks into it nor carries it off, and every instant
restores exactly."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("dm_control")

from tests.conftest import mask_overlap
from twist_sim import panda
from twist_sim.tasks import TASKS, TaskEnv

REPEAT = 4  # the quick preset's action repeat, for which the tasks are made


def _steer(env: TaskEnv, step, target: np.ndarray, steps: int, grip: float | None = None):
    """Move the fingertips towards ``target`` (a proportional controller, clipped)."""
    reward = 0.0
    for _ in range(steps):
        action = np.clip((target - step.state[:3]) * 50, -1, 1)
        step = env.step(action if grip is None else np.r_[action, grip])
        reward += step.reward
    return step, reward


def test_both_tasks_are_registered_with_their_layouts() -> None:
    assert {"panda-push", "panda-lift"} <= set(TASKS)
    push, lift = TaskEnv("panda-push", REPEAT), TaskEnv("panda-lift", REPEAT)
    # push: fingertips, block, goal (x, y); lift: fingertips, opening, block.
    assert push.state_layout == (("position", 8), ("velocity", 6)) and push.action_dim == 3
    assert lift.state_layout == (("position", 7), ("velocity", 7)) and lift.action_dim == 4
    # 150 agent steps at action repeat 4, as the paper's episodes.
    steps = 0
    step = push.reset(seed=0)
    while not step.is_last:
        step, steps = push.step(np.zeros(3)), steps + 1
    assert steps == panda.EPISODE_STEPS // REPEAT == 150


def test_the_gripper_starts_at_its_start_and_moves_two_centimetres_per_agent_step() -> None:
    env = TaskEnv("panda-push", REPEAT)
    first = env.reset(seed=0)
    np.testing.assert_allclose(first.state[:3], panda.START, atol=2e-3)
    blocks = {tuple(TaskEnv("panda-push", REPEAT).reset(seed=s).state[3:5]) for s in range(4)}
    assert len(blocks) == 4  # the block's place is the episode's draw
    step = env.step(np.array([1.0, 0.0, 0.0]))  # under way
    for _ in range(4):
        before, step = step, env.step(np.array([1.0, 0.0, 0.0]))
        moved = step.state[:3] - before.state[:3]
        assert 0.75 * REPEAT * panda.MAX_DELTA < moved[0] < REPEAT * panda.MAX_DELTA + 0.002
        assert abs(moved[1]) < 0.003 and abs(moved[2]) < 0.003  # the arm dips as it goes
    held = env.step(np.zeros(3)).state[:3]
    assert np.linalg.norm(env.step(np.zeros(3)).state[:3] - held) < 0.002  # no action: it stays


def test_the_workspace_keeps_the_gripper_above_the_table() -> None:
    env = TaskEnv("panda-push", REPEAT)
    step = env.reset(seed=0)
    for _ in range(40):
        step = env.step(np.array([0.0, 0.0, -1.0]))
    assert step.state[2] == pytest.approx(panda.WORKSPACE[2, 0], abs=0.01)


def test_a_scripted_grasp_lifts_the_block_and_earns_the_lift_reward() -> None:
    env = TaskEnv("panda-lift", REPEAT)
    step = env.reset(seed=1)
    block = step.state[4:7].copy()
    step, _ = _steer(env, step, [*block[:2], block[2] + 0.08], 25, grip=1.0)
    assert step.reward / REPEAT < 0.2  # reached above it, not yet grasped
    step, _ = _steer(env, step, block, 15, grip=1.0)
    step, _ = _steer(env, step, block, 10, grip=-1.0)
    step, _ = _steer(env, step, [*block[:2], block[2] + 0.2], 40, grip=-1.0)
    height = step.state[6] - panda.BLOCK_HALF
    assert height >= panda.LIFT_HEIGHT
    assert step.state[3] == pytest.approx(panda.BLOCK_HALF, abs=0.005)  # fingers on its faces
    assert step.reward / REPEAT > 0.9  # rewards add up over the repeated control steps
    # Held to the episode's end, where success is judged, without slipping down the fingers.
    step, _ = _steer(env, step, [*block[:2], block[2] + 0.2], 60, grip=-1.0)
    assert step.is_last
    assert step.state[6] - panda.BLOCK_HALF == pytest.approx(height, abs=0.005)
    assert TASKS["panda-lift"].success(step.state)


def test_fingers_pressed_onto_the_blocks_top_earn_no_grasp() -> None:
    # Half-open fingers pressed down onto the block both touch it, on its top face: reaching
    # pays, grasping must not (a teacher paid for it held blocks down instead of lifting).
    env = TaskEnv("panda-lift", REPEAT)
    step = env.reset(seed=1)
    block = step.state[4:7].copy()
    step, _ = _steer(env, step, [*block[:2], block[2] + 0.08], 25, grip=-0.45)
    step, _ = _steer(env, step, [*block[:2], 0.0], 20, grip=-0.45)
    assert step.state[3] < panda.BLOCK_HALF - 0.01  # narrower than the block: on top of it
    assert step.state[2] - step.state[6] > panda.BLOCK_HALF  # the fingertips above its top
    assert step.reward / REPEAT < 0.2 + 0.01  # the reach term's at most: no grasp
    # The same fingers closed on its sides, the block still on the table, grasp it.
    step, _ = _steer(env, step, [*block[:2], block[2] + 0.08], 10, grip=1.0)
    step, _ = _steer(env, step, block, 15, grip=1.0)
    step, _ = _steer(env, step, block, 10, grip=-1.0)
    assert step.reward / REPEAT > 0.2 + 0.3


def test_a_scripted_push_puts_the_block_on_the_goal() -> None:
    env = TaskEnv("panda-push", REPEAT)
    step = env.reset(seed=1)
    block, goal = step.state[3:5].copy(), step.state[6:8].copy()
    start_reward = step.reward
    way = (goal - block) / np.linalg.norm(goal - block)
    behind = np.r_[block - 0.06 * way, panda.BLOCK_HALF]
    step, _ = _steer(env, step, np.r_[behind[:2], 0.1], 30)
    step, _ = _steer(env, step, behind, 15)
    step, _ = _steer(env, step, np.r_[goal - 0.035 * way, panda.BLOCK_HALF], 60)
    assert np.linalg.norm(step.state[3:5] - goal) < panda.PUSH_TOLERANCE
    assert step.reward / REPEAT > 0.9 > start_reward / REPEAT


def test_a_hand_pressed_onto_the_block_neither_sinks_into_it_nor_carries_it_off() -> None:
    # Its servos press with a bounded force: the fingers stay on the block's top (soft
    # contacts give a few millimetres), and when the hand rises the block stays on the table.
    env = TaskEnv("panda-push", REPEAT)
    step = env.reset(seed=1)
    block = step.state[3:6].copy()
    step, _ = _steer(env, step, np.r_[block[:2], 0.1], 30)
    step, _ = _steer(env, step, np.r_[block[:2], 0.0], 20)  # pressed down onto its top
    assert step.state[2] > 2 * panda.BLOCK_HALF - 0.005
    step, _ = _steer(env, step, np.r_[block[:2], 0.25], 30)
    assert step.state[2] > 0.2
    assert step.state[5] == pytest.approx(panda.BLOCK_HALF, abs=0.002)


def test_an_instant_restores_exactly_and_steps_on_alike() -> None:
    env = TaskEnv("panda-lift", REPEAT)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(10):
        env.step(rng.uniform(-1, 1, 4))
    saved = env.physics_state()
    actions = rng.uniform(-1, 1, (5, 4))
    ahead = [env.step(a).state for a in actions]
    other = TaskEnv("panda-lift", REPEAT, seed=9)
    other.reset(seed=4)
    other.set_physics_state(saved)
    np.testing.assert_array_equal(other.physics_state(), saved)
    # Stepped on, they agree to the contact solver's tolerance: its warm start is not part
    # of the instant (nor of any suite task's).
    np.testing.assert_allclose(np.stack([other.step(a).state for a in actions]),
                               np.stack(ahead), rtol=0, atol=1e-9)


@pytest.mark.parametrize("task", ["panda-push", "panda-lift"])
def test_a_tiny_collection_rerenders_bit_exactly(task: str, tmp_path, gl: None) -> None:
    from twist_data.reader import open_dataset
    from twist_data.verify import verify_dataset
    from twist_pipeline.collect import collect, collect_preset
    from twist_sim.rerender import check_reproduction

    collect(tmp_path, collect_preset("tiny", task=task, action_repeat=REPEAT, frames=200))
    assert verify_dataset(tmp_path).ok
    data = open_dataset(tmp_path)
    assert data.spec.task == task and data.spec.physics_dim == TaskEnv(task).physics_dim
    # Under per-step DR the block is recoloured: its material's colour differs step to step.
    colour = data.column("dr/colour")
    assert not np.array_equal(colour[0], colour[1])
    assert check_reproduction(data, n_steps=20) == []
    if task == "panda-push":  # the goal stays put within an episode; the hand moves
        from twist_models.readout import episode_constants

        state, is_first = data.column("state"), np.zeros(data.n_steps, bool)
        is_first[data.episode_starts] = True
        assert episode_constants(state, is_first, (6, 7)) == (6, 7)
        assert episode_constants(state, is_first, range(3)) == ()


@pytest.mark.parametrize("task", ["panda-push", "panda-lift"])
def test_the_mirrored_scene_moves_as_the_declared_mirror_and_renders_as_the_mirror_image(
        task: str, gl: None) -> None:
    """An episode begun with the block (and goal) reflected through y = 0 and driven by the
    reflected actions stays the reflection of the original, state for state as
    ``TaskSpec.mirror`` signs it, and the camera shows the block where the original's mirror
    image has it (the arm's upper links and the table's shading are not symmetric; under DR
    they are recoloured anyway)."""
    from twist_sim.randomisation import dr_preset
    from twist_sim.render import DRRenderer
    from twist_sim.tasks import state_mirror

    lift = task == "panda-lift"
    actions = np.random.default_rng(0).uniform(-1, 1, (25, 4 if lift else 3))
    actions[:, 1] = np.clip(actions[:, 1] + 0.6, -1, 1)  # the hand drifts off y = 0

    def episode(sign: int) -> tuple[np.ndarray, np.ndarray]:
        env = TaskEnv(task, REPEAT, seed=3)
        env.reset(seed=3)
        physics = env.physics
        physics.named.data.qpos["block"][1] = sign * 0.1
        if not lift:
            physics.named.model.site_pos["goal"][1] = sign * -0.08
        physics.forward()
        states = [env.step(a * np.r_[1, sign, 1, [1] * lift]).state for a in actions]
        return np.array(states), env.physics_state()

    (states, physics), (reflected, of_reflected) = episode(1), episode(-1)
    assert states[-1, 1] > 0.1  # the hand ends well off the plane of symmetry
    expected = states * np.array(state_mirror(task))
    if lift:  # the gripper's actuator drives one finger and the other follows: near symmetry
        np.testing.assert_allclose(reflected[:, :7], expected[:, :7], atol=5e-4)  # 0.5 mm
        np.testing.assert_allclose(reflected[:, 7:], expected[:, 7:], atol=0.02)  # 2 cm/s
    else:
        np.testing.assert_allclose(reflected, expected, atol=1e-6)
    with DRRenderer(task, dr_preset("none"), 64, 1) as renderer:
        params = renderer.sampler(0).sample()
        block, of_reflected_block = (_yellow(renderer.render(p, params)[0])
                                     for p in (physics, of_reflected))

    assert block.sum() > 10  # the block is seen
    assert mask_overlap(block[:, ::-1], of_reflected_block) > 0.8
    assert mask_overlap(block, of_reflected_block) < 0.2


def _yellow(view: np.ndarray) -> np.ndarray:
    """Pixels of the block's nominal yellow, which nothing else in the nominal scene shows."""
    r, g, b = (view[..., c].astype(int) for c in range(3))
    return (r > 100) & (g > 80) & (b < 0.4 * r)


class ScriptedPush:
    """Above the block's far side from the goal, down, then through to the goal: a policy of
    the privileged state, as `twist-eval --agent module:function` takes one."""

    observe = ("state",)
    task = "panda-push"

    def reset(self) -> None:
        self.steps, self.plan = 0, None

    def __call__(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        state = observation["state"]
        if self.plan is None:
            block, goal = state[3:5], state[6:8]
            way = (goal - block) / np.linalg.norm(goal - block)
            behind = block - 0.06 * way
            self.plan = [(np.r_[behind, 0.1], 30), (np.r_[behind, panda.BLOCK_HALF], 15),
                         (np.r_[goal - 0.035 * way, panda.BLOCK_HALF], 10**6)]
        self.steps += 1
        ends = np.cumsum([steps for _, steps in self.plan])
        target = self.plan[int(np.searchsorted(ends, self.steps))][0]
        return np.clip((target - state[:3]) * 50, -1, 1)


def test_evaluation_reports_the_success_rate_beside_the_return(tmp_path) -> None:
    import pandas as pd

    from twist_pipeline.acting import PolicyAgent
    from twist_pipeline.evaluation import EvalConfig, run_evaluation

    script = ScriptedPush()
    agents = {"script": PolicyAgent(script, script.observe, script.task), "zero": "zero"}
    config = EvalConfig(task="panda-push", dr="none", episodes=2, action_repeat=REPEAT)
    summary = run_evaluation(agents, config, [0], tmp_path)
    table = pd.read_csv(tmp_path / "episodes.csv")
    assert table.loc[table["agent"] == "script", "success"].tolist() == [1, 1]
    assert summary["agents"]["script"]["success_rate"] == 1.0
    # Doing nothing leaves the block where it started, 10-20 cm from the goal.
    assert summary["agents"]["zero"]["success_rate"] == 0.0
