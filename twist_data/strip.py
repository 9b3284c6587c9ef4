"""A dataset without its pixels: every array but ``data/image``, and a digest of each episode's
frames, so that ``twist-data render --reproduce`` can rebuild the images from the stored
physics and DR draws and prove the rebuild bit-identical.

A `quick` D of cartpole is ~1.1 GiB, nearly all of it images; the rest (states, physics,
actions, rewards, DR draws, provenance) is a few MB that travels where the images cannot.
The stripped copy is a dataset of its own kind (datasets.md, §2 ``images``): ``info``,
``episodes``, ``verify`` and every non-image reader accept it, and every image reader refuses
it in one sentence naming the command that restores the images.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import zarr

from twist_data.errors import ConfigError
from twist_data.reader import ShardReader, open_dataset
from twist_data.schema import ATTRS_KEY, FRAME_ARRAYS, IMAGES_KEY, ImagesRecord, image_digest
from twist_data.staging import built_aside, require_new_folder

log = logging.getLogger(__name__)

#: Files of a collector's run folder (``collect/<shard>/``) that a stripped copy keeps: its
#: configuration and logs, never its checkpoints (see ``teacher`` in :func:`strip_dataset`).
RUN_FILES = ("config.json", "summary.json", "eval.csv", "metrics.csv")
#: What a shard copy leaves out besides the images: the writer's lock and temporary files.
SKIPPED = ("writer.lock",)
FINAL_TEACHER = "teacher.pt"


def strip_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str],
                  copy_teacher: Callable[[Path, Path], object] | None = None,
                  on_episode: Callable[[int, int], None] | None = None) -> Path:
    """Copy ``source`` without its images into the new folder ``out`` (absent or empty).

    Each shard keeps every other array byte for byte (the committed rows and anything
    beyond them, which readers ignore) and records in its ``twist.images`` block the digest of
    each committed episode's frames. The collectors' run folders keep their configs and logs;
    with ``copy_teacher(checkpoint, dest)`` also each final teacher, as that function writes
    it (``twist_models.checkpoint.weights_only``: no optimiser states), so that
    ``twist-distil`` finds it beside the rebuilt D. Built under a hidden name and renamed into
    place: a failure leaves nothing at ``out``."""
    out = Path(out)
    require_new_folder(out)
    src = open_dataset(source)
    if not src.has_images:
        raise ConfigError(f"dataset {str(source)!r} was stripped of its images already")
    teachers = _final_teachers(Path(source)) if copy_teacher is not None else []
    if copy_teacher is not None and not teachers:
        raise ConfigError(f"dataset {str(source)!r} has no final teacher "
                          f"(collect/*/{FINAL_TEACHER}) to keep beside the stripped copy")
    with built_aside(out, "stripping") as staging:
        done = 0
        for shard in src.shards:
            digests = []
            for local in range(shard.n_episodes):
                a, b = int(shard.episode_starts[local]), int(shard.episode_ends[local])
                digests.append(image_digest(shard.read("image", a, b)))
                done += 1
                if on_episode is not None:
                    on_episode(done, src.n_episodes)
            _copy_shard(shard, staging / shard.path.name, digests, Path(source))
        _copy_run_folders(Path(source), staging)
        for path in teachers:
            copy_teacher(path, staging / "collect" / path.parent.name / FINAL_TEACHER)
    log.info("stripped %s into %s: %d episodes", source, out, src.n_episodes)
    return out


def _copy_shard(shard: ShardReader, dest: Path, digests: list[str], source: Path) -> None:
    # Frame pairs go too: the rebuild that restores the images redraws them (ImagesRecord.pairs).
    frames = [n for n in FRAME_ARRAYS if (shard.path / "data" / n).is_dir()]
    image_bytes = sum(f.stat().st_size for n in frames
                      for f in (shard.path / "data" / n).rglob("*") if f.is_file())

    def ignore(folder: str, names: list[str]) -> list[str]:
        skipped = [n for n in names if n in SKIPPED or n.endswith(".partial")]
        if Path(folder) == shard.path / "data":
            skipped.extend(frames)
        return skipped

    shutil.copytree(shard.path, dest, ignore=ignore)
    group = zarr.open_group(dest, mode="r+")
    block = dict(group.attrs[ATTRS_KEY])
    record = ImagesRecord(stored=False, sha256=tuple(digests), stored_bytes=image_bytes,
                          stripped_from=str(source), pairs=shard.has_pairs)
    block[IMAGES_KEY] = record.to_json()
    group.attrs[ATTRS_KEY] = block


def _final_teachers(source: Path) -> list[Path]:
    return sorted((source / "collect").glob(f"*/{FINAL_TEACHER}"))


def _copy_run_folders(source: Path, staging: Path) -> None:
    for run in sorted((source / "collect").glob("*/")):
        (staging / "collect" / run.name).mkdir(parents=True, exist_ok=True)
        for name in RUN_FILES:
            if (run / name).is_file():
                shutil.copy2(run / name, staging / "collect" / run.name / name)
