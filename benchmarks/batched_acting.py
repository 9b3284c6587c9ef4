"""Evaluation episodes stepped together (``twist-eval --batch N``) against one at a time, in
one run: the agent steps per second of ``evaluate`` for N episodes of a `quick`-sized
student (random weights; on rendered 64x64 views) and of a `quick` teacher (on states), each
with batch 1 (the baseline, measured in the same run), batch N, and with ``--workers W`` also
batch N with the environments in W worker processes (``twist-eval --workers``). Batching
alone removes N - 1 of the N policy calls per step (on a GPU, their host-device round
trips); workers also simulate and render the N environments in parallel. Medians of
``--repeats`` alternating runs; each run builds its renderer(s) and one simulator per episode
slot, and starts its workers, as one ``evaluate`` call does. With ``--steady`` they are made
before the clock starts, as ``twist-eval`` makes them once for all of an agent's seeds: the
rate of a long evaluation. Prints one JSON line.

    python benchmarks/batched_acting.py [--episodes 16] [--steps 250] [--repeats 3]
        [--device cpu] [--workers W] [--steady]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from twist_models.agent import Agent
from twist_models.config import AgentConfig, student_preset, teacher_preset
from twist_models.teacher import Teacher
from twist_pipeline.acting import ImageAgent, StateAgent
from twist_pipeline.evaluation import EvalConfig, evaluate, evaluation_envs
from twist_sim.tasks import TaskEnv

TASK = "cartpole-balance"


def steps_per_second(agent: object, config: EvalConfig, batch: int, workers: int = 1,
                     steady: bool = False) -> float:
    if not steady:
        start = time.perf_counter()
        results = evaluate(agent, config, seed=0, batch=batch, workers=workers)
        return sum(r.steps for r in results) / (time.perf_counter() - start)
    with evaluation_envs(agent, config, batch, workers) as envs:
        start = time.perf_counter()
        results = evaluate(agent, config, seed=0, batch=batch, workers=workers, envs=envs)
        return sum(r.steps for r in results) / (time.perf_counter() - start)


def medians(agent: object, config: EvalConfig, batch: int, repeats: int, workers: int,
            steady: bool = False) -> dict[str, float]:
    """Median agent steps/s alone, with ``batch``, and (``workers`` > 1) with ``batch`` in
    that many worker processes, the variants measured in turn."""
    variants = {"alone": (1, 1), "batched": (batch, 1)}
    if workers > 1:
        variants["workers"] = (batch, workers)
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, (n, w) in variants.items():
            samples[name].append(steps_per_second(agent, config, n, w, steady))
    return {name: statistics.median(values) for name, values in samples.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--steps", type=int, default=250, help="agent steps per episode")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--workers", type=int, default=1,
                        help="also time the batch with its environments in this many processes")
    parser.add_argument("--steady", action="store_true",
                        help="make the environments (and start the workers) before the clock")
    args = parser.parse_args()
    torch.manual_seed(0)
    env = TaskEnv(TASK)  # for the state and action sizes
    teacher = Teacher(teacher_preset("quick", env.state_dim, env.action_dim))
    student = student_preset("quick", teacher.config, 64)
    bundle = Agent(AgentConfig(student=student, actor_critic=teacher.config.actor_critic),
                   {"task": TASK, "image_size": 64}).to(args.device).eval()
    agents = {"student": ImageAgent(bundle),
              "oracle": StateAgent(teacher, TASK, device=args.device)}
    config = EvalConfig(task=TASK, dr="heldout", episodes=args.episodes, max_steps=args.steps)
    row: dict[str, object] = {"device": args.device, "episodes": args.episodes,
                              "steps_per_episode": args.steps, "workers": args.workers,
                              "steady": args.steady}
    for name, agent in agents.items():
        rates = medians(agent, config, args.episodes, args.repeats, args.workers, args.steady)
        for variant, rate in rates.items():
            row[f"{name}_steps_per_s_{variant}"] = round(rate, 1)
        row[f"{name}_speedup"] = round(rates["batched"] / rates["alone"], 2)
        if "workers" in rates:
            row[f"{name}_speedup_workers"] = round(rates["workers"] / rates["alone"], 2)
    print(json.dumps(row))


if __name__ == "__main__":
    main()
