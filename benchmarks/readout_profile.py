"""Where a `readout` student's update goes: ``--updates`` updates of the recipe's single-frame
stage (``twist-distil --recipe readout``, a ``--preset`` student on a synthetic 64x64, K=2 D
and a random teacher of its sizes) under ``torch.profiler``, split by the stage's own named
ranges: drawing the batch (``frame/data``), the CNN and read-out forward and loss
(``frame/forward``), the backward (``frame/backward``) and the clipped Adam step
(``frame/step``). The baseline, from the same run, is the stage's own seconds per update
(``frame-metrics.csv``, which the profiler's overhead inflates alike): ``parts_over_update``
says how much of it the four ranges hold. Prints one JSON line.

    python benchmarks/readout_profile.py [--preset quick] [--updates 60] [--episodes 8]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import tempfile
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.config import teacher_preset
from twist_models.distillation import distil_preset
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline.distil import distil

RANGES = ("frame/data", "frame/forward", "frame/backward", "frame/step")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick", choices=("tiny", "quick", "paper"))
    parser.add_argument("--updates", type=int, default=60)
    parser.add_argument("--episodes", type=int, default=8)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        dataset = write_synthetic_dataset(
            root / "ds", SynthConfig(episodes=args.episodes, steps=500, image_size=64))
        torch.manual_seed(0)
        teacher = save_teacher(root / "teacher.pt", Teacher(teacher_preset(args.preset, 5, 1)))
        config = distil_preset(args.preset, recipe="readout", frame_steps=args.updates, **{
            "schedule.frame_eval_every": args.updates, "schedule.holdout_every": 4,
            "schedule.heldout_windows": 4})
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            distil(dataset, root / "run", config, teacher=teacher)
        with open(root / "run" / "frame-metrics.csv") as f:
            per_update = 1 / float(list(csv.DictReader(f))[-1]["updates_per_s"])
    totals = {e.key: e.cpu_time_total / 1e6 / args.updates for e in prof.key_averages()
              if e.key in RANGES}
    parts = {name.split("/")[1]: totals.get(name, 0.0) for name in RANGES}
    whole = sum(parts.values())
    print(json.dumps({
        "benchmark": "readout_profile", "preset": args.preset, "updates": args.updates,
        "frame_batch": config.frame_batch, "threads": torch.get_num_threads(),
        "cpus": os.cpu_count(), "update_s": round(per_update, 4),
        **{f"{k}_s": round(v, 4) for k, v in parts.items()},
        **{f"{k}_share": round(v / whole, 3) for k, v in parts.items()},
        "parts_over_update": round(whole / per_update, 3)}))


if __name__ == "__main__":
    main()
