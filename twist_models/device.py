"""The torch device a command runs on, checked before anything is created."""

from __future__ import annotations

import contextlib

import torch

from twist_data.errors import ConfigError
from twist_models.config import PRECISIONS


def resolve_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch device, or ConfigError in one sentence if this machine's torch
    cannot use it (an unknown name, CUDA on a CPU-only build, a GPU index that is not there)."""
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError(f"unknown device {str(device)!r}; use cpu, cuda or cuda:N") from None
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device {str(device)!r} is not available: this torch "
                              f"({torch.__version__}) sees no CUDA GPU")
        if resolved.index is not None and resolved.index >= torch.cuda.device_count():
            raise ConfigError(f"device {str(device)!r} does not exist: "
                              f"{torch.cuda.device_count()} CUDA GPU(s) visible")
    elif resolved.type != "cpu":
        raise ConfigError(f"device {str(device)!r} is not supported; use cpu, cuda or cuda:N")
    return resolved


#: ``compile`` settings of the training commands: ``auto`` compiles where it was measured to
#: pay (a CUDA device), ``on`` everywhere, ``off`` nowhere (eager, the reference).
COMPILE_SETTINGS = ("auto", "on", "off")


def compile_mode(setting: str, device: torch.device) -> str | None:
    """torch.compile's mode for ``setting`` (:data:`COMPILE_SETTINGS`) on ``device``, or None
    for eager. On CUDA the updates are chains of small kernels (a 50-step filter, a 15-step
    imagination) bound by launches, so the compiled graphs are also captured as CUDA graphs
    (``reduce-overhead``): the paper-sized world-model update ran 11x faster on an H200
    (docs/performance.md). On a CPU the updates' loops are compiled in pieces
    (:meth:`~twist_models.dreamer.Dreamer.compile_update`): on 2 cores the `quick`
    collector's update then ran 1.59x eager float32 (1.35x the eager bfloat16 update it
    replaces) after ~3 minutes of compiling, and a collection learned 15% sooner; but its
    teacher, another draw of the random numbers, learned for longer before it stopped, so
    ``auto`` stays eager there, the arithmetic every measured teacher learned with
    (``benchmarks/teacher_update_modes.py``; docs/findings.md)."""
    if setting not in COMPILE_SETTINGS:
        raise ConfigError(f"unknown compile setting {setting!r}; valid: "
                          f"{', '.join(COMPILE_SETTINGS)}")
    if setting == "off" or (setting == "auto" and device.type != "cuda"):
        return None
    return "reduce-overhead" if device.type == "cuda" else "default"


def compiles_whole(mode: str | None, whole: bool | None) -> bool:
    """Whether an update compiled in ``mode`` is compiled as whole graphs rather than its loops
    in pieces: ``whole`` if given, else only for CUDA graphs (``reduce-overhead``), which want
    the fewest launches; on a CPU pieces compile in a fraction of the time and ran about as
    fast (docs/performance.md)."""
    return mode == "reduce-overhead" if whole is None else whole


# Read once: a plain constant to torch.compile. Queried inside a compiled objective, the call
# broke the graph within the autocast block it decides, and the code resumed after the break
# guarded on that block's context object, a new one at every call: the objective recompiled
# at every update until dynamo gave up on it (docs/performance.md).
_CPU_HAS_BFLOAT16 = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def resolve_precision(precision: str, device: torch.device) -> str:
    """``float32`` or ``bfloat16`` for ``precision`` (:data:`PRECISIONS`) on ``device``:
    ``auto`` is bfloat16 on CUDA and on CPUs with AVX512-BF16 or AMX, where matrix products in
    it run about twice as fast (``benchmarks/encoder_speed.py``), and float32 on other CPUs,
    where autocast would emulate it and run slower."""
    if precision not in PRECISIONS:
        raise ConfigError(f"unknown precision {precision!r}; valid: {', '.join(PRECISIONS)}")
    if precision == "auto":
        native = device.type == "cuda" or (device.type == "cpu" and _CPU_HAS_BFLOAT16)
        return "bfloat16" if native else "float32"
    return precision


def precision_autocast(precision: str, device: torch.device
                       ) -> contextlib.AbstractContextManager:
    """The context networks run in for ``precision`` (:data:`PRECISIONS`) on ``device``:
    bfloat16 autocast, or nothing for float32."""
    if resolve_precision(precision, device) == "bfloat16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()
