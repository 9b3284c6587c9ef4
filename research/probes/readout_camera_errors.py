"""Read-out students' errors on the same frames: does a student trained on a D that shows
the camera move read plain scenes less precisely?

Draws ``--frames`` frames (a random view each) from the held-out episodes of every dataset
given, and reports for every read-out agent its read-out error on them, in D's robust spreads
(:meth:`~twist_models.readout.StateReadOut.error`): over every frame and over the typical
ones (every read component within ``ReadOutStage.typical_spreads`` of its median), as the distiller's
``read_error`` and ``read_error_typical`` do on its own held-out windows, but on one set of
frames for all agents.

Prints one JSON line: {"AGENT on DATASET": [error, typical error]}; with ``--components``,
each value also lists the typical frames' RMS error per read slot in the state's units (an
angle pair's sine slot holds its angle's error in radians, its cosine slot the pair's length),
comparable across Ds, whose spreads differ. ``python
research/probes/readout_camera_errors.py --dataset runs/c0/dataset --dataset runs/c0/dataset-full
--agent wide=runs/c0/ro/agent.pt --agent full=runs/c0/ro-full/agent.pt [--frames 2048]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.distillation import ReadOutStage
from twist_models.readout import typical as typical_rows

#: Frames per pass of the CNN.
CHUNK = 256


def heldout_frames(dataset: str, frames: int, seed: int, every: int = 10
                   ) -> tuple[np.ndarray, torch.Tensor]:
    """``frames`` random (step, view) frames of the held-out episodes (every ``every``-th, as
    the distiller holds out) -> (images uint8 [N, H, W, 3], states [N, S])."""
    data = open_dataset(dataset)
    rng = np.random.default_rng(seed)
    lengths = data.episodes()["length"].to_numpy()
    starts = np.concatenate([[0], lengths.cumsum()[:-1]])
    held = np.flatnonzero(heldout_episodes(data.n_episodes, every))
    steps = np.concatenate([np.arange(starts[e], starts[e] + lengths[e]) for e in held])
    steps = np.sort(rng.choice(steps, min(frames, steps.size), replace=False))
    images = np.empty((steps.size, *data.spec.image_shape), np.uint8)
    data.read_frames(steps, rng.integers(0, data.spec.views, steps.size), images)
    return images, torch.as_tensor(data.column("state")[steps]).float()


@torch.no_grad()
def read_errors(agent: Agent, images: np.ndarray, states: torch.Tensor
                ) -> tuple[float, float, list[float]]:
    """The agent's read-out error over every frame and over the typical ones (D's spreads),
    and the typical ones' RMS error per read slot (the state's units)."""
    student = agent.student.eval()
    features = torch.cat([student.perception.encoder(torch.as_tensor(images[i:i + CHUNK])).flatten(1).float()
                          for i in range(0, len(images), CHUNK)])
    readout = student.perception.readout
    spreads = ReadOutStage().typical_spreads
    errors = readout.errors(readout.read(features), states)
    rows = typical_rows(states, readout.config, readout.mean, readout.scale, spreads)
    typical = errors[rows].pow(2)
    return (float(errors.pow(2).mean().sqrt()),
            float(typical.mean().sqrt()) if typical.numel() else float("nan"),
            (typical.mean(0).sqrt() * readout.scale).tolist())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True)
    parser.add_argument("--agent", action="append", required=True, help="NAME=agent.pt")
    parser.add_argument("--frames", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--components", action="store_true", help="also the error per read slot")
    args = parser.parse_args()
    agents = {}
    for spec in args.agent:
        name, _, path = spec.rpartition("=")
        agents[name or Path(path).parent.name] = Agent.load(path)
    out = {}
    for dataset in args.dataset:
        images, states = heldout_frames(dataset, args.frames, args.seed)
        for name, agent in agents.items():
            error, typical, per_slot = read_errors(agent, images, states)
            row = [round(error, 3), round(typical, 3)]
            out[f"{name} on {Path(dataset).name}"] = row + (
                [[round(v, 3) for v in per_slot]] if args.components else [])
    print(json.dumps(out))


if __name__ == "__main__":
    main()
