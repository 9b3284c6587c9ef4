"""Can the teacher's own filter act on positions a CNN reads from the image?

A teacher whose state encoder never reads the velocities (``state_hidden``) infers them in
its recurrence from successive positions, as a pixel Dreamer must. Its filter could then run
on positions read from one randomised image each step: a student whose only learned part is
a CNN, with the teacher's posterior, GRU and actor unchanged. This script measures that
student on cartpole-balance:

``train DATASET OUT``: a CNN (the ``quick`` preset's, layer-normalised, bfloat16 autocast)
with a linear head regresses the cart's position and the pole's sine on D's training frames
within ``--within`` of upright (cosine at least that), each standardised over those frames
(the target under which the near-upright lean was learned, research/log.md);
``--all-frames`` trains on every frame with a Huber loss to read the cosine as well (in the
sine's scaling), so that the angle is known on the whole circle. Every
``--every`` updates it prints the held-out RMSE of both, and the sine's RMSE on frames within
10° of upright beside that set's spread, as JSON lines; it saves ``OUT`` (weights and the
standardisation; plain tensors, loaded with ``weights_only``).

``policy``: the agent ``twist-eval`` imports (``--agent state_bottleneck:policy`` with
``research/probes`` on ``PYTHONPATH``), built from ``TWIST_BOTTLENECK_CNN`` (the file ``train``
wrote) and ``TWIST_BOTTLENECK_TEACHER`` (the teacher checkpoint): each step it reads x and
sin θ from the image, sets cos θ = sqrt(1 - sin² θ) (the pole above horizontal) and the
velocities to 0 (a positions-only teacher never reads them), and acts with the teacher's
``policy`` on that state, its posterior sampled as the oracle's is. With
``TWIST_BOTTLENECK_VELOCITIES=difference`` the velocities are instead the differences of
successive read-outs over ``TWIST_BOTTLENECK_DT`` seconds (default 0.04: cartpole's 0.01 s
at action repeat 4), 0 on the first step: what two images show, for a teacher that reads the
full state. ``TWIST_BOTTLENECK_CNN_FAR`` names a second CNN (``--all-frames``), which reads
every frame; the first then reads only those the second puts within 20° of upright. An
imported policy carries no render settings: pass D's (``--supersample 2``, and ``--action-
repeat 4`` unless a teacher checkpoint is evaluated beside it, whose repeat the run then
takes). With ``TWIST_BOTTLENECK_LOG`` set it writes there, as JSON, the read-out's closed-
loop RMSE against the true state so far (every 250 steps), and beside it
(``<stem>.visited.npy``) each step's true state followed by the x and sin θ read from its
image.

``python research/probes/state_bottleneck.py train DATASET OUT [--steps 15000] [--within 0.94]
[--all-frames]``, then ``TWIST_BOTTLENECK_CNN=OUT TWIST_BOTTLENECK_TEACHER=TEACHER
PYTHONPATH=research/probes twist-eval --agent oracle=TEACHER --agent state_bottleneck:policy
--dr heldout --supersample 2``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np
import torch
from torch import nn

from twist_data.reader import MatchingDataset, open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.config import PRESETS, CNNConfig
from twist_models.device import precision_autocast
from twist_models.networks import ImageEncoder
from twist_models.teacher import load_teacher

#: Cartpole's state layout: cart x, cos θ, sin θ, then the velocities.
X, COS, SIN, X_VELOCITY, ANGULAR_VELOCITY = 0, 1, 2, 3, 4
#: What the CNN reads: near upright the sine gives the angle; over every frame the cosine too.
NEAR_READ, ALL_READ = (X, SIN), (X, COS, SIN)
#: From two frames (``--frames 2``) the velocities as well.
MOTION_READ = (X, SIN, X_VELOCITY, ANGULAR_VELOCITY)


def reader(image_size: int, outputs: int, frames: int = 1) -> tuple[nn.Module, nn.Module]:
    """The CNN, applied to each frame alone, and a linear head on the ``frames`` embeddings
    side by side (most recent first): a velocity is a difference the head can take."""
    cnn = dataclasses.replace(PRESETS["quick"].get("cnn", CNNConfig()), image_size=image_size,
                              norm="layer")
    encoder = ImageEncoder(cnn)
    return encoder, nn.Linear(encoder.out_dim * frames, outputs)


def embed_frames(encoder: nn.Module, images: torch.Tensor) -> torch.Tensor:
    """images uint8 [N, frames, H, W, 3] -> [N, frames * E]."""
    n, frames = images.shape[:2]
    return encoder(images.flatten(0, 1)).reshape(n, frames * encoder.out_dim)


def frames_before(data: MatchingDataset, steps: np.ndarray, frames: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Each of ``steps`` and the ``frames - 1`` before it in its episode (its first step
    repeated before the start), one view per step: uint8 [N, frames, H, W, 3]."""
    starts = data.episode_starts[np.searchsorted(data.episode_starts, steps, "right") - 1]
    back = np.maximum(steps[:, None] - np.arange(frames), starts[:, None])
    views = np.repeat(rng.integers(0, data.spec.views, steps.size), frames)
    out = np.empty((back.size, *data.spec.image_shape), np.uint8)
    data.read_frames(back.reshape(-1), views, out)
    return out.reshape(steps.size, frames, *data.spec.image_shape)


def train(args: argparse.Namespace) -> None:
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    data = open_dataset(args.dataset)
    states = data.column("state").astype(np.float32)
    held = np.repeat(heldout_episodes(data.n_episodes, 10), data.episode_lengths)
    read = ALL_READ if args.all_frames else MOTION_READ if args.frames == 2 else NEAR_READ
    kept = states[:, COS] >= args.within
    train_steps, test_steps = np.flatnonzero(~held & kept), np.flatnonzero(held & kept)
    kept_read = states[train_steps][:, read]
    mean, scale = kept_read.mean(0), kept_read.std(0).clip(1e-4)
    if args.all_frames:  # the same scaling, every training frame, a bounded-gradient loss
        train_steps = np.flatnonzero(~held)
        scale[1] = scale[2]  # the cosine in the sine's units: near upright it barely moves
    target = torch.as_tensor((states[:, read] - mean) / scale)
    test_steps = np.sort(rng.choice(test_steps, min(1024, test_steps.size), replace=False))
    test_images = torch.as_tensor(frames_before(data, test_steps, args.frames, rng))
    near = states[test_steps, COS] >= 0.985
    near_spread = states[test_steps][near][:, SIN].std()
    encoder, head = reader(data.spec.image_height, len(read), args.frames)
    optimiser = torch.optim.Adam([*encoder.parameters(), *head.parameters()], args.lr)
    device = torch.device("cpu")
    start = time.perf_counter()
    for update in range(1, args.steps + 1):
        steps = rng.choice(train_steps, args.batch)
        with precision_autocast("auto", device):
            images = torch.as_tensor(frames_before(data, steps, args.frames, rng))
            predicted = head(embed_frames(encoder, images)).float()
        loss = (nn.functional.huber_loss(predicted, target[steps]) if args.all_frames
                else ((predicted - target[steps]) ** 2).mean())
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        if update % args.every == 0 or update == args.steps:
            with torch.no_grad(), precision_autocast("auto", device):
                test = head(embed_frames(encoder, test_images)).float().numpy() * scale + mean
            error = (test - states[test_steps][:, read])[:, [0, read.index(SIN)]]
            print(json.dumps({
                "updates": update, "loss": round(float(loss.detach()), 4),
                "rmse_x": round(float(np.sqrt((error[:, 0] ** 2).mean())), 4),
                "rmse_sin": round(float(np.sqrt((error[:, 1] ** 2).mean())), 4),
                "near_rmse_sin": round(float(np.sqrt((error[near, 1] ** 2).mean())), 4),
                "near_spread_sin": round(float(near_spread), 4),
                **({"near_rmse_angular_velocity": round(float(np.sqrt(
                    ((test - states[test_steps][:, read])[near, 3] ** 2).mean())), 4),
                    "near_spread_angular_velocity": round(float(
                        states[test_steps][near][:, ANGULAR_VELOCITY].std()), 4)}
                   if args.frames == 2 else {}),
                "seconds": round(time.perf_counter() - start, 1)}), flush=True)
            torch.save({"encoder": encoder.state_dict(), "head": head.state_dict(),
                        "mean": torch.as_tensor(mean), "scale": torch.as_tensor(scale),
                        "image_size": data.spec.image_height, "read": torch.tensor(read),
                        "frames": args.frames},
                       args.out)


#: Within this cosine of upright the near-upright CNN reads the pole (a CNN trained there).
NEAR_COS = 0.94


class ReadOut:
    """A CNN that ``train`` wrote: image -> (its read-out in the state's units, the angle)."""

    def __init__(self, path: str) -> None:
        saved = torch.load(path, weights_only=True)
        self.read = tuple(saved.get("read", torch.tensor(NEAR_READ)).tolist())
        self.frames = int(saved.get("frames", 1))
        self.encoder, self.head = reader(int(saved["image_size"]), len(self.read), self.frames)
        self.encoder.load_state_dict(saved["encoder"])
        self.head.load_state_dict(saved["head"])
        self.encoder.eval()
        self.mean, self.scale = saved["mean"], saved["scale"]
        self.reset()

    def reset(self) -> None:
        self.previous: torch.Tensor | None = None

    def __call__(self, image: torch.Tensor) -> tuple[torch.Tensor, float]:
        embed = self.encoder(image)
        if self.frames == 2:  # the episode's first image stands in for the one before it
            embed, self.previous = torch.cat([embed, embed if self.previous is None
                                              else self.previous], -1), embed
        read = self.head(embed).float()[0] * self.scale + self.mean
        if COS in self.read:  # both read: the angle on the whole circle
            return read, float(torch.atan2(read[-1], read[1]))
        return read, float(torch.asin(read[-1].clamp(-1.0, 1.0)))  # above horizontal


class BottleneckPolicy:
    """The teacher's filter and actor on the state a CNN reads from each image."""

    observe = ("image", "state")
    task = "cartpole-balance"

    def __init__(self) -> None:
        self._loaded = False
        self.errors: list[list[float]] = []
        self.visited: list[list[float]] = []

    def _load(self) -> None:
        self.readers = [ReadOut(os.environ["TWIST_BOTTLENECK_CNN"])]
        if os.environ.get("TWIST_BOTTLENECK_CNN_FAR"):
            self.readers.append(ReadOut(os.environ["TWIST_BOTTLENECK_CNN_FAR"]))
        self.teacher, _ = load_teacher(os.environ["TWIST_BOTTLENECK_TEACHER"])
        self.teacher.eval()
        self.state_dim = self.teacher.config.world_model.state_dim
        self.action_dim = self.teacher.config.world_model.action_dim
        self._loaded = True

    def reset(self) -> None:
        if not self._loaded:
            self._load()
        self.latent, self.first = None, True
        self.previous = torch.zeros(1, self.action_dim)
        for read_out in self.readers:
            read_out.reset()
        self.last_read: tuple[float, float] | None = None

    @torch.no_grad()
    def __call__(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        image = torch.as_tensor(observation["image"])[None]
        read, angle = self.readers[-1](image)
        near = self.readers[0](image) if len(self.readers) > 1 else None
        if near is not None and np.cos(angle) >= NEAR_COS:  # near upright: the near CNN
            read, angle = near
        sine = torch.tensor(np.sin(angle))
        state = torch.zeros(1, self.state_dim)
        state[0, X], state[0, SIN], state[0, COS] = read[0], sine, float(np.cos(angle))
        if os.environ.get("TWIST_BOTTLENECK_VELOCITIES") == "difference" and self.last_read:
            step = float(os.environ.get("TWIST_BOTTLENECK_DT", "0.04"))
            turned = (angle - self.last_read[1] + np.pi) % (2 * np.pi) - np.pi
            state[0, X_VELOCITY] = (float(read[0]) - self.last_read[0]) / step
            state[0, ANGULAR_VELOCITY] = turned / step
        self.last_read = (float(read[0]), angle)
        if X_VELOCITY in self.readers[0].read:  # the near CNN read them from two frames
            motion = self.readers[0].read
            state[0, X_VELOCITY] = read[motion.index(X_VELOCITY)]
            state[0, ANGULAR_VELOCITY] = read[motion.index(ANGULAR_VELOCITY)]
        truth = observation["state"]
        self.errors.append([float(read[0]) - truth[X], float(sine) - truth[SIN], truth[COS]])
        self.visited.append([*np.asarray(truth, np.float64), float(read[0]), float(sine)])
        first = torch.tensor([self.first])
        action, self.latent = self.teacher.policy(state, self.latent, self.previous, first,
                                                  explore=False)
        self.previous, self.first = action, False
        if os.environ.get("TWIST_BOTTLENECK_LOG") and len(self.errors) % 250 == 0:
            self._write_errors(os.environ["TWIST_BOTTLENECK_LOG"])
        return action[0].numpy()

    def _write_errors(self, path: str) -> None:
        """The read-out's RMSE in closed loop so far, over all steps and within 10° of
        upright (the image reads the state the policy itself led to)."""
        errors = np.asarray(self.errors)
        near = errors[:, 2] >= 0.985
        with open(path, "w") as f:
            json.dump({"steps": len(errors), "rmse_x": float(np.sqrt((errors[:, 0] ** 2).mean())),
                       "rmse_sin": float(np.sqrt((errors[:, 1] ** 2).mean())),
                       "near_steps": int(near.sum()),
                       "near_rmse_sin": float(np.sqrt((errors[near, 1] ** 2).mean())),
                       "near_bias_sin": float(errors[near, 1].mean())}, f)
        np.save(os.path.splitext(path)[0] + ".visited.npy", np.asarray(self.visited))


policy = BottleneckPolicy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("dataset")
    t.add_argument("out")
    t.add_argument("--steps", type=int, default=15_000)
    t.add_argument("--batch", type=int, default=64)
    t.add_argument("--lr", type=float, default=3e-4)
    t.add_argument("--within", type=float, default=0.94, help="cosine of the widest lean kept")
    t.add_argument("--every", type=int, default=1000)
    t.add_argument("--all-frames", action="store_true",
                   help="train on every frame (Huber loss), scaled as the kept ones")
    t.add_argument("--frames", type=int, choices=(1, 2), default=1,
                   help="2: the frame before as well, and read the velocities too")
    t.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    train(args)


if __name__ == "__main__":
    main()
