"""Write a folder of training background textures, for re-rendering D with a wider bank.

Does the read-out student lose held-out scenes because D shows it too few backgrounds (the
``train`` bank holds 128 textures of three families) or too few *kinds*? This script writes
``--count`` textures as PNGs: the ``train`` families, as the procedural bank draws them, and
with ``--extra`` the ``wide`` bank's (:data:`twist_data.backgrounds.FAMILIES`), which adds
two families that the held-out bank does not use either: thin line segments shaped like the
pole itself, and soft ellipses. The ``train-wide`` DR preset draws the same families
procedurally (``twist-data render D D2 --dr train-wide``); this folder is how they were first
measured, and stays for any bank a user wants to edit by hand.

The folder is then used as the training DR of a re-render of D's stored states
(``twist-data render D D2 --backgrounds DIR --supersample 2``), and a student distilled from
D2 with D's teacher. The held-out families (cells, rings, Mondrian) stay unseen either way.

Measured (research/log.md, "Does a wider training bank make unseen backgrounds read
better?"): 1,024 textures with ``--extra`` read held-out frames better and lose the same
scenes.

``python research/probes/texture_folder.py OUT [--count 1024] [--size 256] [--extra] [--seed 1]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from twist_data.backgrounds import FAMILIES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--count", type=int, default=1024)
    parser.add_argument("--size", type=int, default=256, help="the bank's texture side at "
                        "64x64 renders supersampled 2x")
    parser.add_argument("--extra", action="store_true", help="add the lines and blobs families")
    parser.add_argument("--seed", type=int, default=1, help="not the train bank's seed 0")
    args = parser.parse_args()
    families = list(FAMILIES["wide" if args.extra else "train"].items())
    args.out.mkdir(parents=True, exist_ok=False)
    for i in range(args.count):
        name, make = families[i % len(families)]
        texture = make(np.random.default_rng([args.seed, i]), args.size)
        cv2.imwrite(str(args.out / f"{i:05d}-{name}.png"), cv2.cvtColor(texture, cv2.COLOR_RGB2BGR))
    print(f"{args.count} textures of {len(families)} families in {args.out}")


if __name__ == "__main__":
    main()
