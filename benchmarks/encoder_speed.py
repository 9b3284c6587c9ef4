"""How many frames per second the student's CNN trains on, and what bf16 autocast or the memory
format change, all measured in the same run (the first variant is the baseline).

One "pass" is a forward and backward pass of the encoder plus a linear read-out on a batch of
``--batch`` 64x64 uint8 frames, the work of one update of the ``dense`` recipe's single-frame
stage. Variants: ``fp32`` (the default path: channels_last input, float32), ``contiguous``
(NCHW input instead), ``bf16`` (CPU autocast to bfloat16 around the same pass) and, with
``--compile``, ``bf16_compiled`` (the same forward through ``torch.compile``, its first call's
compilation timed apart). Rounds of
the variants are interleaved so that a machine's drift affects each alike; medians reported.
With ``--profile``, ``bf16_time_share`` splits the ``bf16`` pass's operator time (forward and
backward, from ``torch.profiler``) into convolutions, the normalisation, the activation and
the rest: what a faster implementation of each could save at most.

Prints one JSON line. ``python benchmarks/encoder_speed.py [--preset quick] [--norm layer]
[--batch 64] [--rounds 15] [--threads N] [--compile] [--profile]``
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


#: Operator kinds of ``--profile``, by a substring of the ATen operator's name (forward and
#: backward alike); the first that matches wins.
OPERATOR_KINDS = {"convolution": "conv", "normalisation": "norm", "activation": "elu"}


def time_shares(step: Callable[[], None], passes: int = 10) -> dict[str, float]:
    """Share of ``step``'s self CPU time in each of :data:`OPERATOR_KINDS` and the rest."""
    from torch.profiler import profile

    with profile() as prof:
        for _ in range(passes):
            step()
    totals = dict.fromkeys([*OPERATOR_KINDS, "other"], 0.0)
    for event in prof.key_averages():
        if not event.key.startswith("aten::"):
            continue  # autograd and optimiser wrappers: their time is their operators'
        kind = next((k for k, part in OPERATOR_KINDS.items() if part in event.key), "other")
        totals[kind] += event.self_cpu_time_total
    whole = sum(totals.values())
    return {k: round(v / whole, 3) for k, v in totals.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="quick", choices=list(PRESETS))
    parser.add_argument("--norm", default="layer", choices=CNN_NORMS)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's)")
    parser.add_argument("--compile", action="store_true",
                        help="also torch.compile the bf16 forward (backward through it)")
    parser.add_argument("--profile", action="store_true",
                        help="split the bf16 pass's operator time by kind of operator")
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
    shares = time_shares(variants["bf16"]) if args.profile else None
    base = medians["fp32"]
    print(json.dumps({
        "benchmark": "encoder_speed", "preset": args.preset, "norm": args.norm,
        "batch": args.batch, "threads": torch.get_num_threads(),
        "frames_per_s": {k: round(args.batch / v, 1) for k, v in medians.items()},
        "median_ms": {k: round(1000 * v, 2) for k, v in medians.items()},
        "speedup_vs_fp32": {k: round(base / v, 3) for k, v in medians.items()},
        "compile_s": None if compile_s is None else round(compile_s, 1),
        "bf16_time_share": shares,
    }))


if __name__ == "__main__":
    main()
