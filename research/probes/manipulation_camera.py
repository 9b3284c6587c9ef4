"""Which camera pose lets a read-out place the manipulation scene best? One CNN per pose

The panda read-out students erred most along x, the axis that runs toward the task's camera,
when it looked down at 27 degrees (``docs/results.md``, panda-push and panda-lift): a
centimetre along x moved an object less than half as far in the image as one along y. The
task's camera now looks down at 47 degrees, chosen by this probe. It measures, without a
teacher or a D, how precisely the read-out recipe's CNN and linear head place the scene from
each camera pose, at equal updates on the same states and DR draws:

* states: episodes of the hand-written controller (``scripted_manipulation.py``) with Gaussian
  noise of a per-episode scale on its actions, so that the hand also wanders off its path;
* frames: each state rendered at 64x64 (supersample 2) under ``--dr`` from every pose, with the
  same DR draws for every pose; every 5th episode is held out and rendered under
  ``--test-dr`` too (deployment: unseen backgrounds and colours, light, a moved camera);
* per pose, a CNN (DreamerV2's four convolutions) and linear head trained from the same seed on
  the position block, each component in units of its spread over the states (Huber loss, the
  read-out's delta), then measured on the held-out frames: RMS error per component, in cm.

``--camera NAME=X,Y,Z@TX,TY,TZ`` (repeatable) puts the task's camera at X,Y,Z looking at
TX,TY,TZ (metres, the world's z up; the table's top at z = 0); ``task`` is the task's own pose.

``python research/probes/manipulation_camera.py panda-lift [--camera task]
[--camera shallow=.7,0,.45@-.2,0,0] [--episodes 200] [--updates 15000] [--eval-every 5000]``;
prints a JSON line per pose and checkpoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

from twist_models.config import PRESETS, CNNConfig
from twist_models.device import precision_autocast
from twist_models.distillation import ReadOutStage, distil_preset
from twist_models.losses import readout_loss
from twist_models.networks import ImageEncoder
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TaskEnv

sys.path.insert(0, str(Path(__file__).parent))
from readout_heads import LinearHead, images_in
from scripted_manipulation import BUDGETS, GAIN, REPEAT, WAYPOINTS

#: The position block's components per task, for the printout.
NAMES = {"panda-push": ("tip_x", "tip_y", "tip_z", "block_x", "block_y", "block_z",
                        "goal_x", "goal_y"),
         "panda-lift": ("tip_x", "tip_y", "tip_z", "opening", "block_x", "block_y", "block_z")}
BATCH = 64


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A MuJoCo camera's quaternion (w, x, y, z) at ``position`` looking at ``target`` with
    the image's rows level (a camera looks along its -z, its x to the image's right)."""
    back = (position - target) / np.linalg.norm(position - target)
    right = np.cross((0.0, 0.0, 1.0), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.stack([right, up, back], 1).ravel())
    return quat


def parse_camera(text: str) -> tuple[str, tuple[np.ndarray, np.ndarray] | None]:
    if text == "task":
        return "task", None
    name, pose = text.split("=", 1)
    eye, target = (np.array([float(v) for v in part.split(",")]) for part in pose.split("@"))
    return name, (eye, target)


def scripted_states(task: str, episodes: int, seed: int) -> tuple[list[np.ndarray], np.ndarray,
                                                                   np.ndarray]:
    """Physics vectors, states [N, S] and episode indices [N] of noisy controller episodes."""
    env = TaskEnv(task, REPEAT)
    rng = np.random.default_rng(seed)
    waypoints, budgets = WAYPOINTS[task], BUDGETS[task]
    physics, states, index = [], [], []
    for episode in range(episodes):
        step = env.reset(seed=int(rng.integers(2**31)))
        noise = rng.uniform(0.0, 1.0)
        plan = list(zip(waypoints(step.state), budgets, strict=False))
        t = 0
        while not step.is_last:
            physics.append(step.physics)
            states.append(step.state)
            index.append(episode)
            t += 1
            target, grip = _current(plan, t)
            action = np.clip((target - step.state[:3]) * GAIN + noise * rng.standard_normal(3),
                             -1, 1)
            step = env.step(action if grip is None else np.r_[action, grip])
    return physics, np.array(states), np.array(index)


def _current(plan: list, t: int) -> tuple[np.ndarray, float | None]:
    """The waypoint the controller holds at its ``t``-th step (1-based)."""
    for waypoint, budget in plan:
        if t <= budget:
            return waypoint
        t -= budget
    return plan[-1][0]


def render_all(task: str, dr: str, physics: list[np.ndarray], episode: np.ndarray, seed: int,
               pose: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """Every state rendered once under ``dr`` from ``pose`` (None: the task's) -> [N, 64, 64,
    3]; the DR draws depend on ``seed`` and the episodes only, so are the same for every
    pose."""
    out = np.empty((len(physics), 64, 64, 3), np.uint8)
    with DRRenderer(task, dr_preset(dr), 64, views=1, supersample=2, states=16) as renderer:
        if pose is not None:
            camera = renderer.spec.camera
            renderer.model.cam_pos[camera] = pose[0]
            renderer.model.cam_quat[camera] = look_at(*pose)
        sampler = renderer.sampler(seed)
        params = []
        for i in range(len(physics)):
            if i == 0 or episode[i] != episode[i - 1]:
                sampler.begin_episode(seed * 100_003 + int(episode[i]))
            params.append(sampler.sample())
        for start in range(0, len(physics), 16):
            stop = min(start + 16, len(physics))
            out[start:stop] = renderer.render_states(physics[start:stop], params[start:stop])[:, 0]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("task", choices=sorted(NAMES))
    parser.add_argument("--camera", action="append", help="task, or NAME=X,Y,Z@TX,TY,TZ")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--updates", type=int, default=15000)
    parser.add_argument("--eval-every", type=int, default=5000)
    parser.add_argument("--dr", default="train-wide-full")
    parser.add_argument("--test-dr", default="heldout-full")
    parser.add_argument("--preset", default="quick", help="the CNN's size preset")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    cameras = [parse_camera(c) for c in (args.camera or ["task", "shallow=.7,0,.45@-.2,0,0"])]
    physics, states, episode = scripted_states(args.task, args.episodes, args.seed)
    read = list(range(len(NAMES[args.task])))  # the position block leads the state
    held = episode % 5 == 4
    target = torch.as_tensor(states[:, read], dtype=torch.float32)
    centre, spread = target[~held].mean(0), target[~held].std(0).clamp_min(1e-3)
    train_rows = np.flatnonzero(~held)
    print(json.dumps({"task": args.task, "states": len(states), "held_out": int(held.sum()),
                      "spread_cm": [round(float(v) * 100, 2) for v in spread]}), flush=True)
    for name, pose in cameras:
        train = render_all(args.task, args.dr, physics, episode, args.seed, pose)
        tests = {"test": train[held],
                 args.test_dr: render_all(args.task, args.test_dr,
                                          [p for p, h in zip(physics, held, strict=True) if h],
                                          episode[held], args.seed + 1, pose)}
        torch.manual_seed(args.seed)
        cnn = dataclasses.replace(PRESETS[args.preset].get("cnn", CNNConfig()),
                                  norm=distil_preset(args.preset, "readout").encoder_norm)
        model = LinearHead(ImageEncoder(cnn), len(read))
        optimiser = torch.optim.Adam(model.parameters(), lr=3e-4, eps=1e-5)
        draw = np.random.default_rng(args.seed + 1)
        start = time.perf_counter()
        for update in range(1, args.updates + 1):
            rows = train_rows[draw.integers(0, train_rows.size, BATCH)]
            # As the recipe runs: float32 on a CPU (compute.precision=auto).
            with precision_autocast("auto", torch.device("cpu")):
                out = model(images_in(torch.from_numpy(train[rows])))
            loss = readout_loss(out.float() - (target[rows] - centre) / spread,
                                ReadOutStage().huber_delta)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 100.0)
            optimiser.step()
            if update % args.eval_every == 0:
                entry = {"camera": name, "pose": None if pose is None else
                         [list(map(float, p)) for p in pose], "updates": update,
                         "s": round(time.perf_counter() - start, 1)}
                model.eval()
                with torch.no_grad():
                    for label, images in tests.items():
                        out = torch.cat([model(images_in(torch.from_numpy(images[i:i + 256])))
                                         .float() for i in range(0, len(images), 256)])
                        rms = ((out * spread + centre - target[held]).pow(2).mean(0).sqrt())
                        entry[f"{label}_rms_cm"] = dict(zip(
                            NAMES[args.task], (round(float(v) * 100, 2) for v in rms),
                            strict=True))
                model.train()
                print(json.dumps(entry), flush=True)


if __name__ == "__main__":
    main()
