"""Full integrity check of a dataset: collects every problem, naming shard, episode and array.

Data is read through zarr's own API (not the sampler's direct reader), so a check passes only
if a plain zarr user can read every committed chunk; zarr also verifies each shard index CRC.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from twist_data.errors import DatasetCorruptError, TwistError
from twist_data.reader import FRAME_PATHS, ShardReader, find_shards, open_dataset, rows_per_file
from twist_data.rules import rule_problems
from twist_data.schema import (
    EPISODE_COLUMNS,
    FRAME_ARRAYS,
    PAIR_IMAGE,
    Episode,
    EpisodeInfo,
    episode_problems,
    step_arrays,
)
from twist_data.storage import FrameFile, reason, shard_file

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Problem:
    """One integrity problem."""

    shard: str
    message: str
    array: str | None = None
    episode: int | None = None

    def __str__(self) -> str:
        where = [f"shard {self.shard}"]
        if self.episode is not None:
            where.append(f"episode {self.episode}")
        if self.array is not None:
            where.append(self.array)
        return ", ".join(where) + ": " + self.message


@dataclass
class VerifyReport:
    """What :func:`verify_dataset` found."""

    path: Path
    problems: list[Problem] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    shards: int = 0
    episodes: int = 0
    steps: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems


def _shard_index_problem(arr: zarr.Array, folder: Path, index: int, inner: int) -> str | None:
    """What is wrong with image shard file ``index``'s own index (size, CRC32C), if anything."""
    try:
        FrameFile(shard_file(arr, folder, index), inner).close()
    except DatasetCorruptError as exc:
        return str(exc).rsplit(" is ", 1)[-1].rsplit(" has ", 1)[-1]
    return None


def _verify_images(shard: ShardReader, problem: Callable[..., None],
                   tick: Callable[[int], None], key: str = "data/image") -> None:
    """Every committed frame of frame array ``key``, one shard file at a time through zarr
    (which checks the index's and, in format 2, each frame's CRC32C); a file that fails is
    read frame by frame so that each damaged episode is named with its damaged steps."""
    arr, n, views = shard.array(key), shard.n_steps, shard.spec.views
    missing = dict(shard.missing_chunks(key, 0, n))
    per_file = rows_per_file(arr)
    for a in range(0, n, per_file):
        b = min(a + per_file, n)
        if a in missing:
            problem(f"{shard.rows_of(key, a, b)}: its shard file is missing", key)
            tick(b - a)
            continue
        try:
            frames = arr[a:b]
        except Exception:  # zarr and the codecs raise assorted types
            index_problem = _shard_index_problem(arr, shard.path / key, a // per_file,
                                                 per_file * views)
            if index_problem:  # the whole file: its frames cannot even be located
                problem(f"{shard.rows_of(key, a, b)}: {index_problem}", key)
                tick(b - a)
                continue
            bad: dict[int, list[tuple[int, str]]] = {}
            for t in range(a, b):
                for v in range(views):
                    try:
                        arr[t, v]
                    except Exception as exc:
                        episode = int(np.searchsorted(shard.episode_ends, t, side="right"))
                        bad.setdefault(episode, []).append(
                            (t - int(shard.episode_starts[episode]), reason(exc)))
                        break
            for episode, steps in bad.items():
                first, last = steps[0][0], steps[-1][0]
                problem(f"{len(steps)} step(s) between its steps {first} and {last} cannot be "
                        f"decoded ({steps[0][1]})", key, episode)
        else:  # twist draws no frame of zeros: one is a frame overwritten, checksum and all
            black = (np.flatnonzero(frames.reshape((b - a) * views, -1).max(1) == 0)
                     if shard.spec.drawn else np.zeros(0, np.int64))
            for i in black[:16].tolist():
                t, v = a + i // views, i % views
                episode = int(np.searchsorted(shard.episode_ends, t, side="right"))
                problem(f"the frame of its step {t - int(shard.episode_starts[episode])} view {v} "
                        "is all zeros, which no render draws", key, episode)
        tick(b - a)


def _verify_shard(shard: ShardReader, report: VerifyReport,
                  tick: Callable[[int], None]) -> None:
    name, n = shard.name, shard.n_steps

    def problem(message: str, array: str | None = None, episode: int | None = None) -> None:
        report.problems.append(Problem(name, message, array, episode))

    expected = _expected_arrays(shard)
    if not shard.has_images:
        digests = len(shard.images.sha256)
        if digests != shard.n_episodes:
            problem(f"records {digests} episode image digests for {shard.n_episodes} committed "
                    "episodes", "images")
        report.notes.append(f"shard {name}: stripped of its images ({digests} episode digests "
                            "kept); twist-data render --reproduce rebuilds them")
    loaded: dict[str, np.ndarray] = {}
    for key, dtype, trailing, committed in expected:
        structure = _structure_problem(shard, key, dtype, trailing, committed)
        if structure is not None:
            problem(structure, key)
            continue
        arr = shard.array(key)
        if key.startswith("meta/"):
            for a, b, why in shard.damaged_chunks(key, 0, committed):
                problem(f"{shard.rows_of(key, a, b)}: {why}", key)
            continue
        if key in FRAME_PATHS:
            _verify_images(shard, problem, tick, key)
            continue
        damaged = shard.damaged_chunks(key, 0, n)
        for a, b, why in damaged:
            problem(f"{shard.rows_of(key, a, b)}: {why}", key)
        if damaged:
            continue
        block = arr[0:n]
        loaded[key] = block

    _check_episodes(shard, loaded, problem)
    leftovers = list(shard.path.rglob("*.partial"))
    if leftovers:
        report.notes.append(
            f"shard {name}: {len(leftovers)} temporary file(s) left by an interrupted write "
            "(harmless; removed when a writer resumes the shard)"
        )
    beyond = shard.array("data/reward").shape[0] - n if "data/reward" in loaded else 0
    if beyond > 0:
        report.notes.append(
            f"shard {name}: {beyond} uncommitted step(s) beyond the commit record "
            "(an interrupted episode; invisible to readers, discarded on resume)"
        )


def _expected_arrays(shard: ShardReader) -> list[tuple[str, Any, tuple[int, ...], int]]:
    """(key, dtype, trailing shape, committed rows) of every array the shard must hold."""
    n = shard.n_steps
    expected = [(a.path, a.dtype, a.trailing, n) for a in step_arrays(shard.spec, shard.has_pairs)
                if shard.has_images or a.name != "image"]
    expected += [(f"meta/{c}", dt, (), shard.n_episodes) for c, (dt, _) in EPISODE_COLUMNS.items()]
    expected += [(f"meta/dr/{p.name}", p.dtype, p.shape, shard.n_episodes)
                 for p in shard.spec.episode_dr_params]
    return expected


def _structure_problem(shard: ShardReader, key: str, dtype: Any, trailing: tuple[int, ...],
                       committed: int) -> str | None:
    """What is wrong with array ``key`` before a byte of it is decoded: absent, another dtype or
    shape, fewer rows than ``committed``."""
    try:
        arr = shard.array(key)
    except TwistError as exc:
        return str(exc).split(": ", 1)[-1]
    if arr.dtype != np.dtype(dtype) or tuple(arr.shape[1:]) != trailing:
        return (f"has dtype {arr.dtype} and shape {arr.shape}, expected {dtype} "
                f"[*, {', '.join(map(str, trailing))}]")
    if arr.shape[0] < committed:
        return f"holds {arr.shape[0]} rows but {committed} are committed (truncated)"
    return None


def quick_problems(path: str | os.PathLike[str]) -> list[str]:
    """What a look at the dataset at ``path`` finds wrong without decoding anything: shards
    that do not open, arrays absent, of another shape or shorter than their commit record,
    chunk files missing. An empty list is no clean bill of health: only
    :func:`verify_dataset` decodes and checksums every byte."""
    found = []
    for p in find_shards(Path(path)):
        try:
            shard = ShardReader(p)
        except TwistError as exc:
            found.append(f"shard {p.name}: {exc}")
            continue
        for key, dtype, trailing, committed in _expected_arrays(shard):
            structure = _structure_problem(shard, key, dtype, trailing, committed)
            gaps = shard.missing_chunks(key, 0, committed) if structure is None else []
            if gaps:
                structure = f"{len(gaps)} chunk file(s) missing"
            if structure is not None:
                found.append(f"shard {shard.name}, {key}: {structure}")
            elif key in FRAME_PATHS:  # each frame file's own index: a few KiB, no frame
                arr = shard.array(key)
                per_file = rows_per_file(arr)
                for a in range(0, committed, per_file):
                    index = _shard_index_problem(
                        arr, shard.path / key, a // per_file,
                        per_file * shard.spec.views)
                    if index:
                        found.append(f"shard {shard.name}, {key}: "
                                     f"{shard.rows_of(key, a, min(a + per_file, committed))}: "
                                     f"{index}")
    return found


def require_intact(path: str | os.PathLike[str], needed_by: str) -> None:
    """Raise :class:`~twist_data.errors.DatasetCorruptError` naming the first problem
    :func:`quick_problems` finds in the dataset at ``path`` (no frame decoded), or the
    first episode rule it breaks (:mod:`twist_data.rules`, on its low-dimensional arrays):
    what every reader that would otherwise read around the damage (an export of one
    episode) asks first."""
    found = quick_problems(path)
    if found:
        more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
        raise DatasetCorruptError(f"{needed_by} refuses dataset {str(path)!r}: {found[0]}{more};"
                                  f" twist-data verify {path} lists every problem")
    broken = open_dataset(path).rule_problem(("state", "action"))
    if broken is not None:
        raise DatasetCorruptError(f"{needed_by} refuses {broken}")


def _check_episodes(shard: ShardReader, loaded: dict[str, np.ndarray],
                    problem: Callable[..., None]) -> None:
    """The writer's own rules (:func:`~twist_data.schema.episode_problems`, one source) on
    every committed episode whose arrays all read, and the stored return against the
    rewards. Images are checked for shape only (their bytes were checked above)."""
    spec = shard.spec
    names = [a.name for a in step_arrays(spec) if a.name not in FRAME_ARRAYS]
    if not all(f"data/{name}" in loaded for name in names):
        return  # a damaged array was reported already; its episodes cannot be judged
    frame_shape = (spec.views, *spec.image_shape)
    returns = shard.episode_column("episode_return")
    policies = shard.policy_names
    for e, (a, b) in enumerate(zip(shard.episode_starts.tolist(), shard.episode_ends.tolist(),
                                   strict=True)):
        data = {name: loaded[f"data/{name}"][a:b] for name in names}
        data["image"] = np.broadcast_to(np.zeros((), np.uint8), (b - a, *frame_shape))
        if shard.has_pairs:
            data[PAIR_IMAGE] = data["image"]
        dr = {k.removeprefix("dr/"): data.pop(k) for k in list(data) if k.startswith("dr/")}
        code = int(shard.episode_column("episode_policy")[e])
        try:
            info = EpisodeInfo(
                seed=int(shard.episode_column("episode_seed")[e]),
                policy=policies.get(code, f"code {code}"),
                teacher_step=int(shard.episode_column("episode_teacher_step")[e]),
                env_step=int(shard.episode_column("episode_env_step")[e]),
                dr={p.name: shard.episode_column(f"dr/{p.name}")[e]
                    for p in spec.episode_dr_params})
        except TwistError as exc:
            problem(str(exc), "meta/episode_policy", e)
            continue
        for message in episode_problems(Episode(**data, dr=dr), info, spec, shard.has_pairs):
            problem(message, None, e)
    # The rules every reader applies (twist_data.rules) beyond the writer's own above.
    actions = np.nan_to_num(loaded["data/action"])  # a NaN is the writer's rule, named above
    for e, rule in rule_problems(shard.episode_starts, shard.episode_ends,
                                 {"action": actions, "reward": loaded["data/reward"]}, returns):
        problem(rule, "meta/episode_return" if "return" in rule else "data/action", e)


def verify_dataset(path: str | os.PathLike[str],
                   on_progress: Callable[[int, int], None] | None = None) -> VerifyReport:
    """Check every shard of the dataset at ``path``; never modifies anything.

    ``on_progress(done, total)`` reports image steps checked. Raises
    :class:`~twist_data.errors.NotADatasetError` only when ``path`` holds no shard at all;
    every other problem lands in the report.
    """
    path = Path(path)
    report = VerifyReport(path)
    shards: list[ShardReader] = []
    for p in find_shards(path):
        try:
            shards.append(ShardReader(p))
        except TwistError as exc:
            report.problems.append(Problem(p.name.removesuffix(".zarr"), str(exc)))
    report.shards = len(shards)
    if shards:
        ref = shards[0]
        for s in shards[1:]:
            if s.spec.schema_key() != ref.spec.schema_key():
                report.problems.append(Problem(
                    s.name, f"schema differs from shard {ref.name}; they cannot form one dataset"))
            elif s.has_pairs != ref.has_pairs:
                report.problems.append(Problem(
                    s.name, f"{'stores' if s.has_pairs else 'lacks'} the frame pairs "
                            f"(data/{PAIR_IMAGE}) that shard {ref.name} "
                            f"{'lacks' if s.has_pairs else 'stores'}", f"data/{PAIR_IMAGE}"))
    total = sum(s.n_steps * (2 if s.has_pairs else 1) for s in shards)
    done = 0

    def tick(steps: int) -> None:
        nonlocal done
        done += steps
        if on_progress is not None:
            on_progress(done, total)

    for shard in shards:
        _verify_shard(shard, report, tick)
        report.episodes += shard.n_episodes
        report.steps += shard.n_steps
    log.info("verified %s: %d problem(s)", path, len(report.problems))
    return report
