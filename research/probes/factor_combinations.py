"""Which held-out factors, together, cost a student its return? Pairs of factors, same episodes

``twist-eval --dr heldout,heldout-camera,heldout-light,heldout-physics,heldout-full`` measures
each ``-full`` factor alone and all of them together. When all together cost more than the
factors alone add to, this names the pair that does: it builds, in this process only, a preset
per combination of factors from the per-factor presets' own settings (``camera+light`` is
``heldout`` with ``heldout-camera``'s and ``heldout-light``'s fields) and evaluates every agent
under each on the same seeded episodes, every other draw (backgrounds, colours, initial state,
and each factor's own draw) unchanged, as between the shipped presets.

A combination that holds the student's return while another with the third factor does not
puts the loss on that third factor together with the rest; if every pair holds and only all
three together fail, the loss needs all three.

``python research/probes/factor_combinations.py --agent NAME=PATH [--agent ...]
[--combination camera+light] [--episodes 30] [--seed 0]``; prints one JSON line per agent
and condition: its return, the share of its ``heldout`` return and the paired difference.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from unittest import mock

import numpy as np

from twist_pipeline.acting import load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate
from twist_sim.randomisation import DR_PRESETS, DRConfig

FACTORS = ("camera", "light", "physics")
DEFAULT_COMBINATIONS = ("camera", "light", "physics", "camera+light", "camera+physics",
                        "light+physics", "camera+light+physics")


def factor_fields(factor: str) -> dict:
    """The fields in which ``heldout-<factor>`` differs from ``heldout``."""
    plain, moved = DR_PRESETS["heldout"], DR_PRESETS[f"heldout-{factor}"]
    return {f.name: getattr(moved, f.name) for f in dataclasses.fields(DRConfig)
            if getattr(moved, f.name) != getattr(plain, f.name)}


def combined_presets(combinations: list[str]) -> dict[str, DRConfig]:
    """Preset name -> ``heldout`` with every named factor's fields, per combination."""
    presets = {}
    for combination in combinations:
        factors = combination.split("+")
        unknown = sorted(set(factors) - set(FACTORS))
        if unknown:
            raise SystemExit(f"unknown factor(s) {unknown} in {combination!r}; "
                             f"factors are {', '.join(FACTORS)}")
        fields = {k: v for factor in factors for k, v in factor_fields(factor).items()}
        presets[f"heldout-{combination}"] = dataclasses.replace(DR_PRESETS["heldout"], **fields)
    return presets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", action="append", required=True, help="NAME=PATH")
    parser.add_argument("--combination", action="append",
                        help="factors joined by +, e.g. camera+light (default: every one)")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    presets = combined_presets(args.combination or list(DEFAULT_COMBINATIONS))
    # The shipped single-factor presets must equal what this builds, or pairs would not compare.
    shipped = {f"heldout-{factor}": f"heldout-{factor}" for factor in FACTORS}
    shipped["heldout-camera+light+physics"] = "heldout-full"
    for built, name in shipped.items():
        if built in presets:
            assert presets[built] == DR_PRESETS[name], built
    with mock.patch.dict(DR_PRESETS, presets):
        for spec in args.agent:
            name, path = spec.split("=", 1)
            agent = load_agent(path)

            def returns(dr: str, agent=agent) -> np.ndarray:
                config = EvalConfig(task=agent.task, dr=dr, episodes=args.episodes,
                                    action_repeat=agent.action_repeat)
                return np.array([r.episode_return
                                 for r in evaluate(agent, config, seed=args.seed, batch=10)])

            plain = returns("heldout")
            print(json.dumps({"agent": name, "condition": "heldout", "episodes": args.episodes,
                              "return": round(plain.mean(), 1),
                              "sem": round(plain.std(ddof=1) / np.sqrt(args.episodes), 1)}),
                  flush=True)
            for preset in presets:
                moved = returns(preset)
                difference = moved - plain
                print(json.dumps({
                    "agent": name, "condition": preset.removeprefix("heldout-"),
                    "episodes": args.episodes, "return": round(moved.mean(), 1),
                    "share": round(moved.mean() / plain.mean(), 2),
                    "difference": round(difference.mean(), 1),
                    "stderr": round(difference.std(ddof=1) / np.sqrt(args.episodes), 1),
                    "better": int((difference > 0).sum())}), flush=True)


if __name__ == "__main__":
    main()
