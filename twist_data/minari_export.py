"""D as a Minari dataset (``pip install twist[minari]``), for offline-RL libraries that read
Minari (torchrl's ``MinariExperienceReplay``, Minari's own loaders).

Minari follows Gymnasium's convention: an episode of T transitions holds T + 1 observations,
and actions, rewards and flags are those of each transition. D's row t holds the action that
*led to* step t (see ``datasets.md``), so D's episode of T rows becomes:

* ``observations``: a dict of ``image_<k>`` (uint8 [T, H, W, 3], one per view k < K) and
  ``state`` (float32 [T, S]), every row of D;
* ``actions`` [T - 1, A], ``rewards`` [T - 1], ``terminations`` [T - 1] and ``truncations``
  [T - 1]: D's rows 1 .. T - 1 (a truncation is a last step that is not terminal);
* ``infos``: ``physics`` [T, P] and ``dr``, a dict of every per-step DR parameter
  [T, K, ...];
* episode metadata (Minari's per-episode attributes): ``seed`` and, under ``options``, who
  acted (``policy``), the teacher's update count (``teacher_step``), the collector's frame
  count (``env_step``), D's episode index and shard (``twist_episode``, ``twist_shard``) and
  ``dr``, a dict of the per-episode DR parameters.

Images are stored losslessly unless ``jpeg`` is asked for. The dataset is written into a
staging folder beside Minari's dataset root and moved into place when complete, so a failed
export leaves no half-written dataset, and ``overwrite`` replaces an existing one only then.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from twist_data.errors import TwistError, import_extra
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.verify import require_intact

log = logging.getLogger(__name__)

#: Minari's dataset IDs, ``[namespace/]name-v<version>`` (letters, digits, ``_`` and ``-``;
#: Minari itself accepts an ID without its version, then fails to write it).
DATASET_ID = re.compile(r"(?:[-\w]+/)*[-\w]+?-v\d+")

#: Episodes handed to Minari per write: bounds memory by this many episodes' images.
EPISODES_PER_WRITE = 16


class MinariExportError(TwistError):
    """A Minari dataset could not be written."""


def _minari() -> Any:
    return import_extra("minari", "minari", "exporting to Minari needs")


def minari_root(root: str | os.PathLike[str] | None = None) -> Path:
    """Minari's dataset root: ``root``, else ``$MINARI_DATASETS_PATH``, else Minari's default
    (``~/.minari/datasets``)."""
    if root is not None:
        return Path(root)
    from minari.storage.datasets_root_dir import get_dataset_path

    return Path(get_dataset_path())


@contextlib.contextmanager
def minari_datasets_path(path: Path) -> Iterator[None]:
    """Point Minari at ``path`` for the duration (it reads the variable on every call)."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def episode_buffer(data: MatchingDataset, index: int) -> Any:
    """D's episode ``index`` (global) as a Minari ``EpisodeBuffer`` in Gymnasium's convention."""
    from minari.data_collector import EpisodeBuffer

    episode, info = data.episode(index), data.episode_info(index)
    shard = data.shards[int(data.locate(data.episode_starts[index:index + 1]).shard[0])]
    observations: dict[str, np.ndarray] = {
        f"image_{k}": np.ascontiguousarray(episode.image[:, k])
        for k in range(episode.image.shape[1])}
    observations["state"] = episode.state
    options: dict[str, Any] = {"policy": info.policy, "teacher_step": int(info.teacher_step),
                               "env_step": int(info.env_step), "twist_episode": int(index),
                               "twist_shard": shard.name}
    options["dr"] = {k: v.item() if isinstance(v, np.generic) else v for k, v in info.dr.items()}
    last = episode.is_last[1:]
    return EpisodeBuffer(
        id=index, seed=int(info.seed), options=options, observations=observations,
        actions=episode.action[1:], rewards=episode.reward[1:],
        terminations=episode.is_terminal[1:], truncations=last & ~episode.is_terminal[1:],
        infos={"physics": episode.physics, "dr": dict(episode.dr)})


def _spaces(data: MatchingDataset) -> tuple[Any, Any]:
    from gymnasium import spaces

    spec = data.spec
    images = {f"image_{k}": spaces.Box(0, 255, spec.image_shape, np.uint8)
              for k in range(spec.views)}
    state = spaces.Box(-np.inf, np.inf, (spec.state_dim,), np.float32)
    actions = spaces.Box(-1.0, 1.0, (spec.action_dim,), np.float32)
    return spaces.Dict({**images, "state": state}), actions


def export_minari(dataset_path: str | os.PathLike[str], dataset_id: str,
                  root: str | os.PathLike[str] | None = None, overwrite: bool = False,
                  jpeg: bool = False, on_progress: Callable[[int, int], None] | None = None
                  ) -> Path:
    """Write every committed episode of the dataset at ``dataset_path`` as the Minari dataset
    ``dataset_id`` (``[namespace/]name-v<version>``) under ``root`` (:func:`minari_root`);
    returns its folder. An existing dataset of that ID is refused unless ``overwrite``."""
    minari = _minari()
    require_intact(dataset_path, "export-minari")
    data = open_dataset(dataset_path)
    root = minari_root(root)
    if DATASET_ID.fullmatch(dataset_id) is None:
        raise MinariExportError(f"dataset ID {dataset_id!r} is not a Minari ID: "
                                "[namespace/]name-v<version>, e.g. twist/cartpole-balance-v0")
    target = root / dataset_id
    if target.exists() and not overwrite:
        raise MinariExportError(f"Minari dataset {dataset_id!r} already exists in {root}; "
                                "pass overwrite (--overwrite) to replace it")
    if data.n_episodes == 0:
        raise MinariExportError(f"{data.path} holds no committed episode to export")
    observation_space, action_space = _spaces(data)
    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".twist-staging-{uuid.uuid4().hex[:8]}"
    try:
        with minari_datasets_path(staging):
            first = [episode_buffer(data, i) for i in range(min(EPISODES_PER_WRITE,
                                                                 data.n_episodes))]
            created = minari.create_dataset_from_buffers(
                dataset_id, first, observation_space=observation_space,
                action_space=action_space, algorithm_name="twist-collect",
                description=_description(data), jpeg_encoding=jpeg)
            done = len(first)
            if on_progress is not None:
                on_progress(done, data.n_episodes)
            while done < data.n_episodes:
                chunk = range(done, min(done + EPISODES_PER_WRITE, data.n_episodes))
                created.update_dataset_from_buffer([episode_buffer(data, i) for i in chunk])
                done = chunk.stop
                if on_progress is not None:
                    on_progress(done, data.n_episodes)
        _move_into_place(staging, root, dataset_id, overwrite)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    log.info("wrote %d episodes of %s as Minari dataset %s in %s", data.n_episodes, data.path,
             dataset_id, root)
    return target


def _move_into_place(staging: Path, root: Path, dataset_id: str, overwrite: bool) -> None:
    """Move the finished dataset from ``staging`` to ``root``, with its namespace's metadata;
    an existing dataset (``overwrite``) is removed only once the new one is complete."""
    target = root / dataset_id
    target.parent.mkdir(parents=True, exist_ok=True)
    namespace = Path(dataset_id).parent
    while str(namespace) not in ("", "."):
        meta = staging / namespace / "namespace_metadata.json"
        if meta.exists() and not (root / namespace / "namespace_metadata.json").exists():
            shutil.copy2(meta, root / namespace / "namespace_metadata.json")
        namespace = namespace.parent
    old = None
    if target.exists():
        if not overwrite:  # appeared while exporting
            raise MinariExportError(f"Minari dataset {dataset_id!r} appeared in {root} "
                                    "while exporting; nothing was replaced")
        old = target.with_name(f".{target.name}.replaced-{uuid.uuid4().hex[:8]}")
        os.replace(target, old)
    os.replace(staging / dataset_id, target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _description(data: MatchingDataset) -> str:
    spec = data.spec
    return (f"A twist matching dataset (task {spec.task}, {spec.views} domain-randomised "
            f"views of {spec.image_shape[0]}x{spec.image_shape[1]} per step, privileged "
            f"state) exported from {data.path}. Observations: image_0..image_{spec.views - 1} "
            "and state; infos: physics and per-step DR parameters; episode options: "
            f"provenance. Spec: {json.dumps(spec.to_json())}")


__all__ = ["MinariExportError", "episode_buffer", "export_minari", "minari_datasets_path",
           "minari_root"]
