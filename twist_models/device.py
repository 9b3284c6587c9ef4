"""The torch device a command runs on, checked before anything is created."""

from __future__ import annotations

import torch

from twist_data.errors import ConfigError


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
    (docs/performance.md). On a CPU compilation gave 1.07-1.17x after minutes of compiling,
    so ``auto`` stays eager there."""
    if setting not in COMPILE_SETTINGS:
        raise ConfigError(f"unknown compile setting {setting!r}; valid: "
                          f"{', '.join(COMPILE_SETTINGS)}")
    if setting == "off" or (setting == "auto" and device.type != "cuda"):
        return None
    return "reduce-overhead" if device.type == "cuda" else "default"
