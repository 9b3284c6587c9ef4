"""The cartpole pole at small tilts, rendered plain and supersampled.

Renders cartpole-balance at pole angles 0, 0.03, 0.06 and 0.1 rad (cart centred), one row per
(DR preset, supersample) in ``none``/``train`` x 1/2, with one fixed draw of DR parameters per
row, and writes the grid, scaled 4x without smoothing, to ``--out``. At supersample 1 a tilted
pole breaks into stray pixels; at 2 it stays a line whose tilt the pixels' shades carry. Prints
one JSON line naming the rows and the image (a figure, not a timing: nothing to compare).

    python research/probes/pole_aliasing.py [--out docs/images/pole-aliasing.png]
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np

from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TaskEnv

ANGLES = (0.0, 0.03, 0.06, 0.1)
CART, HINGE = 1, 2  # cartpole's physics vector: time, qpos (cart slider, pole hinge), qvel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="docs/images/pole-aliasing.png")
    args = parser.parse_args()
    env = TaskEnv("cartpole-balance")
    physics = np.array(env.reset(seed=0).physics, np.float64)
    rows, names = [], []
    for dr in ("none", "train"):
        for supersample in (1, 2):
            with DRRenderer("cartpole-balance", dr_preset(dr), 64, views=1,
                            supersample=supersample) as renderer:
                sampler = renderer.sampler(3)
                sampler.begin_episode(3)
                params = sampler.sample()
                frames = []
                for angle in ANGLES:
                    state = physics.copy()
                    state[CART], state[HINGE] = 0.0, angle
                    frames.append(renderer.render(state, params)[0])
            rows.append(np.concatenate(frames, 1))
            names.append(f"{dr}, supersample {supersample}")
    grid = np.concatenate(rows, 0)
    cv2.imwrite(args.out, cv2.resize(grid[..., ::-1], None, fx=4, fy=4,
                                     interpolation=cv2.INTER_NEAREST))
    print(json.dumps({"angles": ANGLES, "rows": names, "image": args.out}))


if __name__ == "__main__":
    main()
