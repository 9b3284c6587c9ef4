"""What return and success rate does a hand-written controller reach on the manipulation tasks?

A learned teacher's return means little without the task's ceiling: ``panda-push``'s dense
reward pays ~0.2 per control step for doing nothing (the goal starts 10-20 cm from the block)
and at most 1. This script drives the privileged state with a proportional controller that
knows the task's geometry, on the evaluation episodes' seeds, and prints one JSON line: the
mean return and its standard error, the success rate (``TaskSpec.success``), and per episode
the agent step at which the task first counts as solved.

* push: rise above the block's far side from the goal, descend behind it, push it through
  the goal, and hold it there;
* lift: open above the block, descend, close, and raise it 20 cm.

``python research/probes/scripted_manipulation.py panda-push [--episodes 30] [--seed 0]``
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator

import numpy as np

from twist_data.seeding import evaluation_episode_seed
from twist_sim import panda
from twist_sim.tasks import TaskEnv

#: The quick preset's action repeat, for which the tasks are made.
REPEAT = 4
#: Proportional gain from a position error (metres) to an action in [-1, 1].
GAIN = 50.0


def _push_waypoints(state: np.ndarray) -> Iterator[tuple[np.ndarray, float | None]]:
    block, goal = state[3:5], state[6:8]
    way = (goal - block) / np.linalg.norm(goal - block)
    behind = block - 0.06 * way
    yield np.r_[behind, 0.1], None
    yield np.r_[behind, panda.BLOCK_HALF], None
    yield np.r_[goal - 0.035 * way, panda.BLOCK_HALF], None


def _lift_waypoints(state: np.ndarray) -> Iterator[tuple[np.ndarray, float | None]]:
    block = state[4:7]
    yield np.r_[block[:2], block[2] + 0.08], 1.0
    yield block.copy(), 1.0
    yield block.copy(), -1.0
    yield np.r_[block[:2], block[2] + 0.2], -1.0


#: Per task: its waypoints from the first state, and the steps each is held (the last to the
#: episode's end).
WAYPOINTS = {"panda-push": _push_waypoints, "panda-lift": _lift_waypoints}
BUDGETS = {"panda-push": (30, 15, 10**6), "panda-lift": (25, 15, 10, 10**6)}


def run_episode(env: TaskEnv, seed: int) -> tuple[float, bool, int]:
    """(return, success at the end, first agent step that counts as solved, or -1)."""
    step = env.reset(seed=seed)
    waypoints = WAYPOINTS[env.name](step.state)
    budgets = BUDGETS[env.name]
    total, solved, t = 0.0, -1, 0
    for (target, grip), budget in zip(waypoints, budgets, strict=False):
        for _ in range(budget):
            action = np.clip((target - step.state[:3]) * GAIN, -1, 1)
            step = env.step(action if grip is None else np.r_[action, grip])
            total += step.reward
            t += 1
            if solved < 0 and env.spec.success(step.state):
                solved = t
            if step.is_last:
                return total, bool(env.spec.success(step.state)), solved
    raise AssertionError("the episode did not end")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("task", choices=("panda-push", "panda-lift"))
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    env = TaskEnv(args.task, REPEAT)
    rows = [run_episode(env, evaluation_episode_seed(args.seed, i))
            for i in range(args.episodes)]
    returns = np.array([r for r, _, _ in rows])
    print(json.dumps({
        "task": args.task, "episodes": args.episodes,
        "return_mean": round(float(returns.mean()), 1),
        "return_se": round(float(returns.std(ddof=1) / np.sqrt(len(returns))), 1),
        "success_rate": float(np.mean([s for _, s, _ in rows])),
        "solved_at": [t for _, _, t in rows],
    }))


if __name__ == "__main__":
    main()
