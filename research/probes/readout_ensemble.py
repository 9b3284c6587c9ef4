"""Do read-out students distilled with different seeds err differently, so that the mean of
their readings acts better than either?

Two read-out CNNs trained on the same D with different distillation seeds see the same
frames but start from different weights and draw them in a different order. If a held-out
scene's misreading is the scene's (a pole that barely shows), both misread it alike and the
mean of their readings errs as much; if it is each network's own (what a background happens to
look like to one set of features), their errors partly cancel, as the mirror image's did.

The first agent bundle acts with its teacher's filter and actor; each step's read-out (the
positions the filter is handed, each member's mirror-averaged as the recipe reads) is the mean
of every member's, its (cos, sin) pairs put back on the unit circle. Every member alone and
the mean are evaluated on the same held-out episodes (``run_evaluation``, one table)::

    python research/probes/readout_ensemble.py runs/mirror/student/agent.pt \
        runs/mirror1/student/agent.pt --episodes 30 --out runs/ensemble/eval

The members must share D (the read-out's standardisation and velocity gains) and teacher:
checked, refused otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from twist_models.agent import Agent
from twist_models.perception import StateReading
from twist_models.student import Student
from twist_pipeline.acting import ImageAgent
from twist_pipeline.evaluation import EvalConfig, run_evaluation


class EnsembleReading(StateReading):
    """The first member's perception, reading each image as the mean of every member's."""

    def __init__(self, members: list[Student]) -> None:
        super().__init__(members[0].config)
        self.load_state_dict(members[0].perception.state_dict())
        self.members = [m.perception for m in members]  # a plain list: not this module's

    def read_positions(self, image: torch.Tensor) -> torch.Tensor:
        read = torch.stack([member.read_positions(image) for member in self.members]).mean(0)
        parts = list(read.unbind(-1))
        for c, s in self.readout.angle_slots:  # each pair back on the unit circle
            norm = torch.sqrt(parts[c] ** 2 + parts[s] ** 2).clamp_min(1e-6)
            parts[c], parts[s] = parts[c] / norm, parts[s] / norm
        return torch.stack(parts, -1)


def ensemble_reading(members: list[Agent]) -> Agent:
    """The first member's agent, its student reading as :class:`EnsembleReading`."""
    head = members[0].student
    for other in members[1:]:
        readout = other.student.perception.readout
        if not (torch.allclose(readout.mean, head.perception.readout.mean, rtol=1e-6)
                and torch.allclose(readout.gains, head.perception.readout.gains, rtol=1e-6)):
            raise SystemExit("the members were not distilled from the same D (their read-out "
                             "standardisation or velocity gains differ)")
    ensemble = members[0]
    ensemble.student.perception = EnsembleReading([m.student for m in members]).eval()
    return ensemble


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("agents", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--dr", default="heldout")
    parser.add_argument("--skip-members", action="store_true",
                        help="evaluate the mean only (the members were evaluated before)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if len(args.agents) < 2:
        raise SystemExit("give at least two agent bundles")

    agents: dict[str, ImageAgent] = {}
    if not args.skip_members:
        for i, path in enumerate(args.agents):
            agents[f"member{i}"] = ImageAgent(Agent.load(path))
    members = [Agent.load(path) for path in args.agents]
    agents["mean"] = ImageAgent(ensemble_reading(members))
    info = members[0].info
    config = EvalConfig(task=info.get("task"), dr=args.dr, episodes=args.episodes,
                        action_repeat=info.get("action_repeat"))
    summary = run_evaluation(agents, config, seeds=[args.seed], out=args.out, batch=args.batch)
    for name, row in summary["agents"].items():
        print(f"{name}: {row['mean']:.1f}")


if __name__ == "__main__":
    main()
