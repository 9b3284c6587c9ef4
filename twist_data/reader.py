"""Read a matching dataset: a folder of shards (or one shard) opened as one.

Readers trust only each shard's commit record (``twist.commit`` in its root ``zarr.json``):
data beyond it belongs to an episode still being written and is invisible. A dataset that is
still being written can be re-read with :meth:`MatchingDataset.refresh`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import zarr

from twist_data.errors import (
    DatasetCorruptError,
    ImagesStrippedError,
    NotADatasetError,
    PairsMissingError,
    SamplerConfigError,
    SchemaMismatchError,
)
from twist_data.schema import (
    EPISODE_COLUMNS,
    FRAME_ARRAYS,
    PAIR_IMAGE,
    POLICY_CODES,
    DatasetSpec,
    Episode,
    EpisodeInfo,
    ImagesRecord,
    check_format,
    step_arrays,
    stripped_message,
)
from twist_data.storage import (
    FrameCorruptError,
    FrameReader,
    StorageLayout,
    frame_decoder,
    reason,
)

log = logging.getLogger(__name__)

#: The paths of the frame arrays, whose chunk files are shard files of frames.
FRAME_PATHS = tuple(f"data/{name}" for name in FRAME_ARRAYS)


def _open_group(path: Path) -> zarr.Group:
    if not (path / "zarr.json").is_file():
        raise NotADatasetError(f"{path} is not a twist dataset shard (no zarr.json)")
    try:
        return zarr.open_group(path, mode="r")
    except Exception as exc:  # zarr raises a variety of types for unreadable metadata
        raise DatasetCorruptError(f"shard {path} has unreadable metadata: {exc}") from None


class _ZarrFrameReader:
    """Fallback frame reader through zarr's API, for layouts FrameReader does not know."""

    def __init__(self, array: zarr.Array) -> None:
        self.array = array

    def read_into(self, steps: np.ndarray, views: np.ndarray, out: np.ndarray,
                  rows: np.ndarray) -> None:
        for row, t, v in zip(rows.tolist(), steps.tolist(), views.tolist(), strict=True):
            try:
                out[row] = self.array[t, v]
            except Exception as exc:  # zarr and the codecs raise assorted types
                raise FrameCorruptError(f"the frame of step {t} view {v} cannot be decoded "
                                        f"({reason(exc)})", t) from None

    def close(self) -> None:
        pass


def rows_per_file(array: zarr.Array) -> int:
    """Rows along axis 0 that one chunk file of ``array`` holds (a shard file for images)."""
    return int(array.shards[0] if array.shards else array.chunks[0])


class ShardReader:
    """Read-only view of one shard's committed episodes."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.name = self.path.name.removesuffix(".zarr")
        self._frames: dict[str, FrameReader | _ZarrFrameReader] = {}
        self._load_metadata()

    def _load_metadata(self) -> None:
        self._group = _open_group(self.path)
        block = check_format(self._group.attrs, str(self.path))
        self.format_version = int(block["format_version"])
        self.spec = DatasetSpec.from_json(block["spec"])
        self.layout = StorageLayout.from_json(block["layout"])
        self.attrs = dict(block)
        self.images = ImagesRecord.from_attrs(block)
        #: Whether the shard stores frame pairs (``data/pair_image``, datasets.md §2).
        self.has_pairs = (self.images.stored and "data" in self._group
                          and PAIR_IMAGE in self._group["data"])
        commit = block["commit"]
        self.n_episodes = int(commit["n_episodes"])
        self.n_steps = int(commit["n_steps"])
        self._arrays: dict[str, zarr.Array] = {}
        self._table = self._read_table()

    def array(self, key: str) -> zarr.Array:
        """The zarr array at ``key`` (e.g. ``data/state``), with a clear error if missing."""
        arr = self._arrays.get(key)
        if arr is None:
            try:
                arr = self._group[key]
            except KeyError:
                raise DatasetCorruptError(f"shard {self.path}: array {key} is missing") from None
            if not isinstance(arr, zarr.Array):
                raise DatasetCorruptError(f"shard {self.path}: {key} is not an array")
            self._arrays[key] = arr
        return arr

    def _read_table(self) -> dict[str, np.ndarray]:
        table = {}
        keys = [f"meta/{c}" for c in EPISODE_COLUMNS]
        keys += [f"meta/dr/{p.name}" for p in self.spec.episode_dr_params]
        for key in keys:
            arr = self.array(key)
            if arr.shape[0] < self.n_episodes:
                raise DatasetCorruptError(
                    f"shard {self.path}: {key} holds {arr.shape[0]} episodes, "
                    f"but {self.n_episodes} are committed"
                )
            table[key.removeprefix("meta/")] = self._read_rows(key, 0, self.n_episodes)
        ends = table["episode_ends"]
        if self.n_episodes and (ends[-1] != self.n_steps or np.any(np.diff(ends) <= 0)
                                or ends[0] <= 0):
            raise DatasetCorruptError(
                f"shard {self.path}: meta/episode_ends is inconsistent with the commit record "
                f"({self.n_steps} steps)"
            )
        return table

    @property
    def policy_names(self) -> dict[int, str]:
        """``meta/episode_policy`` code -> name, from the shard's own ``policy_codes`` table."""
        return {int(code): name for name, code in self.attrs.get("policy_codes",
                                                                    POLICY_CODES).items()}

    @property
    def episode_ends(self) -> np.ndarray:
        return self._table["episode_ends"]

    @property
    def episode_starts(self) -> np.ndarray:
        ends = self.episode_ends
        return np.concatenate([[0], ends[:-1]]).astype(np.int64)[:ends.size]

    def episode_column(self, name: str) -> np.ndarray:
        """A per-episode column (``episode_seed``, ``dr/<name>`` ...) for committed episodes."""
        return self._table[name]

    def read(self, key: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Committed steps ``[start, stop)`` of the per-step array ``key`` (e.g. ``state``)."""
        stop = self.n_steps if stop is None else stop
        if not 0 <= start <= stop <= self.n_steps:
            raise SamplerConfigError(
                f"shard {self.name}: step range [{start}, {stop}) is outside the "
                f"{self.n_steps} committed steps"
            )
        arr = self.array(f"data/{key}")
        if arr.shape[0] < self.n_steps:
            raise DatasetCorruptError(
                f"shard {self.path}: data/{key} holds {arr.shape[0]} steps, "
                f"but {self.n_steps} are committed"
            )
        if key in FRAME_ARRAYS:
            out = np.empty((stop - start, *arr.shape[1:]), np.uint8)
            k = self.spec.views
            steps = np.repeat(np.arange(start, stop), k)
            views = np.tile(np.arange(k), stop - start)
            flat = out.reshape(-1, *arr.shape[2:])
            self.read_frames(steps, views, flat, np.arange(flat.shape[0]), key)
            return out
        return self._read_rows(f"data/{key}", start, stop)

    @property
    def has_images(self) -> bool:
        """Whether the shard stores its images (False once ``twist-data strip`` removed them)."""
        return self.images.stored

    def read_frames(self, steps: np.ndarray, views: np.ndarray, out: np.ndarray,
                    rows: np.ndarray, key: str = "image") -> None:
        """Decode frame (``steps[i]``, ``views[i]``) of this shard's frame array ``key``
        (``image`` or ``pair_image``) into ``out[rows[i]]``; a frame that cannot be decoded
        raises DatasetCorruptError naming its episode."""
        if not self.has_images:
            raise ImagesStrippedError(stripped_message(self.path))
        try:
            self.frame_reader(key).read_into(steps, views, out, rows)
        except FrameCorruptError as exc:
            raise DatasetCorruptError(
                f"shard {self.name}, {self.where(exc.step)}, data/{key}: {exc}") from None

    def where(self, step: int) -> str:
        """``episode E (its step s)`` for step ``step`` of this shard."""
        episode = int(np.searchsorted(self.episode_ends, step, side="right"))
        if episode >= self.n_episodes:
            return f"step {step} (beyond the committed episodes)"
        return f"episode {episode} (its step {step - int(self.episode_starts[episode])})"

    def rows_of(self, key: str, start: int, stop: int) -> str:
        """Rows [start, stop) of array ``key`` in words: steps and their episodes, or episodes."""
        if key.startswith("meta/"):
            return f"episodes {start}-{stop - 1}"
        ends = self._table["episode_ends"] if hasattr(self, "_table") else np.zeros(0)
        first = int(np.searchsorted(ends, start, side="right"))
        last = int(np.searchsorted(ends, stop - 1, side="right"))
        if first >= ends.size:
            return f"steps {start}-{stop - 1}"
        return f"steps {start}-{stop - 1} (episodes {first}-{min(last, ends.size - 1)})"

    def missing_chunks(self, key: str, start: int, stop: int) -> list[tuple[int, int]]:
        """Row ranges [a, b) within [start, stop) of array ``key`` whose chunk file is absent.
        zarr reads a missing chunk as its fill value (zeros), so only this check finds one.
        Format 1 writers skipped chunks of zeros, so there only image shard files count."""
        arr = self.array(key)
        if start >= stop or not (self.layout.checksums or key in FRAME_PATHS):
            return []
        rows = rows_per_file(arr)
        missing = []
        for c in range(start // rows, (stop - 1) // rows + 1):
            name = arr.metadata.encode_chunk_key((c,) + (0,) * (arr.ndim - 1))
            if not (self.path / key / name).is_file():
                missing.append((max(start, c * rows), min(stop, (c + 1) * rows)))
        return missing

    def damaged_chunks(self, key: str, start: int, stop: int
                       ) -> list[tuple[int, int, str]]:
        """Row ranges [a, b) of array ``key`` within [start, stop) whose chunk is missing or
        cannot be decoded, each with the reason; every chunk is read."""
        arr = self.array(key)
        if start >= stop:
            return []
        damaged = [(a, b, "its chunk file is missing") for a, b in
                   self.missing_chunks(key, start, stop)]
        missing = {a for a, _, _ in damaged}
        rows = rows_per_file(arr)
        for c in range(start // rows, (stop - 1) // rows + 1):
            a, b = max(start, c * rows), min(stop, (c + 1) * rows)
            if a in missing:
                continue
            try:
                arr[a:b]
            except Exception as exc:  # zarr and the codecs raise assorted types
                damaged.append((a, b, f"cannot be decoded ({reason(exc)})"))
        return sorted(damaged)

    def _read_rows(self, key: str, start: int, stop: int) -> np.ndarray:
        """Rows [start, stop) of a low-dimensional array, or DatasetCorruptError naming the
        first damaged chunk's rows (never fill values in place of a missing chunk)."""
        arr = self.array(key)
        try:
            if self.missing_chunks(key, start, stop):
                raise LookupError("missing chunk")
            return arr[start:stop]
        except Exception:  # zarr and the codecs raise assorted types
            damaged = self.damaged_chunks(key, start, stop)
            if not damaged:
                raise
            a, b, why = damaged[0]
            raise DatasetCorruptError(
                f"shard {self.name}, {self.rows_of(key, a, b)}, {key}: {why}") from None

    @property
    def frames(self) -> FrameReader | _ZarrFrameReader:
        """:meth:`frame_reader` of ``image``."""
        return self.frame_reader("image")

    def frame_reader(self, key: str = "image") -> FrameReader | _ZarrFrameReader:
        """Reader of frame array ``key`` with ``read_into(steps, views, out, rows)``; direct
        when possible."""
        reader = self._frames.get(key)
        if reader is None:
            arr = self.array(f"data/{key}")
            direct = frame_decoder(arr)
            if direct is None:
                log.warning("shard %s: %s layout not recognised, reading through zarr (slow)",
                            self.path, key)
                reader = _ZarrFrameReader(arr)
            else:
                decoder, checksum = direct
                reader = FrameReader(arr, self.path / "data" / key, decoder,
                                     int(arr.shards[0]), checksum, refuse_black=self.spec.drawn)
            self._frames[key] = reader
        return reader

    def episode(self, index: int, images: bool = True) -> Episode:
        """Episode ``index`` of this shard, every array read; with ``images`` False its
        ``image`` is an empty array of zero views [T, 0, H, W, 3], which nothing can mistake
        for frames (what a stripped shard gives when asked without images)."""
        if not 0 <= index < self.n_episodes:
            raise SamplerConfigError(
                f"shard {self.name} has {self.n_episodes} episodes; index {index} is out of range"
            )
        start, stop = int(self.episode_starts[index]), int(self.episode_ends[index])
        data = {a.name: self.read(a.name, start, stop)
                for a in step_arrays(self.spec, self.has_pairs and images)
                if images or a.name != "image"}
        if not images:
            data["image"] = np.empty((stop - start, 0, *self.spec.image_shape), np.uint8)
        dr = {k.removeprefix("dr/"): data.pop(k) for k in list(data) if k.startswith("dr/")}
        return Episode(**data, dr=dr)

    def refresh(self) -> bool:
        """Re-read the commit record; returns True when new episodes were committed."""
        old_episodes = self.n_episodes
        # Shard files at the end may have been replaced by the writer: remap lazily.
        for reader in self._frames.values():
            reader.close()
        self._frames = {}
        self._load_metadata()
        return self.n_episodes != old_episodes

    def disk_bytes(self) -> int:
        return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())


def find_shards(path: Path) -> list[Path]:
    """Shard folders of a dataset: ``path`` itself if it is a shard, else its ``*.zarr`` children."""
    if not path.exists():
        raise NotADatasetError(f"{path} does not exist")
    if (path / "zarr.json").is_file():
        return [path]
    if not path.is_dir():
        raise NotADatasetError(f"{path} is not a twist dataset (not a folder)")
    shards = sorted(p for p in path.iterdir()
                    if p.is_dir() and p.suffix == ".zarr" and not p.name.startswith("."))
    if not shards:
        raise NotADatasetError(f"{path} is not a twist dataset: it holds no shard (*.zarr folder)")
    return shards


@dataclass(frozen=True)
class StepLocation:
    """Where global steps live: shard index and step within the shard, arrays of equal shape."""

    shard: np.ndarray
    step: np.ndarray


class MatchingDataset:
    """All committed episodes of a dataset's shards, in shard-name order, as one sequence."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.shards = [ShardReader(p) for p in find_shards(self.path)]
        self._check_schema()
        self._columns: dict[str, np.ndarray] = {}
        self._index()

    def _check_schema(self) -> None:
        ref = self.shards[0]
        for shard in self.shards[1:]:
            if shard.has_images != ref.has_images:
                stripped, full = (ref, shard) if shard.has_images else (shard, ref)
                raise SchemaMismatchError(
                    f"shards {full.name} and {stripped.name} cannot form one dataset: "
                    f"{stripped.name} was stripped of its images and {full.name} was not")
            if shard.has_pairs != ref.has_pairs:
                paired, single = (ref, shard) if ref.has_pairs else (shard, ref)
                raise SchemaMismatchError(
                    f"shards {paired.name} and {single.name} cannot form one dataset: "
                    f"{paired.name} stores frame pairs and {single.name} does not")
            diff = ref.spec.differences(shard.spec)
            if diff:
                raise SchemaMismatchError(
                    f"shards {ref.name} and {shard.name} cannot form one dataset: they differ "
                    f"in {', '.join(diff)}"
                )

    def _index(self) -> None:
        steps = np.array([s.n_steps for s in self.shards], np.int64)
        self.shard_offsets = np.concatenate([[0], np.cumsum(steps)]).astype(np.int64)
        starts = [s.episode_starts + off for s, off in zip(self.shards, self.shard_offsets,
                                                            strict=False)]
        ends = [s.episode_ends + off for s, off in zip(self.shards, self.shard_offsets,
                                                        strict=False)]
        self.episode_starts = np.concatenate(starts) if starts else np.zeros(0, np.int64)
        self.episode_ends = np.concatenate(ends) if ends else np.zeros(0, np.int64)
        self._columns = {}

    @property
    def spec(self) -> DatasetSpec:
        return self.shards[0].spec

    @property
    def n_episodes(self) -> int:
        return int(self.episode_ends.size)

    @property
    def n_steps(self) -> int:
        return int(self.shard_offsets[-1])

    @property
    def episode_lengths(self) -> np.ndarray:
        return self.episode_ends - self.episode_starts

    def refresh(self) -> int:
        """Pick up episodes committed (and shards created) since opening; returns how many."""
        before = self.n_episodes
        known = {s.path for s in self.shards}
        for shard in self.shards:
            shard.refresh()
        for p in find_shards(self.path):
            if p not in known:
                self.shards.append(ShardReader(p))
        self.shards.sort(key=lambda s: s.path.name)
        self._check_schema()
        self._index()
        return self.n_episodes - before

    def locate(self, steps: np.ndarray) -> StepLocation:
        """Map global step indices (any shape) to (shard, step within shard)."""
        shard = np.searchsorted(self.shard_offsets, steps, side="right") - 1
        return StepLocation(shard, steps - self.shard_offsets[shard])

    def column(self, key: str) -> np.ndarray:
        """Per-step array ``key`` for every committed step, concatenated over shards ([N, ...]).

        Low-dimensional arrays are small (about 100 bytes per step) and are kept in memory;
        images are never loaded this way, use :meth:`read_frames`.
        """
        if key in FRAME_ARRAYS:
            raise SamplerConfigError("images are not loaded whole; use read_frames()")
        col = self._columns.get(key)
        if col is None:
            names = {a.name for a in step_arrays(self.spec) if a.name not in FRAME_ARRAYS}
            if key not in names:
                raise SamplerConfigError(f"unknown key {key!r}; valid: {', '.join(sorted(names))}")
            col = np.concatenate([s.read(key) for s in self.shards])
            self._columns[key] = col
        return col

    def read_frames(self, steps: np.ndarray, views: np.ndarray, out: np.ndarray,
                    rows: np.ndarray | None = None, key: str = "image") -> None:
        """Decode frame (global ``steps[i]``, ``views[i]``) into ``out[rows[i]]`` (out: [n, H, W, 3]).

        ``rows`` defaults to ``0..n-1``; ``key`` ``pair_image`` reads the pair frames
        (:meth:`require_pairs`).
        """
        if key == PAIR_IMAGE:
            self.require_pairs()
        self.require_images()
        rows = np.arange(steps.size) if rows is None else rows
        if np.any(views < 0) or np.any(views >= self.spec.views):
            bad = int(views[(views < 0) | (views >= self.spec.views)][0])
            raise SamplerConfigError(
                f"view index {bad} is out of range: the dataset has {self.spec.views} views"
            )
        loc = self.locate(steps)
        if len(self.shards) == 1:
            self.shards[0].read_frames(loc.step, views, out, rows, key)
            return
        for s in np.unique(loc.shard).tolist():
            sel = loc.shard == s
            self.shards[s].read_frames(loc.step[sel], views[sel], out, rows[sel], key)

    def frames_of_random_views(self, steps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frames of global ``steps`` [n], each from a view drawn uniformly by ``rng``:
        uint8 [n, H, W, 3]."""
        out = np.empty((steps.size, *self.spec.image_shape), np.uint8)
        self.read_frames(steps, rng.integers(0, self.spec.views, steps.size), out)
        return out

    @property
    def has_images(self) -> bool:
        """Whether the dataset stores its images (every shard agrees: :meth:`_check_schema`)."""
        return self.shards[0].has_images

    def require_images(self, needed_by: str | None = None) -> None:
        """Raise :class:`ImagesStrippedError` naming ``needed_by`` and the command that
        rebuilds the images when the dataset was stripped of them."""
        if not self.has_images:
            raise ImagesStrippedError(stripped_message(self.path, needed_by))

    @property
    def has_pairs(self) -> bool:
        """Whether the dataset stores frame pairs, ``data/pair_image`` (every shard agrees)."""
        return self.shards[0].has_pairs

    def require_pairs(self, needed_by: str | None = None) -> None:
        """Raise :class:`PairsMissingError` naming ``needed_by`` and the command that adds the
        pairs when the dataset stores none (a stripped one: what rebuilds its images)."""
        self.require_images(needed_by)
        if not self.has_pairs:
            who = f"{needed_by} needs" if needed_by else "reading them needs"
            raise PairsMissingError(
                f"{who} frame pairs of one scene, but dataset {str(self.path)!r} stores none; "
                f"add them with: twist-data render {self.path} OUT --reproduce --pairs")

    def episode(self, index: int, images: bool = True) -> Episode:
        """Global episode ``index`` (episodes numbered over shards in shard-name order);
        ``images`` as :meth:`ShardReader.episode`."""
        if images:
            self.require_images()
        shard, local = self.episode_location(index)
        return self.shards[shard].episode(local, images)

    def episode_info(self, index: int) -> EpisodeInfo:
        """Provenance of global episode ``index`` as the writer received it."""
        shard, local = self.episode_location(index)
        table = self.shards[shard]._table
        return EpisodeInfo(
            seed=int(table["episode_seed"][local]),
            policy=self.shards[shard].policy_names[int(table["episode_policy"][local])],
            teacher_step=int(table["episode_teacher_step"][local]),
            env_step=int(table["episode_env_step"][local]),
            dr={p.name: table[f"dr/{p.name}"][local] for p in self.spec.episode_dr_params},
        )

    def episode_returns(self) -> np.ndarray:
        """Every committed episode's stored ``episode_return``, over shards [E]."""
        return np.concatenate([s.episode_column("episode_return") for s in self.shards])

    def rule_problem(self, columns: tuple[str, ...] = ("state", "action")) -> str | None:
        """The first episode rule (:mod:`twist_data.rules`) D breaks, in one sentence naming
        its shard and episode, or None: the flags, the stored returns and the ``columns``
        asked for are checked (each read whole, as a sampler holds them)."""
        from twist_data.rules import rule_problems

        keys = ("is_first", "is_last", "reward", *columns)
        problems = rule_problems(self.episode_starts, self.episode_ends,
                                 {k: self.column(k) for k in keys}, self.episode_returns())
        if not problems:
            return None
        episode, rule = problems[0]
        shard, local = self.episode_location(episode)
        more = f" ({len(problems) - 1} more episodes break a rule)" if len(problems) > 1 else ""
        return (f"dataset {str(self.path)!r}, shard {self.shards[shard].name}, episode {local} "
                f"(global {episode}): {rule}{more}; twist-data verify names every problem")

    def episode_location(self, index: int) -> tuple[int, int]:
        """(shard number, episode within that shard) of global episode ``index``; negative
        indices count from the end, as in Python (-1 is the last episode)."""
        if not -self.n_episodes <= index < self.n_episodes:
            raise SamplerConfigError(
                f"dataset has {self.n_episodes} episodes; index {index} is out of range"
            )
        index %= self.n_episodes
        counts = np.cumsum([s.n_episodes for s in self.shards])
        shard = int(np.searchsorted(counts, index, side="right"))
        return shard, index - (int(counts[shard - 1]) if shard else 0)

    def iter_episodes(self) -> Iterator[tuple[int, Episode]]:
        for i in range(self.n_episodes):
            yield i, self.episode(i)

    def episodes(self) -> pd.DataFrame:
        """One row per committed episode: shard, index, start, length, return and provenance."""
        frames = []
        for shard in self.shards:
            codes = shard.policy_names
            t = shard._table
            frame = pd.DataFrame({
                "shard": shard.name,
                "episode": np.arange(shard.n_episodes),
                "start": shard.episode_starts,
                "length": shard.episode_ends - shard.episode_starts,
                "return": t["episode_return"],
                "seed": t["episode_seed"],
                "policy": [codes.get(int(c), f"code {int(c)}") for c in t["episode_policy"]],
                "teacher_step": t["episode_teacher_step"],
                "env_step": t["episode_env_step"],
                "committed": pd.to_datetime(t["episode_time"], unit="s", utc=True),
            })
            for p in self.spec.episode_dr_params:
                if p.shape == ():
                    frame[f"dr_{p.name}"] = t[f"dr/{p.name}"]
            frames.append(frame)
        table = pd.concat(frames, ignore_index=True)
        table.index.name = "global_episode"
        return table

    def disk_bytes(self) -> int:
        return sum(s.disk_bytes() for s in self.shards)


def open_dataset(path: str | os.PathLike[str]) -> MatchingDataset:
    """Open a dataset folder (or a single shard folder) for reading."""
    return MatchingDataset(path)


__all__ = ["MatchingDataset", "ShardReader", "open_dataset"]
