"""The matching-dataset schema: the arrays of a shard, their dtypes, shapes and units.

This module is the single source of truth for the format described in ``datasets.md``;
the writer, the reader, ``verify`` and the tests all read the tables below.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twist_data.errors import FormatVersionError, InvalidEpisodeError, NotADatasetError

FORMAT_NAME = "twist.matching-dataset"
FORMAT_VERSION = 2
ATTRS_KEY = "twist"
IMAGE_CHANNELS = 3

#: Codes of ``meta/episode_policy``; the same table is stored in every shard's attributes.
POLICY_CODES: dict[str, int] = {"synthetic": 0, "random": 1, "teacher": 2, "scripted": 3,
                                "student": 4}


@dataclass(frozen=True)
class ParamSpec:
    """One domain-randomisation parameter stored alongside the data."""

    name: str
    """Array name under ``data/dr/`` (per step and view) or ``meta/dr/`` (per episode)."""
    shape: tuple[int, ...] = ()
    """Trailing shape of one value (``()`` for a scalar)."""
    dtype: str = "float32"
    """NumPy dtype name."""
    description: str = ""
    """Meaning and units, written into the shard so the data stays self-describing."""

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ValueError(f"DR parameter name must be an identifier, got {self.name!r}")
        np.dtype(self.dtype)  # raises on an unknown dtype
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))


@dataclass(frozen=True)
class DatasetSpec:
    """What every shard of one dataset agrees on: sizes, task and the DR parameters it records."""

    views: int
    """K: randomised renders stored per step."""
    image_height: int
    """Rendered image height in pixels."""
    image_width: int
    """Rendered image width in pixels."""
    state_dim: int
    """Length of the privileged state vector s_t."""
    action_dim: int
    """Length of the action vector."""
    physics_dim: int
    """Length of the full simulator state vector (enough to restore the exact instant)."""
    task: str
    """Task name, e.g. ``cartpole-balance``."""
    action_repeat: int = 1
    """Simulator steps per agent step."""
    dr_params: tuple[ParamSpec, ...] = ()
    """Per-step, per-view rendering parameters (``data/dr/<name>``, shape ``[N, K, *shape]``)."""
    episode_dr_params: tuple[ParamSpec, ...] = ()
    """Per-episode parameters such as dynamics randomisation (``meta/dr/<name>``, ``[E, *shape]``)."""
    state_layout: tuple[tuple[str, int], ...] = ()
    """Names and sizes of the fields concatenated into the state vector, in order (may be empty)."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    """Free JSON provenance: DR configuration, collector configuration, library versions."""

    def __post_init__(self) -> None:
        problems = []
        for name in ("views", "image_height", "image_width", "action_dim", "action_repeat"):
            if int(getattr(self, name)) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("state_dim", "physics_dim"):
            if int(getattr(self, name)) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.state_layout and sum(n for _, n in self.state_layout) != self.state_dim:
            problems.append(
                f"state_layout sizes sum to {sum(n for _, n in self.state_layout)}, "
                f"but state_dim is {self.state_dim}"
            )
        names = [p.name for p in self.dr_params] + [p.name for p in self.episode_dr_params]
        if len(set(names)) != len(names):
            problems.append(f"DR parameter names must be unique, got {names}")
        if problems:
            raise ValueError("; ".join(problems))

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.image_height, self.image_width, IMAGE_CHANNELS)

    @property
    def supersample(self) -> int | None:
        """The supersampling factor every view was rendered with (the render blocks of
        ``extra["render"]``); None when the views differ in it or nothing records how they
        were rendered (synthetic shards)."""
        factors = {int(block.get("supersample", 1)) for block in self.extra.get("render") or []}
        return factors.pop() if len(factors) == 1 else None

    @property
    def drawn(self) -> bool:
        """Whether twist drew the frames (its renderer or its synthetic generator), which
        never draw a frame of zeros: one in such a D was overwritten under a valid checksum."""
        return "render" in self.extra or "generator" in self.extra

    def image_agent_info(self) -> dict[str, Any]:
        """How an agent trained on these images must be shown the world again: task, action
        repeat, image size and supersampling (None: unknown)."""
        return {"task": self.task, "action_repeat": self.action_repeat,
                "image_size": self.image_height, "supersample": self.supersample}

    def to_json(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["extra"] = json.loads(json.dumps(dict(self.extra)))
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DatasetSpec:
        data = dict(data)
        data["dr_params"] = tuple(ParamSpec(**{**p, "shape": tuple(p["shape"])})
                                  for p in data.get("dr_params", ()))
        data["episode_dr_params"] = tuple(
            ParamSpec(**{**p, "shape": tuple(p["shape"])}) for p in data.get("episode_dr_params", ())
        )
        data["state_layout"] = tuple((str(n), int(s)) for n, s in data.get("state_layout", ()))
        return cls(**data)

    def schema_key(self) -> dict[str, Any]:
        """The parts that must match for shards to form one dataset (everything but ``extra``)."""
        out = self.to_json()
        out.pop("extra")
        return out

    def differences(self, other: DatasetSpec) -> list[str]:
        """Names of the schema fields in which ``other`` differs from this spec."""
        mine, theirs = self.schema_key(), other.schema_key()
        return [k for k, v in mine.items() if theirs.get(k) != v]


@dataclass(frozen=True)
class ArraySpec:
    """One per-step array under ``data/``."""

    name: str
    dtype: str
    trailing: tuple[int, ...]
    per_view: bool
    units: str
    description: str

    @property
    def path(self) -> str:
        return f"data/{self.name}"


#: The optional per-step array of frame pairs (datasets.md, §2 ``pair_image``).
PAIR_IMAGE = "pair_image"
#: The per-step arrays of frames: stored as ``image`` is, one frame per step and view.
FRAME_ARRAYS = ("image", PAIR_IMAGE)


def pair_array(spec: DatasetSpec) -> ArraySpec:
    """``data/pair_image``: per step and view, the step before drawn under this step's draw."""
    return ArraySpec(PAIR_IMAGE, "uint8", (spec.views, *spec.image_shape), True, "RGB 0-255",
                     "the step before drawn under view k's DR draw of this step (this step "
                     "itself where is_first): with image, a pair of one scene")


def step_arrays(spec: DatasetSpec, pairs: bool = False) -> tuple[ArraySpec, ...]:
    """Every per-step array of a shard with this spec, in a fixed order; ``pairs``: the
    shard also stores :func:`pair_array`."""
    k = spec.views
    core = (
        ArraySpec("image", "uint8", (k, *spec.image_shape), True, "RGB 0-255",
                  "K domain-randomised renders of the instant of state[t]"),
        *((pair_array(spec),) if pairs else ()),
        ArraySpec("state", "float32", (spec.state_dim,), False, "task units",
                  "privileged state s_t (flattened simulator observation)"),
        ArraySpec("physics", "float64", (spec.physics_dim,), False, "simulator units",
                  "full simulator state at t, restores the exact instant"),
        ArraySpec("action", "float32", (spec.action_dim,), False, "normalised [-1, 1]",
                  "action a_{t-1} that led to this step; zeros where is_first"),
        ArraySpec("reward", "float32", (), False, "task units",
                  "reward received on arriving at this step; 0 where is_first"),
        ArraySpec("discount", "float32", (), False, "1",
                  "0 where the step is terminal, else 1"),
        ArraySpec("is_first", "bool", (), False, "-", "first step of an episode"),
        ArraySpec("is_last", "bool", (), False, "-", "last step of an episode"),
        ArraySpec("is_terminal", "bool", (), False, "-",
                  "episode ended in a true terminal state (not a time limit)"),
    )
    dr = tuple(
        ArraySpec(f"dr/{p.name}", p.dtype, (k, *p.shape), True, "see description", p.description)
        for p in spec.dr_params
    )
    return core + dr


#: Per-episode arrays under ``meta/`` (besides ``meta/dr/<name>``): name -> (dtype, description).
EPISODE_COLUMNS: dict[str, tuple[str, str]] = {
    "episode_ends": ("int64", "exclusive end step of each episode; start is the previous end or 0"),
    "episode_seed": ("int64", "seed of the environment / randomisation for the episode"),
    "episode_policy": ("uint8", "who acted: code from POLICY_CODES"),
    "episode_teacher_step": ("int64", "teacher update count whose weights acted; -1 if none"),
    "episode_env_step": ("int64", "environment frames this collector had taken before the episode"),
    "episode_return": ("float64", "sum of reward over the episode"),
    "episode_time": ("float64", "commit time, seconds since the Unix epoch"),
}


def check_format(attrs: Mapping[str, Any], where: str) -> Mapping[str, Any]:
    """Return the ``twist`` attribute block of a shard, or raise if it is not a readable shard."""
    block = attrs.get(ATTRS_KEY)
    if not isinstance(block, Mapping) or block.get("format") != FORMAT_NAME:
        raise NotADatasetError(f"{where} is not a twist dataset shard (no '{ATTRS_KEY}' metadata)")
    version = block.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
        raise FormatVersionError(
            f"{where} has format_version {version!r}, but this library reads versions up to "
            f"{FORMAT_VERSION}; upgrade twist to read it"
        )
    return block


#: Key of the image record in a shard's ``twist`` block (datasets.md, §2); absent: images stored.
IMAGES_KEY = "images"


@dataclass(frozen=True)
class ImagesRecord:
    """What a shard says of its images: stored, or stripped with a digest of each committed
    episode's frames so that a rebuild can be checked bit for bit (``twist-data strip``)."""

    stored: bool = True
    """Whether ``data/image`` is present."""
    sha256: tuple[str, ...] = ()
    """Per committed episode, :func:`image_digest` of its frames as they were stored."""
    stored_bytes: int = 0
    """Bytes the image array took on disk before it was stripped."""
    stripped_from: str = ""
    """The dataset the stripped shard was copied from."""
    pairs: bool = False
    """Whether the shard stored frame pairs (``data/pair_image``) before it was stripped:
    ``twist-data render --reproduce`` then rebuilds them too."""

    @classmethod
    def from_attrs(cls, block: Mapping[str, Any]) -> ImagesRecord:
        raw = block.get(IMAGES_KEY)
        if raw is None:
            return cls()
        return cls(stored=bool(raw["stored"]), sha256=tuple(raw.get("sha256", ())),
                   stored_bytes=int(raw.get("stored_bytes", 0)),
                   stripped_from=str(raw.get("stripped_from", "")),
                   pairs=bool(raw.get("pairs", False)))

    def to_json(self) -> dict[str, Any]:
        return {"stored": self.stored, "sha256": list(self.sha256),
                "stored_bytes": self.stored_bytes, "stripped_from": self.stripped_from,
                "pairs": self.pairs}


def image_digest(images: np.ndarray) -> str:
    """SHA-256 of one episode's frames, uint8 [T, K, H, W, 3], with their shape: equal digests
    mean bit-identical frames."""
    h = hashlib.sha256(repr(tuple(images.shape)).encode())
    h.update(np.ascontiguousarray(images, np.uint8).tobytes())
    return h.hexdigest()


def stripped_message(path: Any, needed_by: str | None = None) -> str:
    """The one sentence every image reader gives for a stripped dataset at ``path``."""
    who = f"{needed_by} needs images, but " if needed_by else ""
    return (f"{who}dataset {str(path)!r} holds none: it was stripped of them by twist-data "
            f"strip; rebuild them with: twist-data render {path} OUT --reproduce")


@dataclass(frozen=True)
class Episode:
    """One episode in the format's time convention (see ``datasets.md``). T steps."""

    image: np.ndarray
    """[T, K, H, W, 3] uint8."""
    state: np.ndarray
    """[T, S] float32."""
    physics: np.ndarray
    """[T, P] float64."""
    action: np.ndarray
    """[T, A] float32; action[t] is the action that led to step t (zeros at t = 0)."""
    reward: np.ndarray
    """[T] float32; reward received on arriving at step t (0 at t = 0)."""
    discount: np.ndarray
    """[T] float32."""
    is_first: np.ndarray
    """[T] bool."""
    is_last: np.ndarray
    """[T] bool."""
    is_terminal: np.ndarray
    """[T] bool."""
    dr: Mapping[str, np.ndarray] = field(default_factory=dict)
    """Per-step per-view DR parameters, each [T, K, *shape]."""
    pair_image: np.ndarray | None = None
    """[T, K, H, W, 3] uint8: each step's pair frames (:func:`pair_array`), or None where the
    dataset stores none."""

    def __len__(self) -> int:
        return int(self.reward.shape[0])

    def __repr__(self) -> str:
        parts = [f"{k}={v.dtype}{list(v.shape)}" for k, v in self.arrays().items()]
        return f"Episode(T={len(self)}, " + ", ".join(parts) + ")"

    def arrays(self) -> dict[str, np.ndarray]:
        """All per-step arrays keyed by their name under ``data/``."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name != "dr" and getattr(self, f.name) is not None}
        out.update({f"dr/{k}": v for k, v in self.dr.items()})
        return out


@dataclass(frozen=True)
class EpisodeInfo:
    """Provenance of one episode, written into the per-episode table."""

    seed: int
    """Seed of the environment and randomisation for this episode."""
    policy: str = "teacher"
    """Who acted: one of ``POLICY_CODES``."""
    teacher_step: int = -1
    """Teacher update count whose weights acted; -1 when no teacher acted."""
    env_step: int = 0
    """Environment frames this collector had taken before the episode started."""
    dr: Mapping[str, Any] = field(default_factory=dict)
    """Per-episode DR parameters (e.g. friction scale), keyed as ``DatasetSpec.episode_dr_params``."""

    def __post_init__(self) -> None:
        if self.policy not in POLICY_CODES:
            raise InvalidEpisodeError(
                f"unknown policy {self.policy!r}; valid: {', '.join(POLICY_CODES)}"
            )


def episode_problems(episode: Episode, info: EpisodeInfo, spec: DatasetSpec,
                     pairs: bool = False) -> list[str]:
    """Every way ``episode`` breaks the format for ``spec`` (with frame pairs where ``pairs``);
    empty when it is valid."""
    problems: list[str] = []
    arrays = episode.arrays()
    t = len(episode)
    if t < 1:
        return ["episode has no steps"]
    expected = {a.path[len("data/"):]: a for a in step_arrays(spec, pairs)}
    for name in sorted(set(arrays) - set(expected)):
        problems.append(f"array {name!r} is not in the dataset spec")
    for name, a in expected.items():
        if name not in arrays:
            problems.append(f"array {name!r} is missing")
            continue
        value = arrays[name]
        want_shape = (t, *a.trailing)
        if tuple(value.shape) != want_shape:
            problems.append(f"array {name!r} has shape {tuple(value.shape)}, expected {want_shape}")
        if value.dtype != np.dtype(a.dtype):
            problems.append(f"array {name!r} has dtype {value.dtype}, expected {a.dtype}")
        elif value.dtype.kind == "f" and not np.isfinite(value).all():
            bad = ~np.isfinite(value.reshape(len(value), -1)).all(axis=1)
            problems.append(f"array {name!r} contains NaN or inf (first at step "
                            f"{int(np.flatnonzero(bad)[0])} of the episode)")
    if problems:
        return problems
    first = np.flatnonzero(episode.is_first).tolist()
    last = np.flatnonzero(episode.is_last).tolist()
    if first != [0]:
        problems.append(f"is_first must be true exactly at step 0, got steps {first}")
    if last != [t - 1]:
        problems.append(f"is_last must be true exactly at step {t - 1}, got steps {last}")
    if (episode.is_terminal & ~episode.is_last).any():
        problems.append("is_terminal is true at a step that is not is_last")
    if np.any(episode.discount[episode.is_terminal] != 0):
        problems.append("discount must be 0 where is_terminal")
    if np.any(episode.action[0] != 0) or episode.reward[0] != 0:
        problems.append("action and reward at the first step must be 0 (nothing led to it)")
    want_ep = {p.name: p for p in spec.episode_dr_params}
    if set(info.dr) != set(want_ep):
        problems.append(
            f"episode DR parameters {sorted(info.dr)} do not match the spec's {sorted(want_ep)}"
        )
    else:
        for name, p in want_ep.items():
            if np.shape(info.dr[name]) != p.shape:
                problems.append(
                    f"episode DR parameter {name!r} has shape {np.shape(info.dr[name])}, "
                    f"expected {p.shape}"
                )
    return problems
