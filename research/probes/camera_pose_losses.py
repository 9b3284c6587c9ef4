"""Which part of a moved camera costs a student its return? Each part alone, on the same episodes

``heldout-camera`` draws, once per episode, a camera shift of up to 5 cm per world axis and a
turn of up to 0.1 rad about a random axis (``twist_sim.randomisation``), from the episode's
own seed. This evaluates an agent on the same seeded episodes under ``heldout`` and under
``heldout-camera`` with one part of every pose kept and the others zeroed, every other draw
(backgrounds, colours, initial state) unchanged:

* ``roll``: the turn about the camera's viewing axis (the image rotates: an upright pole
  leans in it);
* ``yaw``, ``pitch``: the turns about its up and right axes (the image slides sideways, or up
  and down, by about the distance to the scene times the angle);
* ``shift``: the translation alone (the image slides by the shift and scales a little);
* ``all``: the whole pose, which reproduces a ``twist-eval --dr heldout-camera`` run.

It prints each condition's paired difference against ``heldout``. A part that sets the loss
costs alone about what the whole pose costs; one the student reads past costs nothing.

``python research/probes/camera_pose_losses.py --agent NAME=PATH [--agent ...] [--episodes
30] [--seed 0]``; prints one JSON line per agent and condition.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from unittest import mock

import mujoco
import numpy as np

from twist_pipeline.acting import load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate
from twist_sim.randomisation import DRSampler
from twist_sim.tasks import TaskEnv


def camera_axes(task: str) -> np.ndarray:
    """The rendered camera's right, up and forward directions in world axes at a reset: the
    rows of a rotation matrix (a MuJoCo camera looks along its -z)."""
    env = TaskEnv(task, action_repeat=1, seed=0)
    env.reset(seed=0)
    mujoco.mj_forward(env.model, env.data)
    frame = env.data.cam_xmat[env.spec.camera].reshape(3, 3)
    return np.stack([frame[:, 0], frame[:, 1], -frame[:, 2]])


#: Per condition: which parts of the turn, in the camera's (right, up, forward) axes, are
#: kept, and whether the shift is.
CONDITIONS = {"roll": ((0, 0, 1), False), "yaw": ((0, 1, 0), False),
              "pitch": ((1, 0, 0), False), "shift": ((0, 0, 0), True), "all": ((1, 1, 1), True)}


def keep_only(axes: np.ndarray, turn_mask: tuple[int, int, int],
              shift: bool) -> contextlib.AbstractContextManager:
    """Within the block, every DR draw keeps the masked parts of its camera turn (in the
    camera's ``axes``, :func:`camera_axes`) and its shift or not; the random stream, and so
    every other draw, is unchanged."""
    draw = DRSampler._draw
    mask = np.asarray(turn_mask, np.float64)

    def masked(sampler: DRSampler) -> dict[str, np.ndarray]:
        params = draw(sampler)
        turn = params["camera_rotation"].astype(np.float64) @ axes.T * mask
        params["camera_rotation"] = (turn @ axes).astype(np.float32)
        if not shift:
            params["camera_shift"] = np.zeros_like(params["camera_shift"])
        return params

    return mock.patch.object(DRSampler, "_draw", masked)


def intervene(name: str, path: str, episodes: int, seed: int) -> list[dict]:
    """The agent under ``heldout`` and under each camera part alone, paired per episode."""
    agent = load_agent(path)
    task = agent.task
    axes = camera_axes(task)

    def returns(dr: str) -> np.ndarray:
        config = EvalConfig(task=task, dr=dr, episodes=episodes, action_repeat=agent.action_repeat)
        return np.array([r.episode_return for r in evaluate(agent, config, seed=seed, batch=10)])

    plain, out = returns("heldout"), []
    for condition, (turn_mask, shift) in CONDITIONS.items():
        with keep_only(axes, turn_mask, shift):
            moved = returns("heldout-camera")
        difference = moved - plain
        out.append({"agent": name, "condition": condition, "episodes": episodes,
                    "heldout": round(plain.mean(), 1), "moved": round(moved.mean(), 1),
                    "share": round(moved.mean() / plain.mean(), 2),
                    "difference": round(difference.mean(), 1),
                    "stderr": round(difference.std(ddof=1) / np.sqrt(episodes), 1),
                    "better": int((difference > 0).sum())})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", action="append", required=True, help="NAME=PATH")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for spec in args.agent:
        name, path = spec.split("=", 1)
        for entry in intervene(name, path, args.episodes, args.seed):
            print(json.dumps(entry), flush=True)


if __name__ == "__main__":
    main()
