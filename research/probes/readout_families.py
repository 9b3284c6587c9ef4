"""How well does a read-out student read each state component in scenes of each kind?

Any task's counterpart of ``readout_scenes.py`` (which measures cartpole's near-upright
lean): the read-out of the frames of D's held-out episodes (never trained on), rendered again
from their stored physics states with one scene per episode under each setting asked for --
``stored`` (D's own views), ``train`` (new scenes of the training families), ``heldout`` (the
held-out families, as ``twist-eval --dr heldout`` draws them) or ``photo`` (``--backgrounds``)
-- against the stored state. A gap between ``train`` and ``heldout`` is what the CNN loses
on background kinds it never saw, apart from any closed-loop effect.

Per setting one JSON line: each read component's RMS error in the state's units, the
median and worst scene's RMS error in D's robust spreads (the read-out's training units).

``python research/probes/readout_families.py AGENT.pt DATASET [--settings stored,train,heldout]
[--backgrounds DIR] [--episodes 30]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent

# The renders and the read-out are readout_scenes.py's, beside this file, wherever it is run
# from.
sys.path.insert(0, str(Path(__file__).resolve().parent))
from readout_scenes import read_positions, rendered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("agent")
    parser.add_argument("dataset")
    parser.add_argument("--settings", default="stored,train,heldout")
    parser.add_argument("--backgrounds", default=None, help="photographs for 'photo'")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    agent = Agent.load(args.agent)
    readout = agent.student.readout
    if readout is None:
        raise SystemExit(f"{args.agent} is not a read-out student")
    dataset = open_dataset(args.dataset)
    episodes = np.flatnonzero(heldout_episodes(dataset.n_episodes, args.holdout_every))
    episodes = episodes[:args.episodes]
    read = list(readout.config.read)
    scale = readout.scale.numpy().astype(np.float64)
    for setting in args.settings.split(","):
        frames = rendered(dataset, episodes, setting, args.backgrounds, args.seed)
        errors, scenes = [], []
        for index, images in zip(episodes, frames, strict=True):
            error = read_positions(agent, images) - dataset.episode(int(index)).state[:, read]
            errors.append(error)
            scenes.append(float(np.sqrt(np.mean((error / scale) ** 2))))
        error = np.concatenate(errors).astype(np.float64)
        print(json.dumps({"setting": setting, "episodes": len(scenes), "read_components": read,
                          "rmse": np.sqrt((error ** 2).mean(0)).round(4).tolist(),
                          "scene_rms_spreads_median": round(float(np.median(scenes)), 3),
                          "scene_rms_spreads_worst": round(float(np.max(scenes)), 3)}),
              flush=True)


if __name__ == "__main__":
    main()
