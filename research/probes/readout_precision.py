"""How precisely can a read-out head place objects? Per-component errors in the state's units

The panda-push read-out student reads fingertips, block and goal 2-5 cm off, and the teacher
handed positions that far off loses most of its successes (``readout_ceiling.py --noise``).
This screens heads on the same frames: each is trained from scratch with the read-out
recipe's loss (:func:`twist_models.losses.readout_loss` at its Huber delta,
:class:`twist_models.readout.StateReadOut`, standardised as ``--agent`` is)
on single frames of D's training episodes (typical frames, as the distiller draws), and
measured every ``--eval-every`` updates on ``--frames`` frames of D's held-out episodes (every
10th): the RMS error of every read component in the state's units, and the RMS over all
in robust spreads (the distiller's ``read_error``).

Heads (the CNN is the agent's: DreamerV2's four stride-2 convolutions):
* ``linear``: the recipe's, a linear map of the flattened last map;
* ``keypoints<k>``: the first ``k`` convolutions, a 1x1 convolution to 32 maps, a spatial
  soft-argmax per map and a linear map of the 32 positions (``readout_heads.KeypointHead``);
* ``both<k>``: the linear head's flattened map and ``keypoints<k>``'s 32 positions, side by
  side, into one linear map: a position as a number where a map's peak finds the object, the
  whole map where it does not;
* ``coord``: the linear head with each pixel's (x, y) in [-1, 1] as two more input channels
  (CoordConv, Liu et al. 2018): a convolution alone cannot tell where on the image it is.

``python research/probes/readout_precision.py DATASET --agent AGENT [--heads
linear,both2] [--updates 15000] [--eval-every 5000] [--frames 1024] [--lr 3e-4] [--depth 48]
[--scale teacher]``; prints a JSON line per head and checkpoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.distillation import ReadOutStage
from twist_models.losses import readout_loss
from twist_models.networks import ImageEncoder
from twist_models.readout import StateReadOut, typical

sys.path.insert(0, str(Path(__file__).parent))
from readout_heads import KeypointHead, LinearHead, images_in

MAPS = 32


class BothHead(nn.Module):
    """The flattened last map and the soft-argmax positions of ``layers`` convolutions' maps."""

    def __init__(self, encoder: ImageEncoder, layers: int, outputs: int) -> None:
        super().__init__()
        self.trunk = encoder.net
        self.cut = 3 * layers  # each layer: convolution, norm (or none), ELU
        self.keypoints = KeypointHead(encoder, layers, MAPS, outputs)  # shares the trunk's layers
        self.head = nn.Linear(encoder.out_dim + 2 * MAPS, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        early = self.trunk[: self.cut](x)
        late = self.trunk[self.cut:](early).flatten(1).float()
        return self.head(torch.cat([late, self.keypoints.points(early)], -1))


class CoordHead(nn.Module):
    """The linear head on a CNN whose first convolution also reads each pixel's (x, y)."""

    def __init__(self, encoder: ImageEncoder, outputs: int) -> None:
        super().__init__()
        first = encoder.net[0]
        self.first = nn.Conv2d(5, first.out_channels, first.kernel_size, first.stride)
        self.rest = encoder.net[1:]
        self.head = nn.Linear(encoder.out_dim, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        ys = torch.linspace(-1, 1, h, device=x.device).view(1, 1, h, 1).expand(n, 1, h, w)
        xs = torch.linspace(-1, 1, w, device=x.device).view(1, 1, 1, w).expand(n, 1, h, w)
        x = torch.cat([x, xs.to(x.dtype), ys.to(x.dtype)], 1)
        return self.head(self.rest(self.first(x)).flatten(1).float())


def teacher_scale(readout: StateReadOut, states: np.ndarray, seed: int) -> torch.Tensor:
    """Each read component's error that moves the teacher's state embedding as much as its
    typical sensitivity says, in the state's units: 1 / sqrt(E ||d embed / d s_i||^2 + 2 g^2
    E ||d embed / d v_i||^2), the second term for the velocity derived from it by a gain g
    (an error independent between steps enters the difference twice)."""
    rows = np.random.default_rng(seed).choice(len(states), min(2048, len(states)), replace=False)
    x = torch.as_tensor(states[rows], dtype=torch.float32)
    jacobian = torch.func.vmap(torch.func.jacrev(readout.encoder))(x)  # [N, E, S]
    sensitivity = jacobian.pow(2).sum(1).mean(0)
    read = list(readout.config.read)
    total = sensitivity[read].clone()
    for k, velocity in enumerate(readout.config.velocities):
        if len(velocity) == 2:
            total[read.index(velocity[1])] += 2 * readout.gains[k] ** 2 * sensitivity[velocity[0]]
    return total.rsqrt().detach()


def episode_steps(data, episodes: np.ndarray) -> np.ndarray:
    lengths = data.episodes()["length"].to_numpy()
    starts = np.concatenate([[0], lengths.cumsum()[:-1]])
    return np.concatenate([np.arange(starts[e], starts[e] + lengths[e]) for e in episodes])


@torch.no_grad()
def measure(model: nn.Module, readout: StateReadOut, images: np.ndarray,
            states: torch.Tensor) -> dict:
    model.eval()
    out = torch.cat([model(images_in(torch.as_tensor(images[i:i + 256]))).float()
                     for i in range(0, len(images), 256)])
    model.train()
    read = out * readout.scale + readout.mean
    truth = states[:, list(readout.config.read)]
    rms = (read - truth).pow(2).mean(0).sqrt()
    return {"rms": [round(float(v), 4) for v in rms],
            "read_error": round(float(readout.errors(read, states).pow(2).mean().sqrt()), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--agent", type=Path, required=True, help="a read-out student of D")
    parser.add_argument("--heads", default="linear,both2")
    parser.add_argument("--updates", type=int, default=15000)
    parser.add_argument("--eval-every", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--depth", type=int, help="the CNN's first width (the agent's if not given)")
    parser.add_argument("--scale", choices=("robust", "teacher"), default="robust",
                        help="the loss's unit per component: D's robust spread (the recipe's) "
                        "or the teacher's sensitivity (teacher_scale)")
    parser.add_argument("--lr", type=float, default=3e-4, help="Adam's rate (the recipe's: 3e-4)")
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    trained = Agent.load(args.agent).student
    data = open_dataset(args.dataset)
    states = data.column("state")
    held = heldout_episodes(data.n_episodes, 10)
    config = trained.perception.readout.config
    mean = trained.perception.readout.mean.numpy()
    scale = trained.perception.readout.scale.numpy()
    train_steps = episode_steps(data, np.flatnonzero(~held))
    train_steps = train_steps[typical(states[train_steps], config, mean, scale,
                                      ReadOutStage().typical_spreads)]
    rng = np.random.default_rng(args.seed)
    test_steps = np.sort(rng.choice(episode_steps(data, np.flatnonzero(held)), args.frames,
                                    replace=False))
    test_images = np.empty((test_steps.size, *data.spec.image_shape), np.uint8)
    data.read_frames(test_steps, rng.integers(0, data.spec.views, test_steps.size), test_images)
    test_states = torch.as_tensor(states[test_steps], dtype=torch.float32)
    all_states = torch.as_tensor(states, dtype=torch.float32)
    for name in args.heads.split(","):
        torch.manual_seed(args.seed)
        cnn = trained.config.cnn
        encoder = ImageEncoder(cnn if args.depth is None else dataclasses.replace(cnn, depth=args.depth))
        readout = StateReadOut(config, encoder.out_dim)
        readout.load_state_dict({k: v for k, v in trained.perception.readout.state_dict().items()
                                 if not k.startswith("head.")}, strict=False)
        if args.scale == "teacher":
            readout.scale.copy_(teacher_scale(readout, states, args.seed))
        outputs = len(config.read)
        if name == "linear":
            model: nn.Module = LinearHead(encoder, outputs)
        elif name == "coord":
            model = CoordHead(encoder, outputs)
        elif name.startswith("keypoints"):
            model = KeypointHead(encoder, int(name.removeprefix("keypoints")), MAPS, outputs)
        else:
            model = BothHead(encoder, int(name.removeprefix("both")), outputs)
        optimiser = torch.optim.Adam(model.parameters(), lr=args.lr, eps=1e-5)
        buffer = np.empty((64, *data.spec.image_shape), np.uint8)
        draw = np.random.default_rng(args.seed + 1)
        start = time.perf_counter()
        for update in range(1, args.updates + 1):
            rows = np.sort(train_steps[draw.integers(0, train_steps.size, 64)])
            data.read_frames(rows, draw.integers(0, data.spec.views, 64), buffer)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                out = model(images_in(torch.from_numpy(buffer)))
            read = out.float() * readout.scale + readout.mean
            errors = readout.errors(read, all_states[rows])
            loss = readout_loss(errors, ReadOutStage().huber_delta)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 100.0)
            optimiser.step()
            if update % args.eval_every == 0:
                print(json.dumps({"dataset": str(args.dataset), "head": name, "scale": args.scale,
                                  "lr": args.lr,
                                  "depth": encoder.net[0].out_channels, "updates": update,
                                  "s": round(time.perf_counter() - start, 1),
                                  "loss": round(float(loss.detach()), 4),
                                  **measure(model, readout, test_images, test_states)}),
                      flush=True)


if __name__ == "__main__":
    main()
