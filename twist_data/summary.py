"""Dataset summary for ``twist-data info``."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from twist_data.reader import open_dataset
from twist_data.schema import step_arrays


def dataset_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Sizes, schema and storage figures of the dataset at ``path`` (JSON-serialisable)."""
    ds = open_dataset(path)
    spec = ds.spec
    raw = 0
    for a in step_arrays(spec, ds.has_pairs):
        raw += ds.n_steps * int(np.prod(a.trailing, dtype=np.int64)) * np.dtype(a.dtype).itemsize
    disk = ds.disk_bytes()
    lengths = ds.episode_lengths
    returns = ds.episodes()["return"].to_numpy() if ds.n_episodes else np.zeros(0)
    return {
        "path": str(ds.path),
        "format_version": max(s.format_version for s in ds.shards),
        "task": spec.task,
        "shards": [{"name": s.name, "episodes": s.n_episodes, "steps": s.n_steps}
                   for s in ds.shards],
        "episodes": ds.n_episodes,
        "steps": ds.n_steps,
        "views": spec.views,
        "image_shape": list(spec.image_shape),
        "frame_pairs": ds.has_pairs,
        "state_dim": spec.state_dim,
        "action_dim": spec.action_dim,
        "physics_dim": spec.physics_dim,
        "action_repeat": spec.action_repeat,
        "dr_params": [p.name for p in spec.dr_params],
        "episode_dr_params": [p.name for p in spec.episode_dr_params],
        "episode_length": {"min": int(lengths.min()), "mean": float(lengths.mean()),
                           "max": int(lengths.max())} if lengths.size else None,
        "episode_return": {"min": float(returns.min()), "mean": float(returns.mean()),
                           "max": float(returns.max())} if returns.size else None,
        "bytes_on_disk": disk,
        "bytes_uncompressed": raw,
        "compression_ratio": raw / disk if disk else None,
    }
