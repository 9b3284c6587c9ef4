"""How well a teacher's world model predicts a task's reward on D, by the reward's level.

On the ``--episodes`` episodes of D with the most return, compares each agent step's reward
(from step 16 on) with three predictions of it:

* ``posterior``: the reward head on the filter's posterior at that step (the model seeing it);
* ``open_loop_15``: the reward head after 15 steps imagined from the posterior 15 steps
  earlier with the recorded actions (what imagination sees);
* ``mlp_on_state``: a 2x256 MLP regressing r_t on the state s_t over D's other episodes
  (3,000 updates of 1,024 steps), the baseline measured in the same run: how much of the
  reward the state itself tells.

Prints one JSON line per part. ``python research/probes/reward_fit.py D TEACHER [--episodes 12]``
"""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_models.teacher import load_teacher

HORIZON = 15
BINS = (0.0, 1.0, 2.0, 2.5, 3.0, 3.5, 4.1)


def binned(true: np.ndarray, **predictions: np.ndarray) -> dict[str, dict[str, float]]:
    """Per reward bin: its steps, mean true reward and the mean of each prediction."""
    out = {}
    for lo, hi in itertools.pairwise(BINS):
        rows = (true >= lo) & (true < hi)
        if rows.any():
            out[f"{lo}-{hi}"] = {"n": int(rows.sum()), "true": round(float(true[rows].mean()), 2),
                                 **{k: round(float(v[rows].mean()), 2)
                                    for k, v in predictions.items()}}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("teacher")
    parser.add_argument("--episodes", type=int, default=12)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    data = open_dataset(args.dataset)
    model = load_teacher(args.teacher)[0].world_model
    chosen = np.argsort(data.episode_returns())[::-1][:args.episodes]
    true, posterior, open_loop, states = [], [], [], []
    with torch.no_grad():
        for index in chosen:
            ep = data.episode(int(index), images=False)
            state = torch.as_tensor(ep.state[None]).float()
            action = torch.as_tensor(ep.action[None]).float()
            post, _ = model.rssm.observe(model.embed(state), action,
                                         torch.as_tensor(ep.is_first[None]))
            starts = np.arange(1, len(ep.reward) - HORIZON)
            start = {k: v[0, starts] for k, v in post.items()}
            imagined, _ = model.rssm.imagine(
                start, HORIZON, actions=action[0, starts[:, None] + np.arange(1, HORIZON + 1)])
            target = starts + HORIZON
            true.append(ep.reward[target])
            posterior.append(model.reward(model.rssm.feature(post))[0].numpy()[target])
            open_loop.append(model.reward(model.rssm.feature(imagined))[:, -1].numpy())
            states.append(ep.state[target])
    true = np.concatenate(true)
    print(json.dumps({"episodes": len(chosen), "steps": int(true.size), **binned(
        true, posterior=np.concatenate(posterior), open_loop_15=np.concatenate(open_loop))}))

    others = sorted(set(range(data.n_episodes)) - set(chosen.tolist()))
    episodes = [data.episode(i, images=False) for i in others]
    s = torch.as_tensor(np.concatenate([ep.state[1:] for ep in episodes])).float()
    r = torch.as_tensor(np.concatenate([ep.reward[1:] for ep in episodes])).float()
    mean, std = s.mean(0), s.std(0) + 1e-6
    mlp = torch.nn.Sequential(torch.nn.Linear(s.shape[1], 256), torch.nn.ELU(),
                              torch.nn.Linear(256, 256), torch.nn.ELU(), torch.nn.Linear(256, 1))
    optimiser = torch.optim.Adam(mlp.parameters(), 1e-3)
    for _ in range(3000):
        rows = torch.randint(len(s), (1024,))
        loss = ((mlp((s[rows] - mean) / std).squeeze(-1) - r[rows]) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        test = torch.as_tensor(np.concatenate(states)).float()
        predicted = mlp((test - mean) / std).squeeze(-1).numpy()
    print(json.dumps({"train_steps": len(s), **binned(true, mlp_on_state=predicted)}))


if __name__ == "__main__":
    main()
