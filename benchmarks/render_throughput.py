"""Collection-path throughput: agent steps/s for one agent step (action repeat 2 by default,
``--action-repeat``; the panda tasks are made for 4) plus K=2 randomised 64x64 views, per task,
against dm_control's default render path in the same run.

Methods, interleaved per task so machine noise hits all of them alike:
  twist          env.step + DR parameter draw + DRRenderer.render (train preset: background and
                 colours every step), supersample 1 (the default)
  twist_ss2      the same rendered at 128x128 and area-downsampled (anti-aliased thin geoms)
  dm_control     env.step + 2 x physics.render(64, 64, camera_id=0), no randomisation at all
  physics_only   env.step
Each figure is the median over 5 slices. Prints one JSON line; target: twist >= 300 steps/s.

    python benchmarks/render_throughput.py [--tasks cheetah-run ...] [--seconds 2]
        [--action-repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TASKS, TaskEnv

TARGET = 300.0
K, SIZE = 2, 64


def steps_per_second(step_fn: Callable[[], None], seconds: float) -> dict:
    """Median agent steps/s over 5 equal time slices."""
    slices = []
    for _ in range(5):
        n, start = 0, time.perf_counter()
        while True:
            step_fn()
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= seconds / 5 and n >= 3:
                slices.append(n / elapsed)
                break
    return {"steps_per_s": round(statistics.median(slices), 1),
            "slices": [round(s, 1) for s in slices]}


def stepper(env: TaskEnv, rng: np.random.Generator) -> Callable[[], object]:
    state = {"step": env.reset(seed=0)}

    def step() -> object:
        if state["step"].is_last:
            state["step"] = env.reset()
        state["step"] = env.step(rng.uniform(-1, 1, env.action_dim))
        return state["step"]

    return step


def bench_task(task: str, seconds: float, action_repeat: int = 2) -> dict:
    env = TaskEnv(task, action_repeat=action_repeat)
    rng = np.random.default_rng(0)
    step = stepper(env, rng)
    out: dict = {}
    for name, supersample in (("twist", 1), ("twist_ss2", 2)):
        with DRRenderer(task, dr_preset("train"), SIZE, K, supersample=supersample) as renderer:
            sampler = renderer.sampler(0)
            sampler.begin_episode()
            frames = np.empty((K, SIZE, SIZE, 3), np.uint8)

            def collect(renderer: DRRenderer = renderer, sampler=sampler, frames=frames) -> None:
                renderer.render(step().physics, sampler.sample(), out=frames)

            out[name] = steps_per_second(collect, seconds)

    def default_path() -> None:
        step()
        for _ in range(K):
            env.physics.render(SIZE, SIZE, camera_id=0)

    out["dm_control"] = steps_per_second(default_path, seconds)
    out["physics_only"] = steps_per_second(step, seconds / 2)
    twist, default = out["twist"]["steps_per_s"], out["dm_control"]["steps_per_s"]
    out["speedup_vs_dm_control"] = round(twist / default, 2)
    out["meets_target"] = twist >= TARGET
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=sorted(TASKS), choices=sorted(TASKS))
    parser.add_argument("--seconds", type=float, default=2.0, help="measuring time per method")
    parser.add_argument("--action-repeat", type=int, default=2,
                        help="physics steps per agent step (the panda tasks are made for 4)")
    args = parser.parse_args()
    results = {}
    for task in args.tasks:
        results[task] = bench_task(task, args.seconds, args.action_repeat)
        r = results[task]
        print(f"{task}: twist {r['twist']['steps_per_s']}/s, ss2 {r['twist_ss2']['steps_per_s']}/s, "
              f"dm_control {r['dm_control']['steps_per_s']}/s, physics "
              f"{r['physics_only']['steps_per_s']}/s", file=sys.stderr)
    twist = [r["twist"]["steps_per_s"] for r in results.values()]
    summary = {
        "benchmark": "render_throughput", "views": K, "image_size": SIZE, "action_repeat": args.action_repeat,
        "target_steps_per_s": TARGET, "min_twist_steps_per_s": min(twist),
        "median_speedup_vs_dm_control": statistics.median(
            r["speedup_vs_dm_control"] for r in results.values()),
        "all_meet_target": all(r["meets_target"] for r in results.values()),
        "cpus": os.cpu_count(), "machine": platform.machine(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"), "tasks": results,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
