"""Does a filter recover from a wrong belief? The teacher's (on states) and a student's (on
images) filters, started from a perturbed latent, on D's held-out episodes.

For ``--starts`` random steps t0 of held-out episodes (every ``holdout_every``-th), each
filter runs ``--horizon`` steps on D's recorded states / images (view 0) and actions from a
start latent built from the teacher's own filter at t0 - 1 (its h and z, filtered from the
episode's start):

* ``exact``: the teacher's latent unchanged (does the filter stay on the teacher's path?);
* ``other``: the teacher's latent from another held-out step (a wrong belief of the kind the
  filter meets when it drifts);
* ``zero``: h = 0, z = 0 (how the paper's windows start mid-episode).

Reported per filter, start and step k: the share of the teacher's h variance its h error
leaves (``h_unexplained`` = MSE / variance; 0 is the teacher's path, 1 as far off as a
random step) and the RMS difference of the teacher's actor on both latents
(``action_rmse``). ``teacher`` is the teacher itself with other sampling draws: the baseline
measured in the same run.

``python research/probes/h_recovery.py DATASET AGENT [--teacher T] [--starts 64] [--horizon 100]``
prints one JSON line.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.rssm import State
from twist_models.teacher import find_teacher, load_teacher

STEPS_REPORTED = (0, 1, 2, 5, 10, 20, 50, 99)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("agent")
    parser.add_argument("--teacher", default=None)
    parser.add_argument("--starts", type=int, default=64)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--read", default="sample", choices=("sample", "mode", "mean"))
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    data = open_dataset(args.dataset)
    teacher = load_teacher(args.teacher or find_teacher(args.dataset))[0].eval()
    agent = Agent.load(args.agent)
    wm, actor = teacher.world_model, teacher.actor_critic.actor
    episodes = np.flatnonzero(heldout_episodes(data.n_episodes, args.holdout_every))
    k = args.horizon
    lengths = data.episode_lengths[episodes]
    episodes = episodes[lengths > k + 1]
    chosen = rng.choice(episodes, args.starts)
    starts = data.episode_starts[chosen]
    offsets = rng.integers(1, data.episode_lengths[chosen] - k)
    states, actions = data.column("state"), data.column("action")

    with torch.no_grad():
        # The teacher's filter from each chosen episode's start to t0 + k.
        span = int(offsets.max()) + k
        index = np.minimum(starts[:, None] + np.arange(span),
                           (starts + data.episode_lengths[chosen] - 1)[:, None])
        is_first = torch.zeros(args.starts, span, dtype=torch.bool)
        is_first[:, 0] = True
        action = torch.as_tensor(actions[index])
        post, _ = wm.rssm.observe(wm.embed(torch.as_tensor(states[index])), action, is_first,
                                  read=args.read)
        rows = np.arange(args.starts)
        before = {key: v[rows, offsets - 1] for key, v in post.items()}
        path = {key: torch.stack([v[i, o:o + k] for i, o in enumerate(offsets)])
                for key, v in post.items()}
        variance = float(path["deter"].flatten(0, 1).var(0).mean())
        window = starts[:, None] + offsets[:, None] + np.arange(k)
        window_action = torch.as_tensor(actions[window])
        window_state = torch.as_tensor(states[window])
        images = np.empty((args.starts * k, *data.spec.image_shape), np.uint8)
        data.read_frames(window.reshape(-1), np.zeros(window.size, np.int64), images)
        images = torch.from_numpy(images).reshape(args.starts, k, *images.shape[1:])
        no_first = torch.zeros(args.starts, k, dtype=torch.bool)
        target_action = actor(wm.rssm.feature(path)).mode

        shuffled = rng.permutation(args.starts)
        starts_by_kind: dict[str, State] = {
            "exact": before,
            "other": {key: v[shuffled] for key, v in before.items()},
            "zero": {key: torch.zeros_like(v) for key, v in before.items()},
        }
        filters = {
            "teacher": lambda start: wm.rssm.observe(wm.embed(window_state), window_action,
                                                     no_first, state=start, read=args.read)[0],
            "student": lambda start: agent.student.rssm.observe(
                agent.student.embed(images, no_first), window_action, no_first, state=start,
                read=args.read)[0],
        }
        result: dict[str, object] = {"dataset": args.dataset, "agent": args.agent,
                                     "starts": args.starts, "horizon": k, "read": args.read,
                                     "h_variance": round(variance, 5)}
        for name, run in filters.items():
            for kind, start in starts_by_kind.items():
                latent = run(start)
                error = ((latent["deter"] - path["deter"]) ** 2).mean((0, 2)) / variance
                acted = actor(agent.student.rssm.feature(latent)).mode
                rmse = ((acted - target_action) ** 2).mean((0, 2)).sqrt()
                result[f"{name}_{kind}_h_unexplained"] = {
                    s: round(float(error[s]), 3) for s in STEPS_REPORTED if s < k}
                result[f"{name}_{kind}_action_rmse"] = {
                    s: round(float(rmse[s]), 3) for s in STEPS_REPORTED if s < k}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
