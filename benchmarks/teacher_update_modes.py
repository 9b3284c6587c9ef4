"""The collector's own teacher update, eager float32 against compiled and bfloat16 variants of
the same weights, measured in the same run.

Where ``benchmarks/world_model_update.py`` times a preset's networks at the paper's B=16 and
every imagination start, this times exactly what ``twist-collect --preset P --task T`` runs at
each update: its teacher config (overshooting, imagination starts, critic head) and its batch
(``batch_size`` x ``batch_length``) on the task's state and action sizes. Variants, each a
copy of the same initial weights:

* ``eager``: float32, no compilation (the reference, ``--set compile=off
  --set imagination_precision=float32``);
* ``bf16``: imagination and the actor-critic in bfloat16 autocast
  (``--set imagination_precision=bfloat16``; the ``quick`` preset's ``auto`` where the CPU
  computes bfloat16 natively);
* ``compiled``: the world-model loss and the imagined rollout each compiled whole
  (``Dreamer.compile_update(whole=True)``, as the collector compiles on a CUDA device);
* ``compiled_bf16``: both;
* ``pieces``: the loops compiled in pieces, the filter a few steps at a time
  (``Dreamer.compile_update(whole=False)``, as the collector compiles on a CPU with
  ``--set compile=on``);
* ``pieces_bf16``: pieces with ``bf16``;
* ``compiled_steps_bf16``: ``bf16`` with only the RSSM's one-step functions compiled
  (``img_step``, ``post_step``, the prior head) and the loops left eager: small graphs that
  compile in well under a minute (an alternative measured here, not in the library);
* ``bf16_world_model``: ``bf16`` with the world model's loss in bfloat16 autocast too (an
  alternative measured here, not in the library: the collector keeps the world model in
  float32).

A compiled variant's first two calls are reported apart (``<name>_compile_s``): they compile,
and nothing else in a run costs as much once. Point ``TORCHINDUCTOR_CACHE_DIR`` at an empty
folder to time a first compilation on a fresh machine; with the default cache a second run
reuses the first's kernels. Rounds of the variants alternate, medians are reported with each
variant's speed-up over ``eager``, and ``break_even_updates`` is the compile time over the
seconds a compiled update saves. Prints one JSON line.

    python benchmarks/teacher_update_modes.py [--preset quick] [--task cartpole-balance]
        [--variants eager,bf16,compiled,compiled_bf16,pieces_bf16] [--rounds 9] [--device cpu]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import statistics
import time
from collections.abc import Callable

import torch

from twist_models.rssm import State
from twist_models.teacher import Teacher
from twist_pipeline.collect import COLLECT_PRESETS, collect_preset
from twist_sim.tasks import TaskEnv

VARIANTS = ("eager", "bf16", "compiled", "compiled_bf16", "compiled_steps_bf16",
            "bf16_world_model", "pieces", "pieces_bf16")


def compile_steps(teacher: Teacher) -> None:
    """Compile the RSSM's one-step functions of ``teacher``, leaving its loops eager."""
    rssm = teacher.world_model.rssm
    for name in ("img_step", "post_step", "_prior"):
        setattr(rssm, name, torch.compile(getattr(rssm, name)))


def bfloat16_world_model(teacher: Teacher) -> None:
    """Run ``teacher``'s world-model loss under bfloat16 autocast (its backward follows)."""
    loss = teacher.world_model.loss

    def autocast_loss(batch: dict[str, torch.Tensor]
                      ) -> tuple[torch.Tensor, State, dict[str, torch.Tensor]]:
        with torch.autocast(batch["state"].device.type, dtype=torch.bfloat16):
            return loss(batch)

    teacher._model_loss = autocast_loss


def collector_batch(batch: int, length: int, state_dim: int, action_dim: int,
                    device: torch.device) -> dict[str, torch.Tensor]:
    """Random windows of the collector's shape (timings do not depend on values)."""
    g = torch.Generator().manual_seed(0)
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[:, 0] = True
    windows = {"state": torch.randn(batch, length, state_dim, generator=g),
               "action": torch.rand(batch, length, action_dim, generator=g) * 2 - 1,
               "reward": torch.rand(batch, length, generator=g), "is_first": is_first}
    return {k: v.to(device) for k, v in windows.items()}


def timed(update: Callable[[], None], device: torch.device) -> float:
    """Seconds of one call of ``update`` (waiting for the GPU on CUDA); each benchmark script
    stands alone, so this small timer is its own."""
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    update()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="quick", choices=sorted(COLLECT_PRESETS))
    parser.add_argument("--task", default="cartpole-balance")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    names = args.variants.split(",")
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown or "eager" not in names:
        parser.error(f"--variants takes eager and any of {', '.join(VARIANTS)}; got "
                     f"{args.variants!r}")
    device = torch.device(args.device)
    collect = collect_preset(args.preset, task=args.task)
    env = TaskEnv(args.task, collect.action_repeat)
    config = collect.teacher_config(env.state_dim, env.action_dim)
    # The reference is float32 whatever the preset runs (quick: ``auto``, bfloat16 on CPUs
    # that compute it natively); the bf16 variants set it themselves.
    config = dataclasses.replace(config, actor_critic=dataclasses.replace(
        config.actor_critic, precision="float32"))
    batch = collector_batch(collect.batch_size, collect.batch_length, env.state_dim,
                            env.action_dim, device)
    torch.manual_seed(0)
    reference = Teacher(config).to_device(device)
    mode = "reduce-overhead" if device.type == "cuda" else "default"
    teachers, compile_s = {}, {}
    for name in names:
        teacher = reference if name == "eager" else copy.deepcopy(reference)
        if "bf16" in name:
            teacher.actor_critic.config = dataclasses.replace(config.actor_critic,
                                                              precision="bfloat16")
        if name == "compiled_steps_bf16":
            compile_steps(teacher)
        elif name.startswith("pieces"):
            teacher.compile_update(mode, whole=False)
        elif name == "bf16_world_model":
            bfloat16_world_model(teacher)
        elif name.startswith("compiled"):
            teacher.compile_update(mode, whole=True)
        start = time.perf_counter()
        teacher.train_step(batch)  # compiles (and records CUDA graphs on the second call)
        teacher.train_step(batch)
        if name.startswith(("compiled", "pieces")):
            compile_s[name] = round(time.perf_counter() - start, 1)
        teachers[name] = teacher
    samples: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(args.rounds):
        for name, teacher in teachers.items():
            samples[name].append(timed(lambda t=teacher: t.train_step(batch), device))
    medians = {name: statistics.median(values) for name, values in samples.items()}
    eager = medians["eager"]
    result = {
        "benchmark": "teacher_update_modes", "preset": args.preset, "task": args.task,
        "batch": collect.batch_size, "length": collect.batch_length,
        "imag_starts": config.actor_critic.imag_starts, "overshoot": config.world_model.overshoot,
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
        "inductor_cache": os.environ.get("TORCHINDUCTOR_CACHE_DIR", "default"),
        **{f"{name}_s": round(value, 4) for name, value in medians.items()},
        **{f"{name}_speedup": round(eager / value, 2) for name, value in medians.items()
           if name != "eager"},
        **{f"{name}_compile_s": value for name, value in compile_s.items()},
        **{f"{name}_break_even_updates": round(compile_s[name] / (eager - medians[name]))
           if medians[name] < eager else None for name in compile_s},
        "samples": {name: [round(x, 4) for x in values] for name, values in samples.items()},
    }
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
