"""Re-rendering a dataset from its stored physics states: reproduce, re-randomise, add views.

A dataset written through :func:`twist_sim.rollout.simulated_spec` records, in
``spec.extra["render"]``, one block per range of views: the DR config, image size, supersampling
and a digest of the background bank. With the stored ``data/physics`` and ``data/dr/*`` that
is everything needed to redraw a frame, so images can be regenerated under a new DR config (or
extended with more views) without re-training a teacher.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing
import os
import queue
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twist_data.errors import ConfigError, SchemaMismatchError
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.schema import PAIR_IMAGE, DatasetSpec, Episode, image_digest, step_arrays
from twist_data.seeding import derived_seed
from twist_data.staging import built_aside, require_new_folder
from twist_data.storage import StorageLayout
from twist_data.writer import ShardWriter
from twist_sim.randomisation import VIEW_PARAMS, DRConfig, stack_view_params
from twist_sim.render import DRRenderer, background_bank, camera_pose
from twist_sim.rollout import library_versions
from twist_sim.tasks import task_spec

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
    check_bank(block)
    start, stop = block["views"]
    renderer = DRRenderer(task, DRConfig.from_json(block["config"]), int(block["image_size"]),
                          views=int(stop) - int(start), supersample=int(block["supersample"]))
    recorded = block.get("camera_pose")  # absent in datasets rendered before it was recorded
    current = camera_pose(renderer.model, renderer.spec.camera)
    if recorded is not None and recorded != current:
        renderer.close()
        raise SchemaMismatchError(
            f"views {start}-{stop} were rendered from camera pose {recorded} but task {task!r} "
            f"now renders from {current}; re-rendering them would not reproduce the dataset")
    return renderer


def check_bank(block: Mapping[str, Any]) -> None:
    """Raise unless the background bank a render block names can be rebuilt as recorded
    (its SHA-256), without opening a GL context: a procedural bank is regenerated, a folder
    must be present and unchanged."""
    start, stop = block["views"]
    config = DRConfig.from_json(block["config"])
    side = int(block["image_size"]) * int(block["supersample"])
    bank = background_bank(config, 2 * side)
    recorded = (block.get("bank") or {}).get("sha256")
    current = bank.digest() if bank is not None else None
    if recorded != current:
        raise SchemaMismatchError(
            f"background bank for views {start}-{stop} differs from the one recorded with the "
            f"dataset (sha256 {recorded} recorded, {current} now); restore "
            f"{block['config'].get('background_dir') or 'the bank'} to reproduce these frames"
        )


def reproduce_frames(dataset: MatchingDataset, steps: np.ndarray) -> np.ndarray:
    """Re-render global ``steps`` from their stored physics and DR parameters -> [n, K, H, W, 3]."""
    steps = np.asarray(steps, np.int64)
    return _redraw(dataset, steps, steps)


def reproduce_pairs(dataset: MatchingDataset, steps: np.ndarray) -> np.ndarray:
    """The pair frames (:func:`pair_frames`) of global ``steps``, redrawn from the stored
    physics and DR draws -> [n, K, H, W, 3]: what ``data/pair_image`` holds there."""
    steps = np.asarray(steps, np.int64)
    first = dataset.column("is_first")[steps].astype(bool)
    return _redraw(dataset, np.where(first, steps, steps - 1), steps)


def _redraw(dataset: MatchingDataset, instants: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """The physics of global steps ``instants`` [n], each drawn under the DR parameters of
    the step ``draws`` [n] with every render block's renderer -> [n, K, H, W, 3]."""
    spec = dataset.spec
    out = np.empty((draws.size, spec.views, *spec.image_shape), np.uint8)
    physics = dataset.column("physics")[instants]
    params = {p.name: dataset.column(f"dr/{p.name}")[draws] for p in VIEW_PARAMS}
    for block in render_blocks(spec):
        start, stop = (int(v) for v in block["views"])
        with renderer_for_block(spec.task, block) as renderer:
            for i in range(draws.size):
                renderer.render(physics[i], {k: v[i, start:stop] for k, v in params.items()},
                                out=out[i, start:stop])
    return out


def check_reproduction(dataset: MatchingDataset, n_steps: int, seed: int = 0) -> list[str]:
    """Re-render ``n_steps`` random steps and list every view whose pixels differ from storage."""
    if n_steps < 0:
        raise ConfigError(f"the number of steps to re-render must be >= 0, got {n_steps}")
    dataset.require_images("comparing re-renders with the stored frames")
    recorded = {a.name for a in step_arrays(dataset.spec)}
    missing = [key for key in ("physics", *(f"dr/{p.name}" for p in VIEW_PARAMS))
               if key not in recorded]
    if missing:
        raise ConfigError(f"{str(dataset.path)!r} was not rendered by twist's simulator: it "
                          f"records no {missing[0]} to re-render from")
    if dataset.n_steps == 0:
        return []
    rng = np.random.default_rng(seed)
    steps = np.sort(rng.choice(dataset.n_steps, min(n_steps, dataset.n_steps), replace=False))
    problems = _differences(dataset, steps, reproduce_frames(dataset, steps), "image",
                            "re-render")
    if dataset.has_pairs:
        problems += _differences(dataset, steps, reproduce_pairs(dataset, steps), PAIR_IMAGE,
                                 "the redrawn pair frame")
    return problems


def _differences(dataset: MatchingDataset, steps: np.ndarray, redrawn: np.ndarray, key: str,
                 what: str) -> list[str]:
    """Every view of ``steps`` whose ``redrawn`` frame [n, K, H, W, 3] differs from the frame
    array ``key`` stores, in one line each."""
    k = dataset.spec.views
    stored = np.empty((steps.size * k, *dataset.spec.image_shape), np.uint8)
    dataset.read_frames(np.repeat(steps, k), np.tile(np.arange(k), steps.size), stored, key=key)
    stored = stored.reshape(redrawn.shape)
    problems = []
    for i, step in enumerate(steps.tolist()):
        for v in range(k):
            diff = np.abs(redrawn[i, v].astype(np.int16) - stored[i, v]).max()
            if diff:
                problems.append(f"step {step} view {v}: {what} differs by up to {diff} levels")
    return problems


def rerender_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str], config: DRConfig,
                     views: int = 2, image_size: int | None = None, add_views: bool = False,
                     supersample: int = 1, seed: int = 0, layout: StorageLayout | None = None,
                     episodes: Sequence[int] | None = None,
                     on_episode: Callable[[int, int], None] | None = None,
                     pairs: bool = False) -> Path:
    """Write a new dataset at ``out`` with the states, actions and rewards of ``source`` and
    images rendered under ``config``; with ``add_views`` the source's views are kept and the
    new ones appended. ``episodes``: the source's episode indices to re-render (negative ones
    count from the end; None: all); each episode's DR draws depend on ``seed`` and its index
    in the source alone, so a subset renders exactly as the same episodes of a full
    re-render. ``pairs``: the new dataset stores frame pairs (:func:`pair_frames`); views
    added to a source that stores pairs get theirs too. The source is only read."""
    if image_size is not None and image_size < 1:
        raise ConfigError(f"image_size must be >= 1 (or omitted for the dataset's), got "
                          f"{image_size}")
    src = open_dataset(source)
    chosen = _episode_indices(episodes, src.n_episodes)
    spec = src.spec
    if add_views:
        src.require_images("adding views to the stored ones")
        if pairs and not src.has_pairs:
            src.require_pairs("adding views with frame pairs")
        pairs = src.has_pairs
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
            extra={**spec.extra, "render": [*blocks, new_block],
                   "versions": {**library_versions(), **renderer.gl_info()},
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
                    writers[name] = ShardWriter.create(out, name, new_spec, layout, pairs)
                episode, info = src.episode(index, images=add_views), src.episode_info(index)
                new = _render_episode(renderer, sampler, episode, derived_seed(seed, index),
                                      pairs)
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


@dataclass
class ReproduceReport:
    """What :func:`reproduce_dataset` rebuilt, and whether it equals what was recorded."""

    out: Path
    source: str = ""
    episodes: int = 0
    identical: list[int] = field(default_factory=list)
    """Global episodes whose rebuilt frames equal the recorded ones bit for bit (the stored
    frames of a full D, the digests of a stripped one)."""
    differing: list[int] = field(default_factory=list)
    gl: dict[str, str] = field(default_factory=dict)
    """The OpenGL implementation that drew the rebuilt frames."""
    seconds: float = 0.0
    workers: int = 1

    @property
    def exact(self) -> bool:
        return not self.differing

    def to_json(self) -> dict[str, Any]:
        return {"source": self.source, "episodes": self.episodes,
                "identical": len(self.identical), "differing": self.differing, "gl": self.gl,
                "seconds": round(self.seconds, 2), "workers": self.workers}


def reproduce_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str],
                      workers: int = 1, episodes: Sequence[int] | None = None,
                      on_episode: Callable[[int, int], None] | None = None,
                      pairs: bool | None = None) -> ReproduceReport:
    """Rebuild the images of ``source`` (a full or a stripped D) from its stored physics, DR
    draws and render settings (every render block's image size, supersampling, views and
    bank) into the new dataset ``out``, in ``workers`` processes.

    One worker writes shards named as the source's; ``workers`` > 1 split the episodes into
    that many contiguous blocks, each written by its own process into shards named
    ``<source shard>-<block>``, so that shard-name order keeps every episode's global index
    (and with it the held-out split). Each episode's frames are compared with the recorded
    ones by digest; frames that differ (another GL implementation draws other pixels) are
    kept and reported. ``episodes``: the source's episodes to rebuild (negative ones count
    from the end; None: all), recorded as ``extra["rerendered_episodes"]``. ``pairs``: whether
    ``out`` stores frame pairs (:func:`pair_frames`; None: as the source did, stripped or
    not). ``out`` also gets
    the report as :data:`REPORT` (readers ignore files beside the shards). Built under a
    hidden name and renamed into place: a failure leaves nothing at ``out``."""
    if workers < 1:
        raise ConfigError(f"workers must be at least 1 process, got {workers}")
    out = Path(out)
    require_new_folder(out)
    src = open_dataset(source)
    blocks = render_blocks(src.spec)
    task_spec(src.spec.task)  # an unknown task is refused before anything is written
    for block in blocks:
        check_bank(block)
    if src.n_episodes == 0:
        raise ConfigError(f"dataset {str(source)!r} has no committed episode to rebuild")
    chosen = _episode_indices(episodes, src.n_episodes)
    if pairs is None:
        pairs = src.has_pairs or src.shards[0].images.pairs
    parts = _reproduction_plan(src, chosen, workers)
    report = ReproduceReport(out, str(source), workers=len(parts))
    started = time.perf_counter()
    with built_aside(out, "reproducing") as staging:
        subset = None if episodes is None else chosen
        if len(parts) == 1:
            results = _reproduce_part(str(source), str(staging), parts[0], subset, pairs, None,
                                      on_episode, len(chosen))
        else:
            results = _reproduce_in_processes(str(source), str(staging), parts, subset, pairs,
                                              on_episode, len(chosen))
        report.seconds = time.perf_counter() - started
        for index, rebuilt, recorded, gl in sorted(results):
            report.episodes += 1
            report.gl = gl
            (report.identical if rebuilt == recorded else report.differing).append(index)
        (staging / REPORT).write_text(json.dumps(report.to_json(), indent=2))
    if report.differing:
        log.warning("%d of %d rebuilt episodes differ from the recorded frames (first: %d); "
                    "they were drawn by %s", len(report.differing), report.episodes,
                    report.differing[0], report.gl.get("gl_renderer", "an unknown GL"))
    log.info("rebuilt %d episodes of %s into %s in %.1f s with %d worker(s)", report.episodes,
             source, out, report.seconds, report.workers)
    return report


#: The reproduction's report, written beside the rebuilt shards.
REPORT = "reproduction.json"
#: One rebuilt episode: (global index, digest of the rebuilt frames, the recorded digest, GL).
Rebuilt = tuple[int, str, str, dict[str, str]]


def _reproduction_plan(src: MatchingDataset, chosen: list[int], workers: int
                       ) -> list[list[tuple[int, str]]]:
    """Per worker, its (global episode, output shard name) pairs: contiguous blocks of the
    ``chosen`` (sorted) episodes."""
    n = len(chosen)
    workers = min(workers, n)
    bounds = np.linspace(0, n, workers + 1).round().astype(int)
    parts = []
    for w in range(workers):
        jobs = []
        for index in chosen[int(bounds[w]):int(bounds[w + 1])]:
            name = src.shards[src.episode_location(index)[0]].name
            jobs.append((index, name if workers == 1 else f"{name}-{w:03d}"))
        parts.append(jobs)
    return parts


def _reproduce_part(source: str, staging: str, jobs: list[tuple[int, str]],
                    subset: list[int] | None, pairs: bool, progress: Any,
                    on_episode: Callable[[int, int], None] | None = None,
                    total: int = 0) -> list[Rebuilt]:
    """Rebuild ``jobs`` into shards under ``staging``; each finished episode is put on the
    ``progress`` queue (a worker process) or reported to ``on_episode`` (in-process)."""
    src = open_dataset(source)
    spec = src.spec
    blocks = render_blocks(spec)
    renderers = [renderer_for_block(spec.task, block) for block in blocks]
    gl = renderers[0].gl_info()
    new_spec = dataclasses.replace(spec, extra={
        **spec.extra, "versions": {**library_versions(), **gl}, "reproduced_from": source,
        **({} if subset is None else {"rerendered_episodes": subset})})
    writers: dict[str, ShardWriter] = {}
    results: list[Rebuilt] = []
    try:
        for done, (index, name) in enumerate(jobs, 1):
            shard_index, local = src.episode_location(index)
            shard = src.shards[shard_index]
            episode = shard.episode(local, images=False)
            images = np.empty((len(episode), spec.views, *spec.image_shape), np.uint8)
            pair = np.empty_like(images) if pairs else None
            for block, renderer in zip(blocks, renderers, strict=True):
                a, b = (int(v) for v in block["views"])
                for t in range(len(episode)):
                    params = {k: v[t, a:b] for k, v in episode.dr.items()}
                    renderer.render(episode.physics[t], params, out=images[t, a:b])
                    if pair is not None:
                        pair_frames(renderer, episode.physics, t, params, pair[t, a:b])
            if shard.has_images:
                first, last = int(shard.episode_starts[local]), int(shard.episode_ends[local])
                recorded = image_digest(shard.read("image", first, last))
            else:
                recorded = shard.images.sha256[local]
            if name not in writers:
                writers[name] = ShardWriter.create(staging, name, new_spec, shard.layout, pairs)
            writers[name].append(dataclasses.replace(episode, image=images, pair_image=pair),
                                 src.episode_info(index))
            results.append((index, image_digest(images), recorded, gl))
            if progress is not None:
                progress.put(1)
            elif on_episode is not None:
                on_episode(done, total)
    finally:
        for writer in writers.values():
            writer.close()
        for renderer in renderers:
            renderer.close()
    return results


def _reproduce_in_processes(source: str, staging: str, parts: list[list[tuple[int, str]]],
                            subset: list[int] | None, pairs: bool,
                            on_episode: Callable[[int, int], None] | None,
                            total: int) -> list[Rebuilt]:
    # Spawned, not forked: each worker opens its own GL context, which a fork cannot share.
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager, ProcessPoolExecutor(len(parts), mp_context=context) as pool:
        progress = manager.Queue()
        futures = [pool.submit(_reproduce_part, source, staging, jobs, subset, pairs, progress)
                   for jobs in parts]
        done = 0
        while True:
            finished, pending = wait(futures, timeout=0.2, return_when=FIRST_EXCEPTION)
            while True:
                try:
                    done += progress.get_nowait()
                except queue.Empty:
                    break
            if on_episode is not None and done:
                on_episode(done, total)
            failed = [f for f in finished if f.exception() is not None]
            if failed:
                for future in pending:
                    future.cancel()
                raise failed[0].exception()
            if not pending:
                return [r for future in futures for r in future.result()]


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


def _render_episode(renderer: DRRenderer, sampler: Any, episode: Episode, seed: int,
                    pairs: bool = False) -> Episode:
    sampler.begin_episode(seed)  # dynamics are the source's: physics cannot be re-simulated here
    t = len(episode)
    images = np.empty((t, renderer.views, renderer.image_size, renderer.image_size, 3), np.uint8)
    params = []
    for i in range(t):
        params.append(sampler.sample())
        renderer.render(episode.physics[i], params[-1], out=images[i])
    pair = None
    if pairs:
        pair = np.empty_like(images)
        for i in range(t):
            pair_frames(renderer, episode.physics, i, params[i], pair[i])
    return dataclasses.replace(episode, image=images, dr=stack_view_params(params),
                               pair_image=pair)


def pair_instant(t: int) -> int:
    """The instant step ``t``'s pair frame draws (under step ``t``'s draw): the step before,
    or ``t`` itself at the episode's first step, where nothing came before."""
    return max(t - 1, 0)


def pair_frames(renderer: DRRenderer, physics: np.ndarray, t: int,
                params: Mapping[str, np.ndarray], out: np.ndarray) -> np.ndarray:
    """Step ``t``'s pair frames (datasets.md, §2 ``pair_image``): the step before drawn
    under step ``t``'s draw ``params`` as its own frame (camera and lights where they stood
    then), or step ``t`` itself at the episode's first step; ``physics`` [T, P] is the
    episode's -> ``out`` [K, H, W, 3].

    Why: acting holds one scene per episode, so the frame before a step is that scene at the
    step before, seen from where a tracking camera stood then; D draws a new scene at every
    step, and this draws the step before again in this step's scene."""
    return renderer.render(physics[pair_instant(t)], params, out=out)


def _concat_views(old: Episode, new: Episode) -> Episode:
    if set(old.dr) != set(new.dr):
        raise SchemaMismatchError(f"cannot add views: the dataset's DR parameters {sorted(old.dr)} "
                                  f"differ from the renderer's {sorted(new.dr)}")
    pair = None
    if old.pair_image is not None and new.pair_image is not None:
        pair = np.concatenate([old.pair_image, new.pair_image], 1)
    return dataclasses.replace(old, image=np.concatenate([old.image, new.image], 1),
                               dr={k: np.concatenate([old.dr[k], new.dr[k]], 1) for k in old.dr},
                               pair_image=pair)


