"""The read-out student's perception: the teacher's state read from images (not in the paper).

The teacher's filter, given the exact state, is what the student tries to imitate from
images. This module lets the student hand that filter a state instead of an image embedding:

* a linear head on the CNN reads the components a single frame shows (positions, and the
  (cos, sin) of angles), trained per frame against D's states on D's typical frames (every
  read component within ``typical_spreads`` of its median), each error in units of its
  *robust* spread over D (median and MAD), so that the near-upright lean a balancing teacher
  keeps, which fills most of D, sets the scale rather than the rare fallen poles;
* each velocity is a gain times the difference of two successive read-outs (an angle's
  difference wrapped to (-pi, pi]); which component is the rate of which, and the gain, are
  measured on D by :func:`pair_velocities`, so no task needs a hand-written table;
* a velocity that is the rate of nothing one frame shows (a root a camera tracks, whose
  position no state holds) is read by a second head from a second CNN's features of a pair
  of frames of one scene stacked as six channels: the step before and the step (D's
  ``pair_image``; acting: the episode's previous frame), in units of its robust spread, as
  the positions. Stacked, so that the first layer compares the two frames pixel by pixel:
  two frames encoded apart show a displacement only through positions no state holds
  (docs/design.md, "Velocities no frame shows");
* the teacher's own state encoder (copied, fixed) embeds the result for the teacher's
  posterior.

Why: the measured alternative, velocities learned from two stacked frames, was no better than
predicting their mean, and the filter balanced on nothing but the velocity
(docs/findings.md, "A student that reads the state").
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from twist_data.errors import ConfigError
from twist_models.config import MLPConfig, ReadOutConfig
from twist_models.losses import readout_loss
from twist_models.networks import StateEncoder

log = logging.getLogger(__name__)

#: The default least correlation of a velocity with the difference it is derived from
#: (``ReadOutStage.min_pairing``, which gives the measurements).
MIN_PAIRING = 0.7
#: A (cos, sin) pair lies on the unit circle when c^2 + s^2 is this close to 1 on average.
UNIT_CIRCLE = 1e-3
#: MAD of a normal variable over its standard deviation: turns the MAD into a spread.
MAD_TO_STD = 1.4826
#: The least spread a read component is standardised by (a component D never varies).
MIN_SCALE = 1e-3
#: How far, relative to its largest magnitude over D (at least 1), a component may move
#: within an episode and still count as constant there: float32 rounding, not motion.
CONSTANT_TOLERANCE = 1e-6


def episode_constants(states: np.ndarray, is_first: np.ndarray, candidates: Sequence[int]
                      ) -> tuple[int, ...]:
    """Which of the state components ``candidates`` no episode of ``states`` [N, S] changes
    (``is_first`` [N] marks each episode's first step; row 0 starts one)."""
    starts = np.flatnonzero(is_first)
    if len(starts) == 0 or starts[0] != 0:
        raise ConfigError("the steps measured for constant components must start an episode")
    span = np.maximum.reduceat(states, starts, 0) - np.minimum.reduceat(states, starts, 0)
    tolerance = CONSTANT_TOLERANCE * np.maximum(1.0, np.abs(states).max(0))
    return tuple(i for i in candidates if bool((span[:, i] <= tolerance[i]).all()))


def unit_circle_pairs(states: np.ndarray, read: list[int]) -> list[tuple[int, int]]:
    """Adjacent components of ``read`` whose squares sum to 1 on every row of ``states``
    [N, S]: a (cos, sin) pair, as dm_control lays out an angle."""
    pairs: list[tuple[int, int]] = []
    for a, b in itertools.pairwise(read):
        radius = float(np.abs(states[:, a] ** 2 + states[:, b] ** 2 - 1).mean())
        if b == a + 1 and radius < UNIT_CIRCLE and (not pairs or a not in pairs[-1]):
            pairs.append((a, b))
    return pairs


def wrapped(angle: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """An angle difference wrapped to [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def pair_velocities(states: np.ndarray, is_first: np.ndarray,
                    layout: tuple[tuple[str, int], ...], encoder: MLPConfig,
                    task: str = "this task", hidden: tuple[int, ...] = (),
                    min_pairing: float = MIN_PAIRING) -> ReadOutConfig:
    """Measure on D which read component each velocity is the rate of.

    ``states`` [N, S] and ``is_first`` [N] are consecutive steps of D's training episodes;
    ``layout`` is D's state layout: components of blocks named ``velocity`` are derived, the
    rest read, except the ``hidden`` ones, which the teacher never reads (its
    ``state_hidden``) and the student need not either. Each velocity is paired with the
    difference (over successive steps of one episode) of a read component, or of a
    unit-circle pair's angle, that correlates best with it, where that reaches
    ``min_pairing`` (``ReadOutStage.min_pairing``); its gain is the least-squares factor. A
    velocity that pairs with nothing (a tracked root's speed: its position is in no state) is
    ``moving``, read from a pair of frames of one scene."""
    if not layout:
        raise ConfigError(f"the dataset of {task} declares no state layout; the readout recipe "
                          "needs to know which state components are velocities")
    names = [name for name, size in layout for _ in range(size)]
    derived = [i for i, name in enumerate(names) if name == "velocity" and i not in hidden]
    read = [i for i, name in enumerate(names) if name != "velocity" and i not in hidden]
    if not read:
        raise ConfigError(f"the state layout of {task} ({list(layout)}) leaves the readout "
                          f"recipe nothing to read from an image (hidden: {sorted(hidden)})")
    states = states.astype(np.float64)
    angles = unit_circle_pairs(states, read)
    in_pairs = {i for pair in angles for i in pair}
    step = ~is_first[1:]
    change = np.diff(states, axis=0)[step]
    candidates = {(i,): change[:, i] for i in read if i not in in_pairs}
    for c, s in angles:
        candidates[(c, s)] = wrapped(np.diff(np.arctan2(states[:, s], states[:, c]))[step])
    velocities, gains, moving, pairing = [], [], [], []
    for v in derived:
        target = states[1:, v][step]
        scores = {k: abs(_correlation(d, target)) for k, d in candidates.items()}
        best = max(scores, key=scores.__getitem__, default=None)
        if best is None or scores[best] < min_pairing:
            score = scores[best] if best is not None else 0.0
            log.info("velocity component %d of %s is read from frame pairs (best correlation "
                     "%.2f with a read component's change, needs %s)", v, task, score,
                     min_pairing)
            moving.append(v)
            pairing.append(score)
            continue
        taken = {tuple(pair[1:]): pair[0] for pair in velocities}
        if best in taken:
            raise ConfigError(f"velocity components {taken[best]} and {v} of {task} pair "
                              f"with the same component(s) {list(best)}")
        difference = candidates[best]
        gains.append(float(difference @ target / max(difference @ difference, 1e-12)))
        velocities.append((v, *best))
    return ReadOutConfig(state_dim=states.shape[1], read=tuple(read), angles=tuple(angles),
                         velocities=tuple(velocities), gains=tuple(gains), encoder=encoder,
                         hidden=tuple(sorted(hidden)), moving=tuple(moving),
                         moving_pairing=tuple(round(p, 4) for p in pairing))


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    if a.std() == 0 or b.std() == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def motion_standardisation(states: np.ndarray, config: ReadOutConfig
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Centre (median) and spread (MAD x 1.4826) of each moving velocity over ``states``
    [N, S] -> (mean [M], scale [M])."""
    moving = states[:, list(config.moving)].astype(np.float64)
    centre = np.median(moving, 0)
    scale = np.maximum(MAD_TO_STD * np.median(np.abs(moving - centre), 0), MIN_SCALE)
    return centre.astype(np.float32), scale.astype(np.float32)


def robust_standardisation(states: np.ndarray, config: ReadOutConfig
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Centre (median) and spread (MAD x 1.4826) of each read component over ``states``
    [N, S] -> (mean [R], scale [R]); both members of an angle pair take the larger spread,
    so its direction is read evenly (near upright the cosine barely moves)."""
    read = states[:, list(config.read)].astype(np.float64)
    centre = np.median(read, 0)
    scale = np.maximum(MAD_TO_STD * np.median(np.abs(read - centre), 0), MIN_SCALE)
    position = {i: k for k, i in enumerate(config.read)}
    for c, s in config.angles:
        scale[[position[c], position[s]]] = scale[[position[c], position[s]]].max()
    return centre.astype(np.float32), scale.astype(np.float32)


def typical(states: np.ndarray, config: ReadOutConfig, centre: np.ndarray,
            scale: np.ndarray, spreads: float) -> np.ndarray:
    """Which rows of ``states`` [N, S] have every read component within ``spreads`` robust
    spreads (``scale`` [R]) of its median (``centre`` [R]): bool [N]."""
    read = states[:, list(config.read)]
    return (np.abs(read - centre) <= spreads * scale).all(1)


def training_frames(typical_rows: np.ndarray, mode: str, max_atypical_share: float
                    ) -> np.ndarray:
    """Which frames the read-out's first stage trains on, given which are typical
    (bool [N]): ``typical``, ``all``, or ``auto``: the typical ones unless more than
    ``max_atypical_share`` of them are not -> bool [N]."""
    if mode == "typical" or (mode == "auto"
                             and 1.0 - typical_rows.mean() <= max_atypical_share):
        return typical_rows
    return np.ones_like(typical_rows, dtype=bool)


class StateReadOut(nn.Module):
    """CNN features -> the teacher's state -> the teacher's state embedding."""

    def __init__(self, config: ReadOutConfig, features: int, motion_features: int = 0) -> None:
        super().__init__()
        self.config = config
        self.head = nn.Linear(features, len(config.read))
        self.register_buffer("mean", torch.zeros(len(config.read)))
        self.register_buffer("scale", torch.ones(len(config.read)))
        self.register_buffer("gains", torch.tensor(config.gains, dtype=torch.float32))
        # From the config, so not saved: bundles written before mirroring existed still load.
        self.register_buffer("mirror", torch.tensor(config.mirror, dtype=torch.float32),
                             persistent=False)
        # What the loss multiplies each robust-spread error by (:meth:`weigh_by_teacher`);
        # measured again by every run that trains, so not saved.
        self.register_buffer("loss_weight", torch.ones(len(config.read)), persistent=False)
        self.encoder = StateEncoder(config.state_dim, config.encoder, config.symlog)
        self.out_dim = self.encoder.out_dim
        position = {i: k for k, i in enumerate(config.read)}
        #: Each (cos, sin) pair's slots in the read vector.
        self.angle_slots = [(position[c], position[s]) for c, s in config.angles]
        self._linear = [(k, position[v[1]]) for k, v in enumerate(config.velocities)
                        if len(v) == 2]
        self._angular = [(k, position[v[1]], position[v[2]])
                         for k, v in enumerate(config.velocities) if len(v) == 3]
        #: The slots of ``config.pooled`` in the read vector.
        self.pooled_slots = [position[i] for i in config.pooled]
        moving = len(config.moving)
        if moving and motion_features < 1:
            raise ConfigError(f"velocity components {list(config.moving)} are read from frame "
                              "pairs: the read-out needs the width of a pair's features")
        #: Reads the ``config.moving`` velocities from a frame pair's features (None: none).
        self.motion = nn.Linear(motion_features, moving) if moving else None
        # Saved only where there are any: bundles written before they existed still load.
        self.register_buffer("motion_mean", torch.zeros(moving), persistent=bool(moving))
        self.register_buffer("motion_scale", torch.ones(moving), persistent=bool(moving))
        self.register_buffer("motion_weight", torch.ones(moving), persistent=False)

    def loss(self, features: torch.Tensor, state: torch.Tensor, delta: float,
             motion_features: torch.Tensor | None = None) -> torch.Tensor:
        """The first stage's term: CNN features [..., F] and the true state [..., S] -> []:
        the Huber loss of :meth:`errors` times ``loss_weight`` (and, with each frame's pair's
        features [..., F'], of :meth:`motion_errors` times ``motion_weight``), quadratic to
        ``delta`` units (robust spreads unless :meth:`weigh_by_teacher` set other units;
        :func:`~twist_models.losses.readout_loss`)."""
        errors = self.errors(self.read(features), state) * self.loss_weight
        if self.motion is not None:
            motion = self.motion_errors(self.read_motion(self._given(motion_features)), state)
            errors = torch.cat([errors, motion * self.motion_weight], -1)
        return readout_loss(errors, delta)

    def _given(self, value: torch.Tensor | None) -> torch.Tensor:
        if value is None:
            raise ConfigError(f"velocity components {list(self.config.moving)} are read from "
                              "frame pairs, and none was given")
        return value

    def read_motion(self, motion_features: torch.Tensor) -> torch.Tensor:
        """The ``config.moving`` velocities in the state's units, from the features of a
        frame pair of one scene [..., F'] -> [..., M]."""
        if self.motion is None:
            return motion_features.new_zeros(*motion_features.shape[:-1], 0)
        return self.motion(motion_features).float() * self.motion_scale + self.motion_mean

    def motion_errors(self, motion: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """:meth:`read_motion`'s errors in units of D's robust spread: [..., M], the true state
        [..., S] -> [..., M]."""
        return (motion - state[..., list(self.config.moving)]) / self.motion_scale

    @torch.no_grad()
    def teacher_units(self, states: torch.Tensor) -> torch.Tensor:
        """Each read component's error that moves the teacher's state embedding by one unit
        (root mean square over ``states`` [N, S], the teacher's own encoder) -> [R], in the
        units of :meth:`errors`' slots times ``scale`` (a position's, an angle's radians, a
        (cos, sin) pair's length). A component's velocity is derived from it by a gain g,
        and an error independent between steps enters that difference twice, so its share
        is 2 g^2 times the velocity's sensitivity."""
        jacobian = torch.func.vmap(torch.func.jacrev(self.encoder))(states.float())  # [N, E, S]
        # Per sample, the embedding's change per unit of each slot's error: [N, E, R].
        along = jacobian[..., list(self.config.read)].clone()
        for c, s in self.angle_slots:
            cos, sin = states[:, self.config.read[c], None], states[:, self.config.read[s], None]
            d_cos, d_sin = jacobian[..., self.config.read[c]], jacobian[..., self.config.read[s]]
            along[..., s] = -sin * d_cos + cos * d_sin  # turning the angle
            along[..., c] = cos * d_cos + sin * d_sin  # lengthening the pair
        sensitivity = along.pow(2).sum(1).mean(0)
        # Each velocity's slot: a linear rate's position, an angle's sine.
        for k, slot in [*self._linear, *((k, s) for k, _, s in self._angular)]:
            velocity = jacobian[..., self.config.velocities[k][0]]
            sensitivity[slot] += 2 * self.gains[k] ** 2 * velocity.pow(2).sum(1).mean()
        return sensitivity.clamp_min(1e-12).rsqrt()

    @torch.no_grad()
    def weigh_by_teacher(self, states: torch.Tensor) -> None:
        """Measure the loss's errors in :meth:`teacher_units` over ``states`` [N, S] instead
        of D's robust spreads, so that the CNN is spent on what moves the teacher's filter:
        a robust spread can be millimetres for a component the filter hardly reads (a pushed
        block's height), which the squared error then outweighs every other with. A moving
        velocity's unit is the error that moves the embedding by one unit."""
        self.loss_weight.copy_(self.scale / self.teacher_units(states))
        if self.motion is not None:
            jacobian = torch.func.vmap(torch.func.jacrev(self.encoder))(states.float())
            moved = jacobian[..., list(self.config.moving)].pow(2).sum(1).mean(0)
            self.motion_weight.copy_(self.motion_scale * moved.clamp_min(1e-12).sqrt())

    def read(self, features: torch.Tensor) -> torch.Tensor:
        """The read components in the state's units, as the head gives them: [..., F] ->
        [..., R]."""
        return self.head(features).float() * self.scale + self.mean

    def errors(self, read: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Read-out errors in units of D's robust spread: read [..., R] (as :meth:`read`
        gives it), the true state [..., S] -> [..., R]. A (cos, sin) pair's slots hold the
        error of its angle (the sine's slot, wrapped) and of its length against 1 (the
        cosine's): near upright the cosine carries no first-order information, so asking for
        it component by component spends the CNN on what the filter does not need."""
        truth = state[..., list(self.config.read)]
        errors = read - truth
        if not self.angle_slots:
            return errors / self.scale
        parts = list(errors.unbind(-1))
        for c, s in self.angle_slots:
            parts[s] = wrapped(torch.atan2(read[..., s], read[..., c])
                               - torch.atan2(truth[..., s], truth[..., c]))
            parts[c] = torch.sqrt(read[..., c] ** 2 + read[..., s] ** 2) - 1.0
        return torch.stack(parts, -1) / self.scale

    @torch.no_grad()
    def error(self, features: torch.Tensor, state: torch.Tensor,
              within: float | None = None, motion_features: torch.Tensor | None = None
              ) -> float:
        """RMS of :meth:`errors` over steps and components: features [..., F], state
        [..., S] -> a float; with the frame pairs' features [..., F'], of
        :meth:`motion_errors` too. With ``within``, only over the steps whose every read
        component lies within that many robust spreads of D's median, as :func:`typical`
        picks the frames the first stage trains on (NaN where none does): a fallen pole's
        frames, read tens of spreads off by design, would otherwise outweigh every other
        frame's error."""
        errors = self.errors(self.read(features), state)
        if self.motion is not None and motion_features is not None:
            errors = torch.cat([errors, self.motion_errors(self.read_motion(motion_features),
                                                           state)], -1)
        if within is not None:
            read = state[..., list(self.config.read)]
            errors = errors[((read - self.mean).abs() <= within * self.scale).all(-1)]
        return float(errors.pow(2).mean().sqrt()) if errors.numel() else float("nan")

    def positions(self, features: torch.Tensor, mirrored: torch.Tensor | None = None
                  ) -> torch.Tensor:
        """What the filter is handed: the read components, a (cos, sin) pair put on the
        unit circle (trained for its angle, :meth:`errors`) and leaned by ``config.lean``:
        [..., F] -> [..., R]. With the features of the mirrored image (``mirrored``
        [..., F]), the mean of both readings, the mirror's mirrored back
        (``config.mirror``)."""
        read = self.read(features)
        if mirrored is not None:
            read = (read + self.mirror * self.read(mirrored)) / 2
        if not self.angle_slots:
            return read
        parts = list(read.unbind(-1))
        for c, s in self.angle_slots:
            norm = torch.sqrt(parts[c] ** 2 + parts[s] ** 2).clamp_min(1e-6)
            parts[c], parts[s] = parts[c] / norm, parts[s] / norm
            if self.config.lean != 1.0:
                parts[c], parts[s] = self._leaned(parts[c], parts[s], c, s)
        return torch.stack(parts, -1)

    def _leaned(self, cos: torch.Tensor, sin: torch.Tensor, c: int, s: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
        # A squared-error read-out shrinks a lean it sees faintly towards the upright D is full
        # of, and the teacher's actor loses the pole far sooner when the lean it is handed is
        # too small than when too large. So the reading is handed on
        # `lean` times further from D's median angle: d + (lean - 1) sin d has slope `lean`
        # at d = 0, is monotone for lean < 2 and leaves a fallen pole (d = pi) where it is
        # (research/findings-full.md, "Does reading the lean larger hold the lost scenes?"). An
        # angle the mirror turns over leans about 0, so a mirror-symmetric reading stays so.
        mirrored = bool(self.config.mirror) and self.config.mirror[s] < 0
        centre = self.mean.new_zeros(()) if mirrored else torch.atan2(self.mean[s], self.mean[c])
        offset = wrapped(torch.atan2(sin, cos) - centre)
        angle = centre + offset + (self.config.lean - 1.0) * torch.sin(offset)
        return torch.cos(angle), torch.sin(angle)

    def state(self, positions: torch.Tensor, previous: torch.Tensor,
              motion: torch.Tensor | None = None) -> torch.Tensor:
        """The full state from this step's read-out and the last one's (the same tensor at an
        episode's first step: velocities 0), and the moving velocities read from the step's
        frame pair (:meth:`read_motion`; required where ``config.moving`` names any):
        [..., R], [..., R], [..., M] -> [..., S]."""
        rates = []
        for k, i in self._linear:
            rates.append((k, self.gains[k] * (positions[..., i] - previous[..., i])))
        for k, c, s in self._angular:
            turned = wrapped(torch.atan2(positions[..., s], positions[..., c])
                             - torch.atan2(previous[..., s], previous[..., c]))
            rates.append((k, self.gains[k] * turned))
        state = positions.new_zeros(*positions.shape[:-1], self.config.state_dim)
        state[..., list(self.config.read)] = positions
        for k, rate in rates:
            state[..., self.config.velocities[k][0]] = rate
        if self.motion is not None:
            state[..., list(self.config.moving)] = self._given(motion).to(state.dtype)
        return state

    def pool_step(self, reading: torch.Tensor, history: torch.Tensor | None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One acting step's reading [N, R] and the history the last step returned (None at
        an episode's start) -> (the positions handed on [N, R], the last step's [N, R], the
        next history). Each ``config.pooled`` slot is handed on as the mean of its readings
        over the episode so far; the history is the handed positions, followed by the count
        of frames read where any slot is pooled ([N, R + 1], then in float32 whatever autocast
        read it: bfloat16 counts no further than 256)."""
        previous = reading if history is None else history[..., :reading.shape[-1]]
        if not self.pooled_slots:
            return reading, previous, reading
        reading, previous = reading.float(), previous.float()
        slots, positions = self.pooled_slots, reading.clone()
        if history is None:
            count = reading.new_ones(*reading.shape[:-1], 1)
        else:
            count = history[..., -1:] + 1
            positions[..., slots] = (previous[..., slots]
                                     + (reading[..., slots] - previous[..., slots]) / count)
        return positions, previous, torch.cat([positions, count], -1)

    def pool_window(self, reading: torch.Tensor, is_first: torch.Tensor) -> torch.Tensor:
        """:meth:`pool_step` along windows: reading [B, T, R], is_first [B, T] -> the positions
        handed on [B, T, R]. A window's pool starts at its first step, or at an episode's
        first step within it: what a window mid-episode shows of the frames before is not
        read."""
        if not self.pooled_slots:
            return reading
        reading = reading.float()
        pooled = reading[..., self.pooled_slots]
        mean, count = pooled[:, 0], torch.ones_like(pooled[:, 0])
        means = [mean]
        for t in range(1, reading.shape[1]):
            first = is_first[:, t, None].bool()
            count = torch.where(first, torch.ones_like(count), count + 1)
            mean = torch.where(first, pooled[:, t], mean + (pooled[:, t] - mean) / count)
            means.append(mean)
        positions = reading.clone()
        positions[..., self.pooled_slots] = torch.stack(means, 1)
        return positions

    def window_state(self, positions: torch.Tensor, is_first: torch.Tensor,
                     before: torch.Tensor | None = None, motion: torch.Tensor | None = None
                     ) -> torch.Tensor:
        """:meth:`state` along windows: positions [B, T, R], is_first [B, T] (and the moving
        velocities [B, T, M]) -> [B, T, S]. A window's first step takes its velocities from
        the read-out of the step ``before`` it ([B, R]), or without one has none: velocities
        0, as at an episode's first step."""
        first = positions[:, :1] if before is None else before[:, None]
        shifted = torch.cat([first, positions[:, :-1]], 1)
        previous = torch.where(is_first.bool()[..., None], positions, shifted)
        return self.state(positions, previous, motion)

    @torch.no_grad()
    def set_standardisation(self, mean: np.ndarray, scale: np.ndarray,
                            motion: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Centre and spread of the read components [R] and, where any are moving, of the
        moving velocities (``motion``: [M], [M]; :func:`robust_standardisation`)."""
        self.mean.copy_(torch.as_tensor(mean))
        self.scale.copy_(torch.as_tensor(scale))
        if motion is not None:
            self.motion_mean.copy_(torch.as_tensor(motion[0]))
            self.motion_scale.copy_(torch.as_tensor(motion[1]))

