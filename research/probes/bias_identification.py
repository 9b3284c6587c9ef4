"""Can a cartpole read-out's scene bias be told from its own readings and the actions?

In the held-out scenes a read-out student loses, its CNN reads the pole's angle with a
constant offset of 2-3 degrees (research/log.md, "Is a lost scene read with a bias?"):
the teacher's filter balances a lean that is not there and the cart runs off to hold the
true pole. A constant offset is physically inconsistent: a pole that reads upright while the
cart keeps accelerating must in truth lean. This script measures whether that inconsistency
is large enough to estimate the offset within an episode, before acting on it:

* a linear model of the next positions from the last two and the action,
  ``p[t+1] = W [p[t], p[t-1], a[t+1], 1]`` with ``p = (x, angle)``, is fitted by least
  squares on D's steps near upright (D stores at t the action that led to t);
* readings ``r = p + b`` give residuals ``e = r[t+1] - W [r[t], r[t-1], a, 1]`` whose mean is
  ``(I - W_p - W_q) b`` plus noise, so ``b`` is estimated from the first N steps' residuals
  (the cart's position has no restoring force: its offset is not identifiable and is left);
* along each episode ``twist-eval --save-trajectories`` wrote, the states are rendered again
  in that episode's held-out scene and read as the agent reads them (the mirror too), and the
  estimate is set beside the episode's true mean angle error before the pole first passes 20
  degrees.

It could show the opposite: read noise, correlated over steps, may swamp the gravity term.
Per episode it also prints how the reading follows the true angle within 12 degrees of
upright (the slope and offset of a line fitted to read on true angle): whether a lost scene
is read with an offset, or shrunk toward upright.

``python research/probes/bias_identification.py AGENT.pt DATASET TRAJECTORIES --name NAME``
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.seeding import evaluation_episode_seed
from twist_models.agent import Agent
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.rerender import render_blocks

X, COS, SIN = 0, 1, 2
NEAR = math.radians(20.0)


def positions(state: np.ndarray) -> np.ndarray:
    """Cart x and the pole's angle: [T, S] -> [T, 2]."""
    return np.stack([state[:, X], np.arctan2(state[:, SIN], state[:, COS])], 1)


def regressors(p: np.ndarray, action: np.ndarray) -> np.ndarray:
    """[p[t], p[t-1], a, 1] for t = 1..T-2: p [T, 2], action [T-2, A] -> [T-2, 4 + A + 1]."""
    return np.concatenate([p[1:-1], p[:-2], action, np.ones((len(action), 1))], 1)


def fit_dynamics(dataset) -> tuple[np.ndarray, dict]:
    rows, targets = [], []
    for index in range(dataset.n_episodes):
        episode = dataset.episode(index)
        p = positions(episode.state)
        near = np.abs(p[:, 1]) < NEAR
        keep = near[:-2] & near[1:-1] & near[2:]
        rows.append(regressors(p, episode.action[2:])[keep])
        targets.append(p[2:][keep])
    design, target = np.concatenate(rows), np.concatenate(targets)
    weights, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = target - design @ weights
    return weights.T, {"steps": len(design),
                       "residual_std_x": float(residual[:, 0].std()),
                       "residual_std_angle_deg": math.degrees(float(residual[:, 1].std()))}


@torch.no_grad()
def read(agent: Agent, images: np.ndarray) -> np.ndarray:
    """The agent's reading (with its mirror if it reads one) -> [T, 2] (x, angle)."""
    out = agent.student.perception.read_positions(torch.from_numpy(images)[:, None])[:, 0].numpy()
    return positions(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("agent")
    parser.add_argument("dataset")
    parser.add_argument("trajectories", type=Path)
    parser.add_argument("--name", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", default="10,25,50,100")
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    agent = Agent.load(args.agent)
    dataset = open_dataset(args.dataset)
    weights, fit = fit_dynamics(dataset)
    a_dim = dataset.episode(0).action.shape[1]
    gain = np.eye(2) - weights[:, 0:2] - weights[:, 2:4]
    print(json.dumps({"fit": fit, "I-Wp-Wq": gain.round(5).tolist(),
                      "action_gain": weights[:, 4:4 + a_dim].round(5).tolist()}), flush=True)
    spec = dataset.spec
    supersample = int(render_blocks(spec)[0]["supersample"])
    horizons = [int(n) for n in args.steps.split(",")]
    with DRRenderer(spec.task, dr_preset("heldout"), spec.image_height, 1,
                    supersample) as renderer:
        sampler = renderer.sampler(args.seed)
        for path in sorted(args.trajectories.glob(f"{args.name}-seed{args.seed}-episode*.npz"),
                           key=lambda p: int(p.stem.rsplit("episode", 1)[1])):
            episode = int(path.stem.rsplit("episode", 1)[1])
            data = np.load(path)
            state, action = data["state"], data["action"]
            sampler.begin_episode(evaluation_episode_seed(args.seed, episode))
            p = positions(state)
            physics = np.stack([np.zeros(len(state)), p[:, 0], p[:, 1], state[:, 3],
                                state[:, 4]], 1)
            images = np.empty((len(state), spec.image_height, spec.image_width, 3), np.uint8)
            for t in range(len(state)):
                renderer.render(physics[t], sampler.sample(), out=images[t:t + 1])
            r = read(agent, images)
            near = np.abs(p[:, 1]) < NEAR
            fall = int(np.argmin(near)) if not near.all() else len(p)
            bias = (r - p)[:fall].mean(0)
            # action[t] moved state[t] to state[t+1]: the step t+1 -> t+2 used action[t+1].
            residual = r[2:] - regressors(r, action[1:len(r) - 1]) @ weights.T
            true_residual = p[2:] - regressors(p, action[1:len(p) - 1]) @ weights.T
            estimates = {}
            for n in horizons:
                n = min(n, max(fall - 2, 1))
                mean = residual[:n].mean(0)
                estimates[n] = math.degrees(mean[1] / gain[1, 1])
            within = np.abs(p[:, 1]) < math.radians(12.0)
            slope, offset = np.polyfit(np.degrees(p[within, 1]), np.degrees(r[within, 1]), 1)
            print(json.dumps({
                "episode": episode, "fall_step": fall,
                "slope": round(float(slope), 2), "offset_deg": round(float(offset), 2),
                "angle_bias_deg": round(math.degrees(bias[1]), 2),
                "x_bias": round(float(bias[0]), 3),
                "estimate_deg": {n: round(v, 2) for n, v in estimates.items()},
                "true_states_estimate_deg": round(math.degrees(
                    true_residual[:min(50, fall)].mean(0)[1] / gain[1, 1]), 2)}), flush=True)


if __name__ == "__main__":
    main()
