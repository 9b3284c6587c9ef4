"""Random training windows: L consecutive steps of one episode, one view per step.

* Starts are uniform over all valid starts of all episodes (a window never crosses an
  episode boundary) without a table of starts: per-episode counts, a cumulative sum over
  episodes and a binary search.
* Several streams (DataLoader workers x distributed ranks) draw from disjoint sets of
  windows: stream j of P only draws flat start indices congruent to j modulo P. The union of
  the streams is uniform, and each stream is deterministic under the seed.
* Images are decoded on demand into a bounded FIFO arena of decoded frames (``cache_bytes``);
  with uniform access, FIFO evicts as well as LRU and allows vectorised hit lookup. Low-
  dimensional arrays (about 100 bytes per step) are held in memory; images never are beyond
  the arena, so a dataset far larger than RAM is read with bounded memory.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from twist_data.errors import DatasetCorruptError, SamplerConfigError
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.schema import FRAME_ARRAYS, PAIR_IMAGE, step_arrays

log = logging.getLogger(__name__)

SPLITS = ("all", "train", "heldout")
DEFAULT_KEYS = ("image", "state", "action", "reward", "discount", "is_first", "is_last",
                "is_terminal")


def heldout_episodes(n_episodes: int, every: int) -> np.ndarray:
    """The held-out split: a boolean mask [n_episodes], True for every ``every``-th episode
    (global index % every == every - 1), so it stays fixed as a dataset grows."""
    return np.arange(n_episodes) % every == every - 1


@dataclass(frozen=True)
class SamplerConfig:
    """How windows are drawn and batched."""

    #: Removed switches and the value that meant "off" (twist_models.config.removed_fields):
    #: a draw favouring rare states lowered the student's return (docs/findings.md).
    REMOVED: ClassVar[dict[str, Any]] = {"rare_states": 0.0}

    length: int = 50
    """L: steps per window (the paper's distillation windows are 50)."""
    batch_size: int = 16
    """Windows per batch."""
    view: int | None = None
    """Fixed view index for every step, or None for a uniformly random view per step."""
    seed: int = 0
    """Seed of the window and view draws."""
    keys: tuple[str, ...] = DEFAULT_KEYS
    """Per-step arrays to return (``physics`` and ``dr/<name>`` are available too)."""
    cache_bytes: int = 1 << 30
    """Budget of the decoded-frame arena per sampler (per DataLoader worker); 0 disables it."""
    refresh_every: int = 0
    """Re-read the dataset for new commits every this many batches; 0: only on refresh()."""
    holdout_every: int = 0
    """Every n-th episode (global index % n == n - 1) is held out; 0: none. The split is
    stable as a dataset grows, so held-out episodes stay held out."""
    split: str = "all"
    """Episodes windows come from: ``all``, ``train`` (not held out) or ``heldout``."""

    def __post_init__(self) -> None:
        problems = []
        if self.length < 1:
            problems.append(f"window length must be >= 1, got {self.length}")
        if self.batch_size < 1:
            problems.append(f"batch size must be >= 1, got {self.batch_size}")
        if self.view is not None and self.view < 0:
            problems.append(f"view index must be >= 0, got {self.view}")
        if self.cache_bytes < 0 or self.refresh_every < 0:
            problems.append("cache_bytes and refresh_every must be >= 0")
        if self.split not in SPLITS:
            problems.append(f"split must be one of {', '.join(SPLITS)}, got {self.split!r}")
        elif self.split != "all" and self.holdout_every < 2:
            problems.append(f"split {self.split!r} needs holdout_every >= 2, got "
                            f"{self.holdout_every}")
        if len(set(self.keys)) != len(self.keys) or not self.keys:
            problems.append(f"keys must be non-empty and unique, got {self.keys}")
        if problems:
            raise SamplerConfigError("; ".join(problems))


class FrameCache:
    """Bounded FIFO arena of decoded frames, keyed by global frame id (step * K + view)."""

    def __init__(self, capacity: int, frame_shape: tuple[int, ...]) -> None:
        self.capacity = capacity
        self.frame_shape = frame_shape
        self._arena: np.ndarray | None = None  # allocated on first use (in the worker)
        self._slot_of = np.zeros(0, np.int64)
        self._owner = np.full(capacity, -1, np.int64)
        self._next = 0
        self.hits = 0
        self.lookups = 0

    def clear(self, n_frames: int) -> None:
        self._slot_of = np.full(n_frames, -1, np.int64)
        self._owner[:] = -1
        self._next = 0

    def fetch(self, dataset: MatchingDataset, steps: np.ndarray, views: np.ndarray,
              out: np.ndarray) -> None:
        """Fill ``out[i]`` with frame (steps[i], views[i]), decoding only what is not cached."""
        k = dataset.spec.views
        ids = steps * k + views
        self.lookups += ids.size
        if self.capacity == 0:
            dataset.read_frames(steps, views, out)
            return
        if self._arena is None:
            self._arena = np.empty((self.capacity, *self.frame_shape), np.uint8)
        if self._slot_of.size < dataset.n_steps * k:
            self._slot_of = np.concatenate(
                [self._slot_of, np.full(dataset.n_steps * k - self._slot_of.size, -1, np.int64)])
        slots = self._slot_of[ids]
        hit = slots >= 0
        n_hit = int(hit.sum())
        self.hits += n_hit
        if n_hit:
            # One gather straight into out; rows that missed get slot 0 and are overwritten
            # by the decoder below (cheaper than a masked gather plus scatter).
            # mode="clip": indices are valid by construction, and numpy buffers `out` for
            # the default mode="raise", which would copy every frame twice.
            np.take(self._arena, np.where(hit, slots, 0), axis=0, out=out, mode="clip")
        if n_hit == ids.size:
            return
        miss_rows = np.flatnonzero(~hit)
        new_ids, first, inverse = np.unique(ids[miss_rows], return_index=True,
                                            return_inverse=True)
        first_rows = miss_rows[first]
        dataset.read_frames(steps[first_rows], views[first_rows], out, first_rows)
        out[miss_rows] = out[first_rows[inverse]]  # duplicates within the batch
        keep = min(new_ids.size, self.capacity)
        new_ids, first_rows = new_ids[-keep:], first_rows[-keep:]
        slot = (self._next + np.arange(keep)) % self.capacity
        evicted = self._owner[slot]
        self._slot_of[evicted[evicted >= 0]] = -1
        self._owner[slot] = new_ids
        self._slot_of[new_ids] = slot
        self._arena[slot] = out[first_rows]
        self._next = int((self._next + keep) % self.capacity)


def image_problem(dataset: MatchingDataset) -> str | None:
    """Why ``dataset``'s images cannot be read (each shard's first frame is tried), or None:
    a trainer asks before it writes anything."""
    frame = np.empty((1, *dataset.spec.image_shape), np.uint8)
    try:
        for shard_start in dataset.shard_offsets[:-1]:
            dataset.read_frames(np.array([shard_start]), np.array([0]), frame)
    except Exception as exc:  # zarr and the codecs raise assorted types for missing chunks
        return f"it has no readable images ({type(exc).__name__}: {exc})"
    return None


def window_problem(dataset: MatchingDataset, length: int, view: int | None) -> str | None:
    """Why windows of ``length`` steps showing ``view`` (None: any) cannot be drawn from
    ``dataset`` at all, in one sentence; None when they can. The one check behind every
    command that samples windows (a split may still leave too few: see WindowSampler)."""
    spec = dataset.spec
    if view is not None and not 0 <= view < spec.views:
        return (f"view index {view} is out of range: the dataset has {spec.views} views "
                f"(valid: 0..{spec.views - 1})")
    lengths = dataset.episode_lengths
    longest = int(lengths.max()) if lengths.size else 0
    if length > longest:
        return (f"window length {length} is longer than every episode (the longest has "
                f"{longest} steps)")
    return None


class WindowSampler:
    """Draws batches of windows from a dataset; one of ``n_streams`` disjoint streams.

    A batch is a dict of arrays: ``image`` uint8 [B, L, H, W, 3], ``state`` float32 [B, L, S],
    ``action`` float32 [B, L, A], ``reward``/``discount`` float32 [B, L], flags bool [B, L],
    plus ``view`` int64 [B, L] (the view shown at each step), ``start`` int64 [B] (global step
    of each window's first step) and ``episode`` int64 [B] (global episode index).
    """

    def __init__(self, dataset: MatchingDataset | str | os.PathLike[str],
                 config: SamplerConfig | None = None, stream: int = 0, n_streams: int = 1) -> None:
        self.dataset = dataset if isinstance(dataset, MatchingDataset) else open_dataset(dataset)
        self.config = config = config or SamplerConfig()
        if not 0 <= stream < n_streams:
            raise SamplerConfigError(f"stream {stream} is out of range for {n_streams} streams")
        self.stream, self.n_streams = stream, n_streams
        spec = self.dataset.spec
        # The view here; the length below, per split (a split may hold only short episodes).
        problem = window_problem(self.dataset, 1, config.view)
        if problem is not None:
            raise SamplerConfigError(problem)
        if PAIR_IMAGE in config.keys:
            self.dataset.require_pairs("windows with frame pairs")
        self._per_view = {a.name: a.per_view for a in step_arrays(spec, self.dataset.has_pairs)}
        unknown = [k for k in config.keys if k not in self._per_view]
        if unknown:
            raise SamplerConfigError(
                f"unknown key {unknown[0]!r}; valid: {', '.join(sorted(self._per_view))}"
            )
        frame_bytes = int(np.prod(spec.image_shape))
        self.cache = FrameCache(config.cache_bytes // frame_bytes, spec.image_shape)
        seq = np.random.SeedSequence(config.seed, spawn_key=(n_streams, stream))
        self._rng = np.random.default_rng(seq)
        self._batches = 0
        self._reindex()

    def _reindex(self) -> None:
        lengths = self.dataset.episode_lengths
        cfg = self.config
        valid = np.maximum(lengths - cfg.length + 1, 0)
        where = ""
        if cfg.split != "all":
            held = heldout_episodes(lengths.size, cfg.holdout_every)
            chosen = held if cfg.split == "heldout" else ~held
            valid, lengths = np.where(chosen, valid, 0), lengths[chosen]
            where = f" of the {cfg.split} split ({lengths.size} episodes)"
        self._cum_valid = np.cumsum(valid)
        self.total_windows = int(self._cum_valid[-1]) if valid.size else 0
        if self.total_windows == 0:
            longest = int(lengths.max()) if lengths.size else 0
            raise SamplerConfigError(
                f"window length {cfg.length} is longer than every episode{where} "
                f"(the longest has {longest} steps)"
            )
        if self.total_windows < self.n_streams:
            raise SamplerConfigError(
                f"the dataset has {self.total_windows} windows of length {self.config.length}, "
                f"fewer than the {self.n_streams} sampler streams"
            )
        self._columns = {k: self.dataset.column(k) for k in self.config.keys
                         if k not in FRAME_ARRAYS}
        # Damage under valid checksums (a flag moved, a NaN, a rewritten reward) would be
        # served as data: the rules are checked on the columns just read.
        problem = self.dataset.rule_problem(tuple(k for k in ("state", "action")
                                                  if k in self._columns))
        if problem is not None:
            raise DatasetCorruptError(problem)
        self.cache.clear(self.dataset.n_steps * self.dataset.spec.views)

    def refresh(self) -> int:
        """Pick up newly committed episodes; returns how many arrived."""
        new = self.dataset.refresh()
        if new:
            self._reindex()
        return new

    @property
    def rng_state(self) -> dict:
        """The draw generator's state (JSON-safe), to resume a stream exactly."""
        return self._rng.bit_generator.state

    @rng_state.setter
    def rng_state(self, state: dict) -> None:
        self._rng.bit_generator.state = state

    def flat_to_start(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map flat window indices to (global start step, global episode index)."""
        episode = np.searchsorted(self._cum_valid, flat, side="right")
        before = np.where(episode > 0, self._cum_valid[episode - 1], 0)
        return self.dataset.episode_starts[episode] + (flat - before), episode

    def sample_starts(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``n`` windows of this stream: (global start step [n], global episode [n])."""
        p, j = self.n_streams, self.stream
        count = (self.total_windows - j + p - 1) // p
        return self.flat_to_start(j + p * self._rng.integers(0, count, n))

    def draw(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The next batch's windows without reading them: (global start step [B], global
        episode [B], steps [B, L], views [B, L]). :meth:`batch` reads what this draws; a
        reader of another copy of D (:class:`ResidentWindows`) draws the same stream."""
        cfg = self.config
        self._batches += 1
        b, length, k = cfg.batch_size, cfg.length, self.dataset.spec.views
        starts, episode = self.sample_starts(b)
        steps = starts[:, None] + np.arange(length)
        if cfg.view is None:
            views = self._rng.integers(0, k, (b, length))
        else:
            views = np.full((b, length), cfg.view, np.int64)
        return starts, episode, steps, views

    def batch(self, image_out: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The next batch of windows; images are decoded into ``image_out`` when given.

        ``image_out`` ([B, L, H, W, 3] uint8) lets a DataLoader worker decode straight into
        shared memory instead of having the batch copied there afterwards.
        """
        cfg = self.config
        if cfg.refresh_every and self._batches and self._batches % cfg.refresh_every == 0:
            self.refresh()
        b, length = cfg.batch_size, cfg.length
        starts, episode, steps, views = self.draw()
        out: dict[str, np.ndarray] = {}
        for key in cfg.keys:
            if key == "image":
                shape = (b, length, *self.dataset.spec.image_shape)
                if image_out is None:
                    image_out = np.empty(shape, np.uint8)
                elif image_out.shape != shape or image_out.dtype != np.uint8:
                    raise SamplerConfigError(
                        f"image_out must be uint8 {shape}, got {image_out.dtype} {image_out.shape}"
                    )
                frames = image_out.reshape(b * length, *shape[2:])
                self.cache.fetch(self.dataset, steps.ravel(), views.ravel(), frames)
                out[key] = image_out
            elif key == PAIR_IMAGE:  # each step's pair frame in the view its image shows
                pair = np.empty((b, length, *self.dataset.spec.image_shape), np.uint8)
                self.dataset.read_frames(steps.ravel(), views.ravel(),
                                         pair.reshape(b * length, *pair.shape[2:]), key=key)
                out[key] = pair
            elif self._per_view[key]:
                out[key] = self._columns[key][steps, views]
            else:
                out[key] = self._columns[key][steps]
        out["view"] = views
        out["start"] = starts
        out["episode"] = episode
        return out

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        while True:
            yield self.batch()


class ResidentWindows:
    """Windows gathered from a copy of all of D held in one tensor per array on ``device``
    (images decoded once, uint8): no decoding or host-to-device copy per batch, for a GPU on
    which D fits. The windows are :class:`WindowSampler`'s stream for the same config, seed
    and stream, drawn by it and gathered here; D must not grow meanwhile (``refresh_every``
    0). :func:`resident_bytes` says what the copy needs."""

    def __init__(self, dataset: MatchingDataset | str | os.PathLike[str],
                 config: SamplerConfig, device: torch.device | str = "cpu",
                 stream: int = 0, n_streams: int = 1) -> None:
        if config.refresh_every:
            raise SamplerConfigError("a resident copy of D cannot follow a growing dataset; "
                                     f"refresh_every must be 0, got {config.refresh_every}")
        self.sampler = WindowSampler(dataset, config, stream, n_streams)
        data, self.device = self.sampler.dataset, torch.device(device)
        self.columns: dict[str, torch.Tensor] = {}
        for key in config.keys:
            if key in FRAME_ARRAYS:
                continue
            self.columns[key] = torch.as_tensor(data.column(key)).to(self.device)
        self.frames = {key: resident_images(data, self.device, key) for key in FRAME_ARRAYS
                       if key in config.keys}
        self.images = self.frames.get("image")

    def batch(self) -> dict[str, torch.Tensor]:
        """The next batch as tensors on the device, keys as :meth:`WindowSampler.batch`."""
        starts, episode, steps, views = self.sampler.draw()
        index = torch.as_tensor(steps, device=self.device)
        view = torch.as_tensor(views, device=self.device)
        out: dict[str, torch.Tensor] = {}
        for key in self.sampler.config.keys:
            if key in self.frames:
                out[key] = self.frames[key][index, view]
            elif self.sampler._per_view[key]:
                out[key] = self.columns[key][index, view]
            else:
                out[key] = self.columns[key][index]
        out.update(view=view, start=torch.as_tensor(starts, device=self.device),
                   episode=torch.as_tensor(episode, device=self.device))
        return out

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        while True:
            yield self.batch()


def resident_images(dataset: MatchingDataset, device: torch.device | str = "cpu",
                    key: str = "image") -> torch.Tensor:
    """Every frame of ``dataset``'s frame array ``key`` decoded once -> uint8 [steps, views,
    H, W, 3] on ``device`` (``resident_bytes(dataset, (key,))`` bytes)."""
    spec = dataset.spec
    images = np.empty((dataset.n_steps, spec.views, *spec.image_shape), np.uint8)
    chunk = np.empty((4096, *spec.image_shape), np.uint8)  # readers fill contiguous rows
    for view in range(spec.views):
        for lo in range(0, dataset.n_steps, len(chunk)):
            steps = np.arange(lo, min(lo + len(chunk), dataset.n_steps))
            dataset.read_frames(steps, np.full(steps.size, view), chunk[:steps.size], key=key)
            images[steps, view] = chunk[:steps.size]
    return torch.from_numpy(images).to(device)


def resident_bytes(dataset: MatchingDataset, keys: tuple[str, ...]) -> int:
    """Bytes a :class:`ResidentWindows` copy of ``dataset``'s ``keys`` takes."""
    spec, total = dataset.spec, 0
    for array in step_arrays(spec, dataset.has_pairs):
        if array.name not in keys:
            continue
        if array.name in FRAME_ARRAYS:
            total += dataset.n_steps * spec.views * int(np.prod(spec.image_shape))
        else:
            total += dataset.column(array.name).nbytes
    return total


def _rank_and_world(rank: int | None, world_size: int | None) -> tuple[int, int]:
    if rank is not None and world_size is not None:
        return rank, world_size
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class WindowDataset(IterableDataset):
    """PyTorch view of :class:`WindowSampler`: yields batches as tensors, forever.

    Use with ``DataLoader(ds, batch_size=None, num_workers=n)``. Each (rank, worker) pair
    becomes one disjoint stream; rank and world size come from ``torch.distributed`` when it
    is initialised, or from the arguments. The dataset is opened inside each worker.
    """

    def __init__(self, path: str | os.PathLike[str], config: SamplerConfig | None = None,
                 rank: int | None = None, world_size: int | None = None) -> None:
        super().__init__()
        self.path = Path(path)
        self.config = config or SamplerConfig()
        self.rank, self.world_size = rank, world_size
        open_dataset(self.path)  # fail early, in the caller's process, on a bad path

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        rank, world = _rank_and_world(self.rank, self.world_size)
        sampler = WindowSampler(self.path, self.config, stream=rank * workers + worker,
                                n_streams=world * workers)
        spec = sampler.dataset.spec
        shape = (self.config.batch_size, self.config.length, *spec.image_shape)
        while True:
            image = None
            if "image" in self.config.keys:
                image = torch.empty(shape, dtype=torch.uint8)
                if info is not None:
                    # Decode straight into shared memory: the DataLoader then passes a handle
                    # to the main process instead of copying ~10 MB per batch.
                    image.share_memory_()
            batch = sampler.batch(None if image is None else image.numpy())
            out = {k: torch.from_numpy(v) for k, v in batch.items() if k != "image"}
            if image is not None:
                out["image"] = image
            yield out

