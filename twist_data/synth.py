"""Synthetic matching datasets: the fixtures of the tests and the data of demos and benchmarks.

A small cart-pole-like system is simulated and drawn with procedural, per-view randomised
backgrounds, so images are textured (compress like renders, not like constant frames) and
every frame can be re-rendered exactly from the stored physics state and DR parameters
(:func:`render_synthetic`), as a real collector's frames can. Its ``tracked`` variant is seen
by a camera that follows the cart, as DMC's follow a runner: the state holds no cart
position, and its speed shows only as the motion between two frames of one scene, which the
dataset stores as frame pairs (``pair_image``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from twist_data.schema import DatasetSpec, Episode, EpisodeInfo, ParamSpec
from twist_data.seeding import derived_seed
from twist_data.staging import require_disk, require_memory, require_writable
from twist_data.storage import StorageLayout
from twist_data.writer import ShardWriter

log = logging.getLogger(__name__)

SYNTH_TASK = "synthetic-cartpole"
#: The tracked variant's task name (:attr:`SynthConfig.tracked`).
SYNTH_TRACKED_TASK = "synthetic-cartpole-tracked"
#: Image widths the floor moves per unit of cart position where the camera tracks the cart:
#: a step at a typical speed moves it by a pixel or two of a 32-pixel image, well within
#: the half wave (a quarter of the width) that tells its direction.
_TRACKED_SHIFT = 1.0
#: The synthetic state's signs in the mirrored picture (drawn about the image's centre
#: column): x, cos, sin | x_dot, theta_dot, as cartpole-balance's ``TaskSpec.mirror``.
SYNTH_MIRROR = (-1.0, 1.0, -1.0, -1.0, -1.0)
_DT = 0.05


@dataclass(frozen=True)
class SynthConfig:
    """What ``write_synthetic_dataset`` writes."""

    episodes: int = 4
    """Episodes in total, spread evenly over the shards."""
    steps: int = 60
    """Steps per episode (T, including the first step), before jitter."""
    views: int = 2
    """K randomised renders per step."""
    image_size: int = 64
    """Square image side in pixels."""
    shards: int = 1
    """Number of shards (as if written by that many collectors)."""
    length_jitter: int = 0
    """Episodes are shortened by up to this many steps; shortened ones end terminally."""
    seed: int = 0
    """Seed of everything: the data is a pure function of the config."""
    tracked: bool = False
    """A camera that follows the cart: the state is (cos, sin | x_dot, theta_dot), the cart is
    drawn at the centre with the scene shifted by its position, and D stores frame pairs."""

    def __post_init__(self) -> None:
        problems = []
        for name in ("episodes", "views", "image_size", "shards"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.image_size < 16:
            problems.append(f"image_size must be >= 16, got {self.image_size}")
        if self.steps < 2:
            problems.append(f"steps must be >= 2, got {self.steps}")
        elif not 0 <= self.length_jitter < self.steps - 1:
            problems.append(f"length_jitter must be in [0, steps - 1), got {self.length_jitter}")
        if problems:
            raise ValueError("; ".join(problems))


def synth_spec(views: int = 2, image_size: int = 64, tracked: bool = False) -> DatasetSpec:
    """The dataset spec of synthetic data (state and physics laid out like DMC cartpole; the
    ``tracked`` variant's state without the cart's position)."""
    return DatasetSpec(
        views=views, image_height=image_size, image_width=image_size,
        state_dim=4 if tracked else 5, action_dim=1, physics_dim=4,
        task=SYNTH_TRACKED_TASK if tracked else SYNTH_TASK, action_repeat=1,
        dr_params=(
            ParamSpec("background_seed", (), "int64", "seed of the procedural background"),
            ParamSpec("agent_rgb", (3,), "float32", "RGB colour of cart and pole, 0-1"),
            ParamSpec("brightness", (), "float32", "light intensity multiplier"),
        ),
        episode_dr_params=(ParamSpec("pole_mass_scale", (), "float32", "pole mass multiplier"),),
        state_layout=(("position", 2 if tracked else 3), ("velocity", 2)),
        extra={"generator": "twist_data.synth"},
    )


def render_synthetic(physics: np.ndarray, background_seed: int, agent_rgb: np.ndarray,
                     brightness: float, size: int, tracked: bool = False) -> np.ndarray:
    """Draw one view of the state ``physics`` = [x, theta, x_dot, theta_dot] -> [size, size, 3]
    (``tracked``: the cart at the centre, the scene shifted by its position)."""
    rng = np.random.default_rng(int(background_seed))
    cells = int(rng.integers(2, 9))
    low = rng.integers(0, 256, (cells, cells, 3), dtype=np.uint8)
    image = cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC)
    period = int(rng.integers(3, 12))
    yy, xx = np.indices((size, size))
    checker = ((yy // period + xx // period) % 2).astype(np.uint8) * np.uint8(40)
    image = cv2.add(image, np.repeat(checker[..., None], 3, axis=2))
    floor = int(size * 0.8)
    image[floor:] = (90, 90, 90)
    x, theta = float(physics[0]), float(physics[1])
    if tracked:  # the floor's waves move past a cart held at the centre; the sky stays
        phase = 2 * np.pi * (xx[0] / size + x * _TRACKED_SHIFT)
        image[size // 2:] = np.round(75 + 50 * np.sin(2 * phase)).astype(np.uint8)[:, None]
        x = 0.0
    colour = tuple(int(c) for c in np.round(np.asarray(agent_rgb, np.float64) * 255))
    cx = round(size / 2 + x * size / 6)
    cy = floor - size // 16
    half_w, half_h = size // 10, size // 20
    cv2.rectangle(image, (cx - half_w, cy - half_h), (cx + half_w, cy + half_h), colour, -1)
    pole = size * 0.35
    tip = (round(cx + pole * np.sin(theta)), round(cy - pole * np.cos(theta)))
    cv2.line(image, (cx, cy), tip, colour, max(1, size // 32))
    return cv2.convertScaleAbs(image, alpha=float(brightness))


def synth_episode(spec: DatasetSpec, seed: int, length: int,
                  terminal: bool = False) -> tuple[Episode, EpisodeInfo]:
    """One deterministic episode of ``length`` steps in the format's time convention."""
    rng = np.random.default_rng(seed)
    k, size = spec.views, spec.image_height
    mass_scale = np.float32(rng.uniform(0.5, 2.0))
    physics = np.zeros((length, 4), np.float64)
    physics[0] = [rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), 0.0, 0.0]
    action = np.zeros((length, 1), np.float32)
    noise = 0.0
    for t in range(1, length):
        # Smooth random actions (Ornstein-Uhlenbeck); action[t] is applied at step t-1.
        noise = 0.8 * noise + 0.6 * rng.normal()
        action[t, 0] = np.clip(noise, -1.0, 1.0)
        x, th, xd, thd = physics[t - 1]
        a = float(action[t, 0])
        xdd = 4.0 * a - 0.5 * xd - 2.0 * x
        thdd = (9.8 * np.sin(th) - 0.3 * thd - 2.0 * a * np.cos(th)) / float(mass_scale)
        xd, thd = xd + _DT * xdd, thd + _DT * thdd
        physics[t] = [x + _DT * xd, th + _DT * thd, xd, thd]
    x, th = physics[:, 0], physics[:, 1]
    state = np.stack([x, np.cos(th), np.sin(th), physics[:, 2], physics[:, 3]], 1)
    tracked = spec.task == SYNTH_TRACKED_TASK
    if tracked:
        state = state[:, 1:]
    reward = ((np.cos(th) + 1) / 2 * np.exp(-(x**2))).astype(np.float32)
    reward[0] = 0.0
    flags = np.zeros(length, bool)
    is_first, is_last, is_terminal = flags.copy(), flags.copy(), flags.copy()
    is_first[0], is_last[-1], is_terminal[-1] = True, True, terminal
    discount = np.ones(length, np.float32)
    discount[-1] = 0.0 if terminal else 1.0
    background_seed = rng.integers(0, 2**62, (length, k), dtype=np.int64)
    agent_rgb = rng.uniform(0.1, 1.0, (length, k, 3)).astype(np.float32)
    brightness = rng.uniform(0.6, 1.3, (length, k)).astype(np.float32)
    image = np.empty((length, k, size, size, 3), np.uint8)
    pair = np.empty_like(image) if tracked else None
    for t in range(length):
        for v in range(k):
            draw = (background_seed[t, v], agent_rgb[t, v], brightness[t, v], size, tracked)
            image[t, v] = render_synthetic(physics[t], *draw)
            if pair is not None:  # the step before in this step's scene (datasets.md, §2)
                pair[t, v] = render_synthetic(physics[max(t - 1, 0)], *draw)
    episode = Episode(
        image=image, state=state.astype(np.float32), physics=physics, action=action,
        reward=reward, discount=discount, is_first=is_first, is_last=is_last,
        is_terminal=is_terminal,
        dr={"background_seed": background_seed, "agent_rgb": agent_rgb, "brightness": brightness},
        pair_image=pair,
    )
    info = EpisodeInfo(seed=seed, policy="synthetic", dr={"pole_mass_scale": mass_scale})
    return episode, info


def episode_seed(config: SynthConfig, index: int) -> int:
    """Seed of global synthetic episode ``index`` under ``config``."""
    return derived_seed(config.seed, index)


def episode_length(config: SynthConfig, index: int) -> int:
    """Length of global synthetic episode ``index`` (jittered deterministically)."""
    if config.length_jitter == 0:
        return config.steps
    rng = np.random.default_rng(episode_seed(config, index) ^ 0x5EED)
    return config.steps - int(rng.integers(0, config.length_jitter + 1))


def synthetic_episode(config: SynthConfig, index: int) -> tuple[Episode, EpisodeInfo]:
    """Global synthetic episode ``index`` exactly as ``write_synthetic_dataset`` writes it."""
    length = episode_length(config, index)
    return synth_episode(synth_spec(config.views, config.image_size, config.tracked),
                         episode_seed(config, index), length, terminal=length < config.steps)


def shard_names(config: SynthConfig) -> list[str]:
    return [f"synth-{i:03d}" for i in range(config.shards)]


def write_synthetic_dataset(out: str | os.PathLike[str], config: SynthConfig,
                            layout: StorageLayout | None = None,
                            on_episode: Callable[[int, int], None] | None = None) -> Path:
    """Write a synthetic dataset to the folder ``out``.

    Shards get contiguous blocks of episodes, so global episode i of the dataset (shards in
    name order) is exactly ``synthetic_episode(config, i)``.

    ``on_episode(done, total)`` is called after each committed episode (progress display).
    """
    out = Path(out)
    require_writable(out, "dataset folder")
    frame = config.views * config.image_size ** 2 * 3
    # One episode is made whole in memory; its frames compress little on disk.
    require_memory(config.steps * (frame + 64), f"a synthetic episode of {config.steps} steps")
    require_disk(config.episodes * config.steps * frame, out,
                 f"writing {config.episodes} synthetic episodes of {config.steps} steps")
    spec = synth_spec(config.views, config.image_size, config.tracked)
    writers = [ShardWriter.create(out, name, spec, layout, pairs=config.tracked)
               for name in shard_names(config)]
    try:
        for i in range(config.episodes):
            episode, info = synthetic_episode(config, i)
            writers[i * config.shards // config.episodes].append(episode, info)
            if on_episode is not None:
                on_episode(i + 1, config.episodes)
    finally:
        for w in writers:
            w.close()
    log.info("wrote %d synthetic episodes to %s", config.episodes, out)
    return out
