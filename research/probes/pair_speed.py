"""Which frames show a tracked body's speed: one frame, two frames of D, or a pair of one scene?

A tracking camera (cheetah's, walker's, hopper's) follows the body, so no single frame shows its
forward speed, and D redraws its scene at every step, so two consecutive frames of D differ by
the whole scene as well as by the motion. :func:`twist_sim.rerender.reproduce_pairs` draws the
step before in this step's scene, so that the two differ by the motion alone. This trains the
same small CNN (two frames stacked as six channels, as the read-out's motion CNN reads them; a
linear head on its features) to read one state component from each kind of input, on the same
steps of D's first episodes, and scores it on its last ones (R^2; 0 is predicting the mean):

* ``frame``: the step's frame alone;
* ``consecutive``: D's frames of the step before and of the step, each in its own scene;
* ``pair``: the step before drawn in this step's scene from where the camera stood then (what
  acting sees: one scene per episode, a tracking camera that moved), and the step;
* ``framed``: the step before drawn in this step's scene from where the camera stands now (a
  camera that did not follow: not what acting sees, the upper bound of what motion shows).

``python research/probes/pair_speed.py D [--component 8] [--steps 6000] [--updates 1500]
[--seed 0]`` (component 8 of cheetah-run's state is the root's forward speed); prints one
JSON line.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from torch import nn

from twist_data.reader import open_dataset
from twist_models.config import CNNConfig
from twist_models.networks import ImageEncoder
from twist_sim.randomisation import VIEW_PARAMS
from twist_sim.rerender import render_blocks, renderer_for_block, reproduce_pairs


def inputs(path: str, steps: int, seed: int) -> dict[str, np.ndarray]:
    """View 0 of ``steps`` random non-first steps of D: the frame, the frame before, the pair's
    first frame, the state and whether the step is held out (D's last fifth of episodes)."""
    dataset = open_dataset(path)
    first = dataset.column("is_first").astype(bool)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(np.flatnonzero(~first), steps, replace=False))
    frames = np.empty((2 * steps, *dataset.spec.image_shape), np.uint8)
    dataset.read_frames(np.concatenate([chosen, chosen - 1]), np.zeros(2 * steps, np.int64),
                        frames)
    episode = np.searchsorted(dataset.episode_starts, chosen, side="right") - 1
    return {"frame": frames[:steps], "before": frames[steps:],
            "pair": reproduce_pairs(dataset, chosen)[:, 0], "framed": framed(dataset, chosen),
            "state": dataset.column("state")[chosen],
            "heldout": episode >= int(0.8 * dataset.n_episodes)}


def framed(dataset, steps: np.ndarray) -> np.ndarray:
    """View 0 of the step before each of ``steps`` (none is an episode's first) drawn under the
    step's draw and camera framing."""
    physics = dataset.column("physics")
    params = {p.name: dataset.column(f"dr/{p.name}")[steps, :1] for p in VIEW_PARAMS}
    block = render_blocks(dataset.spec)[0]
    out = np.empty((steps.size, 1, *dataset.spec.image_shape), np.uint8)
    with renderer_for_block(dataset.spec.task, {**block, "views": [0, 1]}) as renderer:
        for i, step in enumerate(steps.tolist()):
            renderer.render_states([physics[step - 1]], [{k: v[i] for k, v in params.items()}],
                                   out=out[i:i + 1], framed_by=[physics[step]])
    return out[:, 0]


class Reader(nn.Module):
    """A small CNN on the frames stacked along their channels, a linear head on its features."""

    def __init__(self, frames: int) -> None:
        super().__init__()
        self.cnn = ImageEncoder(CNNConfig(depth=16, norm="layer"), channels=3 * frames)
        self.head = nn.Linear(self.cnn.out_dim, 1)

    def forward(self, *frames: torch.Tensor) -> torch.Tensor:
        return self.head(self.cnn(torch.cat([f.float() / 255 - 0.5 for f in frames],
                                            -1))).squeeze(-1)


def score(frames: list[np.ndarray], target: np.ndarray, heldout: np.ndarray, updates: int,
          seed: int) -> float:
    """Held-out R^2 of a :class:`Reader` trained on the other steps."""
    torch.manual_seed(seed)
    model = Reader(len(frames))
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-4)
    train = np.flatnonzero(~heldout)
    mean, std = target[train].mean(), target[train].std()
    y = torch.as_tensor((target - mean) / std, dtype=torch.float32)
    x = [torch.as_tensor(f) for f in frames]
    rng = np.random.default_rng(seed)
    for _ in range(updates):
        batch = torch.as_tensor(rng.choice(train, 64))
        loss = (model(*(f[batch] for f in x)) - y[batch]).pow(2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    test = torch.as_tensor(np.flatnonzero(heldout))
    with torch.no_grad():
        error = (model(*(f[test] for f in x)) - y[test]).pow(2).mean()
    return float(1 - error / y[test].var(unbiased=False))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--component", type=int, default=8)
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--updates", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    data = inputs(args.dataset, args.steps, args.seed)
    target = data["state"][:, args.component].astype(np.float64)
    kinds = {"frame": [data["frame"]], "consecutive": [data["before"], data["frame"]],
             "pair": [data["pair"], data["frame"]], "framed": [data["framed"], data["frame"]]}
    result = {"dataset": args.dataset, "component": args.component, "steps": args.steps,
              "heldout_steps": int(data["heldout"].sum()), "updates": args.updates,
              "seed": args.seed}
    for name, frames in kinds.items():
        result[f"r2_{name}"] = round(score(frames, target, data["heldout"], args.updates,
                                           args.seed), 3)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
