"""Where a teacher update's time goes: the collector's update (``Dreamer.train_step``, eager,
float32, the ``--preset`` collection's batch, imagination starts and overshooting) split into
the world model's loss forward (overshooting included), its backward, its clipped Adam step,
and the behaviour update (actor and critic from imagination), the imagined rollout's forward
alone beside it. The whole update, timed in the same run on a copy of the same weights, is the
baseline the parts must add up to (``parts_over_whole``). With ``--run RUN`` it also splits a
collection's wall time by its own counters (``RUN/metrics.csv``: physics, rendering, the
acting policy, writes, learning, evaluation, checkpoints). Rounds alternate whole and parts;
medians. Prints one JSON line.

    python benchmarks/teacher_profile.py [--preset quick] [--task walker-walk] [--rounds 9]
        [--run runs/w0/dataset/collect/collect-000]
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

import torch
from torch import nn

from twist_models.teacher import Teacher
from twist_pipeline.collect import COLLECT_PRESETS, collect_preset
from twist_sim.tasks import TaskEnv

PARTS = ("model_forward", "model_backward", "model_step", "behaviour")
COUNTERS = ("physics", "render", "policy", "write", "learn", "eval", "checkpoint")


def windows(batch: int, length: int, state_dim: int, action_dim: int) -> dict[str, torch.Tensor]:
    """Random windows of the collector's shape (the timings do not depend on values)."""
    g = torch.Generator().manual_seed(0)
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[:, 0] = True
    return {"state": torch.randn(batch, length, state_dim, generator=g),
            "action": torch.rand(batch, length, action_dim, generator=g) * 2 - 1,
            "reward": torch.rand(batch, length, generator=g), "is_first": is_first}


def parts(teacher: Teacher, batch: dict[str, torch.Tensor]) -> dict[str, float]:
    """Seconds of each part of one ``train_step``, done as it does them."""
    out, tick = {}, time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        out[name], tick = now - tick, now

    loss, post, _ = teacher.world_model.loss(batch)
    lap("model_forward")
    teacher.model_opt.zero_grad(set_to_none=True)
    loss.backward()
    lap("model_backward")
    nn.utils.clip_grad_norm_(teacher.world_model.parameters(), teacher.config.optim.grad_clip)
    teacher.model_opt.step()
    lap("model_step")
    start = {k: v.detach().flatten(0, 1).clone() for k, v in post.items()}
    teacher.actor_critic.train_step(teacher.world_model, start)
    lap("behaviour")
    return out


def imagination(teacher: Teacher, batch: dict[str, torch.Tensor]) -> float:
    """Seconds of the imagined rollout's forward, with its graph, from the update's starts."""
    with torch.no_grad():
        _, post, _ = teacher.world_model.loss(batch)
    ac = teacher.actor_critic
    start = {k: v.flatten(0, 1) for k, v in post.items()}
    n = start["deter"].shape[0]
    if 0 < ac.config.imag_starts < n:
        start = {k: v[: ac.config.imag_starts] for k, v in start.items()}
    tick = time.perf_counter()
    ac._imagine_fn(teacher.world_model.rssm, start, True)
    return time.perf_counter() - tick


def collection_split(run: Path) -> dict[str, float]:
    """A collection's seconds by counter, as shares of its wall time (its last metrics row)."""
    with open(run / "metrics.csv") as f:
        last = list(csv.DictReader(f))[-1]
    wall = float(last["wall_s"])
    return {"frames": int(last["frames"]), "wall_s": wall,
            **{f"{c}_share": round(float(last[f"seconds_{c}"]) / wall, 4) for c in COUNTERS}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick", choices=sorted(COLLECT_PRESETS))
    parser.add_argument("--task", default="cartpole-balance")
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--run", type=Path, help="a collection's folder (its metrics.csv)")
    args = parser.parse_args()
    collect = collect_preset(args.preset, task=args.task)
    env = TaskEnv(args.task, collect.action_repeat)
    config = collect.teacher_config(env.state_dim, env.action_dim)
    config = dataclasses.replace(config, actor_critic=dataclasses.replace(
        config.actor_critic, precision="float32"))
    batch = windows(collect.batch_size, collect.batch_length, env.state_dim, env.action_dim)
    torch.manual_seed(0)
    whole = Teacher(config)
    split = copy.deepcopy(whole)
    for teacher in (whole, split):
        teacher.train_step(batch)  # first-call allocations out of the timings
    samples: dict[str, list[float]] = {"whole": [], "imagination": [], **{p: [] for p in PARTS}}
    for _ in range(args.rounds):
        tick = time.perf_counter()
        whole.train_step(batch)
        samples["whole"].append(time.perf_counter() - tick)
        for name, seconds in parts(split, batch).items():
            samples[name].append(seconds)
        samples["imagination"].append(imagination(split, batch))
    medians = {k: statistics.median(v) for k, v in samples.items()}
    total = sum(medians[p] for p in PARTS)
    result = {"benchmark": "teacher_profile", "preset": args.preset, "task": args.task,
              "state_dim": env.state_dim, "batch": collect.batch_size,
              "length": collect.batch_length, "imag_starts": config.actor_critic.imag_starts,
              "overshoot": config.world_model.overshoot, "threads": torch.get_num_threads(),
              "cpus": os.cpu_count(), "whole_s": round(medians["whole"], 4),
              **{f"{p}_s": round(medians[p], 4) for p in PARTS},
              **{f"{p}_share": round(medians[p] / total, 3) for p in PARTS},
              "imagination_forward_s": round(medians["imagination"], 4),
              "parts_over_whole": round(total / medians["whole"], 3)}
    if args.run is not None:
        result["collection"] = collection_split(args.run)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
