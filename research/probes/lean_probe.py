"""How fast does a CNN learn which way cartpole's pole leans?

The balance task needs the student to read a one-pixel pole's lean from randomised 64x64
images. This trains the student's CNN of ``--preset`` with a linear head to classify the sign
of state component ``--component`` (the pole angle's sine on cartpole) on D's training frames
whose |value| lies in [``--low``, ``--high``] (5-30 degrees by default), classes balanced,
batches of ``--batch`` random frames and views, and reports held-out accuracy every
``--every`` updates, for each ``--norm`` in the same run (``none``: DreamerV2's CNN, the
baseline; ``layer``: ``CNNConfig.norm="layer"``). Held-out frames come from every
``--holdout-every``-th episode, as in ``twist-distil``.

Prints one JSON line. ``python research/probes/lean_probe.py DATASET [--steps 800]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch
from torch.nn import functional

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.config import CNN_NORMS, PRESETS, CNNConfig
from twist_models.networks import ImageEncoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--preset", default="quick", choices=list(PRESETS))
    parser.add_argument("--norm", nargs="+", default=list(CNN_NORMS), choices=CNN_NORMS)
    parser.add_argument("--component", type=int, default=2)
    parser.add_argument("--low", type=float, default=float(np.sin(np.deg2rad(5))))
    parser.add_argument("--high", type=float, default=float(np.sin(np.deg2rad(30))))
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--every", type=int, default=100)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--test-frames", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    data = open_dataset(args.dataset)
    value = data.column("state")[:, args.component]
    held = np.repeat(heldout_episodes(data.n_episodes, args.holdout_every), data.episode_lengths)
    leaning = (np.abs(value) >= args.low) & (np.abs(value) <= args.high)
    positive = np.flatnonzero(leaning & ~held & (value > 0))
    negative = np.flatnonzero(leaning & ~held & (value < 0))
    rng = np.random.default_rng(args.seed)
    test = np.flatnonzero(leaning & held)
    test = rng.choice(test, min(args.test_frames, test.size), replace=False)
    test_images = torch.as_tensor(data.frames_of_random_views(test, rng))
    test_labels = torch.as_tensor(value[test] > 0)
    result: dict[str, object] = {"dataset": args.dataset, "train_frames": [positive.size,
                                 negative.size], "heldout_frames": int(test.size)}
    for norm in args.norm:
        torch.manual_seed(args.seed)
        rng = np.random.default_rng(args.seed)
        encoder = ImageEncoder(dataclasses.replace(PRESETS[args.preset].get("cnn", CNNConfig()),
                                                   image_size=data.spec.image_height, norm=norm))
        head = torch.nn.Linear(encoder.out_dim, 1)
        optimiser = torch.optim.Adam([*encoder.parameters(), *head.parameters()], args.lr)
        accuracy, start = [], time.perf_counter()
        for update in range(1, args.steps + 1):
            half = args.batch // 2
            steps = np.r_[rng.choice(positive, half), rng.choice(negative, half)]
            images = torch.as_tensor(data.frames_of_random_views(steps, rng))
            logits = head(encoder(images))[:, 0]
            loss = functional.binary_cross_entropy_with_logits(
                logits, torch.as_tensor(value[steps] > 0).float())
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            if update % args.every == 0:
                with torch.no_grad():
                    correct = (head(encoder(test_images))[:, 0] > 0) == test_labels
                accuracy.append(round(float(correct.float().mean()), 3))
        result[norm] = {"heldout_accuracy": accuracy, "every": args.every,
                        "seconds": round(time.perf_counter() - start, 1)}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
