"""A student's perception: what its posterior reads of an image, the part a recipe chooses.

Every part holds the student's CNN (``encoder``) behind one interface, along windows
(:meth:`Perception.window`) and one step at a time (:meth:`Perception.step`), so that
:class:`~twist_models.student.Student` never branches on the recipe; a new way of seeing is a
new part here, picked by :func:`build_perception` from the student's config:

* :class:`FrameEmbedding` (the ``paper`` and ``dense`` recipes): the CNN's embedding of the
  image, with those of the ``frames - 1`` images before it stacked;
* :class:`StateReading` (the ``readout`` recipe): the CNN's features read as the teacher's
  state, velocities derived from successive readings or read from a pair of frames of one
  scene, embedded by the teacher's own state encoder (:mod:`twist_models.readout`).
"""

from __future__ import annotations

import torch
from torch import nn

from twist_data.errors import ConfigError
from twist_models.config import StudentConfig
from twist_models.networks import ImageEncoder, preprocess_image
from twist_models.readout import StateReadOut


class Perception(nn.Module):
    """Images -> what the student's posterior reads.

    ``encoder`` is the CNN every part trains; ``out_dim`` the width of what the posterior
    reads; ``readout`` the state read-out a part hands the posterior through, where it has
    one; ``trains_filter`` whether the student's RSSM trains behind this part (False: it is
    the teacher's filter, copied and kept fixed)."""

    encoder: ImageEncoder
    out_dim: int
    readout: StateReadOut | None
    trains_filter: bool = True

    def __init__(self) -> None:
        super().__init__()
        self.readout = None

    def window(self, image: torch.Tensor, is_first: torch.Tensor,
               before: torch.Tensor | None = None, pair: torch.Tensor | None = None
               ) -> torch.Tensor:
        """Along windows: image uint8 [B, T, H, W, 3], is_first [B, T], and where the part
        uses them the frame ``before`` each window (uint8 [B, H, W, 3]) and each step's pair
        frame (D's ``pair_image``, uint8 [B, T, H, W, 3]) -> [B, T, out_dim]."""
        raise NotImplementedError

    def step(self, image: torch.Tensor, history: torch.Tensor | None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`window` one step at a time: image uint8 [N, H, W, 3] and the history the
        previous step returned (None at an episode's first step) -> (posterior input
        [N, out_dim], next history)."""
        raise NotImplementedError


class FrameEmbedding(Perception):
    """The CNN's embedding of each image, with the ``frames - 1`` before it stacked
    (:func:`stack_frames`); one frame is the paper's student."""

    def __init__(self, config: StudentConfig) -> None:
        super().__init__()
        self.encoder = ImageEncoder(config.cnn)
        self.frames = config.frames
        self.out_dim = self.encoder.out_dim * config.frames

    def window(self, image: torch.Tensor, is_first: torch.Tensor,
               before: torch.Tensor | None = None, pair: torch.Tensor | None = None
               ) -> torch.Tensor:
        return stack_frames(self.encoder(image), is_first, self.frames)

    def step(self, image: torch.Tensor, history: torch.Tensor | None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
        return step_frames(self.encoder(image), history, self.frames)


class StateReading(Perception):
    """The CNN's features read as the teacher's state and embedded by the teacher's own state
    encoder: the history is the last step's reading, whose difference gives the velocities
    (and the frames read so far where it pools a component, ``ReadOutConfig.pooled``), then
    where any velocity is moving (``ReadOutConfig.moving``) the last frame, with which this
    one makes the pair a second CNN (``motion_encoder``) reads them from: acting holds one
    scene per episode, so the frame before is the step before in the same scene."""

    trains_filter = False

    def __init__(self, config: StudentConfig) -> None:
        super().__init__()
        if config.readout is None:
            raise ConfigError("a state-reading student needs StudentConfig.readout")
        self.encoder = ImageEncoder(config.cnn)
        #: Reads a frame pair stacked as six channels (None: no velocity is moving).
        self.motion_encoder = (ImageEncoder(config.cnn, channels=6) if config.readout.moving
                               else None)
        self.readout = StateReadOut(config.readout, self.encoder.out_dim,
                                    0 if self.motion_encoder is None
                                    else self.motion_encoder.out_dim)
        self.readout.encoder.requires_grad_(False)  # the teacher's (copy_teacher_filter)
        self.out_dim = self.readout.out_dim

    def window(self, image: torch.Tensor, is_first: torch.Tensor,
               before: torch.Tensor | None = None, pair: torch.Tensor | None = None
               ) -> torch.Tensor:
        features = self.encoder(image)
        positions = self.readout.pool_window(self.read_positions(image, features), is_first)
        previous = None if before is None else self.read_positions(before)
        motion = None
        if self.motion_encoder is not None:
            if pair is None:
                raise ConfigError(f"velocity components {list(self.readout.config.moving)} "
                                  "are read from frame pairs: windows need their pair_image")
            motion = self.readout.read_motion(self.motion_features(pair, image))
        return self.embed_state(self.readout.window_state(positions, is_first, previous,
                                                          motion))

    def step(self, image: torch.Tensor, history: torch.Tensor | None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
        features = self.encoder(image)
        reading = self.read_positions(image, features)
        width = reading.shape[-1] + (1 if self.readout.pooled_slots else 0)
        positions, previous, after = self.readout.pool_step(
            reading, None if history is None else history[..., :width])
        motion = None
        if self.motion_encoder is not None:  # at an episode's start the frame is its own pair
            frame = preprocess_image(image)
            before = frame if history is None else history[..., width:].reshape(frame.shape)
            motion = self.readout.read_motion(self.motion_features(before, frame))
            after = torch.cat([after.float(), frame.flatten(1).float()], -1)
        return self.embed_state(self.readout.state(positions, previous, motion)), after

    def motion_features(self, pair: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """The motion CNN's features of frame pairs: the frame before (uint8, or float as
        :func:`~twist_models.networks.preprocess_image` gives it) [..., H, W, 3] and the frame
        [..., H, W, 3] -> [..., F']."""
        return self.motion_encoder(torch.cat([preprocess_image(pair).to(torch.float32),
                                              preprocess_image(image).to(torch.float32)], -1))

    def read_positions(self, image: torch.Tensor, features: torch.Tensor | None = None
                       ) -> torch.Tensor:
        """The reading of uint8 images [..., H, W, 3] (whose CNN ``features`` [..., F] may be
        at hand) -> [..., R]: what the filter is handed before the velocities are derived."""
        # A background never seen biases one reading and its mirror image's differently: the
        # mean of both errs less (research/findings-full.md, "Does reading the mirror image too hold
        # the lost scenes?").
        mirrored = self.encoder(image.flip(-2)) if self.readout.config.mirror else None
        return self.readout.positions(self.encoder(image) if features is None else features,
                                      mirrored)

    def embed_state(self, state: torch.Tensor) -> torch.Tensor:
        # In float32 whatever autocast the CNN ran under: this is the teacher's encoder.
        with torch.autocast(state.device.type, enabled=False):
            return self.readout.encoder(state.float())


def build_perception(config: StudentConfig) -> Perception:
    """The part a student's config asks for: a read state where ``config.readout`` is set,
    else the CNN's (stacked) embedding."""
    return StateReading(config) if config.readout is not None else FrameEmbedding(config)


def stack_frames(embed: torch.Tensor, is_first: torch.Tensor, frames: int) -> torch.Tensor:
    """What the posterior reads along windows: embed [B, T, E], is_first [B, T] ->
    [B, T, frames * E], each step's embedding followed by those of the ``frames - 1`` steps
    before it, most recent first. Before an episode's (or a window's) first step that step's
    embedding repeats, so the start reads as a scene at rest.

    Why more than one frame: the teacher's posterior reads the full state, velocities
    included, so its recurrence never had to infer them; from one image a velocity can only
    come from h, and an error there is never corrected by what the student sees."""
    if frames == 1:
        return embed
    stacked, previous, first = [embed], embed, is_first.bool()[..., None]
    for _ in range(frames - 1):
        shifted = torch.cat([previous[:, :1], previous[:, :-1]], 1)
        previous = torch.where(first, previous, shifted)
        stacked.append(previous)
    return torch.cat(stacked, -1)


def step_frames(embed: torch.Tensor, history: torch.Tensor | None, frames: int
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`stack_frames` one step at a time: embed [N, E] and the history the previous
    step returned ([N, frames - 1, E], None at an episode's first step) -> (posterior input
    [N, frames * E], next history; None for one frame, which keeps none)."""
    if frames == 1:  # the paper's student: nothing to stack on this per-step path
        return embed, None
    if history is None:
        history = embed[:, None].expand(-1, frames - 1, -1)
    stacked = torch.cat([embed, history.flatten(1)], -1)
    return stacked, torch.cat([embed[:, None], history], 1)[:, :frames - 1]
