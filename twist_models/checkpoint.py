"""One checkpoint format for teacher and student: weights, optimiser states, config, counters.

A checkpoint is a ``torch.save`` file of plain containers, tensors and JSON-typed values only,
read back with ``torch.load(weights_only=True)``: loading never unpickles arbitrary objects.
Files are written to a temporary name and renamed, so a crash never leaves a torn checkpoint.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from twist_data.errors import TwistError
from twist_models.config import to_json, without_removed

FORMAT = "twist.checkpoint"
VERSION = 1


class CheckpointError(TwistError):
    """A file is not a readable twist checkpoint, or holds a different kind of model."""


class CheckpointMismatchError(CheckpointError):
    """A checkpoint's configuration does not match the model or data it is loaded for."""


@dataclass(frozen=True)
class Checkpoint:
    """The contents of a checkpoint file."""

    kind: str
    """``teacher`` or ``student``."""
    config: dict[str, Any]
    """The model's config as JSON (rebuild with ``config.from_json``)."""
    weights: dict[str, torch.Tensor]
    """The module's state dict."""
    optimisers: dict[str, Any]
    """Optimiser state dicts by name."""
    counters: dict[str, int]
    """Step counters (updates, environment steps, ...)."""
    versions: dict[str, str]
    """Library versions that wrote it."""
    extra: dict[str, Any]
    """JSON run state of whoever wrote it (e.g. the collector's RNG states); may be empty."""


def save_checkpoint(path: str | os.PathLike[str], kind: str, module: nn.Module, config: Any,
                    optimisers: Mapping[str, torch.optim.Optimizer] | None = None,
                    counters: Mapping[str, int] | None = None,
                    extra: Mapping[str, Any] | None = None) -> Path:
    """Atomically write ``module``'s weights, its ``config`` and optimiser states to ``path``;
    ``extra`` is any JSON-serialisable run state."""
    import twist_data

    path = Path(path)
    payload = {
        "format": FORMAT, "version": VERSION, "kind": kind,
        "config": json.dumps(to_json(config), sort_keys=True),
        "weights": module.state_dict(),
        "optimisers": {k: v.state_dict() for k, v in (optimisers or {}).items()},
        "counters": {k: int(v) for k, v in (counters or {}).items()},
        "versions": {"twist": str(twist_data.__version__), "torch": str(torch.__version__)},
        "extra": json.dumps(dict(extra or {}), sort_keys=True),
    }
    return _write_payload(path, payload)


def _write_payload(path: Path, payload: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def weights_only(path: str | os.PathLike[str], dest: str | os.PathLike[str]) -> Path:
    """Copy the checkpoint at ``path`` to ``dest`` without its optimiser states (a `quick`
    teacher: 4.9 MiB instead of 12.4): what deploys or distils from it, never what resumes
    its training. Read and written as plain containers, never unpickled."""
    payload = _load_payload(Path(path))
    payload["optimisers"] = {}
    return _write_payload(Path(dest), payload)


def read_checkpoint(path: str | os.PathLike[str], kind: str | None = None) -> Checkpoint:
    """Read a checkpoint without unpickling code; ``kind`` requires that kind of model."""
    path = Path(path)
    payload = _load_payload(path)
    if kind is not None and payload["kind"] != kind:
        raise CheckpointError(f"checkpoint {str(path)!r} holds a {payload['kind']}, "
                              f"not a {kind}")
    return Checkpoint(kind=payload["kind"], config=json.loads(payload["config"]),
                      weights=payload["weights"], optimisers=payload["optimisers"],
                      counters=payload["counters"], versions=payload["versions"],
                      extra=json.loads(payload.get("extra", "{}")))


def _load_payload(path: Path) -> dict[str, Any]:
    """A checkpoint file's payload, checked for format and version."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist") from None
    except Exception as exc:  # torch raises assorted types for foreign or corrupt files
        raise CheckpointError(f"{str(path)!r} is not a readable twist checkpoint: "
                              f"{type(exc).__name__}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{str(path)!r} is not a twist checkpoint")
    if payload.get("version", 0) > VERSION:
        raise CheckpointError(f"checkpoint {str(path)!r} has version {payload.get('version')}; "
                              f"this library reads up to {VERSION}")
    return payload


def config_differences(stored: Mapping[str, Any], expected: Mapping[str, Any],
                       prefix: str = "") -> list[str]:
    """``name: stored vs expected`` for every leaf where two config JSON trees differ.

    A key only ``expected`` has is a field added after the checkpoint was written; the model
    was rebuilt from the stored config with that field's default, so it is no difference."""
    out = []
    for key in sorted(set(stored) | set(expected)):
        if key not in stored:
            continue
        name = f"{prefix}{key}"
        a, b = stored.get(key), expected.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += config_differences(a, b, f"{name}.")
        elif a != b:
            out.append(f"{name} is {a!r} in the checkpoint but {b!r} here")
    return out


def restore(checkpoint: Checkpoint, module: nn.Module, config: Any,
            optimisers: Mapping[str, torch.optim.Optimizer] | None = None) -> None:
    """Load weights (and optimiser states) into a module built from ``config``; refuses with
    every differing config value named when the checkpoint was written for another config."""
    differences = config_differences(without_removed(type(config), checkpoint.config),
                                     to_json(config))
    if differences:
        raise CheckpointMismatchError(f"{checkpoint.kind} checkpoint does not match the model: "
                                      + "; ".join(differences))
    try:
        module.load_state_dict(checkpoint.weights)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1].strip()
        raise CheckpointMismatchError(f"{checkpoint.kind} checkpoint's weights do not fit the "
                                      f"model: {first}") from None
    for name, optimiser in (optimisers or {}).items():
        if name in checkpoint.optimisers:
            optimiser.load_state_dict(checkpoint.optimisers[name])


def move_optimiser_state(optimiser: torch.optim.Optimizer, device: torch.device | str) -> None:
    """Move a (restored) optimiser's moment tensors to ``device``: ``Module.to`` leaves them on
    the CPU. Adam's scalar step counters stay where they are, by design."""
    for state in optimiser.state.values():
        for key, value in state.items():
            if torch.is_tensor(value) and value.dim() > 0:
                state[key] = value.to(device)
