"""Distillation speed: updates/s of ``twist-distil`` and the share of step time spent
waiting for data, against the same updates on one batch held in memory (the baseline, run in
the same process: no decoding, no transfer).

A synthetic 64x64, K=2 dataset of ``--episodes`` x 500 steps is written to a temporary folder
(or ``--dataset``), a random-weights teacher of ``--preset`` sizes is saved beside it, and
``distil()`` runs ``--updates`` updates at B=16, L=50, H=15 (Eq. 3 + Eq. 4 from
``--imag-starts`` states; 0 = all 800, as the paper). Prints one JSON line.

    python benchmarks/distil_update.py [--preset quick|paper] [--updates 20] [--workers 1]
        [--imag-starts 256] [--device cpu|cuda]

Targets: data wait < 5% of step time (CPU and GPU); >= 25 updates/s on an H100 (paper sizes).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from twist_data.sampler import WindowSampler
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.config import student_preset, teacher_preset
from twist_models.distillation import KEYS, Distillation, distil_preset
from twist_models.student import Student
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline.distil import distil


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick", choices=("tiny", "quick", "paper"))
    parser.add_argument("--updates", type=int, default=20)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--imag-starts", type=int, default=256)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dataset", type=Path, default=None)
    args = parser.parse_args()
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        dataset = args.dataset or write_synthetic_dataset(
            root / "ds", SynthConfig(episodes=args.episodes, steps=500, image_size=64))
        torch.manual_seed(0)
        teacher = Teacher(teacher_preset(args.preset, 5, 1))
        teacher_path = save_teacher(root / "teacher.pt", teacher)
        config = distil_preset(
            args.preset, steps=args.updates, batch_size=16, length=50, horizon=15,
            imag_starts=args.imag_starts, **{
                "compute.workers": args.workers, "schedule.eval_every": args.updates,
                "schedule.checkpoint_every": args.updates,
                "schedule.snapshot_every": 10 * args.updates, "schedule.holdout_every": 4,
                "schedule.heldout_windows": 4})
        summary = distil(dataset, root / "run", config, teacher=teacher_path, device=args.device)

        # Baseline: the same objective on one batch already on the device.
        sampler = WindowSampler(dataset, config.sampler("train", 0))
        batch = {k: torch.as_tensor(v).to(device) for k, v in sampler.batch().items()
                 if k in KEYS}
        student = Student(student_preset(args.preset, teacher.config)).to(device)
        objective = Distillation(student, teacher.to_device(device), config)
        optimiser = torch.optim.AdamW(student.parameters(), config.lr)
        samples = []
        for i in range(min(args.updates, 10) + 1):
            if device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            loss, _ = objective(batch)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            if device.type == "cuda":
                torch.cuda.synchronize()
            if i:  # the first is a warm-up
                samples.append(time.perf_counter() - start)
    in_memory = 1 / statistics.median(samples)
    print(json.dumps({
        "benchmark": "distil_update", "preset": args.preset, "device": args.device,
        "batch": 16, "length": 50, "horizon": 15, "imag_starts": args.imag_starts,
        "workers": args.workers, "updates": args.updates,
        "updates_per_s": summary.updates_per_second,
        "data_wait_share": summary.data_wait_share,
        "in_memory_updates_per_s": round(in_memory, 3),
        "ratio_to_in_memory": round(summary.updates_per_second / in_memory, 3),
        "targets": {"data_wait_share_max": 0.05, "h100_updates_per_s_min": 25},
    }))


if __name__ == "__main__":
    main()
