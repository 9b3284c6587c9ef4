"""Append-only, crash-safe writer of one shard.

Commit protocol (see ``datasets.md``): for each episode the writer (1) grows every array,
(2) writes the per-step data, (3) writes the episode's row of the per-episode table, and only
then (4) rewrites the shard's root ``zarr.json`` whose ``twist.commit`` block holds the numbers
of committed episodes and steps. zarr's local store writes every key to a temporary file and
renames it into place, so each of these writes is atomic: a process killed at any instant
leaves either the old or the new version of each file. Readers trust only ``twist.commit``,
so a half-written episode is invisible, and committed bytes are never rewritten in place.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import logging
import os
import shutil
import time
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import zarr

from twist_data import __version__
from twist_data.errors import (
    InvalidEpisodeError,
    NotADatasetError,
    SchemaMismatchError,
    ShardLockedError,
)
from twist_data.reader import ShardReader
from twist_data.schema import (
    ATTRS_KEY,
    EPISODE_COLUMNS,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAME_ARRAYS,
    PAIR_IMAGE,
    POLICY_CODES,
    DatasetSpec,
    Episode,
    EpisodeInfo,
    ImagesRecord,
    check_format,
    episode_problems,
    step_arrays,
)
from twist_data.storage import (
    FrameWriter,
    StorageLayout,
    create_episode_array,
    create_step_array,
    frame_encoder,
)

log = logging.getLogger(__name__)

LOCK_FILE = "writer.lock"


def shard_path(dataset_dir: str | os.PathLike[str], name: str) -> Path:
    """Where shard ``name`` of the dataset at ``dataset_dir`` lives."""
    if not name or "/" in name or name.startswith(".") or name.endswith(".zarr"):
        raise NotADatasetError(
            f"shard name {name!r} must be non-empty, must not contain '/', start with '.' "
            "or end with '.zarr'"
        )
    return Path(dataset_dir) / f"{name}.zarr"


def refuse_other_schema(dataset_dir: Path, spec: DatasetSpec) -> None:
    """Refuse to add a shard of ``spec`` to ``dataset_dir`` if that is a file, or a folder
    holding shards of another schema: the new shard would make the whole dataset unreadable.
    Checked before anything is created."""
    if dataset_dir.exists() and not dataset_dir.is_dir():
        raise NotADatasetError(f"{dataset_dir} exists and is not a folder; a dataset is a folder")
    if not dataset_dir.is_dir():
        return
    for existing in sorted(dataset_dir.glob("*.zarr")):
        if existing.name.startswith(".") or not (existing / "zarr.json").is_file():
            continue
        diff = ShardReader(existing).spec.differences(spec)
        if diff:
            raise SchemaMismatchError(
                f"{dataset_dir} already holds a dataset (shard {existing.stem}) that differs from "
                f"the new shard in {', '.join(diff)}; write to another folder")
        return


class ShardWriter:
    """Appends whole episodes to one shard. Use :meth:`create` or :meth:`resume`."""

    def __init__(self, path: Path, group: zarr.Group, lock_fd: int) -> None:
        self.path = path
        self._group = group
        self._lock_fd = lock_fd
        block = dict(group.attrs[ATTRS_KEY])
        self.spec = DatasetSpec.from_json(block["spec"])
        self.layout = StorageLayout.from_json(block["layout"])
        self._block = block
        # Every chunk is written, zeros too (zarr's runtime default skips a chunk equal to
        # the fill value): in format 2 a missing chunk file can then only mean damage.
        def opened(key: str) -> zarr.Array:
            return group[key].with_config({"write_empty_chunks": True})

        #: Whether the shard stores frame pairs (``data/pair_image``, made by :meth:`create`).
        self.pairs = "data" in group and PAIR_IMAGE in group["data"]
        self._step_arrays = {a.path: opened(a.path) for a in step_arrays(self.spec, self.pairs)}
        self._frames: dict[str, FrameWriter] = {}
        for name in FRAME_ARRAYS:
            frames = self._step_arrays.get(f"data/{name}")
            encoder = None if frames is None else frame_encoder(frames)
            if encoder is not None:
                self._frames[name] = FrameWriter(frames, path / "data" / name, encoder,
                                                 int(frames.shards[0]))
        self._episode_arrays = {f"meta/{c}": opened(f"meta/{c}") for c in EPISODE_COLUMNS}
        self._episode_arrays.update(
            {f"meta/dr/{p.name}": opened(f"meta/dr/{p.name}") for p in self.spec.episode_dr_params}
        )
        commit = block["commit"]
        self.n_episodes = int(commit["n_episodes"])
        self.n_steps = int(commit["n_steps"])
        self.durable = False

    # -- opening -------------------------------------------------------------------------

    @classmethod
    def create(cls, dataset_dir: str | os.PathLike[str], name: str, spec: DatasetSpec,
               layout: StorageLayout | None = None, pairs: bool = False) -> ShardWriter:
        """Create shard ``name`` in ``dataset_dir`` (made if needed); fails if it exists.
        ``pairs``: it also stores frame pairs, which every appended episode then carries.

        The shard is built under a hidden temporary name and renamed into place, so readers
        never see a shard without its metadata.
        """
        layout = layout or StorageLayout()
        final = shard_path(dataset_dir, name)
        if final.exists():
            raise NotADatasetError(f"shard {final} already exists; resume it instead of creating it")
        refuse_other_schema(final.parent, spec)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.parent / f".{name}.zarr.creating-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        group = zarr.open_group(tmp, mode="w")
        for a in step_arrays(spec, pairs):
            create_step_array(group, a.path, a.dtype, a.trailing, layout,
                              sharded_frames=a.name in FRAME_ARRAYS)
        for column, (dtype, _) in EPISODE_COLUMNS.items():
            create_episode_array(group, f"meta/{column}", dtype, (), layout)
        for p in spec.episode_dr_params:
            create_episode_array(group, f"meta/dr/{p.name}", p.dtype, p.shape, layout)
        now = _dt.datetime.now(_dt.timezone.utc).isoformat()
        group.attrs[ATTRS_KEY] = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "shard": name,
            "created": now,
            "writer": {"library": "twist", "version": __version__, "zarr": zarr.__version__},
            "policy_codes": POLICY_CODES,
            "spec": spec.to_json(),
            "layout": layout.to_json(),
            "commit": {"n_episodes": 0, "n_steps": 0, "updated": now},
        }
        os.rename(tmp, final)
        log.info("created shard %s", final)
        return cls._open(final)

    @classmethod
    def resume(cls, path: str | os.PathLike[str]) -> ShardWriter:
        """Reopen an existing shard to append after its last committed episode.

        Anything an interrupted writer left beyond the commit (grown arrays, orphan chunks,
        temporary files) is discarded first.
        """
        path = Path(path)
        if not (path / "zarr.json").is_file():
            raise NotADatasetError(f"{path} is not a twist shard (no zarr.json)")
        writer = cls._open(path)
        writer._discard_uncommitted()
        return writer

    @classmethod
    def _open(cls, path: Path) -> ShardWriter:
        lock_fd = os.open(path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            # flock is released by the kernel when the process dies, so a SIGKILLed writer
            # never leaves a stale lock behind.
            fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(lock_fd)
            raise ShardLockedError(f"shard {path} is already being written by another process") \
                from None
        try:
            group = zarr.open_group(path, mode="r+")
            block = check_format(group.attrs, str(path))
            if not ImagesRecord.from_attrs(block).stored:
                raise NotADatasetError(f"shard {path} was stripped of its images "
                                       "(twist-data strip); a stripped shard is never appended to")
            return cls(path, group, lock_fd)
        except BaseException:
            os.close(lock_fd)
            raise

    def _discard_uncommitted(self) -> None:
        for leftover in self.path.rglob("*.partial"):
            leftover.unlink(missing_ok=True)
        for arr in self._step_arrays.values():
            if arr.shape[0] != self.n_steps:
                arr.resize((self.n_steps, *arr.shape[1:]))
        for arr in self._episode_arrays.values():
            if arr.shape[0] != self.n_episodes:
                arr.resize((self.n_episodes, *arr.shape[1:]))

    # -- writing -------------------------------------------------------------------------

    def append(self, episode: Episode, info: EpisodeInfo) -> int:
        """Validate, write and commit one episode; returns its index within the shard."""
        problems = episode_problems(episode, info, self.spec, self.pairs)
        if problems:
            raise InvalidEpisodeError(
                f"episode rejected by shard {self.path.name}: " + "; ".join(problems)
            )
        start, stop = self.n_steps, self.n_steps + len(episode)
        arrays = episode.arrays()
        for key, arr in self._step_arrays.items():
            arr.resize((stop, *arr.shape[1:]))
            name = key[len("data/"):]
            if name in self._frames:
                self._frames[name].append(start, arrays[name])
            else:
                arr[start:stop] = arrays[key[len("data/"):]]
        e = self.n_episodes
        row: dict[str, Any] = {
            "meta/episode_ends": stop,
            "meta/episode_seed": info.seed,
            "meta/episode_policy": POLICY_CODES[info.policy],
            "meta/episode_teacher_step": info.teacher_step,
            "meta/episode_env_step": info.env_step,
            "meta/episode_return": float(np.sum(episode.reward, dtype=np.float64)),
            "meta/episode_time": time.time(),
        }
        row.update({f"meta/dr/{k}": v for k, v in info.dr.items()})
        for key, arr in self._episode_arrays.items():
            arr.resize((e + 1, *arr.shape[1:]))
            arr[e] = row[key]
        if self.durable:
            os.sync()
        self._commit(e + 1, stop)
        return e

    def _commit(self, n_episodes: int, n_steps: int) -> None:
        self._block["commit"] = {
            "n_episodes": n_episodes,
            "n_steps": n_steps,
            "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(),
        }
        # Codes are only ever added, so this library's table covers an older shard's: a
        # resumed shard whose new episodes use a newer code names it.
        self._block["policy_codes"] = POLICY_CODES
        # One atomic write of the root zarr.json: the commit point.
        self._group.attrs[ATTRS_KEY] = self._block
        if self.durable:
            os.sync()
        self.n_episodes, self.n_steps = n_episodes, n_steps

    def close(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
