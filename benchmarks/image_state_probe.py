"""How well can a CNN read the privileged state from D's randomised images? (issue 7 diagnosis)

A student acts well only if its encoder recovers what the teacher's actor needs (on cartpole:
the pole's angle) from one randomised 64x64 image. This probe trains, on D's training
episodes, a linear head from image embeddings to the normalised state for ``--steps`` updates
(Adam, batches of ``--batch`` random frames and views) and reports the R² of each state
component on the held-out episodes (every ``--holdout-every``-th, as ``twist-distil``):

* ``random_cnn``: a frozen, freshly initialised CNN of ``--preset`` -- the baseline measured
  in the same run (what untrained features give a linear head);
* ``supervised_cnn``: the same CNN trained with the head, directly on the state -- roughly what
  any image student of that size can learn in that many updates;
* ``student``: with ``--agent``, the distilled student's frozen encoder -- what distillation
  taught it.

R² is 1 - MSE / variance per component over the held-out frames (0: no better than the mean).
``--within I:LOW:HIGH`` keeps only frames whose state component I lies in [LOW, HIGH], e.g.
``0:-0.6:0.6`` for cartpole frames with the cart in the central third of the view.
Prints one JSON line. ``python benchmarks/image_state_probe.py DATASET [--agent AGENT]
[--steps 300] [--preset quick] [--within I:LOW:HIGH]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch
from torch import nn

from twist_data.reader import MatchingDataset, open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.config import PRESETS, CNNConfig
from twist_models.networks import ImageEncoder


def frames(data: MatchingDataset, steps: np.ndarray, rng: np.random.Generator) -> torch.Tensor:
    out = np.empty((steps.size, *data.spec.image_shape), np.uint8)
    data.read_frames(steps, rng.integers(0, data.spec.views, steps.size), out)
    return torch.as_tensor(out)


def probe(encoder: nn.Module, train_encoder: bool, data: MatchingDataset, target: torch.Tensor,
          train: np.ndarray, test: tuple[torch.Tensor, torch.Tensor], args: argparse.Namespace
          ) -> list[float]:
    """Train a linear head (and the encoder when ``train_encoder``) -> held-out R² per component."""
    rng = np.random.default_rng(args.seed)
    head = nn.Linear(encoder.out_dim, target.shape[1])
    encoder.requires_grad_(train_encoder)
    params = [*head.parameters(), *(encoder.parameters() if train_encoder else [])]
    optimiser = torch.optim.Adam(params, lr=args.lr)
    for _ in range(args.steps):
        steps = rng.choice(train, args.batch)
        loss = ((head(encoder(frames(data, steps, rng))) - target[steps]) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    images, truth = test
    with torch.no_grad():
        error = ((head(encoder(images)) - truth) ** 2).mean(0)
    return [round(float(v), 3) for v in 1.0 - error / truth.var(0)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--agent", help="a distilled agent bundle whose encoder to probe")
    parser.add_argument("--preset", default="quick", choices=list(PRESETS))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--test-frames", type=int, default=512)
    parser.add_argument("--within", help="I:LOW:HIGH, only frames with LOW <= state[I] <= HIGH")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    data = open_dataset(args.dataset)
    states = data.column("state").astype(np.float32)
    target = torch.as_tensor((states - states.mean(0)) / states.std(0).clip(1e-3))
    held = np.repeat(heldout_episodes(data.n_episodes, args.holdout_every), data.episode_lengths)
    kept = np.ones(held.size, bool)
    if args.within:
        index, low, high = args.within.split(":")
        component = states[:, int(index)]
        kept = (component >= float(low)) & (component <= float(high))
    train, heldout = np.flatnonzero(~held & kept), np.flatnonzero(held & kept)
    rng = np.random.default_rng(args.seed + 1)
    test_steps = np.sort(rng.choice(heldout, min(args.test_frames, heldout.size), replace=False))
    test = (frames(data, test_steps, rng), target[test_steps])
    cnn = dataclasses.replace(PRESETS[args.preset].get("cnn", CNNConfig()),
                              image_size=data.spec.image_height)
    result = {"dataset": args.dataset, "preset": args.preset, "within": args.within,
              "steps": args.steps,
              "batch": args.batch, "train_frames": int(train.size),
              "heldout_frames": int(test_steps.size),
              "random_cnn": probe(ImageEncoder(cnn), False, data, target, train, test, args),
              "supervised_cnn": probe(ImageEncoder(cnn), True, data, target, train, test, args)}
    if args.agent:
        encoder = Agent.load(args.agent).student.encoder
        result["student"] = probe(encoder, False, data, target, train, test, args)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
