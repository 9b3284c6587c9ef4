"""Evaluation episodes stepped together (``twist-eval --batch N``) against one at a time, in
one run: the agent steps per second of ``evaluate`` for N episodes of a `quick`-sized
student (random weights; on rendered 64x64 views) and of a `quick` teacher (on states), each
with batch 1 (the baseline, measured in the same run) and batch N. Simulation and rendering
stay one environment at a time; what batching removes is N - 1 of the N policy calls per
step (on a GPU, their host-device round trips). Medians of ``--repeats`` alternating runs;
each run builds its renderer and, batched, one simulator per episode slot (~70 ms each), as
``twist-eval`` does. Prints one JSON line.

    python benchmarks/batched_acting.py [--episodes 16] [--steps 250] [--repeats 3] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from twist_data.tasks import TaskEnv
from twist_models.agent import Agent
from twist_models.config import AgentConfig, student_preset, teacher_preset
from twist_models.stages.evaluation import EvalConfig, ImageAgent, StateAgent, evaluate
from twist_models.teacher import Teacher

TASK = "cartpole-balance"


def steps_per_second(agent: object, config: EvalConfig, batch: int) -> float:
    start = time.perf_counter()
    results = evaluate(agent, config, seed=0, batch=batch)
    return sum(r.steps for r in results) / (time.perf_counter() - start)


def medians(agent: object, config: EvalConfig, batch: int, repeats: int) -> tuple[float, float]:
    """Median agent steps/s alone and with ``batch``, the two measured alternately."""
    alone, together = [], []
    for _ in range(repeats):
        alone.append(steps_per_second(agent, config, 1))
        together.append(steps_per_second(agent, config, batch))
    return statistics.median(alone), statistics.median(together)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--steps", type=int, default=250, help="agent steps per episode")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
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
                              "steps_per_episode": args.steps}
    for name, agent in agents.items():
        alone, together = medians(agent, config, args.episodes, args.repeats)
        row[f"{name}_steps_per_s_alone"] = round(alone, 1)
        row[f"{name}_steps_per_s_batched"] = round(together, 1)
        row[f"{name}_speedup"] = round(together / alone, 2)
    print(json.dumps(row))


if __name__ == "__main__":
    main()
