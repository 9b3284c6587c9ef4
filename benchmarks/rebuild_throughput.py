"""Rebuilding D's images from its stored physics and DR draws (``twist-data render
--reproduce``) with 1 worker against N workers, on the first episodes of a D, in one run.

Rounds alternate the worker counts (1, N, 1, N, ...) so that machine noise hits both alike;
each round rebuilds the same episodes into a fresh folder. Prints one JSON line: the median
seconds and steps/s per worker count, the speed-up of N over 1 (median of the per-round
ratios), whether every rebuild was bit-identical, the GL renderer and the cores. Target (2
cores): N=2 at least 1.6x one worker, or the measured reason it cannot be.

    python benchmarks/rebuild_throughput.py D [--episodes 20] [--workers 2] [--rounds 3]

The source may be a full D: its stored frames are then decoded and hashed too, as a
stripped D's digests are read instead; benchmark a stripped D for the rebuild alone.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from twist_data.reader import open_dataset
from twist_sim.rerender import reproduce_dataset

TARGET = 1.6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a D, full or stripped")
    parser.add_argument("--episodes", type=int, default=20, help="its first episodes rebuilt")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    data = open_dataset(args.dataset)
    chosen = list(range(min(args.episodes, data.n_episodes)))
    steps = int(data.episode_lengths[chosen].sum())
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seconds: dict[int, list[float]] = {1: [], args.workers: []}
        exact, gl = True, {}
        for round_ in range(args.rounds):
            for workers in (1, args.workers):
                out = folder / f"rebuilt-{round_}-{workers}"
                report = reproduce_dataset(args.dataset, out, workers, chosen)
                seconds[workers].append(report.seconds)
                exact, gl = exact and report.exact, report.gl
                shutil.rmtree(out)
    ratios = [a / b for a, b in zip(seconds[1], seconds[args.workers], strict=True)]
    print(json.dumps({
        "benchmark": "rebuild_throughput", "dataset": str(args.dataset), "steps": steps,
        "episodes": len(chosen), "views": data.spec.views, "cores": os.cpu_count(),
        "gl_renderer": gl.get("gl_renderer"),
        **{f"workers_{w}": {"median_s": round(statistics.median(s), 2),
                            "steps_per_s": round(steps / statistics.median(s), 1),
                            "rounds_s": [round(x, 2) for x in s]} for w, s in seconds.items()},
        "speedup": round(statistics.median(ratios), 3), "target": TARGET,
        "every_rebuild_identical": exact}))


if __name__ == "__main__":
    main()
