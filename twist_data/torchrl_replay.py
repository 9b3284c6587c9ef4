"""A Minari export of D as a torchrl replay buffer (``pip install twist[torchrl]``).

torchrl's own reader, ``MinariExperienceReplay(..., load_from_local_minari=True)``, builds
the right structure from a local Minari dataset but, in torchrl 0.14.1 with tensordict 0.14,
fills it with zeros: it copies the episodes into an in-memory TensorDict and then returns
``memmap_like`` of it, which allocates memory-mapped tensors of the same shapes without their
contents (``tests/test_minari_export.py`` records this with a strict expected failure, so a
fixed torchrl shows up). :func:`minari_replay_buffer` reads the same dataset into the same
layout (``observation``, ``action``, ``("next", "observation")``, ``("next", "reward")``,
``("next", "terminated" | "truncated" | "done")``, ``episode``, ``info``), so code written
against it works unchanged with ``MinariExperienceReplay`` once that is fixed.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from twist_data.errors import import_extra


def _imports() -> tuple[Any, Any, Any, Any]:
    reason = "a torchrl replay buffer needs"
    minari = import_extra("minari", "torchrl", reason)
    tensordict = import_extra("tensordict", "torchrl", reason)
    data = import_extra("torchrl.data", "torchrl", reason)
    import torch

    return minari, torch, tensordict.TensorDict, (data.LazyTensorStorage, data.SliceSampler,
                                                  data.TensorDictReplayBuffer)


def minari_replay_buffer(dataset_id: str, root: str | os.PathLike[str] | None = None,
                         slice_len: int = 50, batch_size: int = 800) -> Any:
    """Every transition of the local Minari dataset ``dataset_id`` (under ``root``, else
    Minari's root) in a torchrl ``TensorDictReplayBuffer`` whose sampler draws ``batch_size``
    transitions as ``batch_size // slice_len`` slices of ``slice_len`` consecutive steps of one
    episode each. Held in memory."""
    minari, torch, tensordict_type, (storage_type, sampler_type, buffer_type) = _imports()
    from twist_data.minari_export import MinariExportError, minari_datasets_path, minari_root

    if not (minari_root(root) / dataset_id / "data").is_dir():
        raise MinariExportError(f"no Minari dataset {dataset_id!r} in {minari_root(root)} "
                                "(twist-data export-minari writes one)")
    with minari_datasets_path(minari_root(root)):
        dataset = minari.load_dataset(dataset_id)
        episodes = [_episode_tensordict(e, torch, tensordict_type)
                    for e in dataset.iterate_episodes()]
    data = torch.cat(episodes)
    buffer = buffer_type(storage=storage_type(len(data)), batch_size=batch_size,
                         sampler=sampler_type(slice_len=slice_len, traj_key="episode",
                                              strict_length=False))
    buffer.extend(data)
    return buffer


def _episode_tensordict(episode: Any, torch: Any, tensordict_type: Any) -> Any:
    """One Minari episode of T transitions as a TensorDict of batch size [T]."""
    steps = len(episode.actions)

    def tree(values: Any, rows: slice) -> Any:
        if isinstance(values, dict):
            return {k: tree(v, rows) for k, v in values.items()}
        return torch.as_tensor(np.ascontiguousarray(values[rows]))

    now, after = slice(0, steps), slice(1, steps + 1)
    terminated = torch.as_tensor(episode.terminations)[:, None]
    truncated = torch.as_tensor(episode.truncations)[:, None]
    return tensordict_type({
        "observation": tree(episode.observations, now),
        "info": tree(episode.infos, now),
        "action": torch.as_tensor(episode.actions),
        "episode": torch.full((steps,), int(episode.id)),
        "next": {"observation": tree(episode.observations, after),
                 "info": tree(episode.infos, after),
                 "reward": torch.as_tensor(episode.rewards, dtype=torch.float32)[:, None],
                 "terminated": terminated, "truncated": truncated,
                 "done": terminated | truncated},
    }, batch_size=[steps])


__all__ = ["minari_replay_buffer"]
