"""A user's own task, registered from outside the package: found by name in every stage,
collected and distilled at `tiny` size; and the registrations refused."""

from __future__ import annotations

import collections
import dataclasses
import importlib
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dm_control")

from dm_control import mujoco
from dm_control.rl import control
from dm_control.suite import base

from twist_data.errors import ConfigError
from twist_data.reader import open_dataset
from twist_sim import tasks
from twist_sim.errors import TaskRegistrationError, UnknownTaskError
from twist_sim.tasks import TASKS, TaskEnv, TaskSpec, register_task, task_spec

EXAMPLE = Path(__file__).parents[1] / "docs" / "examples" / "slider_task.py"


@pytest.fixture
def slider(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The documented example module, found as a user's is: importable in every process (on
    PYTHONPATH: the renderer runs in a child) and named in TWIST_TASK_MODULES; unregistered
    afterwards so that no other test sees it."""
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(EXAMPLE.parent), *filter(None, [os.environ.get("PYTHONPATH")])]))
    monkeypatch.setenv(tasks.TASK_MODULES_VARIABLE, "slider_task")
    monkeypatch.setattr(tasks, "_LOADED_MODULES", False)
    yield "slider-reach"
    tasks._REGISTERED.pop("slider-reach", None)
    tasks._PRISTINE.pop("slider-reach", None)
    sys.modules.pop("slider_task", None)


def test_the_example_task_fits_in_forty_lines() -> None:
    assert len(EXAMPLE.read_text().splitlines()) <= 40


def test_a_task_module_named_in_the_environment_registers_on_first_lookup(slider: str) -> None:
    assert slider not in TASKS
    spec = task_spec(slider)
    assert spec.name == slider and slider in TASKS and spec.source.endswith("environment")
    env = TaskEnv(slider, seed=0)
    first = env.reset(seed=3)
    assert env.state_layout == (("position", 1), ("velocity", 1))
    # The block starts where the task's own random draw put it, and a push moves it along x.
    start = np.random.RandomState(3).uniform(-0.4, 0.4)
    assert first.state[0] == pytest.approx(start, abs=1e-6)
    moved = env.step(np.ones(1))
    assert moved.state[0] > first.state[0] and moved.state[1] > 0
    # Its physics vector restores the exact instant, as every task's does.
    again = TaskEnv(slider, seed=5)
    again.reset()
    again.set_physics_state(moved.physics)
    np.testing.assert_array_equal(again.physics_state(), moved.physics)


def test_an_action_outside_the_tasks_bounds_is_refused(slider: str) -> None:
    env = TaskEnv(slider)
    env.reset(seed=0)
    with pytest.raises(ConfigError, match=re.escape(
            "slider-reach's actions lie within [-1, 1]; got [1.5]")):
        env.step(np.array([1.5]))
    with pytest.raises(ConfigError, match="got \\[nan\\]"):
        env.step(np.array([np.nan]))
    env.step(np.array([1.0]))  # the bound itself is an action


def test_a_users_task_is_collected_and_distilled_at_tiny_size(
        slider: str, tmp_path: Path, gl: None) -> None:
    from twist_data.verify import verify_dataset
    from twist_models.distillation import distil_preset
    from twist_pipeline.collect import collect, collect_preset
    from twist_pipeline.distil import distil

    out = tmp_path / "D"
    collect(out, collect_preset("tiny", task=slider))
    assert verify_dataset(out).ok
    data = open_dataset(out)
    assert data.spec.task == slider and data.spec.state_dim == 2
    images = np.empty((4, *data.spec.image_shape), np.uint8)
    data.read_frames(np.arange(4), np.zeros(4, int), images)
    assert images.std() > 0  # the scene was drawn, not a blank frame
    summary = distil(out, tmp_path / "student", dataclasses.replace(
        distil_preset("tiny", "paper"), steps=4))
    assert Path(summary.agent).is_file()


def _environment(xml: str, observation: dict | None = None):
    class Still(base.Task):
        def initialize_episode(self, physics):
            pass

        def get_observation(self, physics):
            if observation is not None:
                return observation
            return collections.OrderedDict(position=physics.data.qpos.copy())

        def get_reward(self, physics):
            return 0.0

    return lambda: control.Environment(mujoco.Physics.from_xml_string(xml), Still(random=0))


SCENE = ("<mujoco><asset><material name='{material}'/></asset><worldbody>"
         "<camera pos='0 -1 0'/><body><joint name='x' type='slide'/>"
         "<geom size='.1' material='{material}'/></body></worldbody><actuator>"
         "<motor joint='x' ctrlrange='{low} 1' ctrllimited='true'/></actuator></mujoco>")


def _scene(material: str = "self", low: float = -1) -> str:
    return SCENE.format(material=material, low=low)


@pytest.mark.parametrize(("spec", "message"), [
    (TaskSpec("cartpole-balance", environment=_environment(_scene())),
     "a task named 'cartpole-balance' is registered already (dm_control cartpole/balance)"),
    (TaskSpec("user-empty", environment=_environment(_scene(), observation={})),
     "task 'user-empty' declares no state layout: its task's get_observation must return a "
     "non-empty mapping of named arrays, got {}"),
    (TaskSpec("user-grey", environment=_environment(_scene(material="paint"))),
     "task 'user-grey' has no material domain randomisation recolours: name at least one of "
     "its materials self, effector, decoration, target, grid"),
    (TaskSpec("user-wide", environment=_environment(_scene(low=-2))),
     "task 'user-wide' must take a vector of actions within [-1, 1] (an actor's tanh range), "
     "got shape (1,) within [-2.0, 1.0]"),
    (TaskSpec("user-field", environment=_environment(_scene()),
              model_fields=(("site_pos", "goal"),)),
     "task 'user-field' names model field site_pos[goal], which its model lacks"),
    (TaskSpec("user-mirror", environment=_environment(_scene()), mirror=(1.0, -1.0)),
     "task 'user-mirror' declares a mirror of 2 signs for a state of 1 components"),
    (TaskSpec("user-camera", environment=_environment(_scene()), camera=1),
     "task 'user-camera' renders camera 1, but its model has 1 cameras"),
])
def test_a_task_that_cannot_work_is_refused_and_nothing_registers(spec: TaskSpec,
                                                                  message: str) -> None:
    before = dict(TASKS)
    with pytest.raises(TaskRegistrationError, match=re.escape(message)):
        register_task(spec)
    assert dict(TASKS) == before


def test_a_spec_names_its_task_well_and_says_where_it_comes_from() -> None:
    with pytest.raises(TaskRegistrationError, match=re.escape(
            "a task's name is lower-case words joined by one hyphen, like 'cup-catch'; "
            "got 'Push'")):
        TaskSpec("Push", environment=_environment(_scene()))
    with pytest.raises(TaskRegistrationError, match="not neither"):
        TaskSpec("user-none")
    with pytest.raises(TaskRegistrationError, match="not both"):
        TaskSpec("user-both", "cartpole", "balance", environment=_environment(_scene()))
    with pytest.raises(TaskRegistrationError, match="needs a revision >= 1, got 0"):
        TaskSpec("user-push", environment=_environment(_scene()), revision=0)


def test_an_unknown_task_lists_the_registered_ones_and_a_broken_module_is_named(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tasks, "_LOADED_MODULES", False)
    monkeypatch.setenv(tasks.TASK_MODULES_VARIABLE, "no_such_task_module")
    with pytest.raises(TaskRegistrationError, match=re.escape(
            "task module 'no_such_task_module' named in TWIST_TASK_MODULES does not import")):
        task_spec("user-push")
    monkeypatch.setattr(tasks, "_LOADED_MODULES", True)
    with pytest.raises(UnknownTaskError, match=re.escape(
            "unknown task 'user-push'; registered tasks are: cartpole-balance, cheetah-run")):
        task_spec("user-push")


def test_the_gymnasium_ids_follow_a_registration(slider: str) -> None:
    gymnasium = pytest.importorskip("gymnasium")
    gym_env = importlib.import_module("twist_sim.gym_env")
    task_spec(slider)
    assert gym_env.environment_id(slider, "heldout") in gymnasium.registry
