"""The Gymnasium environments (the ``gym`` extra): Gymnasium's own checker, the same scenes,
initial states and returns as ``twist-eval`` for the same seeds, and bad settings refused."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from twist_data.errors import ConfigError, TwistError  # noqa: E402
from twist_pipeline.acting import PolicyAgent  # noqa: E402
from twist_pipeline.evaluation import EvalConfig, evaluate, run_evaluation  # noqa: E402
from twist_sim.gym_env import TwistEnv, environment_id  # noqa: E402
from twist_sim.randomisation import DR_PRESETS  # noqa: E402
from twist_sim.tasks import TASKS  # noqa: E402

STEPS = 12


def leaning_policy(observation: dict[str, np.ndarray]) -> np.ndarray:
    """A state feedback law: pushes toward the pole's lean (cartpole's sine and its rate)."""
    state = observation["state"]
    return np.array([np.tanh(3 * state[2] + 0.5 * state[4])], np.float32)


@pytest.fixture
def env() -> Iterator[gymnasium.Env]:
    environment = gymnasium.make(environment_id("cartpole-balance", "heldout"), max_steps=STEPS)
    yield environment
    environment.close()


def run_episodes(env: gymnasium.Env, seed: int, episodes: int
                 ) -> tuple[list[float], list[list[np.ndarray]]]:
    returns, images = [], []
    for episode in range(episodes):
        observation, _ = env.reset(seed=seed if episode == 0 else None)
        total, frames, done = 0.0, [observation["image"]], False
        while not done:
            observation, reward, terminated, truncated, _ = env.step(leaning_policy(observation))
            total += reward
            frames.append(observation["image"])
            done = terminated or truncated
        returns.append(total)
        images.append(frames)
    return returns, images


def test_every_task_and_preset_is_registered() -> None:
    for task in TASKS:
        for dr in DR_PRESETS:
            assert environment_id(task, dr) in gymnasium.registry


def test_gymnasiums_checker_passes(env: gymnasium.Env) -> None:
    check_env(env.unwrapped, skip_render_check=True)
    observation, _ = env.reset(seed=0)
    assert observation["image"].shape == (64, 64, 3) and observation["image"].dtype == np.uint8
    assert observation["state"].shape == (5,)
    assert env.action_space.shape == (1,)


def test_the_same_scenes_and_returns_as_twist_eval(env: gymnasium.Env) -> None:
    """Episode i after reset(seed=s) is twist-eval's episode i of seed s: the same frames
    (DR drawn once per episode from the same seed) and, for the same policy, the same return."""
    returns, images = run_episodes(env, seed=3, episodes=3)
    recorded: dict[int, list[np.ndarray]] = {}
    results = evaluate(PolicyAgent(leaning_policy), EvalConfig(episodes=3, max_steps=STEPS),
                       seed=3, record=lambda i, frame: recorded.setdefault(i, []).append(frame))
    assert [r.episode_return for r in results] == pytest.approx(returns, abs=1e-9)
    for episode in range(3):
        assert len(recorded[episode]) == len(images[episode]) == STEPS + 1
        assert all(np.array_equal(a, b) for a, b in zip(recorded[episode], images[episode],
                                                        strict=True))
    # Different seeds and episodes are different scenes.
    assert not np.array_equal(images[0][0], images[1][0])


def test_a_reseed_replays_and_unseeded_resets_continue(env: gymnasium.Env) -> None:
    first, _ = env.reset(seed=5)
    second, info = env.reset()
    again, _ = env.reset(seed=5)
    assert np.array_equal(first["image"], again["image"])
    assert np.array_equal(first["state"], again["state"])
    assert info["episode"] == 1 and not np.array_equal(first["image"], second["image"])


def test_a_policy_of_observations_is_scored_by_twist_eval(tmp_path) -> None:
    summary = run_evaluation({"lean": PolicyAgent(leaning_policy, observe=("state",))},
                             EvalConfig(episodes=2, max_steps=STEPS), seeds=(0,), out=tmp_path)
    episodes = (tmp_path / "episodes.csv").read_text().splitlines()
    assert len(episodes) == 3 and episodes[1].startswith("lean,")
    assert "lean" in str(summary)


def test_state_only_observations_and_stepping_after_the_end(env: gymnasium.Env) -> None:
    states = gymnasium.make(environment_id("cartpole-balance", "train"), observe="state",
                            max_steps=2)
    try:
        observation, _ = states.reset(seed=0)
        assert set(observation) == {"state"}
        for _ in range(2):
            *_, truncated, _ = states.step(np.zeros(1, np.float32))
        assert truncated
        with pytest.raises(gymnasium.error.ResetNeeded):
            states.step(np.zeros(1, np.float32))
    finally:
        states.close()


@pytest.mark.parametrize("settings, message", [
    ({"observe": ("pixels",)}, "observe must name"),
    ({"render_mode": "human"}, "render_mode"),
    ({"task": "cartpole-swingup"}, "unknown task"),
    ({"dr": "wild"}, "DR preset"),
])
def test_bad_settings_are_refused_in_one_line(settings: dict, message: str) -> None:
    with pytest.raises((ConfigError, TwistError), match=message) as error:
        TwistEnv(**settings)
    assert "\n" not in str(error.value)


def test_a_script_that_never_closes_its_environment_exits_silently(gl) -> None:
    """Its renderer's GL context is freed before EGL is torn down at exit, not by MuJoCo's
    destructor after it (which printed an EGLError traceback)."""
    import os
    import subprocess
    import sys

    script = ("import gymnasium, twist_sim.gym_env\n"
              "env = gymnasium.make('twist/cartpole-balance-heldout-v0')\n"
              "env.reset(seed=0)\nenv.step(env.action_space.sample())\nprint('stepped')\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            env={**os.environ, "MUJOCO_GL": "egl"}, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "stepped"
    assert "Exception ignored" not in result.stderr and "Error" not in result.stderr
