"""How much does a small lean of cartpole's pole change the picture, scene by scene?

The read-out student must see the pole's near-upright lean. How much of it a frame shows
depends on the scene: a pole whose colour matches the background behind it changes few
pixel levels when it leans. This script renders the held-out scenes that
``twist-eval --dr heldout --seeds 0`` draws (episode i's background, crop and colours) with
the pole at +lean and -lean degrees, the cart at a few positions, and prints per scene the
*lean signal*: the summed absolute difference of the two 64x64 frames, RGB levels, averaged
over cart positions. ``--dr`` draws the scenes from another preset instead (``train``,
``train-contrast``: how often training shows a pole that faint). ``--nominal`` keeps every
material at its nominal colour, with each scene's background and crop unchanged (the colour
draws are still made), as the nominal-colour evaluation in research/log.md did.

One JSON line per scene, then one summary line (median and quartiles of the signal).

``python research/probes/pole_contrast.py [--episodes 30] [--dr heldout] [--lean 0.5]
[--positions -0.5,0,0.5] [--nominal] [--supersample 2] [--faint 2200]``
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from twist_data.seeding import evaluation_episode_seed
from twist_sim.randomisation import COLOUR_GROUPS, dr_preset
from twist_sim.render import DRRenderer
from twist_sim.tasks import TaskEnv

#: Where cartpole's physics vector holds the cart's position and the pole's hinge angle
#: (time, then qpos; 0 rad is upright).
CART_X, HINGE = 1, 2


def lean_signals(episodes: int, lean_degrees: float, positions: list[float], nominal: bool,
                 supersample: int, dr: str = "heldout", seed: int = 0) -> list[dict]:
    """Per evaluation scene of preset ``dr``: its background, pole colour and lean signal."""
    config = dr_preset(dr).replace(resample="episode")
    if nominal:
        config = config.replace(colour_delta=0.0)
    env = TaskEnv("cartpole-balance")
    env.reset(seed=0)
    base = env.physics_state()
    base[HINGE + 1:] = 0.0  # both velocities: at rest
    lean = math.radians(lean_degrees)
    rows = []
    with DRRenderer("cartpole-balance", config, 64, views=1, supersample=supersample) as renderer:
        sampler = renderer.sampler(seed)
        for i in range(episodes):
            sampler.begin_episode(evaluation_episode_seed(seed, i))
            params = sampler.sample()
            signals = []
            for x in positions:
                frames = []
                for angle in (lean, -lean):
                    physics = base.copy()
                    physics[CART_X], physics[HINGE] = x, angle
                    frames.append(renderer.render(physics, params)[0].astype(np.int32))
                signals.append(float(np.abs(frames[0] - frames[1]).sum()))
            background = int(params["background"][0])
            rows.append({"scene": i, "background": renderer.bank.names[background],
                         "pole_rgb": [round(float(c), 3)
                                      for c in params["colour"][0, COLOUR_GROUPS.index("self")]],
                         "lean_signal": round(float(np.mean(signals)), 1)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--lean", type=float, default=0.5, help="degrees either side of upright")
    parser.add_argument("--positions", default="-0.5,0,0.5", help="cart positions, metres")
    parser.add_argument("--nominal", action="store_true", help="nominal material colours")
    parser.add_argument("--supersample", type=int, default=2)
    parser.add_argument("--dr", default="heldout", help="DR preset the scenes are drawn from")
    parser.add_argument("--faint", type=float, default=2200.0,
                        help="the summary counts scenes whose signal is below this")
    args = parser.parse_args()
    positions = [float(p) for p in args.positions.split(",")]
    rows = lean_signals(args.episodes, args.lean, positions, args.nominal, args.supersample,
                        args.dr)
    for row in rows:
        print(json.dumps(row))
    signal = np.array([r["lean_signal"] for r in rows])
    print(json.dumps({"summary": args.dr + (" nominal" if args.nominal else ""),
                      "median": float(np.median(signal)),
                      "quartiles": np.percentile(signal, [25, 75]).round(1).tolist(),
                      "faint_share": round(float(np.mean(signal < args.faint)), 3),
                      "lowest_scenes": [int(i) for i in np.argsort(signal)[:6]]}))


if __name__ == "__main__":
    main()
