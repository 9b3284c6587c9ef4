"""Teacher update time on this machine: world model alone vs world model + actor-critic.

Paper sizes (DreamerV2 DMC), state input of cheetah-run's size (17) and 6 actions, B=16, L=50,
random data (timing does not depend on values). Each figure is the median over ``--repeats``
updates after one warm-up update; both are measured in the same run. Prints one JSON line.
Target (issue 4): full teacher update <= 0.25 s on the 2-core CPU.

    python benchmarks/teacher_update.py [--preset paper] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from twist_models.config import PRESETS, teacher_preset
from twist_models.teacher import Teacher

TARGET_S = 0.25
B, L, STATE, ACTIONS = 16, 50, 17, 6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset(args.preset, STATE, ACTIONS))
    is_first = torch.zeros(B, L, dtype=torch.bool)
    is_first[:, 0] = True
    batch = {"state": torch.randn(B, L, STATE), "action": torch.rand(B, L, ACTIONS) * 2 - 1,
             "reward": torch.rand(B, L), "is_first": is_first}

    def model_only() -> None:
        loss, _, _ = teacher.world_model.loss(batch)
        teacher.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        teacher.model_opt.step()

    timings: dict[str, list[float]] = {"world_model_s": [], "teacher_update_s": []}
    for name, update in (("world_model_s", model_only),
                         ("teacher_update_s", lambda: teacher.train_step(batch))):
        update()  # warm-up
        for _ in range(args.repeats):
            start = time.perf_counter()
            update()
            timings[name].append(time.perf_counter() - start)
    medians = {k: round(statistics.median(v), 3) for k, v in timings.items()}
    print(json.dumps({
        "benchmark": "teacher_update", "preset": args.preset, "batch": B, "length": L,
        "threads": torch.get_num_threads(), "cpus": os.cpu_count(), **medians,
        "actor_critic_share": round(1 - medians["world_model_s"] / medians["teacher_update_s"], 2),
        "target_s": TARGET_S, "meets_target": medians["teacher_update_s"] <= TARGET_S,
        "samples": {k: [round(x, 3) for x in v] for k, v in timings.items()},
    }))


if __name__ == "__main__":
    main()
