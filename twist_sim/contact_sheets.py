"""Contact sheets: one simulated instant drawn under training and held-out randomisation."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from twist_data.errors import ConfigError
from twist_sim.randomisation import TRAINING_DR, DRConfig, dr_preset
from twist_sim.render import DRRenderer
from twist_sim.rollout import random_policy
from twist_sim.tasks import TaskEnv

_LABEL_WIDTH = 72


def default_rows() -> dict[str, DRConfig]:
    """A contact sheet's rows unless told otherwise: training and held-out scenes."""
    return {"train": dr_preset(TRAINING_DR), "heldout": dr_preset("heldout")}


def contact_sheet(task: str, views: int = 6, image_size: int = 64, warmup_steps: int = 40,
                  seed: int = 0, rows: dict[str, DRConfig] | None = None,
                  scale: int = 2) -> np.ndarray:
    """[rows * S, label + views * S, 3] RGB: each row renders the same state under one config.

    The state is reached by ``warmup_steps`` random actions from ``reset(seed)`` so that the
    agent is in a typical, not an initial, pose. ``rows`` defaults to the training preset
    (:data:`~twist_sim.randomisation.TRAINING_DR`) and ``heldout``.
    """
    if warmup_steps < 0 or scale < 1:
        raise ConfigError(f"warmup_steps must be >= 0 and scale >= 1, got {warmup_steps}, {scale}")
    rows = rows or default_rows()
    env = TaskEnv(task, seed=seed)
    step = env.reset(seed=seed)
    policy = random_policy(env.action_dim, seed)
    for _ in range(warmup_steps):
        if step.is_last:
            break
        step = env.step(policy(step))
    side = image_size * scale
    lines = []
    for label, config in rows.items():
        with DRRenderer(task, config, image_size, views) as renderer:
            sampler = renderer.sampler(seed)
            sampler.begin_episode(seed)
            images = renderer.render(step.physics, sampler.sample())
        tiles = [cv2.resize(im, (side, side), interpolation=cv2.INTER_NEAREST) for im in images]
        margin = np.full((side, _LABEL_WIDTH, 3), 255, np.uint8)
        cv2.putText(margin, label, (4, side // 2 + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
        lines.append(np.concatenate([margin, *tiles], axis=1))
    return np.concatenate(lines, axis=0)


def write_contact_sheet(path: str | os.PathLike[str], sheet: np.ndarray) -> Path:
    """Write an RGB sheet as PNG."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"contact sheets are written as PNG; got output file {str(path)!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)):
        raise ConfigError(f"could not write {str(path)!r}")
    return path
