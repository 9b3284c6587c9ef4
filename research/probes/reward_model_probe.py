"""Does a teacher world model learn how the action changes the reward?

On ``--episodes`` uniform-random episodes of cartpole-balance, compares three estimates of the
one-step *action bonus* at given states -- the reward after action 0 minus the mean reward
after actions -1 and +1 (cartpole's control cost makes it ~0.4 while the pole is upright):

* ``simulator``: restore the recorded physics state and step the simulator (the truth);
* ``world_model``: a teacher world model of ``--preset`` sizes trained for ``--updates``
  updates (B=16, L=50) on the episodes, predicting the reward of ``img_step(posterior, a)``;
* ``mlp``: a plain 2x256 MLP regressing r_t on (s_{t-1}, a_t) for the same number of updates
  (batch 800), the baseline measured in the same run.

Prints one JSON line. ``python research/probes/reward_model_probe.py [--preset quick]
[--updates 1000] [--episodes 10]``
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from torch import nn

from twist_models.config import teacher_preset
from twist_models.teacher import Teacher
from twist_sim.tasks import TaskEnv

PROBE_STEPS = (10, 40, 80, 150)
ACTIONS = (-1.0, 0.0, 1.0)


def random_episodes(env: TaskEnv, n: int, rng: np.random.Generator) -> list[dict[str, np.ndarray]]:
    episodes = []
    for seed in range(n):
        step = env.reset(seed=seed)
        rows = {"state": [step.state], "physics": [step.physics],
                "action": [np.zeros(1, np.float32)], "reward": [0.0]}
        while not step.is_last:
            action = rng.uniform(-1, 1, 1).astype(np.float32)
            step = env.step(action)
            for key, value in (("state", step.state), ("physics", step.physics),
                               ("action", action), ("reward", step.reward)):
                rows[key].append(value)
        episodes.append({k: np.asarray(v, np.float32 if k != "physics" else np.float64)
                         for k, v in rows.items()})
    return episodes


def bonus(rewards: list[float]) -> float:
    return round(rewards[1] - (rewards[0] + rewards[2]) / 2, 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick")
    parser.add_argument("--updates", type=int, default=1000)
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    env = TaskEnv("cartpole-balance", action_repeat=2, seed=0)
    episodes = random_episodes(env, args.episodes, rng)

    probe = episodes[0]
    truth = []
    env.reset(seed=0)
    for t in PROBE_STEPS:
        rewards = []
        for action in ACTIONS:
            env.set_physics_state(probe["physics"][t])
            rewards.append(env.step(np.array([action], np.float32)).reward)
        truth.append(bonus(rewards))

    teacher = Teacher(teacher_preset(args.preset, env.state_dim, env.action_dim))
    wm = teacher.world_model
    length = 50
    for _ in range(args.updates):
        picks = [episodes[i] for i in rng.integers(0, len(episodes), 16)]
        starts = [int(rng.integers(0, len(e["reward"]) - length + 1)) for e in picks]
        batch = {k: torch.tensor(np.stack([e[k][s:s + length]
                                           for e, s in zip(picks, starts, strict=True)]))
                 for k in ("state", "action", "reward")}
        batch["is_first"] = torch.zeros(16, length, dtype=torch.bool)
        batch["is_first"][:, 0] = torch.tensor([s == 0 for s in starts])
        loss, _, metrics = wm.loss(batch)
        teacher.model_opt.zero_grad()
        loss.backward()
        teacher.model_opt.step()
    with torch.no_grad():
        is_first = torch.zeros(1, len(probe["reward"]), dtype=torch.bool)
        is_first[0, 0] = True
        post, _ = wm.rssm.observe(wm.embed(torch.tensor(probe["state"])[None]),
                                  torch.tensor(probe["action"])[None], is_first)
        model = []
        for t in PROBE_STEPS:
            start = {k: v[:, t].expand(64, *v.shape[2:]) for k, v in post.items()}
            model.append(bonus([float(wm.reward(wm.rssm.feature(wm.rssm.img_step(
                start, torch.full((64, 1), a)))).mean()) for a in ACTIONS]))

    inputs = torch.tensor(np.concatenate([np.concatenate([e["state"][:-1], e["action"][1:]], 1)
                                          for e in episodes]))
    targets = torch.tensor(np.concatenate([e["reward"][1:] for e in episodes]))
    mlp = nn.Sequential(nn.Linear(inputs.shape[1], 256), nn.ELU(), nn.Linear(256, 256), nn.ELU(),
                        nn.Linear(256, 1))
    optimiser = torch.optim.Adam(mlp.parameters(), 3e-4)
    for _ in range(args.updates):
        index = torch.randint(0, len(inputs), (800,))
        mse = ((mlp(inputs[index])[:, 0] - targets[index]) ** 2).mean()
        optimiser.zero_grad()
        mse.backward()
        optimiser.step()
    with torch.no_grad():
        baseline = [bonus([float(mlp(torch.cat([torch.tensor(probe["state"][t])[None],
                                                 torch.tensor([[a]])], 1))) for a in ACTIONS])
                    for t in PROBE_STEPS]
    print(json.dumps({
        "benchmark": "reward_model_probe", "preset": args.preset, "updates": args.updates,
        "episodes": args.episodes, "probe_steps": PROBE_STEPS, "simulator_bonus": truth,
        "world_model_bonus": model, "mlp_bonus": baseline,
        "world_model_reward_mse": round(2 * (float(metrics["reward_loss"]) - 0.9189), 4),
        "mlp_reward_mse": round(float(mse), 4)}))


if __name__ == "__main__":
    main()
