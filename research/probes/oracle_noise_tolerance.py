"""How precisely must a student know the state? The oracle on noisy states

A distilled student acts well only if its latent carries what the teacher's actor reacts to,
as precisely as the actor needs it. This measures that precision from the teacher alone: the
teacher acts on privileged states with independent Gaussian noise of std ``SIGMA`` added to
state component ``I`` at every step (``--noise I:SIGMA``, in the state's own units; repeat the
flag for several settings), on the nominal scene, over the same seeded episodes as the
noise-free teacher -- the baseline measured in the same run. A setting whose return stays near
the baseline's is a precision the student may miss by; one that drops towards the zero-action
floor is one it must reach.

On cartpole the state is (cart x, cos angle, sin angle, cart velocity, angular velocity);
near upright, noise on the sine (component 2) is noise on the angle in radians.

``--exact`` adds a teacher trained on noisy states (``twist-collect --set state_noise=S``)
reading them exactly, its own noise switched off: does it act worse because it learned
less, or because it sees less?

``--lean-gain K`` adds the teacher reading the pole's angle as K times what it is (cartpole:
the angle's cos and sin, and the angular velocity with it, as a student's reading that leans
K times less than the pole hands them on): how much too little lean the teacher's actor
tolerates.

``--read mean`` (or ``mode``) adds the noise-free teacher taking z from its posterior's class
probabilities (or most likely classes) instead of a sample.

Prints one JSON line: the mean return per setting. ``python
research/probes/oracle_noise_tolerance.py TEACHER --noise 2:0.035 --noise 4:0.2 [--read mean]
[--exact] [--episodes 5]``
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json

import numpy as np

from twist_pipeline.acting import StateAgent, load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate
from twist_sim.tasks import Step


class NoisyStateAgent:
    """``inner`` acting on states with Gaussian noise of std ``sigma`` on component ``index``."""

    uses_images = False

    def __init__(self, inner: StateAgent, index: int, sigma: float, seed: int = 0) -> None:
        self.inner, self.index, self.sigma = inner, index, sigma
        self.task, self.action_repeat = inner.task, inner.action_repeat
        self.action_dim = inner.action_dim
        self._rng = np.random.default_rng(seed)

    def reset(self) -> None:
        self.inner.reset()

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        state = step.state.copy()
        state[self.index] += self.sigma * self._rng.standard_normal()
        return self.inner.act(dataclasses.replace(step, state=state), image)


class LeaningStateAgent:
    """``inner`` acting on a cartpole state whose pole angle (cos, sin) and angular velocity
    read ``gain`` times what they are."""

    uses_images = False

    def __init__(self, inner: StateAgent, gain: float) -> None:
        self.inner, self.gain = inner, gain
        self.task, self.action_repeat = inner.task, inner.action_repeat
        self.action_dim = inner.action_dim

    def reset(self) -> None:
        self.inner.reset()

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        state = step.state.copy()
        angle = self.gain * np.arctan2(state[2], state[1])
        state[1], state[2], state[4] = np.cos(angle), np.sin(angle), self.gain * state[4]
        return self.inner.act(dataclasses.replace(step, state=state), image)


def parse_noise(text: str) -> tuple[int, float]:
    index, sigma = text.split(":")
    return int(index), float(sigma)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("teacher", help="a teacher checkpoint (teacher.pt of twist-collect)")
    parser.add_argument("--noise", type=parse_noise, action="append", default=[],
                        metavar="I:SIGMA", help="noise std SIGMA on state component I")
    parser.add_argument("--lean-gain", type=float, action="append", default=[], metavar="K",
                        help="the pole's angle and angular velocity read K times what they "
                             "are (cartpole)")
    parser.add_argument("--task", help="for teacher checkpoints that do not record it")
    parser.add_argument("--action-repeat", type=int, help="likewise")
    parser.add_argument("--read", choices=("mode", "mean"), action="append", default=[],
                        help="also the noise-free teacher taking z from its posterior's mode "
                             "or mean instead of a sample (what a student acting with "
                             "twist-eval --posterior asks of the teacher's actor)")
    parser.add_argument("--exact", action="store_true",
                        help="also the teacher with its own state_noise switched off")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    teacher = load_agent(args.teacher, task=args.task)
    assert isinstance(teacher, StateAgent), "pass a teacher checkpoint"
    teacher.task = teacher.task or args.task
    teacher.action_repeat = teacher.action_repeat or args.action_repeat
    config = EvalConfig(task=teacher.task, dr="none", episodes=args.episodes,
                        action_repeat=teacher.action_repeat)

    def mean_return(agent: object) -> float:
        results = evaluate(agent, config, seed=args.seed)  # type: ignore[arg-type]
        return round(float(np.mean([r.episode_return for r in results])), 1)

    returns = {"none": mean_return(teacher)}
    for read in args.read:
        returns[f"read:{read}"] = mean_return(StateAgent(
            teacher.teacher, teacher.task, action_repeat=teacher.action_repeat, posterior=read))
    if args.exact:
        exact = copy.deepcopy(teacher.teacher)
        exact.world_model.config = dataclasses.replace(exact.world_model.config, state_noise=0.0)
        returns["exact"] = mean_return(StateAgent(exact, teacher.task,
                                                  action_repeat=teacher.action_repeat))
    for index, sigma in args.noise:
        returns[f"{index}:{sigma:g}"] = mean_return(
            NoisyStateAgent(teacher, index, sigma, args.seed))
    for gain in args.lean_gain:
        returns[f"lean-gain:{gain:g}"] = mean_return(LeaningStateAgent(teacher, gain))
    print(json.dumps({"teacher": args.teacher, "task": teacher.task, "episodes": args.episodes,
                      "mean_return": returns}))


if __name__ == "__main__":
    main()
