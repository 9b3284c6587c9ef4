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

from twist_data.errors import DatasetCorruptError, TwistError
from twist_data.reader import find_shards, open_dataset
from twist_data.staging import require_new_folder
from twist_data.writer import ShardWriter

log = logging.getLogger(__name__)


@dataclass
class SalvageReport:
    """What :func:`salvage_dataset` kept and left behind: episodes by their index over the
    shards that could be opened (the global index when every shard could), and the shards
    that could not be opened at all."""

    out: Path
    kept: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)
    dropped_shards: dict[str, str] = field(default_factory=dict)


def salvage_dataset(source: str | os.PathLike[str], out: str | os.PathLike[str],
                    on_episode: Callable[[int, int], None] | None = None) -> SalvageReport:
    """Copy every episode of ``source`` that reads without error into the new dataset ``out``
    (which must not exist or be empty); a shard whose own metadata or episode table is damaged
    cannot be opened, and is left behind whole while the others are copied. When nothing can
    be kept, nothing is written and :class:`~twist_data.errors.DatasetCorruptError` says
    why."""
    out = Path(out)
    require_new_folder(out)
    report = SalvageReport(out)
    parts = []
    for path in find_shards(Path(source)):
        try:
            parts.append(open_dataset(path))
        except TwistError as exc:
            report.dropped_shards[path.name] = str(exc)
            log.info("left behind shard %s: %s", path.name, exc)
    total = sum(part.n_episodes for part in parts)
    writers: dict[str, ShardWriter] = {}
    index = 0
    try:
        for part in parts:
            shard = part.shards[0]
            for local in range(part.n_episodes):
                try:
                    episode, info = shard.episode(local), part.episode_info(local)
                except DatasetCorruptError as exc:
                    report.dropped[index] = str(exc)
                    log.info("left behind episode %d: %s", index, exc)
                else:
                    writer = writers.get(shard.name)
                    if writer is None:
                        spec = dataclasses.replace(shard.spec, extra={
                            **shard.spec.extra, "salvaged_from": str(Path(source))})
                        layout = dataclasses.replace(shard.layout, checksums=True)
                        writer = writers[shard.name] = ShardWriter.create(
                            out, shard.name, spec, layout, pairs=shard.has_pairs)
                    writer.append(episode, info)
                    report.kept.append(index)
                index += 1
                if on_episode is not None:
                    on_episode(index, total)
    finally:
        for writer in writers.values():
            writer.close()
    if not report.kept:
        reasons = [*report.dropped_shards.values(), *report.dropped.values()]
        raise DatasetCorruptError(f"nothing in {str(source)!r} could be kept, so nothing was "
                                  f"written: {len(report.dropped)} episode(s) and "
                                  f"{len(report.dropped_shards)} shard(s) are damaged (the "
                                  f"first: {reasons[0] if reasons else 'no episodes at all'})")
    return report
