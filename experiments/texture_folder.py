"""Write a folder of training background textures, for re-rendering D with a wider bank.

Does the read-out student lose held-out scenes because D shows it too few backgrounds (the
``train`` bank holds 128 textures of three families) or too few *kinds*? This script writes
``--count`` textures as PNGs: the ``train`` families, as the procedural bank draws them, and
with ``--extra`` two more families that the held-out bank does not use either:

* ``lines``: thin straight segments of random colour, length and angle on a flat or cloudy
  ground, distractors shaped like the pole itself;
* ``blobs``: overlapping soft ellipses, smooth shapes with edges at every orientation.

The folder is then used as the training DR of a re-render of D's stored states
(``twist-data render D D2 --backgrounds DIR --supersample 2``), and a student distilled from
D2 with D's teacher. The held-out families (cells, rings, Mondrian) stay unseen either way.

Measured (docs/experiments.md, "Does a wider training bank make unseen backgrounds read
better?"): 1,024 textures with ``--extra`` read held-out frames better and lose the same
scenes.

``python experiments/texture_folder.py OUT [--count 1024] [--size 256] [--extra] [--seed 1]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from twist_data.backgrounds import FAMILIES, clouds


def lines(rng: np.random.Generator, size: int) -> np.ndarray:
    """Thin segments of random colour, length and angle over a cloudy or flat ground."""
    image = (clouds(rng, size) if rng.random() < 0.5
             else np.full((size, size, 3), rng.uniform(0, 255, 3), np.uint8)).copy()
    for _ in range(int(rng.integers(5, 40))):
        centre = rng.uniform(0, size, 2)
        half = rng.uniform(0.05, 0.5) * size / 2
        angle = rng.uniform(0, np.pi)
        offset = half * np.array([np.cos(angle), np.sin(angle)])
        start, end = (centre - offset).astype(int), (centre + offset).astype(int)
        colour = tuple(float(v) for v in rng.uniform(0, 255, 3))
        cv2.line(image, tuple(start.tolist()), tuple(end.tolist()), colour,
                 int(rng.integers(1, max(2, size // 32))), cv2.LINE_AA)
    return image


def blobs(rng: np.random.Generator, size: int) -> np.ndarray:
    """Overlapping soft-edged ellipses of random colours on a random ground."""
    image = np.full((size, size, 3), rng.uniform(0, 255, 3), np.float32)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    for _ in range(int(rng.integers(4, 16))):
        cy, cx = rng.uniform(0, 1, 2)
        ry, rx = rng.uniform(0.03, 0.3, 2)
        angle = rng.uniform(0, np.pi)
        u = np.cos(angle) * (xx - cx) + np.sin(angle) * (yy - cy)
        v = -np.sin(angle) * (xx - cx) + np.cos(angle) * (yy - cy)
        inside = np.clip(1.5 - (u / rx) ** 2 - (v / ry) ** 2, 0, 1)[..., None]
        image = image * (1 - inside) + inside * rng.uniform(0, 255, 3)
    return np.clip(image, 0, 255).astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--count", type=int, default=1024)
    parser.add_argument("--size", type=int, default=256, help="the bank's texture side at "
                        "64x64 renders supersampled 2x")
    parser.add_argument("--extra", action="store_true", help="add the lines and blobs families")
    parser.add_argument("--seed", type=int, default=1, help="not the train bank's seed 0")
    args = parser.parse_args()
    families = list(FAMILIES["train"].items())
    if args.extra:
        families += [("lines", lines), ("blobs", blobs)]
    args.out.mkdir(parents=True, exist_ok=False)
    for i in range(args.count):
        name, make = families[i % len(families)]
        texture = make(np.random.default_rng([args.seed, i]), args.size)
        cv2.imwrite(str(args.out / f"{i:05d}-{name}.png"), cv2.cvtColor(texture, cv2.COLOR_RGB2BGR))
    print(f"{args.count} textures of {len(families)} families in {args.out}")


if __name__ == "__main__":
    main()
