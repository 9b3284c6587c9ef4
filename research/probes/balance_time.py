"""How long does each agent keep the pole up, and where is the cart when it falls?

A cartpole-balance return mixes two phases: the steps while the pole is up, and whatever
follows its fall (the task never ends the episode: a fallen pole is caught again after a
whole turn, as some `quick` teachers do on purpose to bring the cart back, or left to spin).
An agent that holds the pole as long as its teacher, then does worse with
a fallen pole, acts as well as its teacher where it matters and still scores less; returns
alone cannot tell the two apart. This script reads the trajectories ``twist-eval
--save-trajectories`` wrote and prints, per agent, one JSON line:

* ``fall_steps``: per episode, the agent step at which the pole first leans past ``--lean``
  degrees (the episode's length if it never does), and their median;
* ``fall_x``: the cart's position at that step (the rails end at |x| ~ 1.87: a fall at the
  rail's end is the cart hitting it);
* ``spells``: per episode, how many separate runs of steps the pole spends past the lean,
  ``longest_spell``: the longest, in steps (a pole caught after a full turn spends ~24 past
  25°, one left to spin ~29 per turn), and ``upright_after_fall``: the share of steps within
  10° of upright after the first fall, over the episodes that fall (a pole caught and held
  stays up; one spinning freely spends ~0.4 of its time near the top);
* ``at_rail_end``: the share of all steps with |x| > 1.5, ``upright``: with the pole within
  10° of upright;
* with ``--against NAME``: the episode-paired difference of fall steps (mean ± standard error)
  and how many episodes fall later, the same pairing as ``twist-eval --paired-with``.

``python research/probes/balance_time.py EVAL_DIR [--against oracle] [--lean 25]``
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from twist_pipeline.evaluation import TRAJECTORIES
from twist_pipeline.statistics import paired_difference

#: Cartpole's state layout: cart x, cos θ, sin θ, then the velocities.
X, COS = 0, 1
RAIL_END = 1.5
NAME = re.compile(r"(?P<agent>.+)-seed(?P<seed>\d+)-episode(?P<episode>\d+)\.npz")


def fall_step(states: np.ndarray, lean_degrees: float) -> int:
    """The first step whose pole leans more than ``lean_degrees``; len(states) if none."""
    fallen = np.flatnonzero(states[:, COS] < np.cos(np.radians(lean_degrees)))
    return int(fallen[0]) if fallen.size else len(states)


def spells(states: np.ndarray, lean_degrees: float) -> list[tuple[int, int]]:
    """The [start, end) runs of steps whose pole leans more than ``lean_degrees``."""
    fallen = np.concatenate([[0], (states[:, COS] < np.cos(np.radians(lean_degrees))).astype(int),
                             [0]])
    edges = np.flatnonzero(np.diff(fallen))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def read(folder: Path) -> dict[str, dict[tuple[int, int], np.ndarray]]:
    """{agent: {(seed, episode): states [T+1, S]}} from an evaluation folder."""
    found: dict[str, dict[tuple[int, int], np.ndarray]] = {}
    for path in sorted((folder / TRAJECTORIES).glob("*.npz")):
        match = NAME.fullmatch(path.name)
        if match is not None:
            key = (int(match["seed"]), int(match["episode"]))
            found.setdefault(match["agent"], {})[key] = np.load(path)["state"]
    if not found:
        raise SystemExit(f"{folder / TRAJECTORIES} holds no trajectories: run twist-eval "
                         "with --save-trajectories")
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("eval_dir", type=Path)
    parser.add_argument("--against", help="agent to pair every other agent's fall steps with")
    parser.add_argument("--lean", type=float, default=25.0, help="degrees that count as fallen")
    args = parser.parse_args()
    agents = read(args.eval_dir)
    falls = {name: {key: fall_step(s, args.lean) for key, s in episodes.items()}
             for name, episodes in agents.items()}
    for name, episodes in agents.items():
        keys = sorted(episodes)
        steps = np.concatenate([episodes[k] for k in keys])
        line = {"agent": name, "episodes": len(keys),
                "fall_steps": [falls[name][k] for k in keys],
                "median_fall_step": float(np.median([falls[name][k] for k in keys])),
                "fall_x": [round(float(episodes[k][min(falls[name][k], len(episodes[k]) - 1),
                                                    X]), 2) for k in keys],
                "at_rail_end": round(float((np.abs(steps[:, X]) > RAIL_END).mean()), 3),
                "upright": round(float((steps[:, COS] >= np.cos(np.radians(10))).mean()), 3)}
        runs = [spells(episodes[k], args.lean) for k in keys]
        line["spells"] = [len(r) for r in runs]
        after = [episodes[k][falls[name][k]:, COS] for k in keys if falls[name][k] < len(episodes[k])]
        line["upright_after_fall"] = round(float(np.mean(
            [(a >= np.cos(np.radians(10))).mean() for a in after])), 3) if after else None
        line["longest_spell"] = [max((end - start for start, end in r), default=0) for r in runs]
        if args.against is not None and name != args.against and args.against in falls:
            shared = [k for k in keys if k in falls[args.against]]
            paired = paired_difference(np.array([falls[name][k] for k in shared], float),
                                       np.array([falls[args.against][k] for k in shared], float))
            line["paired_fall_steps"] = {"against": args.against, **paired.as_dict()}
        print(json.dumps(line))


if __name__ == "__main__":
    main()
