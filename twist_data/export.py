"""Exports: a video of one episode's K views, and the whole dataset as one HDF5 file."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path

import cv2
import h5py
import numpy as np

from twist_data.errors import TwistError
from twist_data.reader import open_dataset
from twist_data.schema import EPISODE_COLUMNS, FORMAT_VERSION, step_arrays
from twist_data.staging import require_memory, require_new_file
from twist_data.verify import require_intact

log = logging.getLogger(__name__)

HDF5_FORMAT = "twist.matching-dataset.hdf5"


class ExportError(TwistError):
    """An export could not be written."""


def episode_strip(images: np.ndarray, scale: int = 4) -> np.ndarray:
    """Lay out K views side by side: [T, K, H, W, 3] -> [T, H*scale, K*W*scale, 3] (RGB)."""
    t, k, h, w, c = images.shape
    strip = images.transpose(0, 2, 1, 3, 4).reshape(t, h, k * w, c)
    return np.repeat(np.repeat(strip, scale, axis=1), scale, axis=2)


def export_video(dataset_path: str | os.PathLike[str], episode: int, out: str | os.PathLike[str],
                 fps: int = 25, scale: int = 4, overwrite: bool = False) -> Path:
    """Write episode ``episode`` (global index) as an ``.mp4`` or ``.gif`` with its K views;
    an existing ``out`` only with ``overwrite``."""
    if scale < 1:
        raise ExportError(f"scale must be >= 1, got {scale}")
    _check_video_path(Path(out), fps)
    require_new_file(Path(out), overwrite, "video file")
    require_intact(dataset_path, "export-video")
    ds = open_dataset(dataset_path)
    shard, local = ds.episode_location(episode)  # refuses an index out of range
    spec, reader = ds.spec, ds.shards[shard]
    length = int(reader.episode_ends[local] - reader.episode_starts[local])
    # The upscaled strip, and the episode's frames it is made from, are held whole.
    strip = length * spec.views * spec.image_height * spec.image_width * 3 * (scale ** 2 + 1)
    require_memory(strip, f"episode {episode}'s video at scale {scale}")
    return write_video(episode_strip(ds.episode(episode).image, scale), out, fps)


def _check_video_path(out: Path, fps: int) -> None:
    if out.suffix.lower() not in (".mp4", ".gif"):
        raise ExportError(f"video file must end in .mp4 or .gif, got {out.name!r}")
    if fps < 1:
        raise ExportError(f"fps must be >= 1, got {fps}")


def write_video(frames: np.ndarray, out: str | os.PathLike[str], fps: int = 25) -> Path:
    """Write RGB frames [T, H, W, 3] uint8 as an ``.mp4`` or ``.gif``, atomically."""
    out = Path(out)
    _check_video_path(out, fps)
    suffix = out.suffix.lower()
    bgr = np.asarray(frames)[..., ::-1]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial{suffix}")
    if suffix == ".mp4" and _h264_available():
        _write_h264(np.asarray(frames), tmp, fps)
    elif suffix == ".mp4":
        log.warning("writing %s as MPEG-4 Part 2, which browsers do not play; "
                    "pip install 'twist[video]' for H.264", out)
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                 (bgr.shape[2], bgr.shape[1]))
        if not writer.isOpened():
            raise ExportError(f"OpenCV cannot write mp4 video to {out}")
        for frame in bgr:
            writer.write(np.ascontiguousarray(frame))
        writer.release()
    else:
        animation = cv2.Animation()
        animation.frames = [np.ascontiguousarray(f) for f in bgr]
        animation.durations = [int(1000 / fps)] * len(bgr)
        if not cv2.imwriteanimation(str(tmp), animation):
            raise ExportError(f"OpenCV cannot write gif animation to {out}")
    os.replace(tmp, out)
    return out


def _h264_available() -> bool:
    try:
        import av
    except ImportError:
        return False
    return "libx264" in av.codecs_available


def _write_h264(frames: np.ndarray, path: Path, fps: int) -> None:
    """RGB frames [T, H, W, 3] as H.264 in yuv420p (what browsers play) through PyAV; odd
    sides are padded by one edge row or column, which the pixel format needs."""
    import av

    h, w = frames.shape[1:3]
    frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    with av.open(str(path), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv420p"
        # Near-lossless: the renders are small and their detail (a one-pixel pole) is the point.
        stream.options = {"crf": "12", "preset": "medium"}
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(
                np.ascontiguousarray(frame), format="rgb24")))
        container.mux(stream.encode())


def export_hdf5(dataset_path: str | os.PathLike[str], out: str | os.PathLike[str],
                on_progress: Callable[[int, int], None] | None = None,
                overwrite: bool = False) -> Path:
    """Write every committed episode into one HDF5 file (layout in ``datasets.md``); an
    existing ``out`` only with ``overwrite``.

    Episodes are streamed one at a time, so memory stays bounded by the longest episode.
    The file is written under a temporary name and renamed when complete.
    """
    out = Path(out)
    if out.is_dir():
        raise TwistError(f"{out} is a folder; give the path of the .h5 file to write")
    require_new_file(out, overwrite, "HDF5 file")
    require_intact(dataset_path, "export-hdf5")
    ds = open_dataset(dataset_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial")
    spec = ds.spec
    n = ds.n_steps
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = HDF5_FORMAT
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["spec"] = json.dumps(spec.to_json())
            f.attrs["source"] = str(ds.path)
            f.attrs["shards"] = json.dumps([s.name for s in ds.shards])
            data = f.create_group("data")
            arrays = {}
            for a in step_arrays(spec):
                chunk = (1, *a.trailing) if a.name == "image" else (min(max(n, 1), 1024),
                                                                     *a.trailing)
                arrays[a.name] = data.create_dataset(
                    a.name, shape=(n, *a.trailing), dtype=a.dtype, chunks=chunk,
                    compression="gzip", compression_opts=4 if a.name == "image" else 6)
            for i, episode in ds.iter_episodes():
                a, b = int(ds.episode_starts[i]), int(ds.episode_ends[i])
                for name, values in episode.arrays().items():
                    arrays[name][a:b] = values
                if on_progress is not None:
                    on_progress(i + 1, ds.n_episodes)
            meta = f.create_group("meta")
            table = ds.episodes()
            meta.create_dataset("episode_ends", data=ds.episode_ends)
            shard_ids = {s.name: i for i, s in enumerate(ds.shards)}
            meta.create_dataset("episode_shard",
                                data=table["shard"].map(shard_ids).to_numpy(np.int64))
            for column in EPISODE_COLUMNS:
                if column == "episode_ends":
                    continue
                meta.create_dataset(column, data=np.concatenate(
                    [s.episode_column(column) for s in ds.shards]))
            for p in spec.episode_dr_params:
                meta.create_dataset(f"dr/{p.name}", data=np.concatenate(
                    [s.episode_column(f"dr/{p.name}") for s in ds.shards]))
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


__all__ = ["ExportError", "episode_strip", "export_hdf5", "export_video"]
