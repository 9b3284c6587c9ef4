"""The student's window update (a recipe's whole objective: Eq. 3, Eq. 4 and the terms beside
them, backward and Adam step) eager and compiled as ``twist-distil --set compile=true``
compiles it, timed in the same run on copies of the same weights and one batch.

Variants: ``eager`` (the reference); ``pieces`` (both filters in compiled pieces, the CNN and
everything else eager: what a CPU runs, :func:`twist_models.distillation.compiled_objective`);
``whole`` (the whole objective as one graph: what a GPU runs, with CUDA graphs there). Every
variant has its own copy of the teacher, since the pieces compile the teacher's filter too.
Each variant's first two updates are timed apart (``compile_s``: compilation); then rounds of
one update per variant, interleaved so that a machine's drift affects each alike; medians.

Random data of the real shapes (B=16, L=50, 64x64 uint8 images; the timings do not depend on
values); the recipe's precision, so ``dense`` and ``readout`` run their CNN in bfloat16 where
the device computes it natively. Prints one JSON line.

    python benchmarks/distil_compile.py [--preset quick] [--recipe dense] [--rounds 7]
        [--variants eager,pieces,whole] [--device cpu|cuda]

Target (2-core CPU, ``quick``): the compiled update >= 1.5x eager in the same run.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from collections.abc import Callable

import torch
from torch.nn import functional as F

from twist_models.config import student_preset, teacher_preset
from twist_models.device import compile_mode, resolve_precision
from twist_models.distillation import DistilConfig, Distillation, compiled_objective, distil_preset
from twist_models.student import Student
from twist_models.teacher import Teacher

B, L, STATE, ACTIONS = 16, 50, 5, 1
VARIANTS = ("eager", "pieces", "whole")


def window_batch(teacher: Teacher, device: torch.device) -> dict[str, torch.Tensor]:
    rssm = teacher.config.world_model.rssm
    is_first = torch.zeros(B, L, dtype=torch.bool)
    is_first[:, 0] = True
    stoch = F.one_hot(torch.randint(0, rssm.classes, (B, rssm.stoch)), rssm.classes).float()
    batch = {"image": torch.randint(0, 256, (B, L, 64, 64, 3), dtype=torch.uint8),
             "state": torch.randn(B, L, STATE), "action": torch.rand(B, L, ACTIONS) * 2 - 1,
             "is_first": is_first, "start_deter": 0.1 * torch.randn(B, rssm.deter),
             "start_stoch": stoch}
    return {k: v.to(device) for k, v in batch.items()}


def updater(variant: str, student: Student, teacher: Teacher, config: DistilConfig,
            device: torch.device, batch: dict[str, torch.Tensor]) -> Callable[[], None]:
    objective = Distillation(student, teacher, config)
    mode = None if variant == "eager" else compile_mode("on", device)
    train = compiled_objective(objective, mode, whole=variant == "whole")
    optimiser = torch.optim.Adam([p for p in student.parameters() if p.requires_grad], config.lr)

    def update() -> None:
        if mode == "reduce-overhead":
            torch.compiler.cudagraph_mark_step_begin()
        loss, _ = train(batch)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        if device.type == "cuda":
            torch.cuda.synchronize()

    return update


def seconds(step: Callable[[], None]) -> float:
    start = time.perf_counter()
    step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick", choices=("tiny", "quick", "paper"))
    parser.add_argument("--recipe", default="dense", choices=("paper", "dense"))
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--variants", default="eager,pieces,whole")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    variants = args.variants.split(",")
    if variants[0] != "eager" or not set(variants) <= set(VARIANTS):
        parser.error(f"--variants must start with eager and name only {', '.join(VARIANTS)}, "
                     f"got {args.variants!r}")
    device = torch.device(args.device)
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset(args.preset, STATE, ACTIONS)).to_device(device)
    config = distil_preset(args.preset, args.recipe)
    student = Student(student_preset(args.preset, teacher.config, 64, norm=config.encoder_norm,
                                     state_head=config.weights.state > 0)).to(device)
    batch = window_batch(teacher, device)
    updates: dict[str, Callable[[], None]] = {}
    compile_s: dict[str, float] = {}
    for variant in variants:
        updates[variant] = updater(variant, copy.deepcopy(student), copy.deepcopy(teacher),
                                   config, device, batch)
        compile_s[variant] = round(seconds(updates[variant]) + seconds(updates[variant]), 1)
    samples: dict[str, list[float]] = {v: [] for v in variants}
    for _ in range(args.rounds):
        for variant in variants:
            samples[variant].append(seconds(updates[variant]))
    medians = {v: statistics.median(s) for v, s in samples.items()}
    print(json.dumps({
        "benchmark": "distil_compile", "preset": args.preset, "recipe": args.recipe,
        "precision": resolve_precision(config.compute.precision, device),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "threads": torch.get_num_threads(), "batch": B, "length": L,
        "imag_starts": config.imag_starts, "median_s": {k: round(v, 4) for k, v in medians.items()},
        "speedup_vs_eager": {k: round(medians["eager"] / v, 3) for k, v in medians.items()},
        "first_two_updates_s": compile_s, "target_speedup": 1.5,
        "samples": {k: [round(x, 4) for x in v] for k, v in samples.items()},
    }), flush=True)


if __name__ == "__main__":
    main()
