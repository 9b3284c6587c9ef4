"""Domain randomisation as data: a frozen config, named presets, and a seeded parameter sampler.

Nothing here renders. :class:`DRSampler` turns a :class:`DRConfig` into explicit per-view
parameter arrays (the ``data/dr/<name>`` arrays of a dataset) and per-episode dynamics (the
``meta/dr/<name>`` arrays); :mod:`twist_sim.render` turns parameters and a physics state into
pixels. Because the parameters are stored, any frame can be reproduced or re-randomised.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

from twist_data.errors import ConfigError
from twist_data.schema import ParamSpec


@dataclass(frozen=True)
class Dynamics:
    """Per-episode dynamics randomisation (multipliers of the model's nominal values)."""

    friction_scale: float = 1.0
    """Multiplier of every geom's sliding friction."""
    mass_scale: float = 1.0
    """Multiplier of every body's mass (and inertia, so shapes keep their density)."""

    def __post_init__(self) -> None:
        for name in ("friction_scale", "mass_scale"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive finite number, got {value}")


#: Material groups whose colours are randomised, in the order of ``dr/colour``'s rows. These
#: are dm_control's shared materials: agent body, end effectors, decorations, targets, floor.
COLOUR_GROUPS: tuple[str, ...] = ("self", "effector", "decoration", "target", "grid")

BackgroundSource = Literal["train", "wide", "leaves", "heldout", "directory", "none"]


@dataclass(frozen=True)
class DRConfig:
    """Which factors are randomised, over what ranges, and how often."""

    background: BackgroundSource = "train"
    """Background bank: procedural ``train``, ``wide`` (``train``'s families and two more),
    ``leaves`` (``wide``'s and dead leaves) or ``heldout`` families, a user ``directory``,
    or ``none`` (dm_control's own sky)."""
    background_dir: str = ""
    """Folder of images/videos when ``background`` is ``directory``."""
    background_count: int = 128
    """Number of procedural textures in the bank."""
    background_seed: int = 0
    """Seed of the procedural bank (the bank is a pure function of source, count, size, seed)."""
    colour_delta: float = 0.3
    """Maximum change of each RGB channel (0-1 scale) of every COLOUR_GROUPS material around
    its nominal colour; 0 keeps the nominal colours (0.3 is Distracting Control's hardest)."""
    light_range: tuple[float, float] = (1.0, 1.0)
    """Uniform range of the multiplier of every light's intensity."""
    camera_shift: float = 0.0
    """Maximum camera translation per world axis, metres."""
    camera_rotation: float = 0.0
    """Maximum camera rotation angle about a random axis, radians."""
    friction_range: tuple[float, float] = (1.0, 1.0)
    """Uniform range of the per-episode multiplier of every geom's sliding friction."""
    mass_range: tuple[float, float] = (1.0, 1.0)
    """Uniform range of the per-episode multiplier of every body's mass and inertia."""
    resample: Literal["step", "episode"] = "step"
    """Draw new rendering parameters every agent step (collection) or once per episode
    (evaluation)."""
    low_contrast_share: float = 0.0
    """Share of views whose agent body (the ``self`` material) takes the colour of a random
    spot of the view's background crop, clipped into its colour range: camouflaged bodies,
    more often than a uniform draw makes them (0 = every colour uniform, as in the paper)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "light_range", tuple(float(v) for v in self.light_range))
        object.__setattr__(self, "friction_range", tuple(float(v) for v in self.friction_range))
        object.__setattr__(self, "mass_range", tuple(float(v) for v in self.mass_range))
        if self.background not in get_args(BackgroundSource):
            raise ConfigError(f"background must be one of "
                              f"{', '.join(get_args(BackgroundSource))}, got {self.background!r}")
        if (self.background == "directory") != bool(self.background_dir):
            raise ConfigError(f"background_dir must be set exactly when background is 'directory', "
                              f"got background={self.background!r}, "
                              f"background_dir={self.background_dir!r}")
        if self.background_count < 1:
            raise ConfigError(f"background_count must be >= 1, got {self.background_count}")
        if not 0.0 <= self.colour_delta <= 1.0:
            raise ConfigError(f"colour_delta must be in [0, 1], got {self.colour_delta}")
        if self.camera_shift < 0 or not 0 <= self.camera_rotation <= np.pi:
            raise ConfigError(f"camera_shift must be >= 0 and camera_rotation in [0, pi], got "
                              f"{self.camera_shift} and {self.camera_rotation}")
        for name in ("light_range", "friction_range", "mass_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ConfigError(f"{name} must satisfy 0 < low <= high, got {(lo, hi)}")
        if self.resample not in ("step", "episode"):
            raise ConfigError(f"resample must be 'step' or 'episode', got {self.resample!r}")
        if not 0.0 <= self.low_contrast_share <= 1.0:
            raise ConfigError(f"low_contrast_share must be in [0, 1], got {self.low_contrast_share}")
        if self.low_contrast_share > 0 and (self.background == "none" or self.colour_delta == 0):
            raise ConfigError(f"low_contrast_share > 0 needs a background bank and colour_delta > 0, "
                              f"got background={self.background!r}, colour_delta={self.colour_delta}")

    def replace(self, **changes: Any) -> DRConfig:
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DRConfig:
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - fields)
        if unknown:
            raise ConfigError(f"unknown DR config fields {unknown}")
        return cls(**data)


_WIDE = DRConfig(background="wide", background_count=1024, resample="step")
_CAMOUFLAGED_SHARE = 0.5
_LIGHT = dict(light_range=(0.5, 1.5))
_CAMERA = dict(camera_shift=0.05, camera_rotation=0.1)
_PHYSICS = dict(friction_range=(0.5, 2.0), mass_range=(0.75, 1.25))
_FULL = {**_LIGHT, **_CAMERA, **_PHYSICS}
_HELDOUT = DRConfig(background="heldout", resample="episode")

#: Named DR configurations. ``train``/``heldout`` are the paper's DMC setting (background and
#: colours; re-sampled every step for collection, once per episode on held-out backgrounds for
#: evaluation); the ``-full`` variants add the manipulation factors (light, camera, friction,
#: mass). Not in the paper: ``train-wide`` draws from 1,024 textures of five families instead
#: of 128 of three (it reads unseen background kinds better); ``train-leaves`` adds dead
#: leaves, a family with the statistics of photographs; ``train-contrast`` and
#: ``train-wide-contrast`` camouflage the body in half of the training views;
#: ``train-wide-full`` adds the ``-full`` factors to ``train-wide`` (a re-render keeps D's
#: physics); ``heldout-camera``, ``heldout-light`` and ``heldout-physics`` add one ``-full``
#: factor each to ``heldout`` with every other draw the same, so that a drop in return is that
#: factor's alone; ``train-wide-episode`` holds one scene per episode, as evaluation does;
#: ``none`` renders the nominal scene. What each measured: docs/findings.md.
DR_PRESETS: dict[str, DRConfig] = {
    "train": DRConfig(background="train", resample="step"),
    "train-wide": _WIDE,
    "train-wide-episode": dataclasses.replace(_WIDE, resample="episode"),
    "train-leaves": DRConfig(background="leaves", background_count=1024, resample="step"),
    "train-contrast": DRConfig(background="train", resample="step",
                               low_contrast_share=_CAMOUFLAGED_SHARE),
    "train-wide-contrast": dataclasses.replace(_WIDE, low_contrast_share=_CAMOUFLAGED_SHARE),
    "train-wide-full": dataclasses.replace(_WIDE, **_FULL),
    "heldout": _HELDOUT,
    "heldout-camera": dataclasses.replace(_HELDOUT, **_CAMERA),
    "heldout-light": dataclasses.replace(_HELDOUT, **_LIGHT),
    "heldout-physics": dataclasses.replace(_HELDOUT, **_PHYSICS),
    "train-full": DRConfig(background="train", resample="step", **_FULL),
    "heldout-full": dataclasses.replace(_HELDOUT, **_FULL),
    "none": DRConfig(background="none", colour_delta=0.0, resample="episode"),
}

#: The preset D is rendered under unless a command is told otherwise (collection, re-render,
#: recording, the contact sheet's training row).
TRAINING_DR = "train-wide"


def dr_preset(name: str, backgrounds: str | os.PathLike[str] | None = None) -> DRConfig:
    """Preset ``name``, with the backgrounds drawn from the images/videos in ``backgrounds``
    instead of the procedural bank when a folder is given."""
    try:
        config = DR_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown DR preset {name!r}; valid presets are: "
                          f"{', '.join(DR_PRESETS)}") from None
    if backgrounds is not None:
        config = config.replace(background="directory", background_dir=str(backgrounds))
    return config


#: Per-step, per-view parameters written to ``data/dr/<name>``.
VIEW_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("background", (), "int32",
              "index into the background bank of the view's render block "
              "(spec.extra.render[i].bank); -1 = dm_control's sky"),
    ParamSpec("background_offset", (2,), "int32",
              "top-left (row, column) of the crop of the background texture, texture pixels"),
    ParamSpec("colour", (len(COLOUR_GROUPS), 3), "float32",
              "RGB 0-1 of the materials " + ", ".join(COLOUR_GROUPS)),
    ParamSpec("light", (), "float32", "multiplier of every light's intensity"),
    ParamSpec("camera_shift", (3,), "float32", "camera translation in world axes, metres"),
    ParamSpec("camera_rotation", (3,), "float32",
              "camera rotation as an axis-angle vector in world axes, radians"),
)

#: Per-episode parameters written to ``meta/dr/<name>``.
EPISODE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("friction_scale", (), "float32", "multiplier of every geom's sliding friction"),
    ParamSpec("mass_scale", (), "float32", "multiplier of every body's mass and inertia"),
)


class DRSampler:
    """Seeded source of DR parameters for K views.

    Call :meth:`begin_episode` at every reset and :meth:`sample` at every step. With
    ``resample="episode"`` every step of an episode gets the parameters drawn at its start.
    ``background_colours`` ([N, C, C, 3], 0-1: :meth:`BackgroundBank.colour_grid` of textures
    ``2 * max_offset`` pixels wide) is needed only for ``low_contrast_share > 0``.
    """

    def __init__(self, config: DRConfig, nominal_colours: np.ndarray, views: int,
                 n_backgrounds: int, max_offset: int, seed: int = 0,
                 background_colours: np.ndarray | None = None) -> None:
        if views < 1:
            raise ConfigError(f"views (K) must be >= 1, got {views}")
        self.config = config
        self.views = views
        self.nominal_colours = np.asarray(nominal_colours, np.float32).reshape(len(COLOUR_GROUPS), 3)
        self.n_backgrounds = 0 if config.background == "none" else int(n_backgrounds)
        self.max_offset = int(max_offset)
        self.background_colours = None
        if config.low_contrast_share > 0 and self.n_backgrounds:
            grid = None if background_colours is None else np.asarray(background_colours, np.float32)
            if grid is None or grid.ndim != 4 or grid.shape[0] != self.n_backgrounds \
                    or grid.shape[1] != grid.shape[2] or grid.shape[1] % 2:
                raise ConfigError(f"low_contrast_share > 0 needs the bank's colour grid "
                                  f"[{self.n_backgrounds}, C, C, 3] with C even, got "
                                  f"{None if grid is None else grid.shape}")
            self.background_colours = grid
        self._rng = np.random.default_rng(seed)
        self._episode_params: dict[str, np.ndarray] | None = None

    def begin_episode(self, seed: int | None = None) -> Dynamics:
        """Start an episode (optionally from its own seed); returns its dynamics."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        c = self.config
        dynamics = Dynamics(friction_scale=float(self._rng.uniform(*c.friction_range)),
                            mass_scale=float(self._rng.uniform(*c.mass_range)))
        self._episode_params = self._draw() if c.resample == "episode" else None
        return dynamics

    def sample(self) -> dict[str, np.ndarray]:
        """Parameters of the K views of the next step: ``{name: [K, *shape]}``."""
        if self._episode_params is not None:
            return {k: v.copy() for k, v in self._episode_params.items()}
        return self._draw()

    def _draw(self) -> dict[str, np.ndarray]:
        c, k, rng = self.config, self.views, self._rng
        if self.n_backgrounds:
            background = rng.integers(0, self.n_backgrounds, k).astype(np.int32)
            offset = rng.integers(0, self.max_offset + 1, (k, 2)).astype(np.int32)
        else:
            background = np.full(k, -1, np.int32)
            offset = np.zeros((k, 2), np.int32)
        delta = rng.uniform(-c.colour_delta, c.colour_delta, (k, *self.nominal_colours.shape))
        colour = np.clip(self.nominal_colours + delta, 0.0, 1.0).astype(np.float32)
        light = rng.uniform(*c.light_range, k).astype(np.float32)
        shift = rng.uniform(-c.camera_shift, c.camera_shift, (k, 3)).astype(np.float32)
        axis = rng.normal(size=(k, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        rotation = (axis * rng.uniform(0, c.camera_rotation, (k, 1))).astype(np.float32)
        if self.background_colours is not None:
            # Drawn after everything else so that the other parameters' stream is the
            # uniform draw's.
            self._camouflage(colour, background, offset)
        return {"background": background, "background_offset": offset, "colour": colour,
                "light": light, "camera_shift": shift, "camera_rotation": rotation}

    def _camouflage(self, colour: np.ndarray, background: np.ndarray, offset: np.ndarray) -> None:
        """Give a ``low_contrast_share`` of the views (in place) a body the colour of a random
        cell of their background crop, as close as the body's colour range allows."""
        grid, rng, k = self.background_colours, self._rng, self.views
        cells = grid.shape[1]
        chosen = rng.random(k) < self.config.low_contrast_share
        # A crop is half the texture's side (textures are twice the view), so it covers
        # cells // 2 grid cells per axis from the cell holding its corner.
        spot = offset * cells // (2 * self.max_offset) + rng.integers(0, cells // 2, (k, 2))
        spot = np.minimum(spot, cells - 1)
        body = COLOUR_GROUPS.index("self")
        nominal, delta = self.nominal_colours[body], self.config.colour_delta
        for v in np.flatnonzero(chosen):
            target = grid[background[v], spot[v, 0], spot[v, 1]]
            colour[v, body] = np.clip(target, np.maximum(nominal - delta, 0.0),
                                      np.minimum(nominal + delta, 1.0))


def stack_view_params(per_step: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Per-step draws of :meth:`DRSampler.sample` -> the episode's ``dr`` arrays [T, K, ...]."""
    return {p.name: np.stack([step[p.name] for step in per_step]) for p in VIEW_PARAMS}


def dynamics_params(dynamics: Dynamics) -> dict[str, np.ndarray]:
    """The ``meta/dr`` values of an episode's dynamics."""
    return {"friction_scale": np.float32(dynamics.friction_scale),
            "mass_scale": np.float32(dynamics.mass_scale)}
