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
