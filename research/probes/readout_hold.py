"""Does a read-out student gain by pooling what an episode never changes? One reading per episode

A read-out student (``--recipe readout``) reads every state component afresh from each frame.
Some never change within an episode (panda-push's goal marker), so an error independent
between frames would shrink as the frames of one episode are pooled. This evaluates a
read-out student on the same seeded episodes under each condition:

* ``as-is``: the student unchanged (the baseline, measured in the same run; a student
  distilled with ``readout_stage.pool=constant`` already pools the components D's episodes
  never change, ``ReadOutConfig.pooled``);
* ``mean``, ``median``: the ``--hold`` components handed to the filter as the mean (or
  median) of their readings over the episode so far;
* ``truth``: the ``--hold`` components handed over exactly as the simulator has them, the most
  any pooling could give.

It prints, per condition, the return, the success rate where the task has one and the paired
difference against ``as-is``. If ``truth`` gains little, the held components' errors are not
what the student loses by; if ``truth`` gains and ``mean`` / ``median`` do not, the errors are
shared by an episode's frames (a camera pose, a scene), which pooling cannot average out.

``python research/probes/readout_hold.py AGENT --hold 6,7 [--dr heldout,heldout-full]
[--episodes 50] [--seed 0] [--conditions as-is,truth]`` (``--hold``: state indices; on
panda-push 6,7 are the goal's x and y); prints one JSON line per preset and condition.
``--conditions as-is,truth`` alone asks which read components an episode's successes hang on,
moving or not (on panda-lift 4,5,6 are the block's x, y and z).
"""

from __future__ import annotations

import argparse
import contextlib
import json
from collections.abc import Iterator, Sequence
from unittest import mock

import numpy as np
import torch

from twist_models.perception import StateReading
from twist_pipeline.acting import ImageAgent, load_agent
from twist_pipeline.evaluation import EvalConfig, evaluate
from twist_sim.tasks import Step

CONDITIONS = ("as-is", "mean", "median", "truth")


@contextlib.contextmanager
def holding(slots: Sequence[int], indices: Sequence[int], condition: str) -> Iterator[None]:
    """Within the block, every read-out student hands its filter the read slots ``slots`` (of
    the state's ``indices``) pooled over the episode so far (``mean``, ``median``) or as the
    simulator has them (``truth``); ``as-is`` changes nothing."""
    if condition == "as-is":
        yield
        return
    act_batch = ImageAgent.act_batch
    seen: list[torch.Tensor] = []
    truth: list[torch.Tensor] = []

    def record_truth(agent: ImageAgent, steps: Sequence[Step], images: np.ndarray | None,
                     uniform: torch.Tensor | None) -> np.ndarray:
        truth[:] = [torch.tensor(np.stack([s.state[list(indices)] for s in steps]),
                                 dtype=torch.float32)]
        return act_batch(agent, steps, images, uniform)

    def held_step(self: StateReading, image: torch.Tensor, history: torch.Tensor | None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        positions = self.read_positions(image).clone()
        if history is None:  # an episode's first step: nothing pooled yet
            seen.clear()
        if condition == "truth":
            positions[..., list(slots)] = truth[0].to(positions.device).reshape(
                positions[..., list(slots)].shape)
        else:
            seen.append(positions[..., list(slots)].clone())
            pooled = torch.stack(seen)
            positions[..., list(slots)] = (pooled.mean(0) if condition == "mean"
                                           else pooled.median(0).values)
        previous = positions if history is None else history
        return self.embed_state(self.readout.state(positions, previous)), positions

    with mock.patch.object(StateReading, "step", held_step), \
            mock.patch.object(ImageAgent, "act_batch", record_truth):
        yield


def compare(path: str, hold: Sequence[int], drs: Sequence[str], episodes: int, seed: int,
            conditions: Sequence[str] = CONDITIONS) -> list[dict]:
    """The student under each of ``conditions`` (``as-is`` always among them, first) on the
    same episodes of each preset in ``drs``."""
    agent = load_agent(path)
    if not isinstance(agent, ImageAgent) or agent.agent.config.student.readout is None:
        raise SystemExit(f"{path} is not a read-out student (--recipe readout)")
    read = list(agent.agent.config.student.readout.read)
    missing = [i for i in hold if i not in read]
    if missing:
        raise SystemExit(f"state components {missing} are not read from images (read: {read})")
    slots = [read.index(i) for i in hold]
    out = []
    for dr in drs:
        config = EvalConfig(task=agent.task, dr=dr, episodes=episodes,
                            action_repeat=agent.action_repeat)
        results = {}
        for condition in ["as-is", *(c for c in conditions if c != "as-is")]:
            with holding(slots, hold, condition):
                # batch=10 steps episodes together, each on its own draws (evaluate's doc);
                # one shared pool per batch is right because a batch's episodes start together.
                results[condition] = evaluate(agent, config, seed=seed, batch=10)
        out.extend(paired_rows(dr, results, "as-is"))
    return out


def paired_rows(dr: str, results: dict[str, list], baseline: str) -> list[dict]:
    """One JSON row per condition of ``results`` (its evaluated episodes, the same seeded
    episodes under each): return, success rate and the paired difference against
    ``baseline``'s."""
    base = np.array([r.episode_return for r in results[baseline]])
    rows = []
    for condition, episodes_run in results.items():
        returns = np.array([r.episode_return for r in episodes_run])
        difference = returns - base
        success = [r.success for r in episodes_run if r.success is not None]
        rows.append({"dr": dr, "condition": condition, "episodes": len(returns),
                     "return": round(float(returns.mean()), 1),
                     "success": round(float(np.mean(success)), 2) if success else None,
                     "difference": round(float(difference.mean()), 1),
                     "stderr": round(float(difference.std(ddof=1) / np.sqrt(len(returns))), 1),
                     "better": int((difference > 0).sum())})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agent", help="a read-out student's agent.pt")
    parser.add_argument("--hold", required=True,
                        help="comma-separated state indices to pool or hand over true")
    parser.add_argument("--conditions", default=",".join(CONDITIONS),
                        help="comma-separated, of " + ", ".join(CONDITIONS) + " (as-is always runs)")
    parser.add_argument("--dr", default="heldout", help="comma-separated evaluation presets")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    hold = [int(i) for i in args.hold.split(",")]
    conditions = args.conditions.split(",")
    unknown = sorted(set(conditions) - set(CONDITIONS))
    if unknown:
        raise SystemExit(f"unknown conditions {unknown}; choose from {', '.join(CONDITIONS)}")
    for entry in compare(args.agent, hold, args.dr.split(","), args.episodes, args.seed,
                         conditions):
        print(json.dumps(entry), flush=True)


if __name__ == "__main__":
    main()
