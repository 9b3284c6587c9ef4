"""Does a read-out student hold its lost scenes when its reading of the pole's lean is
amplified?

Along the student's own episodes in the scenes it loses, its reading leans less than the pole
(slopes 0.22-0.80 against 0.82-0.92 where it holds; ``bias_identification.py``), as a
squared-error read-out does where a frame shows the lean faintly: it shrinks towards the
upright D is full of. The teacher's actor, acting on states, tolerates a lean read too large
far better than one read too small (``oracle_noise_tolerance.py --lean-gain``). If the lost
scenes are lost for the shrinkage, reading every angle ``gain`` times larger (about the
angle's median over D, upright on cartpole; the angular velocity, a difference of readings,
grows with it; the library's map, ``ReadOutConfig.lean``, which leaves a fallen pole where it
is) should hold them, at the price of amplifying the held scenes' read noise too;
if they are lost for noise or an offset, the gain should not help or should hurt.

Each agent is evaluated at every gain on the same held-out episodes, one table::

    python research/probes/readout_amplified.py runs/mirror/student/agent.pt --gain 1 \
        --gain 1.5 --episodes 30 --out runs/amplified/eval [--save runs/amplified/bundles]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from twist_models.agent import Agent
from twist_pipeline.acting import ImageAgent
from twist_pipeline.evaluation import EvalConfig, run_evaluation


def amplified(agent: Agent, lean: float) -> Agent:
    """``agent`` handing its filter each angle it reads ``lean`` times further from D's median
    angle (``ReadOutConfig.lean``, whatever its bundle says), its config saying so."""
    student = dataclasses.replace(agent.config.student, readout=dataclasses.replace(
        agent.config.student.readout, lean=lean))
    agent.config = dataclasses.replace(agent.config, student=student)
    agent.student.config = student
    agent.student.perception.readout.config = student.perception.readout
    agent.info["lean_set_by"] = "research/probes/readout_amplified.py"
    return agent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("agent", type=Path)
    parser.add_argument("--gain", type=float, action="append", required=True)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--dr", default="heldout")
    parser.add_argument("--backgrounds")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--save", type=Path,
                        help="also write each lean's bundle here (agent-lean<K>.pt) for "
                             "twist-eval")
    args = parser.parse_args()

    agents = {f"gain{g:g}": ImageAgent(amplified(Agent.load(args.agent), g)) for g in args.gain}
    if args.save is not None:
        args.save.mkdir(parents=True, exist_ok=True)
        for name, agent in agents.items():
            agent.agent.save(args.save / f"agent-lean{name.removeprefix('gain')}.pt")
    info = Agent.load(args.agent).info
    config = EvalConfig(task=info.get("task"), dr=args.dr, episodes=args.episodes,
                        backgrounds=args.backgrounds, action_repeat=info.get("action_repeat"))
    summary = run_evaluation(agents, config, seeds=[args.seed], out=args.out, batch=args.batch)
    for name, row in summary["agents"].items():
        print(f"{name}: {row['mean']:.1f}")


if __name__ == "__main__":
    main()
