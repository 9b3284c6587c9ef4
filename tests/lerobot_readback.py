"""Reads a LeRobot export with LeRobot's own loader, in the reference environment
(scripts/reference_env.sh), and writes what it read to an .npz for tests/test_lerobot.py:

    python tests/lerobot_readback.py ROOT OUT.npz

The loader (``ledataset``, lerobot-dataset 0.4.4) opens the folder, its metadata, Parquet rows
and tasks; items are read through ``LeRobotDataset.__getitem__`` with the videos left out,
since LeRobot's decoders (torchcodec, torchvision's VideoReader) have no build for this CPU
torch. Each frame is decoded with PyAV at the time LeRobot asks its decoder for
(``videos/<key>/from_timestamp`` + the row's ``timestamp``), to the nearest frame within
LeRobot's tolerance.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

os.environ.update(HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1",
                  HF_DATASETS_CACHE=tempfile.mkdtemp(prefix="lerobot-cache-"))

import av
import numpy as np
import torch

# torchvision's wheel is built against CUDA torch and loads no ops beside this CPU build; its
# import registers fake kernels of these two, which must then exist (ledataset imports it).
_ops = torch.library.Library("torchvision", "DEF")
for _name in ("nms", "qnms"):
    _ops.define(f"{_name}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")

from ledataset.datasets import lerobot_dataset  # noqa: E402
from ledataset.datasets.compute_stats import (  # noqa: E402
    aggregate_stats,
    get_feature_stats,
    sample_indices,
)


def rgb(frame: av.VideoFrame) -> np.ndarray:
    """A decoded frame as RGB [H, W, 3]: a lossless frame's planes as they are (PyAV orders
    them RGB), without the ~7 ms per frame its conversion to rgb24 costs."""
    return frame.to_ndarray() if frame.format.name == "gbrp" else frame.to_ndarray(format="rgb24")


def main(root: str, out: str) -> None:
    dataset = lerobot_dataset.LeRobotDataset("twist/export", root=root)
    meta = dataset.meta
    videos = list(meta.video_keys)
    features = {k: {"dtype": v["dtype"], "shape": list(v["shape"])}
                for k, v in meta.features.items()}
    # Items without their videos, which the loader's decoders cannot open here (see above).
    dataset.meta.info["features"] = {k: v for k, v in meta.features.items() if k not in videos}
    items = [dataset[i] for i in range(len(dataset))]
    result: dict[str, np.ndarray] = {}
    for key in ("observation.environment_state", "observation.physics", "action", "next.reward",
                "next.done", "next.terminal", "timestamp", "episode_index", "index"):
        result[key] = np.stack([np.asarray(item[key]) for item in items])
    # LeRobot's items give float32; the rows themselves keep the stored dtypes.
    rows = dataset.hf_dataset.data  # the Arrow table the loader read
    result["rows.observation.physics"] = np.array(rows.column("observation.physics").to_pylist())
    result["task"] = np.array([item["task"] for item in items])
    for key in videos:
        frames = []
        path = os.path.join(root, meta.get_video_file_path(0, key))
        with av.open(path) as container:
            decoded = [(float(f.pts * f.time_base), rgb(f))
                       for f in container.decode(video=0)]
        times = np.array([t for t, _ in decoded])
        for item in items:
            episode = meta.episodes[int(item["episode_index"])]
            query = episode[f"videos/{key}/from_timestamp"] + float(item["timestamp"])
            nearest = int(np.argmin(np.abs(times - query)))
            if abs(times[nearest] - query) >= dataset.tolerance_s:
                raise SystemExit(f"{key}: no frame within {dataset.tolerance_s} s of {query}")
            frames.append(decoded[nearest][1])
        result[f"frames.{key}"] = np.stack(frames)
    # LeRobot's own statistics of the stored rows, to compare with meta/stats.json.
    ours = {}
    for key in ("observation.environment_state", "action", "next.reward"):
        per_episode = []
        for e in range(meta.total_episodes):
            values = result[key][result["episode_index"] == e]
            per_episode.append({key: get_feature_stats(values, axis=0,
                                                       keepdims=values.ndim == 1)})
        ours[key] = {k: np.asarray(v).tolist() for k, v in aggregate_stats(per_episode)[key].items()}
    for key in videos:
        per_episode = []
        for e in range(meta.total_episodes):
            frames = result[f"frames.{key}"][result["episode_index"] == e].transpose(0, 3, 1, 2)
            # As float: this version squares uint8 frames in uint8, which wraps (std 0).
            frames = frames.astype(np.float64)
            stats = get_feature_stats(frames[sample_indices(len(frames))], axis=(0, 2, 3),
                                      keepdims=True)
            per_episode.append({key: {k: v if k == "count" else np.squeeze(v / 255.0, axis=0)
                                      for k, v in stats.items()}})
        ours[key] = {k: np.asarray(v).tolist() for k, v in aggregate_stats(per_episode)[key].items()}
    summary = {"num_episodes": dataset.num_episodes, "num_frames": dataset.num_frames,
               "fps": dataset.fps, "video_keys": videos,
               "features": features,
               "stats": {k: {s: np.asarray(v).tolist() for s, v in meta.stats[k].items()}
                         for k in meta.stats},
               "lerobot_stats": ours,
               "episodes": [dict(meta.episodes[e]) for e in range(meta.total_episodes)]}
    result["summary"] = np.array(json.dumps(summary, default=str))
    np.savez(out, **result)


if __name__ == "__main__":
    main(*sys.argv[1:3])
