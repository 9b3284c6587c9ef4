"""Does changed physics make a read-out student misread, or does it misact on the same reads?

Under ``heldout-physics`` (friction and masses changed per episode, nothing the camera sees
changed) a read-out student can lose more of its return than the teacher on states does. Two
explanations predict different read-out errors along the student's own episodes:

* *coverage*: changed physics carries the scene into states D (collected under nominal
  physics) never showed, where the CNN reads worse; the read error, and the share of visited
  states outside D's range, grow under ``heldout-physics``;
* *dynamics*: the CNN reads as well as under ``heldout``, but the teacher's filter, whose
  model assumes nominal physics, turns the same read errors (and the velocities derived from
  them) into worse beliefs; the errors stay as they are.

Each preset runs the same seeded episodes (``twist-eval``'s draws); at every step the state
handed to the teacher's filter (read positions, velocities derived from two reads) is set
beside the simulator's. Prints one JSON line per preset: the return, the RMS error per state
component in the state's units, and the share of visited states with a read component outside
D's training range (its 0.5-99.5 percentiles), with the position error inside and outside it,
and per read component the correlation of its error with the same episode's error one step
before (near 0: independent between frames, which averaging over frames removes; near 1:
persistent).

``python research/probes/readout_physics_errors.py AGENT DATASET [--dr heldout,heldout-physics]
[--episodes 30] [--seed 0] [--order 2]``
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from unittest import mock

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_models.readout import StateReadOut
from twist_pipeline.acting import ImageAgent, load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate

sys.path.insert(0, str(Path(__file__).parent))
from readout_ceiling import three_read_state  # a sibling probe


def training_states(dataset, holdout_every: int = 10) -> np.ndarray:
    """Every state of D's training episodes (the held-out ones left out) -> [N, S]."""
    held = heldout_episodes(dataset.n_episodes, holdout_every)
    return np.concatenate([dataset.episode(int(i), images=False).state for i in np.flatnonzero(~held)])


def run(agent: ImageAgent, dr: str, episodes: int, seed: int, order: int = 1
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns [E], the simulator's and the handed states at every acted step [N, S], and
    each step's episode [N] (rows of one episode in time order).
    ``order`` 2 hands the filter velocities from the backward second-order difference of
    three reads (``readout_ceiling.py --order 2``) instead of the recipe's first-order one."""
    true, handed, pending, episode = [], [], [], []
    batches = [-1]
    act_batch, state = ImageAgent.act_batch, StateReadOut.state
    earlier: list[torch.Tensor] = []  # the read before ``previous``; batched episodes step together

    def recording_act(self, steps: Sequence, images, uniform):
        pending.append(np.array([not s.is_last for s in steps]))
        batches[0] += all(s.is_first for s in steps)
        episode.append(batches[0] * len(steps) + np.arange(len(steps)))
        true.append(np.stack([s.state for s in steps]))
        return act_batch(self, steps, images, uniform)

    def recording_state(self, positions: torch.Tensor, previous: torch.Tensor) -> torch.Tensor:
        full = state(self, positions, previous)
        if order == 2:
            first = (positions == previous).all(-1, keepdim=True)
            before = previous if not earlier or earlier[0].shape != previous.shape else \
                torch.where(first, previous, earlier[0])
            full = three_read_state(self, full, state(self, previous, before))
            earlier[:] = [previous]
        handed.append(full.detach().cpu().numpy().reshape(-1, full.shape[-1]))
        return full

    config = EvalConfig(task=agent.task, dr=dr, episodes=episodes,
                        action_repeat=agent.action_repeat)
    with mock.patch.object(ImageAgent, "act_batch", recording_act), \
            mock.patch.object(StateReadOut, "state", recording_state):
        results = evaluate(agent, config, seed=seed, batch=10)
    assert len(true) == len(handed), "one read-out per acted step"
    live = np.concatenate(pending)
    return (np.array([r.episode_return for r in results]),
            np.concatenate(true)[live].astype(np.float64),
            np.concatenate(handed)[live].astype(np.float64), np.concatenate(episode)[live])


def lag_correlation(error: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """Per component, the correlation of ``error`` [N, C] with the same episode's error one
    row before (``episode`` [N], rows of one episode in time order) -> [C]."""
    order = np.argsort(episode, kind="stable")
    error, episode = error[order], episode[order]
    same = episode[1:] == episode[:-1]
    now, before = error[1:][same], error[:-1][same]
    return np.array([np.corrcoef(now[:, c], before[:, c])[0, 1] for c in range(error.shape[1])])


def rms(values: np.ndarray) -> float | None:
    return round(float(np.sqrt((values ** 2).mean())), 4) if len(values) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agent")
    parser.add_argument("dataset")
    parser.add_argument("--dr", default="heldout,heldout-physics")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--order", type=int, default=1, choices=(1, 2))
    args = parser.parse_args()
    agent = load_agent(args.agent)
    assert isinstance(agent, ImageAgent), "a read-out student bundle"
    read = list(agent.agent.student.perception.readout.config.read)
    seen = training_states(open_dataset(args.dataset))[:, read]
    low, high = np.percentile(seen, 0.5, 0), np.percentile(seen, 99.5, 0)
    print(json.dumps({"d_range": [low.round(3).tolist(), high.round(3).tolist()]}), flush=True)
    for dr in args.dr.split(","):
        returns, true, handed, episode = run(agent, dr, args.episodes, args.seed, args.order)
        error = handed - true
        outside = ((true[:, read] < low) | (true[:, read] > high)).any(1)
        position = np.sqrt((error[:, read] ** 2).mean(1))

        print(json.dumps({
            "dr": dr, "order": args.order, "episodes": args.episodes,
            "return": round(float(returns.mean()), 1),
            "sem": round(float(returns.std(ddof=1) / np.sqrt(len(returns))), 1),
            "steps": len(true), "read_components": read,
            "rmse": np.sqrt((error ** 2).mean(0)).round(4).tolist(),
            "true_std": true.std(0).round(4).tolist(),
            "outside_share": round(float(outside.mean()), 4),
            "outside_share_per_component": ((true[:, read] < low) | (true[:, read] > high)
                                            ).mean(0).round(4).tolist(),
            "position_rms_inside": rms(position[~outside]),
            "position_rms_outside": rms(position[outside]),
            "error_lag1_correlation": lag_correlation(error[:, read], episode).round(3).tolist()}),
            flush=True)


if __name__ == "__main__":
    main()
