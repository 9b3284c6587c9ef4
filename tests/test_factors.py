"""Agents under several DR presets: the factor table against hand-computed statistics, and
the per-factor presets meeting the same episodes, so that a paired difference is the factor's
alone."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twist_data.errors import ConfigError
from twist_pipeline.acting import ScriptedAgent
from twist_pipeline.evaluation import EvalConfig
from twist_pipeline.factors import FACTOR_TABLE, evaluate_factors, factor_table


def test_the_factor_table_by_hand() -> None:
    returns = {("a", "heldout"): [900.0, 800.0, 700.0], ("a", "heldout-camera"): [450.0, 800.0, 350.0],
               ("b", "heldout"): [100.0, 200.0, 300.0], ("b", "heldout-camera"): [100.0, 260.0, 300.0]}
    episodes = pd.DataFrame([{"agent": agent, "dr": dr, "seed": 0, "episode": e, "return": r}
                             for (agent, dr), values in returns.items()
                             for e, r in enumerate(values)])
    table = factor_table(episodes.sample(frac=1.0, random_state=0),  # any row order
                         ["heldout", "heldout-camera"]).set_index(["agent", "dr"])
    a = table.loc[("a", "heldout-camera")]
    assert a["mean"] == pytest.approx(1600 / 3) and a["ratio"] == pytest.approx(1600 / 2400)
    assert a["sem"] == pytest.approx(np.std([450, 800, 350], ddof=1) / np.sqrt(3))
    # Episode by episode: -450, 0, -350.
    assert a["paired"] == pytest.approx(-800 / 3)
    assert a["paired_sem"] == pytest.approx(np.std([-450, 0, -350], ddof=1) / np.sqrt(3))
    assert a["better"] == 0 and a["episodes"] == 3
    b = table.loc[("b", "heldout-camera")]
    assert b["paired"] == pytest.approx(20.0) and b["better"] == 1
    assert b["ratio"] == pytest.approx(660 / 600)
    reference = table.loc[("a", "heldout")]
    assert reference["ratio"] == 1.0 and np.isnan(reference["paired"])
    assert list(factor_table(episodes, ["heldout", "heldout-camera"])["agent"]) == ["a"] * 2 + ["b"] * 2


def test_a_blind_agent_meets_the_same_episodes_under_every_view_factor(gl, tmp_path) -> None:
    # Constant actions never look at the image: under a preset that changes only what the
    # camera shows, every episode scores exactly what it scored under heldout; under the
    # physics preset the same actions move other dynamics.
    config = EvalConfig(task="cartpole-balance", episodes=2, max_steps=25)
    agent = ScriptedAgent(lambda step: np.full(1, 0.7, np.float32), task="cartpole-balance")
    presets = ["heldout", "heldout-camera", "heldout-light", "heldout-physics"]
    seen = []
    table = evaluate_factors({"push": agent}, config, presets, [0], tmp_path / "f",
                             on_progress=lambda done, total: seen.append((done, total)))
    rows = table.set_index("dr")
    assert rows.loc["heldout-camera", "paired"] == 0.0 and rows.loc["heldout-light", "paired"] == 0.0
    assert rows.loc["heldout-physics", "paired"] != 0.0
    assert rows.loc["heldout", "mean"] > 0
    assert seen[-1] == (8, 8) and [d for d, _ in seen] == sorted(d for d, _ in seen)
    written = pd.read_csv(tmp_path / "f" / FACTOR_TABLE)
    pd.testing.assert_frame_equal(written, table.reset_index(drop=True), check_dtype=False)
    for name in presets:
        assert len(pd.read_csv(tmp_path / "f" / name / "episodes.csv")) == 2


def test_a_factor_table_needs_two_known_presets_and_writes_nothing_otherwise(tmp_path) -> None:
    config = EvalConfig(task="cartpole-balance", episodes=1, max_steps=2)
    for presets, message in ((["heldout"], "two or more different DR presets"),
                             (["heldout", "heldout"], "two or more different DR presets"),
                             (["heldout", "nowhere"], "unknown DR preset 'nowhere'")):
        with pytest.raises(ConfigError, match=message):
            evaluate_factors({"zero": "zero"}, config, presets, [0], tmp_path / "f")
    assert not (tmp_path / "f").exists()
