"""How well can a CNN read the privileged state from D's randomised images?

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

``--near I:LOW:HIGH`` trains on every kept frame but also scores a second held-out set, the
frames with state component I in [LOW, HIGH]. ``1:0.985:1`` selects cartpole's pole within
10° of upright (cosine at least 0.985), where the teacher's actor needs the sine to ~0.035.
For that set the probe reports the RMSE in the state's units beside ``near_std``, the RMSE
of predicting the set's own mean.
``--teacher CKPT`` weights what the probe learns and scores by what the teacher's actor
needs: each step's component i counts in proportion to the actor's squared sensitivity to it
there (:func:`twist_models.frame_targets.actor_sensitivity`, at the teacher's own h), not to
D's whole-range spread, under which a near-upright pole's errors barely weigh. The probe
then also reports ``action_rmse``: the first-order error of the teacher's action that each
encoder's read-out errors would cause on the held-out frames, sqrt(mean_t sum_i w_ti e_ti^2),
beside ``action_rmse_of_mean`` (predicting the training frames' mean state).
``--every N`` prints a line every N updates of the supervised CNN (its learning curve);
``--supervised-only`` skips the other encoders; ``--norm layer`` probes the layer-normalised
CNN (``--set encoder_norm=layer`` in ``twist-distil``).

Prints JSON lines. ``python research/probes/image_state_probe.py DATASET [--agent AGENT]
[--steps 300] [--preset quick] [--within I:LOW:HIGH] [--near I:LOW:HIGH] [--every N]
[--supervised-only] [--norm layer]``
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
from twist_models.config import CNN_NORMS, PRESETS, CNNConfig
from twist_models.frame_targets import teacher_targets
from twist_models.networks import ImageEncoder
from twist_models.teacher import load_teacher

#: Held-out images [n, H, W, 3] and their normalised states [n, S].
TestSet = tuple[torch.Tensor, torch.Tensor]


def held_out_scores(encoder: nn.Module, head: nn.Module, tests: dict[str, TestSet],
                    scale: torch.Tensor, sensitivity: dict[str, torch.Tensor] | None = None
                    ) -> dict[str, list[float] | float]:
    """R² per component on each test set, for ``near`` the RMSE in the state's units, and with
    ``sensitivity`` (raw, per test set [n, S]) the first-order action RMSE."""
    scores: dict[str, list[float] | float] = {}
    with torch.no_grad():
        for name, (images, truth) in tests.items():
            squared = (head(encoder(images)) - truth) ** 2
            error = squared.mean(0)
            scores[f"{name}_r2" if name != "all" else "r2"] = [
                round(float(v), 3) for v in 1.0 - error / truth.var(0)]
            if name == "near":
                scores["near_rmse"] = [round(float(v), 3) for v in error.sqrt() * scale]
            if sensitivity is not None:
                action = (sensitivity[name] * squared * scale**2).sum(1).mean().sqrt()
                scores[f"{name}_action_rmse"] = round(float(action), 4)
    return scores


def probe(encoder: nn.Module, train_encoder: bool, data: MatchingDataset, target: torch.Tensor,
          train: np.ndarray, tests: dict[str, TestSet], scale: torch.Tensor,
          args: argparse.Namespace, name: str, weight: torch.Tensor | None = None,
          sensitivity: dict[str, torch.Tensor] | None = None) -> dict:
    """Train a linear head (and the encoder when ``train_encoder``) -> held-out scores; with
    ``--every`` the supervised CNN also prints its scores along the way."""
    rng = np.random.default_rng(args.seed)
    head = nn.Linear(encoder.out_dim, target.shape[1])
    encoder.requires_grad_(train_encoder)
    params = [*head.parameters(), *(encoder.parameters() if train_encoder else [])]
    optimiser = torch.optim.Adam(params, lr=args.lr)
    for update in range(1, args.steps + 1):
        steps = rng.choice(train, args.batch)
        images = torch.as_tensor(data.frames_of_random_views(steps, rng))
        squared = (head(encoder(images)) - target[steps]) ** 2
        loss = (squared * weight[steps]).sum(1).mean() if weight is not None else squared.mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if train_encoder and args.every and update % args.every == 0 and update < args.steps:
            print(json.dumps({"encoder": name, "updates": update,
                              **held_out_scores(encoder, head, tests, scale, sensitivity)}),
                  flush=True)
    return held_out_scores(encoder, head, tests, scale, sensitivity)


def actor_weights(teacher_path: str, data: MatchingDataset, scale: torch.Tensor,
                  tests: dict[str, np.ndarray], train: np.ndarray) -> dict:
    """The teacher actor's sensitivity at every step of D: ``weight`` [N, S] for training (in
    standardised units, mean 1 over the training steps) and ``sensitivity`` {test set: raw
    [n, S]} for scoring."""
    teacher, _ = load_teacher(teacher_path, data.spec.state_dim, data.spec.action_dim)
    targets = teacher_targets(teacher.eval(), data, np.arange(data.n_episodes), read="mean")
    raw = torch.empty(data.n_steps, data.spec.state_dim)
    raw[torch.as_tensor(targets.steps)] = targets.sensitivity * targets.scale
    weight = raw * scale**2
    weight = weight / weight[torch.as_tensor(train)].mean()
    return {"weight": weight,
            "sensitivity": {name: raw[torch.as_tensor(steps)] for name, steps in tests.items()}}


def component_range(spec: str, states: np.ndarray) -> np.ndarray:
    """Mask of the steps whose state component I lies in [LOW, HIGH], from ``I:LOW:HIGH``."""
    index, low, high = spec.split(":")
    component = states[:, int(index)]
    return (component >= float(low)) & (component <= float(high))


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
    parser.add_argument("--near", help="I:LOW:HIGH, a second held-out set scored in state units")
    parser.add_argument("--every", type=int, default=0, help="learning-curve line every N updates")
    parser.add_argument("--supervised-only", action="store_true")
    parser.add_argument("--norm", choices=CNN_NORMS, default="none")
    parser.add_argument("--teacher", help="weight components by this teacher actor's sensitivity")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    data = open_dataset(args.dataset)
    states = data.column("state").astype(np.float32)
    mean, scale = states.mean(0), states.std(0).clip(1e-3)
    target = torch.as_tensor((states - mean) / scale)
    held = np.repeat(heldout_episodes(data.n_episodes, args.holdout_every), data.episode_lengths)
    kept = component_range(args.within, states) if args.within else np.ones(held.size, bool)
    train, heldout = np.flatnonzero(~held & kept), np.flatnonzero(held & kept)
    rng = np.random.default_rng(args.seed + 1)
    subsets = {"all": heldout}
    if args.near:
        subsets["near"] = np.flatnonzero(held & kept & component_range(args.near, states))
    tests: dict[str, TestSet] = {}
    tests_steps: dict[str, np.ndarray] = {}
    for name, steps in subsets.items():
        if steps.size < 2:
            raise SystemExit(f"only {steps.size} held-out frames in the {name!r} set")
        chosen = np.sort(rng.choice(steps, min(args.test_frames, steps.size), replace=False))
        tests[name] = (torch.as_tensor(data.frames_of_random_views(chosen, rng)), target[chosen])
        tests_steps[name] = chosen
    cnn = dataclasses.replace(PRESETS[args.preset].get("cnn", CNNConfig()),
                              image_size=data.spec.image_height, norm=args.norm)
    result: dict = {"dataset": args.dataset, "preset": args.preset, "norm": args.norm,
                    "within": args.within, "near": args.near, "steps": args.steps,
                    "batch": args.batch, "train_frames": int(train.size),
                    "heldout_frames": int(tests["all"][0].shape[0])}
    torch_scale = torch.as_tensor(scale)
    if "near" in tests:
        result["near_frames"] = int(tests["near"][0].shape[0])
        spread = tests["near"][1].std(0, unbiased=False) * torch_scale
        result["near_std"] = [round(float(v), 3) for v in spread]
    weights: dict = {}
    if args.teacher:
        weights = actor_weights(args.teacher, data, torch_scale, tests_steps, train)
        mean_error = {name: (target[steps] - target[train].mean(0)) ** 2
                      for name, steps in tests_steps.items()}
        result["action_rmse_of_mean"] = {
            name: round(float((weights["sensitivity"][name] * e * torch_scale**2).sum(1).mean()
                              .sqrt()), 4) for name, e in mean_error.items()}
    if not args.supervised_only:
        result["random_cnn"] = probe(ImageEncoder(cnn), False, data, target, train, tests,
                                     torch_scale, args, "random_cnn", **weights)
    result["supervised_cnn"] = probe(ImageEncoder(cnn), True, data, target, train, tests,
                                     torch_scale, args, "supervised_cnn", **weights)
    if args.agent and not args.supervised_only:
        encoder = Agent.load(args.agent).student.perception.encoder
        result["student"] = probe(encoder, False, data, target, train, tests, torch_scale,
                                  args, "student", **weights)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
