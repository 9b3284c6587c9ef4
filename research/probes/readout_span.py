"""Does a read-out student gain by deriving its velocities over more than one step?

A read-out student derives each velocity as a gain times the difference of two successive
readings, so a reading's error enters the velocity amplified by the gain. Derived over K
steps instead, ``g (x_t - x_t-K) / K`` (fewer at an episode's start), an error that differs
between frames enters it K times less, and the velocity lags the true one by (K - 1) / 2
steps more. ``readout_ceiling.py --span`` measured this with Gaussian noise on the true state;
this measures it on a student's own readings, on the same seeded episodes under each span
(span 1, the student unchanged, is the baseline measured in the same run). If the student's
errors persist from frame to frame, a longer span gains little where Gaussian noise gained.

``python research/probes/readout_span.py AGENT --span 2 --span 3 [--dr heldout,heldout-full]
[--episodes 50] [--seed 0]``; prints one JSON line per preset and span.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import torch

from twist_models.perception import StateReading
from twist_pipeline.acting import ImageAgent, load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate

sys.path.insert(0, str(Path(__file__).parent))
from readout_hold import paired_rows


@contextlib.contextmanager
def spanning(span: int) -> Iterator[None]:
    """Within the block, every read-out student derives its velocities over ``span`` steps
    (what it hands on otherwise unchanged, pooling included)."""
    if span == 1:
        yield
        return
    handed: list[torch.Tensor] = []

    def spanned_step(self: StateReading, image: torch.Tensor, history: torch.Tensor | None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        positions, _, after = self.readout.pool_step(self.read_positions(image), history)
        if history is None:  # an episode's first step
            handed.clear()
        handed.append(positions)
        del handed[:-span - 1]
        state = self.readout.state(positions, handed[0])
        if len(handed) > 2:
            rates = [v[0] for v in self.readout.config.velocities]
            state[..., rates] = state[..., rates] / (len(handed) - 1)
        return self.embed_state(state), after

    with mock.patch.object(StateReading, "step", spanned_step):
        yield


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agent", help="a read-out student's agent.pt")
    parser.add_argument("--span", type=int, action="append", required=True,
                        help="steps each velocity is derived over (repeatable)")
    parser.add_argument("--dr", default="heldout", help="comma-separated evaluation presets")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    agent = load_agent(args.agent)
    if not isinstance(agent, ImageAgent) or agent.agent.config.student.readout is None:
        raise SystemExit(f"{args.agent} is not a read-out student (--recipe readout)")
    for dr in args.dr.split(","):
        config = EvalConfig(task=agent.task, dr=dr, episodes=args.episodes,
                            action_repeat=agent.action_repeat)
        results = {}
        for span in sorted({1, *args.span}):
            with spanning(span):
                results[f"span{span}"] = evaluate(agent, config, seed=args.seed, batch=10)
        for row in paired_rows(dr, results, "span1"):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
