"""Agents evaluated under several DR presets on the same episodes, one factor at a time: how
much of its return an agent keeps when the camera moves, the light changes or the physics
differ (``twist-eval --dr heldout,heldout-camera,...``).

Every preset draws an episode's scene from the same stream (:class:`~twist_sim.randomisation.
DRSampler` draws every parameter whatever its range), so episode ``e`` of seed ``s`` has the
same start, backgrounds and colours under each preset, and differs only in the preset's own
factor. Each agent's return under a preset is therefore paired, episode by episode, with its
return under the first preset (the reference, normally ``heldout``): the difference is that
factor's alone.

Folder layout under ``out``: ``<preset>/`` one evaluation per preset (resumable like any),
``factors.csv`` the table.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from twist_data.errors import ConfigError
from twist_pipeline.acting import EvalAgent
from twist_pipeline.evaluation import EvalConfig, paired_episodes, run_evaluation

FACTOR_COLUMNS = ("agent", "dr", "episodes", "mean", "sem", "ratio", "paired", "paired_sem",
                  "better")
FACTOR_TABLE = "factors.csv"


def evaluate_factors(agents: Mapping[str, str | os.PathLike[str] | EvalAgent],
                     config: EvalConfig, presets: Sequence[str], seeds: Sequence[int],
                     out: str | os.PathLike[str], device: str = "cpu", resume: bool = False,
                     batch: int = 1, workers: int = 1,
                     on_progress: Callable[[int, int], None] | None = None) -> pd.DataFrame:
    """Evaluate ``agents`` under each DR preset of ``presets`` (``config`` with its ``dr``
    replaced), each in ``out/<preset>/``, and write ``out/factors.csv``: per agent and
    preset the mean return and its standard error over episodes, the ratio of the mean to
    the agent's mean under ``presets[0]``, and the paired difference from it (± its standard
    error, and the episodes that scored higher). Returns that table."""
    presets = list(presets)
    if len(presets) < 2 or len(set(presets)) != len(presets):
        raise ConfigError(f"a factor table needs two or more different DR presets, the first "
                          f"the reference, got {','.join(presets)}")
    configs = [dataclasses.replace(config, dr=name) for name in presets]  # validates each
    out = Path(out)
    total = len(presets) * len(agents) * len(seeds) * config.episodes
    for i, (name, preset_config) in enumerate(zip(presets, configs, strict=True)):
        offset = i * total // len(presets)
        run_evaluation(agents, preset_config, seeds, out / name, device=device,
                       resume=resume, batch=batch, workers=workers,
                       on_progress=None if on_progress is None
                       else lambda done, _, offset=offset: on_progress(offset + done, total))
    episodes = pd.concat([pd.read_csv(out / name / "episodes.csv").assign(dr=name)
                          for name in presets])
    episodes = episodes[episodes["agent"].isin(list(agents)) & episodes["seed"].isin(seeds)
                        & (episodes["episode"] < config.episodes)]
    table = factor_table(episodes.drop_duplicates(["dr", "agent", "seed", "episode"]), presets)
    table.to_csv(out / FACTOR_TABLE, index=False)
    return table


def factor_table(episodes: pd.DataFrame, presets: Sequence[str]) -> pd.DataFrame:
    """The factor table of an ``episodes.csv``-shaped table with a ``dr`` column (each
    agent's episodes under each of ``presets``; ``presets[0]`` the reference), one row per
    agent and preset in the order given (see :func:`evaluate_factors`)."""
    reference = presets[0]
    rows = []
    for agent in episodes["agent"].drop_duplicates():
        mine = episodes[episodes["agent"] == agent]
        base = mine.loc[mine["dr"] == reference, "return"].mean()
        for name in presets:
            returns = mine.loc[mine["dr"] == name, "return"].to_numpy(np.float64)
            row = {"agent": agent, "dr": name, "episodes": len(returns),
                   "mean": returns.mean(),
                   "sem": returns.std(ddof=1) / np.sqrt(len(returns)) if len(returns) > 1
                   else np.nan,
                   "ratio": returns.mean() / base if base > 0 else np.nan,
                   "paired": np.nan, "paired_sem": np.nan, "better": np.nan}
            if name != reference:
                both = mine[mine["dr"].isin([name, reference])].assign(
                    agent=lambda t: t["dr"])
                paired = paired_episodes(both, name, reference)
                row.update(paired=paired.mean, paired_sem=paired.standard_error,
                           better=paired.better)
            rows.append(row)
    return pd.DataFrame(rows, columns=list(FACTOR_COLUMNS))
