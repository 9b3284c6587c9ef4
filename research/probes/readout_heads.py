"""Which read-out head keeps a cartpole read-out unbiased on backgrounds it never saw?

The read-out student loses held-out scenes in which its reading of the pole's angle is off
by a constant (a bias of 1-3 degrees makes the teacher's filter chase a lean that is not there,
research/log.md). This screens heads on the same CNN trunk, trained the same number of
single-frame updates on D's typical frames with the read-out recipe's own loss
(:class:`twist_models.readout.StateReadOut`, configured as a trained read-out student is),
and measures each on a *lean sweep*: in each of ``twist-eval --dr heldout``'s first
``--scenes`` scenes, the pole at -10..10 degrees (1-degree steps) and the cart at five
positions, at rest. Per scene: the angle's bias (mean error) and RMS error, near upright
(within 3 degrees) too, and the cart's RMS error; summarised over scenes. A static sweep
reads no velocity and runs no filter: it is a screen, a student is judged by its returns.

Heads:
* ``linear``: the recipe's: DreamerV2's four convolutions flattened into a linear map.
* ``keypoints<k>``: the first ``k`` convolutions, a 1x1 convolution to 32 maps, a spatial
  soft-argmax per map (Levine et al. 2016's deep spatial autoencoder) and a linear map from
  the 32 expected positions, so that a background's texture can move the reading only where
  it wins a map's peak.

``python research/probes/readout_heads.py RUN [--heads linear,keypoints3] [--updates 10000]
[--scenes 30] [--agent AGENT]`` with RUN a main-job folder holding ``dataset`` and a read-out
``student``; ``--agent`` sweeps an agent bundle without training: each image alone, and, where the agent
reads the mirror image too (``readout_stage.mirror``), as it acts.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from twist_data.reader import MatchingDataset, open_dataset
from twist_data.seeding import evaluation_episode_seed
from twist_models.agent import Agent
from twist_models.distillation import ReadOutStage
from twist_models.networks import ImageEncoder
from twist_models.readout import StateReadOut, typical
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TaskEnv, state_mirror

#: Where cartpole's physics vector holds the cart's position and the pole's hinge angle.
CART_X, HINGE = 1, 2
SWEEP_DEGREES = np.arange(-10.0, 10.5, 1.0)
SWEEP_X = (-0.8, -0.4, 0.0, 0.4, 0.8)


class KeypointHead(nn.Module):
    """The CNN's first ``layers`` convolutions -> ``maps`` soft-argmax positions -> read."""

    def __init__(self, encoder: ImageEncoder, layers: int, maps: int, outputs: int) -> None:
        super().__init__()
        self.trunk = encoder.net[: 3 * layers]  # each layer: convolution, norm, ELU
        channels = [m for m in self.trunk if isinstance(m, nn.Conv2d)][-1].out_channels
        self.maps = nn.Conv2d(channels, maps, 1)
        self.log_temperature = nn.Parameter(torch.zeros(()))
        self.head = nn.Linear(2 * maps, outputs)

    def points(self, early: torch.Tensor) -> torch.Tensor:
        """The trunk's output [N, C, H, W] -> the maps' soft-argmax positions [N, 2 * maps]."""
        maps = self.maps(early).float()
        h, w = maps.shape[-2:]
        weights = torch.softmax(maps.flatten(2) * self.log_temperature.exp(), -1)
        ys = torch.linspace(-1, 1, h, device=early.device).repeat_interleave(w)
        xs = torch.linspace(-1, 1, w, device=early.device).repeat(h)
        return torch.cat([(weights * xs).sum(-1), (weights * ys).sum(-1)], -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.points(self.trunk(x)))


class LinearHead(nn.Module):
    def __init__(self, encoder: ImageEncoder, outputs: int) -> None:
        super().__init__()
        self.trunk = encoder.net
        self.head = nn.Linear(encoder.out_dim, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk(x).flatten(1).float())


def images_in(image: torch.Tensor) -> torch.Tensor:
    """uint8 [N, H, W, 3] -> float [-0.5, 0.5] channels-last NCHW, as the student's CNN."""
    x = (image.float() / 255.0 - 0.5).permute(0, 3, 1, 2)
    return x.contiguous(memory_format=torch.channels_last)


def angle_flattening(states: np.ndarray, steps: np.ndarray, power: float,
                     bins: int = 64) -> np.ndarray:
    """Draw probabilities over ``steps`` proportional to 1 / (the density of the pole's angle
    among them) ** ``power``: 0 draws D's mix, 1 every angle bin as often."""
    angle = np.arctan2(states[steps, 2], states[steps, 1])
    edges = np.linspace(angle.min(), angle.max(), bins + 1)
    which = np.clip(np.digitize(angle, edges) - 1, 0, bins - 1)
    weight = np.bincount(which, minlength=bins)[which].astype(np.float64) ** -power
    return weight / weight.sum()


def train(model: nn.Module, readout: StateReadOut, data: MatchingDataset, steps: np.ndarray,
          updates: int, seed: int, draw: np.ndarray | None = None,
          mirror: torch.Tensor | None = None) -> float:
    """``updates`` Adam steps of the read-out's loss on 64 of D's ``steps`` each, drawn
    uniformly or by ``draw`` [len(steps)]; with ``mirror`` (the state's signs in the mirrored
    view) each frame is mirrored with probability 1/2, as ``readout_mirror=augment``."""
    rng = np.random.default_rng(seed)
    states = torch.as_tensor(data.column("state"), dtype=torch.float32)
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-4, eps=1e-5)
    buffer = np.empty((64, *data.spec.image_shape), np.uint8)
    start = time.perf_counter()
    for update in range(updates):
        rows = (steps[rng.integers(0, steps.size, 64)] if draw is None
                else rng.choice(steps, 64, p=draw))
        data.read_frames(rows, rng.integers(0, data.spec.views, 64), buffer)
        image, state = torch.from_numpy(buffer).clone(), states[rows]
        if mirror is not None:
            flip = torch.from_numpy(rng.random(64) < 0.5)
            image[flip] = image[flip].flip(-2)
            state = torch.where(flip[:, None], state * mirror, state)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = model(images_in(image))
        read = out.float() * readout.scale + readout.mean
        loss = F.huber_loss(readout.errors(read, state), torch.zeros_like(read))
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 100.0)
        optimiser.step()
        if (update + 1) % 1000 == 0:
            print(json.dumps({"update": update + 1, "loss": round(float(loss), 4),
                              "s": round(time.perf_counter() - start, 1)}), flush=True)
    return time.perf_counter() - start


def sweep(read: Callable[[torch.Tensor], torch.Tensor], scenes: int) -> dict:
    """Per held-out scene the read-out's errors over the lean sweep, and their summary."""
    config = dr_preset("heldout").replace(resample="episode")
    env = TaskEnv("cartpole-balance")
    env.reset(seed=0)
    base = env.physics_state()
    base[HINGE + 1:] = 0.0
    truth = np.array([(x, math.radians(a)) for x in SWEEP_X for a in SWEEP_DEGREES])
    near = np.abs(truth[:, 1]) <= math.radians(3.0)
    rows = []
    with DRRenderer("cartpole-balance", config, 64, views=1, supersample=2) as renderer:
        sampler = renderer.sampler(0)
        for i in range(scenes):
            sampler.begin_episode(evaluation_episode_seed(0, i))
            params = sampler.sample()
            frames = []
            for x, angle in truth:
                physics = base.copy()
                physics[CART_X], physics[HINGE] = x, angle
                frames.append(renderer.render(physics, params)[0])
            with torch.no_grad():
                pos = read(torch.as_tensor(np.stack(frames))).numpy()
            angle = np.degrees(np.arctan2(pos[:, 2], pos[:, 1]))
            error = angle - np.degrees(truth[:, 1])
            slope = np.polyfit(np.degrees(truth[:, 1]), angle, 1)[0]
            rows.append({"scene": i, "bias": float(error.mean()), "slope": float(slope),
                         "rms": float(np.sqrt((error ** 2).mean())),
                         "near_rms": float(np.sqrt((error[near] ** 2).mean())),
                         "x_rms": float(np.sqrt(((pos[:, 0] - truth[:, 0]) ** 2).mean()))})
    bias = np.abs([r["bias"] for r in rows])
    return {"mean_abs_bias_deg": round(float(bias.mean()), 3),
            "scenes_bias_over_1deg": int((bias > 1.0).sum()),
            "median_near_rms_deg": round(float(np.median([r["near_rms"] for r in rows])), 3),
            "mean_rms_deg": round(float(np.mean([r["rms"] for r in rows])), 3),
            "mean_x_rms": round(float(np.mean([r["x_rms"] for r in rows])), 4),
            "median_slope": round(float(np.median([r["slope"] for r in rows])), 3),
            "scenes_slope_under_0.8": int(sum(r["slope"] < 0.8 for r in rows)),
            "per_scene_bias": [round(r["bias"], 2) for r in rows],
            "per_scene_slope": [round(r["slope"], 2) for r in rows]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--heads", default="linear,keypoints3")
    parser.add_argument("--updates", type=int, default=10000)
    parser.add_argument("--scenes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--agent", type=Path, help="sweep this agent bundle instead")
    parser.add_argument("--init", type=Path, help="fine-tune this agent's CNN and linear head "
                        "(with its mirror augmentation and reading) instead of training anew")
    parser.add_argument("--save-agent", type=Path, help="with --init: write the agent with the "
                        "fine-tuned CNN and head here, for twist-eval")
    parser.add_argument("--flatten", type=float, default=0.0,
                        help="draw frames by 1 / the pole angle's density to this power")
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    if args.agent is not None:
        student = Agent.load(args.agent).student
        readings = {"image": lambda im: student.perception.readout.read(student.perception.encoder(im))}
        if student.perception.readout.config.mirror:  # the agent's own reading: the mean with the mirror's
            readings["mirror-averaged"] = student.perception.read_positions
        for reading, read in readings.items():
            print(json.dumps({"head": "agent", "agent": str(args.agent), "reading": reading,
                              **sweep(read, args.scenes)}), flush=True)
        return
    trained = Agent.load(args.init or args.run / "student" / "agent.pt").student
    data = open_dataset(args.run / "dataset")
    states = data.column("state")
    keep = typical(states, trained.perception.readout.config, trained.perception.readout.mean.numpy(),
                   trained.perception.readout.scale.numpy(), ReadOutStage().typical_spreads)
    steps = np.flatnonzero(keep)
    draw = angle_flattening(states, steps, args.flatten) if args.flatten else None
    for name in args.heads.split(","):
        torch.manual_seed(args.seed)
        encoder = ImageEncoder(trained.config.cnn)
        readout = StateReadOut(trained.perception.readout.config, encoder.out_dim)
        readout.load_state_dict(trained.perception.readout.state_dict())  # standardisation and layout
        outputs = len(readout.config.read)
        model = (LinearHead(encoder, outputs) if name == "linear"
                 else KeypointHead(encoder, int(name.removeprefix("keypoints")), 32, outputs))
        mirror = None
        if args.init is not None:
            encoder.load_state_dict(trained.perception.encoder.state_dict())
            model.head.load_state_dict(trained.perception.readout.head.state_dict())
            if trained.perception.readout.config.mirror:
                mirror = torch.tensor(state_mirror(data.spec.task), dtype=torch.float32)
        seconds = train(model, readout, data, steps, args.updates, args.seed, draw, mirror)
        model.eval()
        if args.save_agent is not None and args.init is not None:
            agent = Agent.load(args.init)
            agent.student.perception.encoder.load_state_dict(encoder.state_dict())
            agent.student.perception.readout.head.load_state_dict(model.head.state_dict())
            agent.save(args.save_agent)

        def read(image: torch.Tensor, model: nn.Module = model,
                 readout: StateReadOut = readout, mirror: torch.Tensor | None = mirror
                 ) -> torch.Tensor:
            out = model(images_in(image)).float() * readout.scale + readout.mean
            if mirror is None:
                return out
            flipped = model(images_in(image.flip(-2))).float() * readout.scale + readout.mean
            return (out + readout.mirror * flipped) / 2

        print(json.dumps({"head": name, "updates": args.updates, "flatten": args.flatten,
                          "train_s": round(seconds, 1),
                          **sweep(read, args.scenes)}), flush=True)


if __name__ == "__main__":
    main()
