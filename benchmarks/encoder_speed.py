"""How many frames per second the student's CNN trains on, and what bf16 autocast or the memory
format change, all measured in the same run (the first variant is the baseline).

One "pass" is a forward and backward pass of the encoder plus a linear read-out on a batch of
``--batch`` 64x64 uint8 frames, the work of one update of the ``dense`` recipe's single-frame
stage. Variants: ``fp32`` (the default path: channels_last input, float32), ``contiguous``
(NCHW input instead), ``bf16`` (CPU autocast to bfloat16 around the same pass) and, with
``--compile``, ``bf16_compiled`` (the same forward through ``torch.compile``, its first call's
compilation timed apart). Rounds of
the variants are interleaved so that a machine's drift affects each alike; medians reported.

Prints one JSON line. ``python benchmarks/encoder_speed.py [--preset quick] [--norm layer]
[--batch 64] [--rounds 15] [--threads N] [--compile]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from contextlib import nullcontext

import torch
from torch import nn

from twist_models.config import CNN_NORMS, PRESETS, CNNConfig
from twist_models.networks import ImageEncoder, preprocess_image


def timed(step: Callable[[], None]) -> float:
    start = time.perf_counter()
    step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="quick", choices=list(PRESETS))
    parser.add_argument("--norm", default="layer", choices=CNN_NORMS)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's)")
    parser.add_argument("--compile", action="store_true",
                        help="also torch.compile the bf16 forward (backward through it)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cnn = dataclasses.replace(PRESETS[args.preset].get("cnn", CNNConfig()), norm=args.norm)
    encoder = ImageEncoder(cnn)
    head = nn.Linear(encoder.out_dim, 5)
    images = torch.randint(0, 256, (args.batch, 64, 64, 3), dtype=torch.uint8)
    target = torch.randn(args.batch, 5)

    def forward(x: torch.Tensor) -> torch.Tensor:
        return head(encoder.net(x).flatten(1))

    compiled_forward = torch.compile(forward) if args.compile else None

    def run(channels_last: bool, bf16: bool, compiled: bool = False) -> Callable[[], None]:
        def step() -> None:
            x = preprocess_image(images).permute(0, 3, 1, 2)
            x = x.contiguous(memory_format=torch.channels_last if channels_last
                             else torch.contiguous_format)
            context = torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else nullcontext()
            with context:
                out = (compiled_forward if compiled else forward)(x)
            loss = ((out.float() - target) ** 2).mean()
            encoder.zero_grad(set_to_none=True)
            head.zero_grad(set_to_none=True)
            loss.backward()
        return step

    variants = {"fp32": run(True, False), "contiguous": run(False, False), "bf16": run(True, True)}
    compile_s = None
    if args.compile:
        variants["bf16_compiled"] = run(True, True, compiled=True)
        compile_s = timed(variants["bf16_compiled"])  # the first call compiles
    for step in variants.values():  # warm-up
        step()
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(args.rounds):
        for name, step in variants.items():
            times[name].append(timed(step))
    medians = {name: statistics.median(t) for name, t in times.items()}
    base = medians["fp32"]
    print(json.dumps({
        "benchmark": "encoder_speed", "preset": args.preset, "norm": args.norm,
        "batch": args.batch, "threads": torch.get_num_threads(),
        "frames_per_s": {k: round(args.batch / v, 1) for k, v in medians.items()},
        "median_ms": {k: round(1000 * v, 2) for k, v in medians.items()},
        "speedup_vs_fp32": {k: round(base / v, 3) for k, v in medians.items()},
        "compile_s": None if compile_s is None else round(compile_s, 1),
    }))


if __name__ == "__main__":
    main()
