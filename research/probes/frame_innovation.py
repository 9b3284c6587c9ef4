"""Does a student's posterior add to its h what the image shows, as the teacher's posterior adds
what the state shows?

A filter corrects a wrong belief only through what its posterior takes from the observation
beyond the prior's prediction (the innovation). On every step of D's held-out episodes
(every ``holdout_every``-th, one random view per step), with the teacher's h filtered from the
episode's start on the exact states, the teacher's actor is read (action mode, z as the class
probabilities) on:

* the teacher's posterior q_T(z | h, s): the target ``a_T``;
* the prior p(z | h) alone (the teacher's, which the student's copies): ``a_P``, what h says
  without looking;
* the student's posterior q_S(z | h, image): ``a_S``.

``innovation_r2`` = 1 - mean (a_S - a_T)^2 / mean (a_P - a_T)^2: the share of the prior's
action error the image removes (1: all, as the state does; 0: the posterior adds nothing to
h; negative: it adds error). ``corr`` is the plain correlation of a_S with a_T, which h alone
inflates (``prior_corr``). Both at the teacher's own h (``own``) and at the teacher's h of
another held-out step (``other``, the state and image unchanged: a drifted belief), on all
steps and on those within ``--upright`` degrees of upright (cartpole's pole: state component
1 and 2 are its angle's cosine and sine).

``python research/probes/frame_innovation.py DATASET STUDENT.pt [...] [--teacher T]`` (student
checkpoints or agent bundles) prints one JSON line per student.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from torch.nn import functional as F

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.agent import Agent
from twist_models.frame_targets import teacher_targets
from twist_models.student import Student
from twist_models.teacher import find_teacher, load_teacher
from twist_pipeline.distil import load_student


def load_any_student(path: str) -> Student:
    try:
        return load_student(path)[0].eval()
    except Exception:  # an agent bundle, not a student checkpoint
        return Agent.load(path).student.eval()


def scores(a_t: torch.Tensor, a_p: torch.Tensor, a_s: torch.Tensor) -> dict[str, float]:
    def corr(x: torch.Tensor, y: torch.Tensor) -> float:
        return float(torch.corrcoef(torch.stack([x.flatten(), y.flatten()]))[0, 1])

    prior_error = float(((a_p - a_t) ** 2).mean())
    student_error = float(((a_s - a_t) ** 2).mean())
    return {"innovation_r2": round(1 - student_error / max(prior_error, 1e-12), 3),
            "corr": round(corr(a_s, a_t), 3), "prior_corr": round(corr(a_p, a_t), 3),
            "student_rmse": round(student_error**0.5, 4),
            "prior_rmse": round(prior_error**0.5, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("students", nargs="+")
    parser.add_argument("--teacher", default=None)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--upright", type=float, default=10.0)
    parser.add_argument("--max-steps", type=int, default=8192)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    data = open_dataset(args.dataset)
    teacher = load_teacher(args.teacher or find_teacher(args.dataset))[0].eval()
    wm, actor = teacher.world_model, teacher.actor_critic.actor
    episodes = np.flatnonzero(heldout_episodes(data.n_episodes, args.holdout_every))
    targets = teacher_targets(teacher, data, episodes, seed=args.seed)
    rows = np.sort(rng.choice(len(targets), min(args.max_steps, len(targets)), replace=False))
    steps = targets.steps[rows]
    images = np.empty((rows.size, *data.spec.image_shape), np.uint8)
    data.read_frames(steps, rng.integers(0, data.spec.views, rows.size), images)
    index = torch.as_tensor(rows)
    state, own_h = targets.state[index], targets.deter[index]
    other_h = own_h[torch.as_tensor(rng.permutation(rows.size))]
    upright = state[:, 1] >= np.cos(np.deg2rad(args.upright))

    def act(h: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        return actor(torch.cat([h, F.softmax(logits, -1).flatten(-2)], -1)).mode

    with torch.no_grad():
        for path in args.students:
            student = load_any_student(path)
            if student.config.frames != 1:
                raise SystemExit(f"{path}: only single-frame students are probed")
            embed = torch.cat([student.perception.encoder(torch.as_tensor(images[i:i + 512])[:, None])[:, 0]
                               for i in range(0, rows.size, 512)])
            result: dict[str, object] = {"student": path, "steps": int(rows.size),
                                         "upright_steps": int(upright.sum())}
            for name, h in (("own", own_h), ("other", other_h)):
                a_t = act(h, wm.rssm.posterior_logits(h, wm.embed(state)))
                a_p = act(h, wm.rssm.prior_logits(h))
                a_s = act(h, student.rssm.posterior_logits(h, embed))
                result[name] = scores(a_t, a_p, a_s)
                result[f"{name}_upright"] = scores(a_t[upright], a_p[upright], a_s[upright])
            if student.state_head is not None:
                read = student.read_state(embed)
                near = upright.numpy()
                sine, guess = state[near, 2], read[near, 2]
                result["upright_sine_rmse"] = round(float(((guess - sine) ** 2).mean().sqrt()), 4)
                result["upright_sine_std"] = round(float(sine.std()), 4)
            print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
