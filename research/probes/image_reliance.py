"""How much does a distilled student's posterior rely on the image?

On held-out windows of D, both filters run as in distillation but on their posteriors' means
(the class probabilities, so the figures carry no sampling noise), with the student's images
left alone (``normal``, the baseline of the same run) and then corrupted three ways: each
window given another window's images (``other_window``), the window's first image held for
every step (``first_image_held``: no motion) and black frames (``black``). For each: the
posterior KL to the teacher's, the share of the teacher's h variance the student's h
reproduces, and the correlation of the teacher's actor (mode) on the student's latent with
it on the teacher's, over all steps and over the second half of each window. A student that
reads the scene loses much of its agreement when the images are wrong; one that does not has
learned to follow its h (and through it the teacher's past actions) instead.

Prints one JSON line per condition. ``python research/probes/image_reliance.py DATASET RUN
TEACHER [--windows 64] [--length 50]`` (RUN: a ``twist-distil`` output folder).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable

import torch

from twist_data.reader import open_dataset
from twist_data.sampler import WindowSampler
from twist_models.losses import distillation_loss
from twist_models.student import Student
from twist_models.teacher import Teacher, load_teacher
from twist_pipeline.distil import load_student, stored_config

Batch = dict[str, torch.Tensor]

CORRUPTIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "normal": lambda image: image,
    "other_window": lambda image: image.roll(1, 0),
    "first_image_held": lambda image: image[:, :1].expand_as(image).contiguous(),
    "black": torch.zeros_like,
}


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack([a.flatten(), b.flatten()]))[0, 1])


@torch.no_grad()
def agreement(student: Student, teacher: Teacher, batch: Batch) -> dict[str, float]:
    wm, action, is_first = teacher.world_model, batch["action"], batch["is_first"]
    t_post, t_prior = wm.rssm.observe(wm.embed(batch["state"]), action, is_first, read="mean")
    s_post, s_prior = student.observe(batch["image"], action, is_first, read="mean")
    terms = distillation_loss(s_post, s_prior["logits"], t_post, t_prior["logits"])
    actor = teacher.actor_critic.actor
    t_action = actor(wm.rssm.feature(t_post)).mode  # [B, L, A]
    s_action = actor(student.rssm.feature(s_post)).mode
    variance = t_post["deter"].flatten(0, -2).var(0).mean()
    h_mse = ((s_post["deter"] - t_post["deter"]) ** 2).mean()
    half = t_action.shape[1] // 2
    return {"post_kl": round(float(terms["post_kl"]), 3),
            "h_explained": round(float(1 - h_mse / variance), 3),
            "action_corr": round(correlation(t_action, s_action), 3),
            "action_corr_second_half": round(correlation(t_action[:, half:],
                                                         s_action[:, half:]), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("run")
    parser.add_argument("teacher")
    parser.add_argument("--windows", type=int, default=64)
    parser.add_argument("--length", type=int, default=50,
                        help="steps per window, the same for every run compared (the paper's L)")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    torch.manual_seed(0)
    config = dataclasses.replace(stored_config(args.run), length=args.length)
    student = load_student(f"{args.run}/student.pt")[0].eval()
    teacher = load_teacher(args.teacher)[0].eval()
    sampler = WindowSampler(open_dataset(args.dataset),
                            config.sampler("heldout", args.seed, args.windows))
    batch = {k: torch.as_tensor(v) for k, v in sampler.batch().items()}
    for name, corrupt in CORRUPTIONS.items():
        print(json.dumps({"run": args.run, "condition": name,
                          **agreement(student, teacher, {**batch, "image": corrupt(batch["image"])})}))


if __name__ == "__main__":
    main()
