"""Every task of the paper's benchmark goes through the pipeline at ``tiny`` size: a teacher
collects D (with frame pairs, which the read-out of a tracked body's speed needs), D verifies
with frames redrawn from its physics, and a ``readout`` student distils from it and acts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from twist_data.reader import open_dataset
from twist_data.verify import verify_dataset
from twist_models.agent import Agent
from twist_models.distillation import distil_preset
from twist_pipeline.collect import collect, collect_preset
from twist_pipeline.distil import distil
from twist_sim.rerender import check_reproduction
from twist_sim.tasks import TaskEnv

#: The DMC tasks beyond the two (cartpole-balance, cup-catch) every other module exercises.
TASKS = ("cheetah-run", "hopper-stand", "walker-walk", "finger-turn_easy")


@pytest.mark.parametrize("task", TASKS)
def test_a_task_collects_verifies_and_distils_at_tiny_size(task: str, tmp_path: Path,
                                                          gl: None) -> None:
    dataset = tmp_path / "dataset"
    collect(dataset, collect_preset("tiny", task=task, frames=200, views=1,
                                    pairs=True))
    report = verify_dataset(dataset)
    assert report.ok, report.problems
    data = open_dataset(dataset)
    assert check_reproduction(data, n_steps=4) == []
    env = TaskEnv(task)
    assert (data.spec.task, data.spec.state_dim) == (task, env.state_dim)
    assert data.has_pairs
    summary = distil(dataset, tmp_path / "student", distil_preset(
        "tiny", "readout", frame_eval_every=2, **{"schedule.holdout_every": 2}))
    agent = Agent.load(summary.agent)
    readout = agent.config.student.readout
    # The read-out covers the teacher's whole state: each component read, derived or read
    # from a frame pair.
    covered = {*readout.read, *(v[0] for v in readout.velocities), *readout.moving}
    assert covered == set(range(env.state_dim))
    image = np.asarray(data.episode(0).image[0, 0])  # step 0, view 0
    action, _ = agent.act(image)
    assert action.shape == (env.action_dim,) and np.all(np.abs(action) <= 1)
