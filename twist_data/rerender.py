"""Re-rendering a dataset from its stored physics states: reproduce, re-randomise, add views.

A dataset written through :func:`twist_data.rollout.simulated_spec` records, in
``spec.extra["render"]``, one block per range of views: the DR config, image size, supersampling
and a digest of the background bank. With the stored ``data/physics`` and ``data/dr/*`` that
is everything needed to redraw a frame, so images can be regenerated under a new DR config (or
extended with more views) without re-training a teacher.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from twist_data.errors import ConfigError, SchemaMismatchError
from twist_data.randomisation import VIEW_PARAMS, DRConfig, stack_view_params
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.render import DRRenderer
from twist_data.rollout import library_versions
from twist_data.schema import DatasetSpec, Episode
from twist_data.seeding import derived_seed
from twist_data.storage import StorageLayout
from twist_data.writer import ShardWriter

log = logging.getLogger(__name__)


def render_blocks(spec: DatasetSpec) -> list[Mapping[str, Any]]:
    """The render provenance blocks of a dataset; raises if it was not rendered by twist."""
    blocks = spec.extra.get("render")
    if not blocks:
        raise ConfigError(f"dataset of task {spec.task!r} has no render provenance "
                          f"(spec.extra['render']); it was not rendered by twist's simulator")
    return list(blocks)


def renderer_for_block(task: str, block: Mapping[str, Any]) -> DRRenderer:
    """A renderer that reproduces the views of one provenance block exactly."""
    start, stop = block["views"]
    renderer = DRRenderer(task, DRConfig.from_json(block["config"]), int(block["image_size"]),
                          views=int(stop) - int(start), supersample=int(block["supersample"]))
    recorded = (block.get("bank") or {}).get("sha256")
    current = renderer.bank.digest() if renderer.bank is not None else None
    if recorded != current:
        renderer.close()
        raise SchemaMismatchError(
            f"background bank for views {start}-{stop} differs from the one recorded with the "
            f"dataset (sha256 {recorded} recorded, {current} now); restore "
            f"{block['config'].get('background_dir') or 'the bank'} to reproduce these frames"
        )
    return renderer


def reproduce_frames(dataset: MatchingDataset, steps: np.ndarray) -> np.ndarray:
    """Re-render global ``steps`` from their stored physics and DR parameters -> [n, K, H, W, 3]."""
    spec = dataset.spec
    steps = np.asarray(steps, np.int64)
    out = np.empty((steps.size, spec.views, *spec.image_shape), np.uint8)
    physics = dataset.column("physics")[steps]
    params = {p.name: dataset.column(f"dr/{p.name}")[steps] for p in VIEW_PARAMS}
    for block in render_blocks(spec):
        start, stop = (int(v) for v in block["views"])
        with renderer_for_block(spec.task, block) as renderer:
            for i in range(steps.size):
                renderer.render(physics[i], {k: v[i, start:stop] for k, v in params.items()},
                                out=out[i, start:stop])
    return out


def check_reproduction(dataset: MatchingDataset, n_steps: int, seed: int = 0) -> list[str]:
    """Re-render ``n_steps`` random steps and list every view whose pixels differ from storage."""
    if dataset.n_steps == 0:
        return []
    rng = np.random.default_rng(seed)
    steps = np.sort(rng.choice(dataset.n_steps, min(n_steps, dataset.n_steps), replace=False))
    rendered = reproduce_frames(dataset, steps)
    problems = []
    k = dataset.spec.views
    stored = np.empty((steps.size * k, *dataset.spec.image_shape), np.uint8)
    dataset.read_frames(np.repeat(steps, k), np.tile(np.arange(k), steps.size), stored)
    stored = stored.reshape(rendered.shape)
    for i, step in enumerate(steps.tolist()):
        for v in range(k):
            diff = np.abs(rendered[i, v].astype(np.int16) - stored[i, v]).max()
            if diff:
                problems.append(f"step {step} view {v}: re-render differs by up to {diff} levels")
    return problems


def rerender_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str], config: DRConfig,
                     views: int = 2, image_size: int | None = None, add_views: bool = False,
                     supersample: int = 1, seed: int = 0, layout: StorageLayout | None = None,
                     episodes: Sequence[int] | None = None,
                     on_episode: Callable[[int, int], None] | None = None) -> Path:
    """Write a new dataset at ``out`` with the states, actions and rewards of ``source`` and
    images rendered under ``config``; with ``add_views`` the source's views are kept and the
    new ones appended. ``episodes``: the source's episode indices to re-render (negative ones
    count from the end; None: all); each episode's DR draws depend on ``seed`` and its index
    in the source alone, so a subset renders exactly as the same episodes of a full
    re-render. The source is only read."""
    if image_size is not None and image_size < 1:
        raise ConfigError(f"image_size must be >= 1 (or omitted for the dataset's), got "
                          f"{image_size}")
    src = open_dataset(source)
    chosen = _episode_indices(episodes, src.n_episodes)
    spec = src.spec
    blocks = render_blocks(spec) if add_views else []
    size = spec.image_height if image_size is None else image_size
    if add_views and size != spec.image_height:
        raise ConfigError(f"added views must match the dataset's image size {spec.image_height}, "
                          f"got {size}")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"output folder {str(out)!r} exists and is not empty")
    kept = spec.views if add_views else 0
    with DRRenderer(spec.task, config, size, views, supersample) as renderer:
        new_block = renderer.provenance(first_view=kept)
        new_spec = dataclasses.replace(
            spec, views=kept + views, image_height=size, image_width=size,
            extra={**spec.extra, "render": [*blocks, new_block], "versions": library_versions(),
                   "rerendered_from": str(Path(source)),
                   **({} if episodes is None else {"rerendered_episodes": chosen})},
        )
        sampler = renderer.sampler(seed)
        writers: dict[str, ShardWriter] = {}
        try:
            for done, index in enumerate(chosen, 1):
                shard, _ = src.episode_location(index)
                name = src.shards[shard].name
                if name not in writers:
                    writers[name] = ShardWriter.create(out, name, new_spec, layout)
                episode, info = src.episode(index), src.episode_info(index)
                new = _render_episode(renderer, sampler, episode, derived_seed(seed, index))
                if add_views:
                    new = _concat_views(episode, new)
                writers[name].append(new, info)
                if on_episode is not None:
                    on_episode(done, len(chosen))
        finally:
            for writer in writers.values():
                writer.close()
    log.info("re-rendered %d episodes of %s into %s", len(chosen), source, out)
    return out


def _episode_indices(episodes: Sequence[int] | None, n_episodes: int) -> list[int]:
    """``episodes`` as sorted, distinct, non-negative indices; all of them for None."""
    if episodes is None:
        return list(range(n_episodes))
    if not episodes:
        raise ConfigError("no episodes chosen to re-render; omit the choice for all of them")
    for index in episodes:
        if not -n_episodes <= index < n_episodes:
            raise ConfigError(f"the dataset has {n_episodes} episodes; index {index} is out "
                              "of range")
    return sorted({index % n_episodes for index in episodes})


def _render_episode(renderer: DRRenderer, sampler: Any, episode: Episode, seed: int) -> Episode:
    sampler.begin_episode(seed)  # dynamics are the source's: physics cannot be re-simulated here
    t = len(episode)
    images = np.empty((t, renderer.views, renderer.image_size, renderer.image_size, 3), np.uint8)
    params = []
    for i in range(t):
        params.append(sampler.sample())
        renderer.render(episode.physics[i], params[-1], out=images[i])
    return dataclasses.replace(episode, image=images, dr=stack_view_params(params))


def _concat_views(old: Episode, new: Episode) -> Episode:
    if set(old.dr) != set(new.dr):
        raise SchemaMismatchError(f"cannot add views: the dataset's DR parameters {sorted(old.dr)} "
                                  f"differ from the renderer's {sorted(new.dr)}")
    return dataclasses.replace(old, image=np.concatenate([old.image, new.image], 1),
                               dr={k: np.concatenate([old.dr[k], new.dr[k]], 1) for k in old.dr})


