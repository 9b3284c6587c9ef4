"""Windows from a copy of D decoded once (ResidentWindows) against the sampler that decodes
each batch (WindowSampler, frame cache off), in one run on one synthetic dataset: batches of
16 windows of L=50, K=2, 64x64, on the CPU (``--device cuda`` where one is lent: there the
copy also saves the host-to-device transfer, which this measures with the sampler's batch
moved to the device). The same for the first stage's single frames (FrameBatches, 64 frames a
batch, decoded against gathered from the copy). Prints one JSON line with windows/s and
frames/s (medians of 5 slices), the copy's bytes and the seconds it took to build.

    python benchmarks/resident_windows.py [--steps 4000] [--seconds 6] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import (
    ResidentWindows,
    SamplerConfig,
    WindowSampler,
    resident_bytes,
    resident_images,
)
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.frame_targets import FrameBatches, FrameRows

B, L = 16, 50
FRAME_BATCH = 64
KEYS = ("image", "state", "action", "is_first")


def per_second(batch_fn, seconds: float, size: int = B) -> float:
    slices, n, start = [], 0, time.perf_counter()
    while len(slices) < 5:
        batch_fn()
        n += 1
        now = time.perf_counter()
        if now - start >= seconds / 5 and n >= 2:
            slices.append(n * size / (now - start))
            n, start = 0, now
    return statistics.median(slices)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        episodes = max(args.steps // 200, 1)
        path = write_synthetic_dataset(Path(tmp) / "ds", SynthConfig(
            episodes=episodes, steps=200, views=2, image_size=64, seed=0))
        config = SamplerConfig(length=L, batch_size=B, keys=KEYS, cache_bytes=0, seed=0)
        sampler = WindowSampler(path, config)

        def decoded() -> None:
            batch = sampler.batch()
            for key in KEYS:
                torch.as_tensor(batch[key]).to(device)
            if device.type == "cuda":
                torch.cuda.synchronize(device)

        t0 = time.perf_counter()
        resident = ResidentWindows(path, config, device)
        build = time.perf_counter() - t0

        def gathered() -> None:
            resident.batch()
            if device.type == "cuda":
                torch.cuda.synchronize(device)

        baseline = per_second(decoded, args.seconds)
        copy = per_second(gathered, args.seconds)

        data = open_dataset(path)
        rows = FrameRows.of(data, np.arange(data.n_episodes))
        frames_decoded = FrameBatches(data, rows, FRAME_BATCH, seed=0)
        frames_resident = FrameBatches(data, rows, FRAME_BATCH, seed=0,
                                       images=resident_images(data, device))

        def frames(batches: FrameBatches) -> None:
            batch = batches.batch()
            batch["image"].to(device)
            if device.type == "cuda":
                torch.cuda.synchronize(device)

        frame_baseline = per_second(lambda: frames(frames_decoded), args.seconds, FRAME_BATCH)
        frame_copy = per_second(lambda: frames(frames_resident), args.seconds, FRAME_BATCH)
        print(json.dumps({
            "device": str(device), "steps": episodes * 200, "batch": B, "length": L,
            "sampler_windows_per_s": round(baseline, 1),
            "resident_windows_per_s": round(copy, 1),
            "speedup": round(copy / baseline, 2),
            "resident_bytes": resident_bytes(resident.sampler.dataset, KEYS),
            "build_s": round(build, 2),
            "decoded_frames_per_s": round(frame_baseline, 1),
            "resident_frames_per_s": round(frame_copy, 1),
            "frames_speedup": round(frame_copy / frame_baseline, 2)}))


if __name__ == "__main__":
    main()
