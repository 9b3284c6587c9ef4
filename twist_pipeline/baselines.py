"""Offline image baselines trained from the same matching dataset D as the student.

* ``dreamer``: DreamerV2 on D's images: an image world model (reconstruction, reward, KL)
  with its own actor-critic in imagination; the paper's *Dreamer w/ DR* on the randomised
  renders, and *Dreamer w/o DR* on a clean re-render of D
  (``twist-data render D D-clean --dr none --views 1``).
* ``state-recon``: the same, but its decoder reconstructs the privileged state instead of the
  image (the paper's *State Recon*).

Both read windows of D exactly as the distiller does (same held-out split, a random view per
step) and end in the same deployable bundle as the student (``agent.pt``: image encoder,
RSSM and actor), so ``twist-eval`` treats every image agent alike. A fair comparison gives
them the student's update budget (``--steps``).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader

from twist_data.errors import ConfigError, TwistError
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.sampler import SamplerConfig, WindowDataset, image_problem, window_problem
from twist_data.seeding import derived_seed
from twist_data.staging import removed_on_failure, require_memory
from twist_models.agent import Agent
from twist_models.checkpoint import read_checkpoint, restore, save_checkpoint
from twist_models.config import (
    PRESETS,
    ActorCriticConfig,
    AgentConfig,
    DreamerConfig,
    StudentConfig,
    from_json,
    image_dreamer_preset,
    require_choice,
    require_non_negative,
    require_positive,
)
from twist_models.device import COMPILE_SETTINGS, compile_mode, resolve_device
from twist_models.dreamer import Dreamer
from twist_pipeline.runlog import RunFolder, TensorBoardLog, append_csv

log = logging.getLogger(__name__)

KINDS = {"dreamer": "obs", "state-recon": "state"}
KEYS = ("image", "state", "action", "reward", "is_first", "is_terminal")
METRIC_COLUMNS = ("updates", "wall_s", "updates_per_s", "model_loss", "recon_loss",
                  "reward_loss", "kl", "actor_loss", "critic_loss", "imagined_return")


class BaselineError(TwistError):
    """A baseline cannot be trained (inputs, output folder)."""


@dataclass(frozen=True)
class BaselineConfig:
    """One offline baseline run."""

    kind: str = "dreamer"
    """``dreamer`` (image reconstruction) or ``state-recon`` (state reconstruction)."""
    model: str = "quick"
    """Size preset of world model and actor-critic (``tiny``, ``quick``, ``paper``)."""
    steps: int = 800
    """Updates (give the student's budget for a fair comparison)."""
    batch_size: int = 16
    """Windows per update."""
    length: int = 50
    """Steps per window."""
    imag_starts: int = 256
    """Posterior states that start imagination (0 = all B*L)."""
    view: int | None = None
    """Camera view; None: a random one of the K per step, as the student."""
    holdout_every: int = 10
    """Every n-th episode of D is held out (the distiller's split)."""
    seed: int = 0
    """Seed of initialisation and windows."""
    log_every: int = 50
    """Updates between metrics.csv rows."""
    checkpoint_every: int = 50
    """Updates between writes of ``latest.pt``."""
    workers: int = 0
    """DataLoader processes (0: decode in the training process)."""
    compile: str = "off"
    """Updates through ``torch.compile`` as the collector's teacher
    (:func:`~twist_models.device.compile_mode`). ``off`` by default, unlike the collector's
    ``auto``: an image world model compiled on a GPU has not been run."""

    def __post_init__(self) -> None:
        require_choice(self, "compile", COMPILE_SETTINGS)
        if self.kind not in KINDS:
            raise ConfigError(f"unknown baseline {self.kind!r}; valid: {', '.join(KINDS)}")
        if self.model not in PRESETS:
            raise ConfigError(f"unknown model preset {self.model!r}; valid: {', '.join(PRESETS)}")
        require_positive(self, "steps", "batch_size", "length", "log_every", "checkpoint_every")
        require_non_negative(self, "imag_starts", "workers")
        if self.holdout_every < 2:
            raise ConfigError(f"holdout_every must be >= 2, got {self.holdout_every}")


@dataclass(frozen=True)
class Progress:
    """Reported every ``log_every`` updates."""

    updates: int
    total: int
    updates_per_second: float
    model_loss: float


def behaviour_config(extra: dict[str, Any], preset: ActorCriticConfig) -> ActorCriticConfig:
    """``preset`` with the behaviour-learning settings of the teacher that collected D
    (``extra["teacher"]``, written by twist-collect) when D records them: a baseline learns
    behaviour as the teacher did (discount for D's action repeat, learning rates, critic head),
    so the comparison with TWIST differs in how the world model is learned, not in how its
    actor is trained. Network sizes stay the preset's."""
    recorded = (extra.get("teacher") or {}).get("actor_critic")
    if recorded is None:
        return preset
    return dataclasses.replace(from_json(ActorCriticConfig, recorded), actor=preset.actor,
                               critic=preset.critic)


def _set_up(data: MatchingDataset, dataset: Path, out: Path, config: BaselineConfig,
            dreamer_config: DreamerConfig, resume: bool, device: str
            ) -> tuple[Dreamer, Iterator[dict[str, torch.Tensor]], float]:
    """The run folder, the model (resumed from ``latest.pt`` if there is one), the training
    windows and the seconds the run has trained so far."""
    folder = RunFolder(out, "baseline", BaselineError, "a baseline run")
    folder.open(config, resume, ("steps", "compile"), "--steps and --set compile")
    torch.manual_seed(config.seed)
    model = Dreamer(dreamer_config)
    seconds = 0.0
    if folder.latest.exists():
        checkpoint = read_checkpoint(folder.latest, kind="dreamer")
        restore(checkpoint, model, dreamer_config, model.optimisers())
        seconds = checkpoint.counters.get("train_ms", 0) / 1000
    model.to_device(device)
    model.compile_update(compile_mode(config.compile, torch.device(device)))
    folder.write_config(config, dreamer=dreamer_config, dataset=Path(dataset))
    sampler = SamplerConfig(length=config.length, batch_size=config.batch_size,
                            view=config.view, keys=KEYS, holdout_every=config.holdout_every,
                            split="train", seed=derived_seed(config.seed, int(model.step)))
    try:
        windows = iter(DataLoader(WindowDataset(dataset, sampler), batch_size=None,
                                  num_workers=config.workers))
    except TwistError as exc:
        raise BaselineError(f"no training windows: {exc}") from None
    # The first batch reads D's arrays whole: damage there is refused with the set-up undone.
    first = next(windows)
    return model, itertools.chain([first], windows), seconds


def train_baseline(dataset: str | os.PathLike[str], out: str | os.PathLike[str],
                   config: BaselineConfig, resume: bool = False, device: str = "cpu",
                   on_progress: Callable[[Progress], None] | None = None,
                   time_limit: float | None = None) -> dict[str, Any]:
    """Train baseline ``config.kind`` offline on D and write ``out/agent.pt``; returns the
    run summary (also ``summary.json``). ``time_limit``: seconds the run may train in all,
    resumed calls included; past them it stops after the update in progress, checkpointed so
    that ``resume`` continues (``stopped`` = ``"time limit"``): a baseline given a student's
    wall clock."""
    if time_limit is not None and not time_limit > 0:
        raise BaselineError(f"the time limit must be a positive number of seconds, got "
                            f"{time_limit}")
    resolve_device(device)
    dataset, out = Path(dataset), Path(out)
    if not dataset.exists():
        raise BaselineError(f"dataset {str(dataset)!r} does not exist")
    data = open_dataset(dataset)
    data.require_images("twist-baseline")
    spec = data.spec
    dreamer_config = image_dreamer_preset(config.model, spec.state_dim, spec.action_dim,
                                          spec.image_height, recon=KINDS[config.kind])
    behaviour = behaviour_config(spec.extra, dreamer_config.actor_critic)
    dreamer_config = dataclasses.replace(dreamer_config, actor_critic=dataclasses.replace(
        behaviour, imag_starts=config.imag_starts))
    problem = window_problem(data, config.length, config.view) or image_problem(data)
    if problem is not None:
        raise BaselineError(f"{str(dataset)!r}: {problem}")
    require_memory(config.batch_size * config.length * int(np.prod(spec.image_shape)) * 4,
                   f"a batch of {config.batch_size} windows of {config.length} steps (its "
                   "images as float32 alone)")
    with removed_on_failure(out):  # a refused set-up leaves no config or log behind
        model, windows, before = _set_up(data, dataset, out, config, dreamer_config, resume,
                                         device)
    latest = RunFolder(out, "baseline", BaselineError, "a baseline run").latest
    board = TensorBoardLog(Path(out))
    start = time.perf_counter()
    deadline = None if time_limit is None else start + time_limit - before
    try:
        _train(model, windows, config, dreamer_config, latest, Path(out), board, device,
               on_progress, deadline, start - before)
    finally:
        board.close()
    seconds = before + time.perf_counter() - start
    agent = image_agent(model, {**spec.image_agent_info(), "dataset": str(dataset),
                                "baseline": config.kind, "updates": int(model.step)})
    path = agent.save(out / "agent.pt")
    summary = {"kind": config.kind, "updates": int(model.step), "agent": str(path),
               "out": str(out), "seconds": round(seconds, 1),
               "stopped": "done" if int(model.step) >= config.steps else "time limit"}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _train(model: Dreamer, windows: Iterator[dict[str, torch.Tensor]], config: BaselineConfig,
           dreamer_config: DreamerConfig, latest: Path, out: Path, board: TensorBoardLog, device: str,
           on_progress: Callable[[Progress], None] | None, deadline: float | None = None,
           origin: float = 0.0) -> None:
    """Updates until ``config.steps`` or the ``deadline`` (a ``perf_counter`` time): a metrics
    row (and TensorBoard scalars) every ``log_every``, a checkpoint every
    ``checkpoint_every`` and where the deadline stops it, recording the run's training
    seconds (``perf_counter`` minus ``origin``) for a resumed call's limit."""
    sums: dict[str, float] = {}
    done, tick = 0, time.perf_counter()

    def checkpoint() -> None:
        save_checkpoint(latest, "dreamer", model, dreamer_config, model.optimisers(),
                        {"updates": int(model.step),
                         "train_ms": round((time.perf_counter() - origin) * 1000)})

    while int(model.step) < config.steps:
        if deadline is not None and time.perf_counter() >= deadline:
            checkpoint()
            return
        batch = {k: v.to(device) for k, v in next(windows).items() if k in KEYS}
        for key, value in model.train_step(batch).items():
            sums[key] = sums.get(key, 0.0) + value
        done += 1
        updates = int(model.step)
        if updates % config.log_every == 0 or updates == config.steps:
            elapsed = time.perf_counter() - tick
            row = {"updates": updates, "wall_s": round(elapsed, 2),
                   "updates_per_s": done / elapsed, **{k: v / done for k, v in sums.items()}}
            append_csv(out / "metrics.csv", row, METRIC_COLUMNS)
            for key, value in row.items():
                if key not in ("updates", "wall_s"):
                    board.scalar(f"train/{key}", value, updates)
            if on_progress is not None:
                on_progress(Progress(updates, config.steps, row["updates_per_s"],
                                     row["model_loss"]))
            sums, done, tick = {}, 0, time.perf_counter()
        if updates % config.checkpoint_every == 0 or updates == config.steps:
            checkpoint()


def image_agent(model: Dreamer, info: dict[str, Any]) -> Agent:
    """The deployable bundle of an image Dreamer: its encoder, RSSM and actor."""
    wm = model.world_model
    config: DreamerConfig = model.config
    student = StudentConfig(rssm=config.world_model.rssm,
                            action_dim=config.world_model.action_dim, cnn=config.world_model.cnn)
    agent = Agent(AgentConfig(student=student, actor_critic=config.actor_critic), info)
    agent.student.perception.encoder.load_state_dict(wm.encoder.state_dict())
    agent.student.rssm.load_state_dict(wm.rssm.state_dict())
    agent.actor.load_state_dict(model.actor_critic.actor.state_dict())
    return agent
