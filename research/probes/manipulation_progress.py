"""What does a manipulation teacher do along its collection, episode by episode?

A return mixes reaching the block with moving it: ``panda-push`` pays ~0.2 per control step for
doing nothing and ~0.5 for hovering by the block. This script reads D's privileged states and
prints, per group of consecutive collection episodes, one JSON line:

* ``reach``: the mean distance from the fingertips to the block's centre (m);
* ``moved``: the share of episodes in which the block moved more than 1 cm;
* push: ``closer``: how much nearer the goal the block ends than it starts (m, mean);
  lift: ``raised``: the block's highest bottom above the table (m, mean);
* ``success``: the share that end solved (the task's ``success``), and the mean ``return``.

``python research/probes/manipulation_progress.py DATASET [--group 20]``
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from twist_data.reader import open_dataset
from twist_sim import panda
from twist_sim.tasks import task_spec


def episode_row(state: np.ndarray, reward: np.ndarray, lift: bool) -> dict[str, float]:
    """The measures of one episode from its privileged states [T, S] and rewards [T]."""
    block = state[:, 4:7] if lift else state[:, 3:6]
    row = {"reach": float(np.linalg.norm(state[:, :3] - block, axis=1).mean()),
           "moved": float(np.linalg.norm(block[:, :2] - block[0, :2], axis=1).max() > 0.01),
           "return": float(reward.sum())}
    if lift:
        row["raised"] = float((block[:, 2] - panda.BLOCK_HALF).max())
    else:
        away = np.linalg.norm(block[:, :2] - state[:, 6:8], axis=1)
        row["closer"] = float(away[0] - away[-1])
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--group", type=int, default=20, help="episodes per printed line")
    args = parser.parse_args()
    data = open_dataset(args.dataset)
    spec = task_spec(data.spec.task)
    lift = data.spec.task == "panda-lift"
    rows = []
    for i in range(data.n_episodes):
        episode = data.episode(i)
        rows.append({**episode_row(episode.state, episode.reward, lift),
                     "success": float(spec.success(episode.state[-1]))})
    for start in range(0, len(rows), args.group):
        group = rows[start:start + args.group]
        means = {key: round(float(np.mean([r[key] for r in group])), 3) for key in group[0]}
        print(json.dumps({"episodes": [start, start + len(group) - 1], **means}))


if __name__ == "__main__":
    main()
