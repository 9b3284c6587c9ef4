"""D as a LeRobotDataset v3.0 folder, the layout LeRobot's ``LeRobotDataset(repo_id, root=OUT)``
reads: ``data/`` Parquet rows, one MP4 per view under ``videos/``, and ``meta/`` (``info.json``,
``stats.json``, ``tasks.parquet``, the episodes table). Written with PyArrow and PyAV alone, so
that LeRobot need not install beside twist.

Each LeRobot frame pairs an observation with the action taken from it (LeRobot's convention),
where D's step t holds the action that *led to* t: frame t of an episode of T steps is D's
observation t (every view, the privileged state as ``observation.environment_state``, the
physics state) with D's action, reward and flags of step t + 1, so an episode gives T - 1
frames and its final observation, from which nothing was done, is not one. Frames are stored
losslessly (H.264 over RGB, constant quantiser 0): they decode to D's bytes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
from collections.abc import Callable, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twist_data.errors import MissingExtraError, TwistError, import_extra
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.sampler import heldout_episodes
from twist_data.schema import FORMAT_VERSION
from twist_data.staging import require_writable
from twist_data.verify import require_intact

log = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"
#: Lossless H.264 over RGB planes: a 64-pixel render's one-pixel pole survives, which 4:2:0
#: chroma (LeRobot's default) blurs by up to 238 levels; ~1/3 of the raw frames' bytes.
VIDEO_CODEC = "libx264rgb"
#: Constant quantiser 0 (lossless), a key frame every 2 frames (LeRobot's GOP, so one frame
#: decodes from at most one before it), no B-frames (decode order is frame order), and x264's
#: veryfast search: 0.6x the encoding time of its default for 3% more bytes.
VIDEO_OPTIONS = {"qp": "0", "g": "2", "bf": "0", "preset": "veryfast"}
#: LeRobot's statistics: these quantiles besides min, max, mean, std and count.
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
#: Frames a view's statistics sample per episode: LeRobot's rule, at most this many.
MAX_STAT_FRAMES = 10_000
#: The held-out split the distiller draws by default (every 10th episode of D).
HOLDOUT_EVERY = 10
DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
CHUNK = "chunk-000/file-000"


class LeRobotExportError(TwistError):
    """A LeRobot export could not be written."""


def view_key(view: int) -> str:
    """The LeRobot feature of D's view ``view``."""
    return f"observation.images.view_{view}"


def _dependencies() -> tuple[Any, Any, Any]:
    reason = "exporting to LeRobot needs"
    av = import_extra("av", "lerobot", reason)
    pa = import_extra("pyarrow", "lerobot", reason)
    pq = import_extra("pyarrow.parquet", "lerobot", reason)
    if VIDEO_CODEC not in av.codecs_available:
        raise MissingExtraError(f"this PyAV build has no {VIDEO_CODEC} encoder, which the "
                                "lossless videos need; PyPI's av wheels bundle it: pip install "
                                "'twist[lerobot]'")
    return av, pa, pq


def _chosen(given: Sequence[int] | None, count: int, what: str) -> list[int]:
    """``given`` indices (negative from the end) as sorted non-negative ones; all if None."""
    if given is None:
        return list(range(count))
    chosen = []
    for index in given:
        if not -count <= index < count:
            raise LeRobotExportError(f"the dataset has {count} {what}s; {what} {index} is out "
                                     "of range")
        chosen.append(index % count)
    if len(set(chosen)) != len(chosen):
        raise LeRobotExportError(f"{what}s {list(given)} name one {what} twice")
    if not chosen:
        raise LeRobotExportError(f"no {what} to export: the list is empty")
    return sorted(chosen)


def step_rate(data: MatchingDataset, fps: int | None) -> int:
    """Frames per second of D's agent steps: ``fps`` if given, else from the stored physics'
    clock (the ``time`` component that DMC and the Panda tasks store)."""
    if fps is not None:
        if fps < 1:
            raise LeRobotExportError(f"fps must be >= 1, got {fps}")
        return fps
    layout = [name for name, _ in data.spec.extra.get("physics_layout", [])]
    if layout[:1] == ["time"]:
        lengths = data.episode_lengths
        first = int(np.argmax(lengths >= 2)) if (lengths >= 2).any() else None
        if first is not None:
            clock = data.episode(first, images=False).physics[:2, 0]
            step = float(clock[1] - clock[0])
            if step > 0 and abs(1 / step - round(1 / step)) < 1e-6:
                return round(1 / step)
            raise LeRobotExportError(f"an agent step of {step} s is no whole number of frames "
                                     "per second, which LeRobot needs; pass --fps")
    raise LeRobotExportError(f"the physics of {str(data.path)!r} keeps no clock to tell a "
                             "step's duration; pass --fps")


def _names(layout: Sequence[Sequence[Any]]) -> list[str] | None:
    names = []
    for name, size in layout:
        names += [str(name)] if int(size) == 1 else [f"{name}_{i}" for i in range(int(size))]
    return names or None


def features(data: MatchingDataset, views: Sequence[int]) -> dict[str, dict[str, Any]]:
    """The LeRobot features of an export of ``views`` (info.json's ``features``)."""
    spec = data.spec
    out: dict[str, dict[str, Any]] = {}
    for k in views:
        out[view_key(k)] = {"dtype": "video",
                            "shape": [spec.image_height, spec.image_width, 3],
                            "names": ["height", "width", "channels"]}
    out["observation.environment_state"] = {
        "dtype": "float32", "shape": [spec.state_dim], "names": _names(spec.state_layout)}
    out["observation.physics"] = {
        "dtype": "float64", "shape": [spec.physics_dim],
        "names": _names(spec.extra.get("physics_layout", []))}
    out["action"] = {"dtype": "float32", "shape": [spec.action_dim], "names": None}
    out["next.reward"] = {"dtype": "float32", "shape": [1], "names": None}
    out["next.done"] = {"dtype": "bool", "shape": [1], "names": None}
    out["next.terminal"] = {"dtype": "bool", "shape": [1], "names": None}
    for p in spec.dr_params:
        size = int(np.prod(p.shape, dtype=np.int64))
        names = [f"view_{k}" if size == 1 else f"view_{k}_{i}" for k in views for i in range(size)]
        out[f"dr.{p.name}"] = {"dtype": p.dtype, "shape": [len(views) * size], "names": names}
    return {**out, **DEFAULT_FEATURES}


def _columns(episode: Any, views: Sequence[int], spec: Any) -> dict[str, np.ndarray]:
    """An episode's LeRobot columns (no video), T - 1 rows."""
    n = len(episode) - 1
    out = {"observation.environment_state": episode.state[:n],
           "observation.physics": episode.physics[:n],
           "action": episode.action[1:],
           "next.reward": episode.reward[1:],
           "next.done": episode.is_last[1:],
           "next.terminal": episode.is_terminal[1:]}
    for p in spec.dr_params:
        out[f"dr.{p.name}"] = np.asarray(episode.dr[p.name])[:n][:, list(views)].reshape(n, -1)
    return out


# -- statistics, as LeRobot computes them (compute_stats.py) --------------------------------
def numeric_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's statistics of one episode's values [n] or [n, D] (a scalar feature keeps a
    trailing axis of 1): min, max, mean, population std, count and the quantiles."""
    x = np.asarray(values)
    if x.ndim == 1:
        x = x[:, None]
    f = x.astype(np.float64)
    stats: dict[str, np.ndarray] = {
        "min": x.min(0), "max": x.max(0), "mean": f.mean(0), "std": f.std(0),
        "count": np.array([len(x)])}
    # The smallest value whose share of values at or below it reaches q: what LeRobot's
    # 5,000-bin histograms approximate (to a bin's width).
    quantiles = np.quantile(f, QUANTILES, axis=0, method="inverted_cdf")
    for q, value in zip(QUANTILES, quantiles, strict=True):
        stats[f"q{round(q * 100):02d}"] = value
    return stats


def stat_frames(length: int) -> np.ndarray:
    """The frames of an episode of ``length`` whose pixels LeRobot's image statistics read."""
    count = max(min(100, length), min(int(length ** 0.75), MAX_STAT_FRAMES))
    return np.round(np.linspace(0, length - 1, count)).astype(np.int64)


def image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-channel statistics of RGB frames [n, H, W, 3] uint8, in [0, 1], each of
    shape (3, 1, 1) (count: [n]); frames with a side of 300 pixels or more are read at the
    stride that brings them to ~150, as LeRobot reads them. Computed from each channel's
    histogram of its 256 levels: exact, and ~50x faster than on the pixels as floats."""
    side = max(frames.shape[1:3])
    if side >= 300:
        stride = int(side / 150)
        frames = frames[:, ::stride, ::stride]
    counts = np.stack([np.bincount(frames[..., c].ravel(), minlength=256) for c in range(3)])
    levels = np.arange(256) / 255.0
    total = counts.sum(1, keepdims=True).astype(np.float64)
    mean = (counts @ levels) / total[:, 0]
    std = np.sqrt(np.maximum((counts @ levels ** 2) / total[:, 0] - mean ** 2, 0.0))
    seen = counts > 0
    stats = {"min": levels[seen.argmax(1)], "max": levels[255 - seen[:, ::-1].argmax(1)],
             "mean": mean, "std": std}
    cumulative = counts.cumsum(1)
    stats["count"] = np.array([len(frames)])
    for q in QUANTILES:  # the smallest level whose share at or below it reaches q
        at = (cumulative >= np.ceil(q * total - 1e-9)).argmax(1)
        stats[f"q{round(q * 100):02d}"] = levels[at]
    return {k: v if k == "count" else v.reshape(3, 1, 1) for k, v in stats.items()}


def aggregate(episodes: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One feature's statistics over episodes, combined as LeRobot combines them: min and max
    elementwise, the mean and variance pooled by count, each quantile count-weighted."""
    counts = np.array([float(e["count"][0]) for e in episodes])
    weights = counts / counts.sum()
    shape = (-1,) + (1,) * (np.asarray(episodes[0]["mean"]).ndim)
    w = weights.reshape(shape)
    means = np.stack([e["mean"] for e in episodes]).astype(np.float64)
    mean = (w * means).sum(0)
    variances = np.stack([e["std"] for e in episodes]).astype(np.float64) ** 2
    out = {"min": np.min(np.stack([e["min"] for e in episodes]), 0),
           "max": np.max(np.stack([e["max"] for e in episodes]), 0),
           "mean": mean,
           "std": np.sqrt((w * (variances + (means - mean) ** 2)).sum(0)),
           "count": np.array([int(counts.sum())])}
    for q in QUANTILES:
        key = f"q{round(q * 100):02d}"
        out[key] = (w * np.stack([e[key] for e in episodes]).astype(np.float64)).sum(0)
    return out


def _listed(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {f: {k: np.asarray(v).tolist() for k, v in s.items()} for f, s in stats.items()}


# -- writing ----------------------------------------------------------------------------------
class _Videos:
    """One lossless MP4 per exported view, every episode in it back to back."""

    def __init__(self, av: Any, root: Path, views: Sequence[int], fps: int, size: tuple[int, int]):
        self.av, self.fps, self.frames = av, fps, 0
        self.containers, self.streams = {}, {}
        for k in views:
            path = root / "videos" / view_key(k) / f"{CHUNK}.mp4"
            path.parent.mkdir(parents=True)
            container = av.open(str(path), mode="w", format="mp4")
            stream = container.add_stream(VIDEO_CODEC, rate=fps, options=dict(VIDEO_OPTIONS))
            stream.height, stream.width = size
            stream.pix_fmt = "rgb24"
            self.containers[k], self.streams[k] = container, stream

    def write(self, images: np.ndarray) -> None:
        """Frames [n, K, H, W, 3] of the exported views (in ``views`` order)."""
        for j, k in enumerate(self.containers):
            stream = self.streams[k]
            for i, frame in enumerate(images[:, j]):
                video_frame = self.av.VideoFrame.from_ndarray(np.ascontiguousarray(frame),
                                                              format="rgb24")
                video_frame.pts = self.frames + i
                video_frame.time_base = Fraction(1, self.fps)
                self.containers[k].mux(stream.encode(video_frame))
        self.frames += len(images)

    def close(self) -> dict[str, Any]:
        """Flush and close every file; the ``info`` block LeRobot records for a video."""
        info = {}
        for k, container in self.containers.items():
            stream = self.streams[k]
            container.mux(stream.encode())
            info = {"video.height": stream.height, "video.width": stream.width,
                    "video.codec": stream.codec_context.codec.canonical_name,
                    "video.pix_fmt": stream.pix_fmt, "video.is_depth_map": False,
                    "video.fps": self.fps, "video.channels": 3, "has_audio": False}
            container.close()
        return info

    def abort(self) -> None:
        """Close every file as it is (the export failed; its folder is removed)."""
        for container in self.containers.values():
            with contextlib.suppress(Exception):  # a half-written file is deleted just after
                container.close()


def _table(pa: Any, columns: dict[str, np.ndarray], feats: dict[str, dict[str, Any]]) -> Any:
    """The Parquet table of the non-video ``feats`` (in their order): a feature of shape [1]
    as a scalar column, one of shape [N] as fixed-size lists."""
    arrays, names = [], []
    for name, feature in feats.items():
        if feature["dtype"] == "video":
            continue
        values = np.asarray(columns[name])
        dtype = np.dtype(feature["dtype"])
        if feature["shape"] == [1]:
            arrays.append(pa.array(values.reshape(-1).astype(dtype)))
        else:
            flat = pa.array(values.astype(dtype).reshape(-1))
            arrays.append(pa.FixedSizeListArray.from_arrays(flat, int(feature["shape"][0])))
        names.append(name)
    return pa.Table.from_arrays(arrays, names=names)


def _replaceable(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise LeRobotExportError(f"output {str(out)!r} is a file; name a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise LeRobotExportError(f"output {str(out)!r} exists and is not empty; pass "
                                     "--overwrite to replace it")
        if not (out / "meta" / "info.json").is_file():
            raise LeRobotExportError(f"output {str(out)!r} is not a LeRobot dataset (no "
                                     "meta/info.json), so --overwrite does not replace it")
    # The export is built beside ``out`` and renamed into place: its folder must take it.
    require_writable(out.parent if out.exists() else out, "output")


def export_lerobot(dataset_path: str | os.PathLike[str], out: str | os.PathLike[str],
                   episodes: Sequence[int] | None = None, views: Sequence[int] | None = None,
                   fps: int | None = None, overwrite: bool = False,
                   on_progress: Callable[[int, int], None] | None = None) -> Path:
    """Write D's ``episodes`` (global indices, negative from the end; all if None, exported in
    D's order) and ``views`` (all if None) as a LeRobotDataset v3.0 folder ``out`` at ``fps``
    frames per second (None: from the stored physics' clock). A folder that is not empty is
    replaced only with ``overwrite``, and only if it holds a LeRobot dataset. The folder is
    built aside and renamed into place when whole."""
    out = Path(out)
    _replaceable(out, overwrite)
    av, pa, pq = _dependencies()
    require_intact(dataset_path, "export-lerobot")
    data = open_dataset(dataset_path)
    data.require_images("export-lerobot")
    if data.n_episodes == 0:
        raise LeRobotExportError(f"{data.path} holds no committed episode to export")
    chosen = _chosen(episodes, data.n_episodes, "episode")
    shown = _chosen(views, data.spec.views, "view")
    short = [i for i in chosen if data.episode_lengths[i] < 2]
    if short and episodes is not None:
        raise LeRobotExportError(f"episode {short[0]} has one step, from which no action was "
                                 "taken: it gives LeRobot no frame")
    if short:
        log.info("leaving out %d one-step episodes (no action was taken in them): %s",
                 len(short), short)
        skipped = set(short)
        chosen = [i for i in chosen if i not in skipped]
        if not chosen:
            raise LeRobotExportError(f"every episode of {data.path} has one step: there is no "
                                     "frame to export")
    rate = step_rate(data, fps)
    spec = data.spec
    feats = features(data, shown)
    held = heldout_episodes(data.n_episodes, HOLDOUT_EVERY)
    table = data.episodes()
    staging = out.parent / f".{out.name}.lerobot-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    videos = None
    try:
        staging.mkdir(parents=True)
        videos = _Videos(av, staging, shown, rate, spec.image_shape[:2])
        parts: dict[str, list[np.ndarray]] = {}
        per_episode: list[dict[str, Any]] = []
        stats: dict[str, list[dict[str, np.ndarray]]] = {}
        start = 0
        for done, index in enumerate(chosen, 1):
            episode = data.episode(index)
            n = len(episode) - 1
            columns = _columns(episode, shown, spec)
            columns.update({
                "timestamp": np.arange(n, dtype=np.float32) / np.float32(rate),
                "frame_index": np.arange(n, dtype=np.int64),
                "episode_index": np.full(n, done - 1, np.int64),
                "index": np.arange(start, start + n, dtype=np.int64),
                "task_index": np.zeros(n, np.int64)})
            images = episode.image[:n][:, shown]
            videos.write(images)
            episode_stats = {name: numeric_stats(columns[name]) for name in columns}
            sample = stat_frames(n)
            for j, k in enumerate(shown):
                episode_stats[view_key(k)] = image_stats(images[sample, j])
            for name, value in columns.items():
                parts.setdefault(name, []).append(value)
            for name, value in episode_stats.items():
                stats.setdefault(name, []).append(value)
            info = data.episode_info(index)
            row: dict[str, Any] = {
                "episode_index": done - 1, "tasks": [spec.task], "length": n,
                "data/chunk_index": 0, "data/file_index": 0,
                "dataset_from_index": start, "dataset_to_index": start + n}
            for k in shown:
                row.update({f"videos/{view_key(k)}/chunk_index": 0,
                            f"videos/{view_key(k)}/file_index": 0,
                            f"videos/{view_key(k)}/from_timestamp": start / rate,
                            f"videos/{view_key(k)}/to_timestamp": (start + n) / rate})
            row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                        "twist/episode": index, "twist/shard": str(table["shard"].iloc[index]),
                        "twist/seed": info.seed, "twist/policy": info.policy,
                        "twist/teacher_step": info.teacher_step, "twist/env_step": info.env_step,
                        "twist/return": float(episode.reward.sum()),
                        "twist/heldout": bool(held[index])})
            for name, value in info.dr.items():
                row[f"twist/dr/{name}"] = np.asarray(value).tolist()
            for name, value in episode_stats.items():
                row.update({f"stats/{name}/{k}": np.asarray(v).tolist() for k, v in value.items()})
            per_episode.append(row)
            start += n
            if on_progress is not None:
                on_progress(done, len(chosen))
        video_info, videos = videos.close(), None
        for k in shown:
            feats[view_key(k)]["info"] = dict(video_info)
        columns = {name: np.concatenate(values) for name, values in parts.items()}
        (staging / "data" / "chunk-000").mkdir(parents=True)
        pq.write_table(_table(pa, columns, feats), staging / "data" / f"{CHUNK}.parquet",
                       compression="snappy")
        (staging / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist(per_episode),
                       staging / "meta" / "episodes" / f"{CHUNK}.parquet", compression="snappy")
        pd.DataFrame({"task_index": np.zeros(1, np.int64)},
                     index=pd.Index([spec.task], name="task")).to_parquet(
            staging / "meta" / "tasks.parquet")
        _write_json(staging / "meta" / "stats.json",
                    _listed({name: aggregate(values) for name, values in stats.items()}))
        _write_json(staging / "meta" / "info.json", {
            "codebase_version": CODEBASE_VERSION, "robot_type": None,
            "total_episodes": len(chosen), "total_frames": start, "total_tasks": 1,
            "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 200,
            "fps": rate, "splits": {"train": f"0:{len(chosen)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
            "features": feats})
        _write_json(staging / "meta" / "twist.json", {
            "source": str(data.path), "format_version": FORMAT_VERSION,
            "shards": [s.name for s in data.shards], "episodes": chosen, "views": shown,
            "holdout_every": HOLDOUT_EVERY,
            "frames": "frame t: D's observation t with the action, reward and flags of step t + 1",
            "video": {"codec": VIDEO_CODEC, "options": VIDEO_OPTIONS},
            "spec": spec.to_json()})
        _into_place(staging, out)
    except BaseException as exc:
        if videos is not None:
            videos.abort()
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):
            raise LeRobotExportError(f"cannot write the LeRobot dataset {str(out)!r}: "
                                     f"{exc.strerror or exc}") from None
        raise
    log.info("wrote %d episodes (%d frames, %d views) of %s as a LeRobot dataset in %s",
             len(chosen), start, len(shown), data.path, out)
    return out


def _into_place(staging: Path, out: Path) -> None:
    """Rename the built ``staging`` to ``out``; an export ``out`` held before is set aside
    first and removed only once the new one is in place (put back if that fails)."""
    aside = out.parent / f".{out.name}.replaced-{os.getpid()}"
    if out.exists():
        os.rename(out, aside)
    try:
        os.rename(staging, out)
    except BaseException:
        if aside.exists():
            os.rename(aside, out)
        raise
    shutil.rmtree(aside, ignore_errors=True)


def _write_json(path: Path, value: Any) -> None:
    path.write_text(json.dumps(value, indent=4, ensure_ascii=False))


__all__ = ["LeRobotExportError", "export_lerobot", "features", "image_stats", "numeric_stats",
           "stat_frames", "view_key"]
