"""Collection overhead: agent steps/s of everything the collector does except the teacher's
gradient updates (target: >= 250 agent steps/s with K=2 views at 64x64).

Each slice records ``--episodes`` episodes of ``--task`` into a fresh shard: physics with
action repeat 2, the acting policy, K randomised renders per step, DR draws and the zarr
writes with their commits. Measured in the same run, per slice:

* ``teacher``: the collector's loop with a ``--preset`` teacher acting (latent filter +
  actor per step), rendering in a child process, as during collection;
* ``teacher_inline``: the same loop rendering in-process (the loop before the render
  process; the same pixels);
* ``random``: the collector's loop with uniform random actions (the prefill);
* ``physics``: physics and random actions alone, the floor no collector can beat.

Medians over ``--repeats`` slices; prints one JSON line.

    python benchmarks/collect_overhead.py [--task cartpole-balance] [--episodes 2]
        [--repeats 3] [--preset quick]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from twist_data.writer import ShardWriter
from twist_models.networks import single_threaded
from twist_models.teacher import Teacher
from twist_pipeline.acting import StateAgent
from twist_pipeline.collect import collect_preset
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.render_process import RenderProcess
from twist_sim.rollout import random_policy, record_episode, simulated_spec
from twist_sim.tasks import TaskEnv

TARGET = 250.0


def collection_slice(task: str, episodes: int, policy_name: str, preset: str,
                     folder: Path, render_process: bool = True) -> tuple[float, dict[str, float]]:
    env = TaskEnv(task, action_repeat=2, seed=0)
    timings: dict[str, float] = {}
    make_renderer = RenderProcess if render_process else DRRenderer
    with make_renderer(task, dr_preset("train"), 64, 2) as renderer:
        sampler = renderer.sampler(0)
        shutil.rmtree(folder, ignore_errors=True)
        # One policy for all episodes: the teacher's latent resets itself at is_first.
        if policy_name == "teacher":
            config = collect_preset(preset).teacher_config(env.state_dim, env.action_dim)
            policy = StateAgent(Teacher(config), None, explore=True)
        else:
            policy = random_policy(env.action_dim, 0)
        with ShardWriter.create(folder, "bench", simulated_spec(env, renderer)) as writer:
            steps, start = 0, time.perf_counter()  # the child's start-up is not timed
            for i in range(episodes):
                with single_threaded():  # as the collector acts
                    episode, info = record_episode(env, renderer, sampler, policy, seed=i,
                                                   timings=timings)
                tick = time.perf_counter()
                writer.append(episode, info)
                timings["write"] = timings.get("write", 0.0) + time.perf_counter() - tick
                steps += len(episode) - 1
            elapsed = time.perf_counter() - start
    return steps / elapsed, {k: round(v / elapsed, 3) for k, v in timings.items()}


def physics_slice(task: str, episodes: int) -> float:
    env = TaskEnv(task, action_repeat=2, seed=0)
    rng = np.random.default_rng(0)
    steps, start = 0, time.perf_counter()
    for i in range(episodes):
        step = env.reset(seed=i)
        while not step.is_last:
            step = env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
            steps += 1
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cartpole-balance")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--preset", default="quick")
    args = parser.parse_args()
    rates: dict[str, list[float]] = {"teacher": [], "teacher_inline": [], "random": [],
                                     "physics": []}
    shares: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            for name in ("teacher", "teacher_inline", "random"):
                rate, shares_now = collection_slice(args.task, args.episodes,
                                                    name.removesuffix("_inline"), args.preset,
                                                    Path(tmp) / name,
                                                    render_process=not name.endswith("_inline"))
                rates[name].append(rate)
                if name == "teacher":
                    shares = shares_now
            rates["physics"].append(physics_slice(args.task, args.episodes))
    medians = {f"{k}_steps_per_s": round(statistics.median(v), 1) for k, v in rates.items()}
    print(json.dumps({
        "benchmark": "collect_overhead", "task": args.task, "views": 2, "image_size": 64,
        "episodes_per_slice": args.episodes, "teacher_preset": args.preset, **medians,
        "teacher_time_shares": shares,
        "collection_vs_physics": round(medians["teacher_steps_per_s"]
                                       / medians["physics_steps_per_s"], 3),
        "render_process_speedup": round(medians["teacher_steps_per_s"]
                                        / medians["teacher_inline_steps_per_s"], 3),
        "target_steps_per_s": TARGET, "meets_target": medians["teacher_steps_per_s"] >= TARGET,
        "samples": {k: [round(x, 1) for x in v] for k, v in rates.items()},
    }))


if __name__ == "__main__":
    main()
