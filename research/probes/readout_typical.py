"""How well does a read-out student read D's frames that its first stage trained on, and the rest?

The read-out's first stage trains on D's *typical* frames: every read component within
``ReadOutStage.typical_spreads`` robust spreads (median and MAD) of its median.
On cartpole that is the pole within ~20° of upright. On a task whose states D holds mostly in
one pose it can leave out the very phase the actor must act in. This script reads D's first
``--episodes`` held-out episodes (stored views, never trained on) and prints one JSON line:
the share of their frames that are typical, and the read-out's RMS error per read component,
in robust spreads and in state units, on typical and on the other frames.

``python research/probes/readout_typical.py AGENT.pt DATASET [--episodes 12] [--holdout-every 10]``
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.distillation import ReadOutStage
from twist_models.readout import typical


@torch.no_grad()
def read_all(agent: Agent, images: np.ndarray, batch: int = 256) -> np.ndarray:
    """The read-out's raw reading of uint8 frames [N, H, W, 3] -> [N, R]."""
    student, out = agent.student, []
    for i in range(0, len(images), batch):
        image = torch.from_numpy(images[i:i + batch])[:, None]
        out.append(student.perception.readout.read(student.perception.encoder(image).flatten(1).float()).numpy())
    return np.concatenate(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("agent")
    parser.add_argument("dataset")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--holdout-every", type=int, default=10)
    args = parser.parse_args()
    agent = Agent.load(args.agent)
    readout = agent.student.perception.readout
    if readout is None:
        raise SystemExit(f"{args.agent} is not a read-out student")
    dataset = open_dataset(args.dataset)
    read = list(readout.config.read)
    scale, centre = readout.scale.numpy(), readout.mean.numpy()
    errors, usual = [], []
    for index in np.flatnonzero(heldout_episodes(dataset.n_episodes, args.holdout_every))[:args.episodes]:
        episode = dataset.episode(int(index))
        errors.append(read_all(agent, episode.image[:, 0]) - episode.state[:, read])
        usual.append(typical(episode.state, readout.config, centre, scale,
                             ReadOutStage().typical_spreads))
    error, keep = np.concatenate(errors), np.concatenate(usual)

    def rms(rows: np.ndarray) -> list[float]:
        return np.sqrt((rows.astype(np.float64) ** 2).mean(0)).round(4).tolist() if len(rows) else []

    print(json.dumps({"read_components": read, "robust_scale": scale.astype(np.float64).round(4).tolist(),
                      "typical_share": round(float(keep.mean()), 3),
                      "rmse_typical": rms(error[keep]), "rmse_other": rms(error[~keep]),
                      "rmse_typical_spreads": rms(error[keep] / scale),
                      "rmse_other_spreads": rms(error[~keep] / scale)}))


if __name__ == "__main__":
    main()
