"""Sampler throughput: batches of 16 windows of L=50 from a 20,000-step, K=2, 64x64 dataset.

Compares, in one run and on one dataset:
  (a) this sampler: cold (no frame cache: every frame decoded), warm (default cache, after a
      warm-up), and cold with 2 DataLoader workers;
  (b) naive per-window slicing of the same zarr arrays (the usual replay-buffer pattern);
  (c) the same bytes as uncompressed NumPy memmaps in the page cache (the practical limit);
  (d) the sampler, cold and warm, on the same data written without checksums (format 1's
      layout): the cost of checking every frame's CRC32C (target: at most 10% slower);
  (e) the episode rules the sampler checks when it opens D (twist_data.rules), timed alone
      on a freshly opened D once the columns they read are loaded (which a sampler serving
      states, actions, rewards and flags loads anyway; timed apart), against 100 cold
      batches (target: at most 5% of them).
Each method runs in its own process so its peak RSS is its own. Prints one JSON line.

    python benchmarks/sampler_throughput.py [--steps 20000] [--dataset DIR] [--seconds 8]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from twist_data.reader import open_dataset
from twist_data.sampler import SamplerConfig, WindowDataset, WindowSampler
from twist_data.storage import StorageLayout
from twist_data.synth import SynthConfig, write_synthetic_dataset

B, L = 16, 50
KEYS = ("state", "action", "reward", "discount", "is_first", "is_last", "is_terminal")


def timed(batch_fn, seconds: float, min_batches: int = 3) -> dict:
    """Run batch_fn repeatedly; windows/s as the median over 5 equal time slices."""
    slices, n, t0 = [], 0, time.perf_counter()
    start = t0
    while True:
        batch_fn()
        n += 1
        now = time.perf_counter()
        if now - start >= seconds / 5 and n >= min_batches:
            slices.append(n * B / (now - start))
            n, start = 0, now
            if len(slices) == 5:
                break
    return {"windows_per_s": statistics.median(slices), "slices": [round(s, 1) for s in slices]}


def run_sampler(path: Path, cache_bytes: int, seconds: float, warmup: int) -> dict:
    sampler = WindowSampler(path, SamplerConfig(length=L, batch_size=B, cache_bytes=cache_bytes))
    for _ in range(warmup):
        sampler.batch()
    out = timed(sampler.batch, seconds)
    out["cache_hit_rate"] = sampler.cache.hits / max(sampler.cache.lookups, 1)
    return out


def run_loader(path: Path, seconds: float, workers: int) -> dict:
    from torch.utils.data import DataLoader

    config = SamplerConfig(length=L, batch_size=B, cache_bytes=0)
    it = iter(DataLoader(WindowDataset(path, config), batch_size=None, num_workers=workers,
                         prefetch_factor=4))
    for _ in range(2 * workers):
        next(it)
    out = timed(lambda: next(it), seconds)
    out["peak_rss_mib"] = round(peak_rss_bytes() / 2**20, 1)  # measured while workers live
    return out


def run_naive(path: Path, seconds: float) -> dict:
    """Per-window zarr slicing: arr[s:s+L] per array, then one view per step."""
    ds = open_dataset(path)
    shard = ds.shards[0]
    arrays = {k: shard.array(f"data/{k}") for k in ("image", *KEYS)}
    rng = np.random.default_rng(0)
    starts = np.concatenate([np.arange(a, b - L + 1) for a, b in
                             zip(shard.episode_starts, shard.episode_ends, strict=True)])

    def batch() -> None:
        for s in rng.choice(starts, B).tolist():
            views = rng.integers(0, shard.spec.views, L)
            window = arrays["image"][s:s + L]
            _ = window[np.arange(L), views]
            for k in KEYS:
                _ = arrays[k][s:s + L]

    return timed(batch, seconds, min_batches=1)


def run_memmap(path: Path, raw: Path, seconds: float) -> dict:
    ds = open_dataset(path)
    image = np.load(raw / "image.npy", mmap_mode="r")
    cols = {k: np.load(raw / f"{k}.npy", mmap_mode="r") for k in KEYS}
    rng = np.random.default_rng(0)
    lengths = ds.episode_lengths
    valid = np.maximum(lengths - L + 1, 0)
    cum = np.cumsum(valid)

    def batch() -> None:
        flat = rng.integers(0, cum[-1], B)
        e = np.searchsorted(cum, flat, side="right")
        starts = ds.episode_starts[e] + flat - np.where(e > 0, cum[e - 1], 0)
        steps = starts[:, None] + np.arange(L)
        views = rng.integers(0, ds.spec.views, (B, L))
        _ = image[steps, views]  # one vectorised gather from the page cache
        for k in KEYS:
            _ = cols[k][steps]

    np.asarray(image).sum()  # fault the file into the page cache first
    return timed(batch, seconds)


def child(args: argparse.Namespace) -> None:
    path = Path(args.dataset)
    if args.method == "sampler_cold":
        fresh = open_dataset(path)
        start = time.perf_counter()
        for key in ("is_first", "is_last", "reward", "state", "action"):
            fresh.column(key)  # what the rules read; a sampler reads most of it anyway
        loaded = time.perf_counter()
        fresh.rule_problem(("state", "action"))
        checked = time.perf_counter()
        out = run_sampler(path, 0, args.seconds, warmup=2)
        out["rules_s"] = round(checked - loaded, 5)
        out["rules_columns_s"] = round(loaded - start, 5)
    elif args.method == "sampler_warm":
        out = run_sampler(path, 1 << 30, args.seconds, warmup=args.warmup)
    elif args.method == "loader_cold_2workers":
        out = run_loader(path, args.seconds, 2)
    elif args.method == "naive_zarr":
        out = run_naive(path, args.seconds)
    else:
        out = run_memmap(path, Path(args.raw), args.seconds)
    out.setdefault("peak_rss_mib", round(peak_rss_bytes() / 2**20, 1))
    print(json.dumps(out))


def peak_rss_bytes() -> int:
    """Peak RSS of this process (VmHWM, which unlike ru_maxrss is reset by exec) plus the
    current RSS of its live children (DataLoader workers)."""
    import psutil

    with open("/proc/self/status") as f:
        hwm = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    return hwm + sum(c.memory_info().rss for c in psutil.Process().children(recursive=True))


def build(args: argparse.Namespace, work: Path) -> tuple[Path, Path, dict]:
    path = Path(args.dataset) if args.dataset else work / "ds"
    if not args.dataset:
        config = SynthConfig(episodes=args.steps // 500, steps=500, views=2, image_size=64,
                             seed=0)
        t = time.perf_counter()
        write_synthetic_dataset(path, config)
        write_synthetic_dataset(work / "ds-unchecked", config, StorageLayout(checksums=False))
        print(f"built {args.steps} steps twice in {time.perf_counter() - t:.1f}s",
              file=sys.stderr)
    ds = open_dataset(path)
    raw = work / "raw"
    raw.mkdir()
    image = np.lib.format.open_memmap(raw / "image.npy", mode="w+", dtype=np.uint8,
                                      shape=(ds.n_steps, ds.spec.views, *ds.spec.image_shape))
    for shard, off in zip(ds.shards, ds.shard_offsets, strict=False):
        for a in range(0, shard.n_steps, 1000):
            b = min(a + 1000, shard.n_steps)
            image[off + a: off + b] = shard.read("image", a, b)
    image.flush()
    for k in KEYS:
        np.save(raw / f"{k}.npy", ds.column(k))
    sizes = {"zarr_bytes_on_disk": ds.disk_bytes(),
             "memmap_bytes_on_disk": sum(p.stat().st_size for p in raw.iterdir()),
             "steps": ds.n_steps, "views": ds.spec.views}
    return path, raw, sizes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--dataset", help="reuse an existing dataset instead of building one")
    parser.add_argument("--seconds", type=float, default=8.0, help="timed seconds per method")
    parser.add_argument("--warmup", type=int, default=400, help="warm-up batches (warm cache)")
    parser.add_argument("--method", help=argparse.SUPPRESS)
    parser.add_argument("--raw", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.method:
        child(args)
        return
    work = Path(tempfile.mkdtemp(prefix="twist-bench-"))
    try:
        path, raw, result = build(args, work)
        methods = ["sampler_cold", "sampler_warm", "loader_cold_2workers", "naive_zarr", "memmap"]
        unchecked = work / "ds-unchecked"
        if unchecked.exists():
            methods += ["sampler_cold_unchecked", "sampler_warm_unchecked"]
        for method in methods:
            source = unchecked if method.endswith("_unchecked") else path
            cmd = [sys.executable, __file__, "--method", method.removesuffix("_unchecked"),
                   "--dataset", str(source), "--raw", str(raw), "--seconds", str(args.seconds),
                   "--warmup", str(args.warmup)]
            line = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            result[method] = json.loads(line.strip().splitlines()[-1])
            print(f"{method}: {result[method]}", file=sys.stderr)
        best = max(result["sampler_cold"]["windows_per_s"], result["sampler_warm"]["windows_per_s"],
                   result["loader_cold_2workers"]["windows_per_s"])
        result["sampler_best_windows_per_s"] = best
        result["ratio_best_vs_naive"] = best / result["naive_zarr"]["windows_per_s"]
        result["ratio_best_vs_memmap"] = best / result["memmap"]["windows_per_s"]
        result["compression_ratio"] = result["memmap_bytes_on_disk"] / result["zarr_bytes_on_disk"]
        for mode in ("cold", "warm"):
            if f"sampler_{mode}_unchecked" in result:
                result[f"checksum_slowdown_{mode}"] = 1 - (
                    result[f"sampler_{mode}"]["windows_per_s"]
                    / result[f"sampler_{mode}_unchecked"]["windows_per_s"])
        cold_100 = 100 * B / result["sampler_cold"]["windows_per_s"]
        result["rules_share_of_100_cold_batches"] = result["sampler_cold"]["rules_s"] / cold_100
        result["rules_columns_share_of_100_cold_batches"] = (
            result["sampler_cold"]["rules_columns_s"] / cold_100)
        result["targets"] = {
            "windows_per_s>=2000": best >= 2000,
            "ratio_vs_naive>=3": result["ratio_best_vs_naive"] >= 3,
            "ratio_vs_memmap>=0.5": result["ratio_best_vs_memmap"] >= 0.5,
            "rules_share<=0.05": result["rules_share_of_100_cold_batches"] <= 0.05,
            **{f"checksum_slowdown_{m}<=0.10": result[f"checksum_slowdown_{m}"] <= 0.10
               for m in ("cold", "warm") if f"checksum_slowdown_{m}" in result},
        }
        print(json.dumps(result))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
