"""What does a read-out student lose with a perfect CNN? The teacher on derived velocities

A read-out student (``--recipe readout``) hands the teacher's filter positions read from
each image and velocities derived from two successive read-outs (a gain times their
difference, :meth:`twist_models.readout.StateReadOut.state`). Even a CNN that read every
position exactly would hand the filter those derived velocities, not the true ones. This
measures that ceiling from the teacher alone, over the same seeded episodes as the teacher
on the true state (the baseline measured in the same run):

* ``derived``: the true positions, the velocities derived from them as the student derives
  them (the agent bundle's pairing and gains; 0 at an episode's first step);
* ``derived+noise:SIGMA`` (``--noise SIGMA``, repeatable): the same with Gaussian noise of
  std ``SIGMA`` (the state's units) on every position before the derivation: a CNN's
  read error, which the difference amplifies;
* ``true-velocities+noise:SIGMA`` (with ``--true-velocities``): the noisy positions, but the
  true velocities: what the noise costs through the positions alone. Far above
  ``derived+noise`` at the same SIGMA, the derived velocities are what the read error costs
  (a smoother derivation is the lever); near it, the positions are.

It also prints how well each derived velocity matches the true one (RMSE, and the share of
the true velocity's variance it explains), offline over D's training steps and along the
teacher's own evaluated episodes under ``--dr``.

``--order 2`` (beside ``--order 1``) derives each velocity from three reads instead, the
backward second-order difference ``g (1.5 x_t - 2 x_t-1 + 0.5 x_t-2)``, which lags the true
velocity less where it changes fast within an agent step, at the price of amplifying read
noise more.

``--span K`` derives each velocity over K agent steps instead, ``g (x_t - x_t-K) / K`` (fewer
steps at an episode's start): read noise enters it K times less, and it lags the true
velocity by (K - 1) / 2 steps more.

A ceiling near the teacher's return says the derivation costs nothing and the student's gap
lies in its read-out; a ceiling near the student's says the derivation caps it.

``python research/probes/readout_ceiling.py AGENT TEACHER DATASET [--noise 0.01] [--episodes
30] [--dr heldout] [--order 1 --order 2] [--span 2] [--true-velocities]``; prints one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_models.agent import Agent
from twist_models.readout import StateReadOut
from twist_pipeline.acting import StateAgent, load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate
from twist_sim.tasks import Step


def three_read_state(readout: StateReadOut, state: torch.Tensor, earlier: torch.Tensor
                     ) -> torch.Tensor:
    """``state`` [..., S] (two-read velocities, x_t and x_t-1) with its velocities replaced by
    the backward second-order difference g (1.5 x_t - 2 x_t-1 + 0.5 x_t-2), from ``earlier``
    [..., S], the state of x_t-1 and x_t-2: 1.5 of this step's rate minus 0.5 of the last's."""
    rates = [v[0] for v in readout.config.velocities]
    state[..., rates] = 1.5 * state[..., rates] - 0.5 * earlier[..., rates]
    return state


class DerivedVelocityAgent:
    """``inner`` acting on the true positions with velocities derived as ``readout`` derives
    them, after Gaussian noise of std ``sigma`` on the positions."""

    uses_images = False

    def __init__(self, inner: StateAgent, readout: StateReadOut, sigma: float = 0.0,
                 seed: int = 0, order: int = 1, true_velocities: bool = False,
                 span: int = 1) -> None:
        self.inner, self.readout, self.sigma, self.order = inner, readout, sigma, order
        self.true_velocities, self.span = true_velocities, span
        self.task, self.action_repeat = inner.task, inner.action_repeat
        self.action_dim = inner.action_dim
        self._rng = np.random.default_rng(seed)
        self._rates = [v[0] for v in readout.config.velocities]
        self._reads: list[torch.Tensor] = []  # this episode's latest reads, oldest first

    def reset(self) -> None:
        self.inner.reset()
        self._reads = []

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        read = list(self.readout.config.read)
        seen = step.state[read] + self.sigma * self._rng.standard_normal(len(read))
        positions = torch.as_tensor(seen, dtype=torch.float32)
        reads = ([] if step.is_first else self._reads[-max(self.span, 2):]) + [positions]
        self._reads = reads
        previous = reads[-2] if len(reads) > 1 else positions
        before = reads[-3] if len(reads) > 2 else previous
        with torch.no_grad():
            state = self.readout.state(positions, previous)
            start = max(0, len(reads) - 1 - self.span)
            if len(reads) - 1 - start > 1:
                spanned = self.readout.state(positions, reads[start])
                state[self._rates] = spanned[self._rates] / (len(reads) - 1 - start)
            if self.order == 2:
                state = three_read_state(self.readout, state, self.readout.state(previous, before))
            state = state.numpy()
        if self.true_velocities:
            state[self._rates] = step.state[self._rates]
        return self.inner.act(dataclasses.replace(step, state=state), image)


def derivation_fit(readout: StateReadOut, states: np.ndarray, is_first: np.ndarray
                   ) -> dict[str, dict[str, float]]:
    """Per velocity component: RMSE of the derived velocity against the true one over
    consecutive steps (``states`` [N, S], ``is_first`` [N]), and the share of the true
    velocity's variance it explains."""
    positions = torch.as_tensor(states[:, list(readout.config.read)], dtype=torch.float32)
    with torch.no_grad():
        derived = readout.window_state(positions[None], torch.as_tensor(is_first)[None])[0].numpy()
    keep = ~is_first
    fit = {}
    for velocity in readout.config.velocities:
        v = velocity[0]
        error = derived[keep, v] - states[keep, v]
        fit[str(v)] = {"rmse": round(float(np.sqrt((error ** 2).mean())), 4),
                       "explained": round(float(1 - error.var() / states[keep, v].var()), 4),
                       "spread": round(float(states[keep, v].std()), 4)}
    return fit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agent", help="a read-out student's agent.pt")
    parser.add_argument("teacher", help="its teacher's checkpoint")
    parser.add_argument("dataset", help="the dataset D it was distilled from")
    parser.add_argument("--noise", type=float, action="append", default=[],
                        help="also with Gaussian noise of this std on the positions")
    parser.add_argument("--order", type=int, action="append", default=None,
                        help="derivation orders to run: 1, the recipe's (default), 2 (also"
                             " a backward second-order difference, less lag)")
    parser.add_argument("--span", type=int, action="append", default=[],
                        help="also each noise with velocities derived over this many steps")
    parser.add_argument("--true-velocities", action="store_true",
                        help="also each --noise with the true velocities handed on")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--dr", default="heldout")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    agent = Agent.load(args.agent)
    readout = agent.student.perception.readout
    assert readout is not None, "pass a read-out student (twist-distil --recipe readout)"
    teacher = load_agent(args.teacher)
    assert isinstance(teacher, StateAgent), "pass a teacher checkpoint"
    config = EvalConfig(task=teacher.task, dr=args.dr, episodes=args.episodes,
                        action_repeat=teacher.action_repeat)

    along: list[np.ndarray] = []  # the teacher's own evaluated states, episode by episode

    def mean_return(agent: object) -> float | dict[str, float]:
        """The mean return, and beside it the success rate where the task defines one."""
        keep = agent is teacher
        results = evaluate(agent, config, seed=args.seed, trajectories=keep)  # type: ignore[arg-type]
        along.extend(r.trajectory["state"] for r in results if keep)
        mean = round(float(np.mean([r.episode_return for r in results])), 1)
        if results[0].success is None:
            return mean
        return {"return": mean, "success": round(float(np.mean([r.success for r in results])), 3)}

    dataset = open_dataset(args.dataset)
    states, first = dataset.column("state"), dataset.column("is_first").astype(bool)
    returns = {"teacher": mean_return(teacher)}
    for order in args.order or [1]:
        name = "derived" if order == 1 else f"derived{order}"
        returns[name] = mean_return(DerivedVelocityAgent(teacher, readout, 0.0, args.seed, order))
        for sigma in args.noise:
            returns[f"{name}+noise:{sigma:g}"] = mean_return(
                DerivedVelocityAgent(teacher, readout, sigma, args.seed, order))
    for span in args.span:
        for sigma in [0.0, *args.noise]:
            returns[f"span{span}+noise:{sigma:g}"] = mean_return(
                DerivedVelocityAgent(teacher, readout, sigma, args.seed, span=span))
    for sigma in args.noise if args.true_velocities else []:
        returns[f"true-velocities+noise:{sigma:g}"] = mean_return(
            DerivedVelocityAgent(teacher, readout, sigma, args.seed, true_velocities=True))
    print(json.dumps({"agent": args.agent, "task": teacher.task, "episodes": args.episodes,
                      "dr": args.dr, "velocities": [list(v) for v in readout.config.velocities],
                      "gains": [round(g, 4) for g in readout.config.gains],
                      "derivation_fit": derivation_fit(readout, states, first),
                      "derivation_fit_along_teacher": derivation_fit(
                          readout, np.concatenate(along),
                          np.concatenate([np.arange(len(a)) == 0 for a in along])),
                      "mean_return": returns}))


if __name__ == "__main__":
    main()
