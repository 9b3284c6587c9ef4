"""Where does a distilled student lose the teacher's behaviour?

The teacher acts on states for ``--episodes`` episodes (``--acting student``: the student acts
on images, so the states are those it meets itself); the same physics is rendered under
``--dr`` (DR drawn once per episode, supersampled as the agent's D was) and two filters run in
its shadow on the executed actions:

* ``teacher_again``: the same teacher on the same states with its own latent samples -- the
  baseline measured in the same run: how far two runs of the teacher itself disagree, since
  its posterior is stochastic;
* ``student``: the agent bundle's student on the rendered images.

For each: the correlation of the teacher's actor (mode) on that latent with the teacher's
action (its filter on the states), the h-MSE to that teacher's h (per element, and against
the variance of the teacher's h over the episode), and the share of latent variables whose
sampled class differs. For the student also the gain: the least-squares slope of its action
on the teacher's (1: the right size; near 0: it barely acts on what the teacher reacts to),
and the swaps: the actor on (student h, teacher z) and on (teacher h, student z), which tell
which half of the latent its error comes from. ``return``: the episodes' return.
``student_h_explained_steps_A_B``: the student's h-explained over steps A..B-1 only (against
the whole episode's variance), in bins of ``--bin`` steps: whether its h drifts further the
longer it filters, e.g. past the length of the windows it was trained on.

Prints one JSON line of means over episodes. ``python research/probes/latent_probe.py TEACHER
AGENT [--dr heldout] [--episodes 4] [--acting student]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch

from twist_models.agent import Agent, AgentState
from twist_models.rssm import POSTERIOR_READS, State
from twist_models.teacher import Teacher, load_teacher
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TaskEnv


def correlation(a: list[float], b: list[float]) -> float:
    return float(np.corrcoef(a, b)[0, 1])


def differing_classes(a: State, b: State) -> float:
    return float((a["stoch"].argmax(-1) != b["stoch"].argmax(-1)).float().mean())


def episode(env: TaskEnv, renderer: DRRenderer, seed: int, teacher: Teacher, agent: Agent,
            student_acts: bool = False, bin_steps: int = 50,
            posterior: str = "sample") -> dict[str, float]:
    sampler = renderer.sampler(seed)
    step = env.reset(seed=seed, dynamics=sampler.begin_episode(seed))
    acting = again = None
    student: AgentState | None = None
    previous = torch.zeros(1, teacher.config.world_model.action_dim)
    rows: dict[str, list] = {k: [] for k in (
        "action", "again_action", "student_action", "student_h_teacher_z",
        "teacher_h_student_z", "h", "again_h", "student_h", "again_z", "student_z")}
    actor = teacher.act_on_latent
    total = 0.0
    while not step.is_last:
        state = torch.as_tensor(step.state, dtype=torch.float32)[None]
        first = torch.tensor([step.is_first])
        with torch.no_grad():
            action, acting = teacher.policy(state, acting, previous, first, explore=False)
            _, again = teacher.policy(state, again, previous, first, explore=False)
        image = renderer.render(step.physics, sampler.sample())[0]
        student_action, student = agent.act(image, student, posterior=posterior)
        mine = student.latent
        with torch.no_grad():
            rows["again_action"].append(float(actor(again)[0, 0]))
            rows["student_action"].append(float(actor(mine)[0, 0]))
            rows["student_h_teacher_z"].append(
                float(actor({"deter": mine["deter"], "stoch": acting["stoch"]})[0, 0]))
            rows["teacher_h_student_z"].append(
                float(actor({"deter": acting["deter"], "stoch": mine["stoch"]})[0, 0]))
        rows["action"].append(float(action[0, 0]))
        for key, latent in (("h", acting), ("again_h", again), ("student_h", mine)):
            rows[key].append(latent["deter"][0].numpy())
        rows["again_z"].append(differing_classes(acting, again))
        rows["student_z"].append(differing_classes(acting, mine))
        if student_acts:
            action = torch.as_tensor(student_action, dtype=torch.float32).reshape(1, -1)
        # Every filter continues from the action that was executed.
        student = dataclasses.replace(student, action=action)
        previous = action
        step = env.step(action[0].numpy())
        total += step.reward
    h = np.array(rows["h"])
    variance = float(h.var(0).mean())
    teacher_actions, student_actions = np.array(rows["action"]), np.array(rows["student_action"])
    result = {"return": total, "h_variance": variance,
              "student_action_gain": float(teacher_actions @ student_actions
                                           / (teacher_actions @ teacher_actions))}
    for name in ("again", "student"):
        mse = float(((np.array(rows[f"{name}_h"]) - h) ** 2).mean())
        result.update({f"{name}_action_corr": correlation(rows["action"], rows[f"{name}_action"]),
                       f"{name}_h_mse": mse, f"{name}_h_explained": 1 - mse / variance,
                       f"{name}_z_differs": float(np.mean(rows[f"{name}_z"]))})
    for swap in ("student_h_teacher_z", "teacher_h_student_z"):
        result[f"{swap}_action_corr"] = correlation(rows["action"], rows[swap])
    squared = ((np.array(rows["student_h"]) - h) ** 2).mean(1)
    for start in range(0, len(squared), bin_steps):
        stop = min(start + bin_steps, len(squared))
        result[f"student_h_explained_steps_{start}_{stop}"] = (
            1 - float(squared[start:stop].mean()) / variance)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("teacher")
    parser.add_argument("agent")
    parser.add_argument("--dr", default="heldout")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=200)
    parser.add_argument("--acting", choices=("teacher", "student"), default="teacher")
    parser.add_argument("--bin", type=int, default=50, help="steps per bin of the h profile")
    parser.add_argument("--posterior", choices=POSTERIOR_READS, default="sample",
                        help="how the student reads its posterior when acting")
    args = parser.parse_args()
    torch.manual_seed(0)
    teacher = load_teacher(args.teacher)[0].eval()
    agent = Agent.load(args.agent)
    task = agent.info["task"]
    env = TaskEnv(task, action_repeat=agent.info["action_repeat"], seed=args.seed)
    dr = dataclasses.replace(dr_preset(args.dr), resample="episode")
    supersample = agent.info.get("supersample") or 1
    with DRRenderer(task, dr, agent.info["image_size"], views=1,
                    supersample=supersample) as renderer:
        runs = [episode(env, renderer, args.seed + i, teacher, agent, args.acting == "student",
                        args.bin, args.posterior)
                for i in range(args.episodes)]
    means = {k: round(float(np.mean([r[k] for r in runs])), 4) for k in runs[0]}
    print(json.dumps({"task": task, "dr": args.dr, "acting": args.acting,
                      "posterior": args.posterior,
                      "episodes": args.episodes, **means}))


if __name__ == "__main__":
    main()
