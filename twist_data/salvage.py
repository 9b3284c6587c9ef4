"""Keep what is intact: copy every episode of a damaged dataset that still reads cleanly into a
new dataset, and name the ones left behind.

Every array of an episode is decoded (and, in format 2, checksummed) on the way, so the copy
holds only verified data and verifies clean. Shards keep their names, specs and provenance
(plus ``extra["salvaged_from"]``); episode order and per-episode provenance are kept, except
``meta/episode_time``, which records the copy's commit.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from twist_data.errors import DatasetCorruptError
from twist_data.reader import open_dataset
from twist_data.staging import require_new_folder
from twist_data.writer import ShardWriter

log = logging.getLogger(__name__)


@dataclass
class SalvageReport:
    """What :func:`salvage_dataset` kept and left behind (global episode indices of the
    source)."""

    out: Path
    kept: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)


def salvage_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str],
                    on_episode: Callable[[int, int], None] | None = None) -> SalvageReport:
    """Copy every episode of ``source`` that reads without error into the new dataset ``out``
    (which must not exist or be empty). A shard whose own metadata or episode table is damaged
    cannot be opened, and then nothing can be salvaged: that error is raised."""
    out = Path(out)
    require_new_folder(out)
    src = open_dataset(source)
    report = SalvageReport(out)
    writers: dict[str, ShardWriter] = {}
    try:
        for index in range(src.n_episodes):
            shard_index, local = src.episode_location(index)
            shard = src.shards[shard_index]
            try:
                episode, info = shard.episode(local), src.episode_info(index)
            except DatasetCorruptError as exc:
                report.dropped[index] = str(exc)
                log.warning("left behind episode %d: %s", index, exc)
            else:
                writer = writers.get(shard.name)
                if writer is None:
                    spec = dataclasses.replace(shard.spec, extra={
                        **shard.spec.extra, "salvaged_from": str(Path(source))})
                    layout = dataclasses.replace(shard.layout, checksums=True)
                    writer = writers[shard.name] = ShardWriter.create(out, shard.name, spec,
                                                                      layout)
                writer.append(episode, info)
                report.kept.append(index)
            if on_episode is not None:
                on_episode(index + 1, src.n_episodes)
    finally:
        for writer in writers.values():
            writer.close()
    return report

