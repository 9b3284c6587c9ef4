"""The TWIST student: a vision world model that maps randomised images into the teacher's
latent space. Only an encoder and an RSSM: it is trained by latent matching, never by
reconstruction or reward prediction, so it needs no decoder or heads."""

from __future__ import annotations

import torch
from torch import nn

from twist_data.errors import ConfigError
from twist_models.config import StudentConfig
from twist_models.networks import ImageEncoder
from twist_models.readout import StateReadOut
from twist_models.rssm import RSSM, State

#: The RSSM's transition modules (the GRU's input layer, the GRU, the prior head): what the
#: student can copy whole from the teacher, and what freezing its dynamics keeps fixed.
TRANSITION = ("img_in", "gru", "img_out")


class Student(nn.Module):
    """Image encoder + RSSM with the teacher's sizes; with ``config.readout`` the encoder's
    features are read as the teacher's state, which the teacher's state encoder embeds
    (:mod:`twist_models.readout`)."""

    def __init__(self, config: StudentConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = ImageEncoder(config.cnn)
        self.readout = (StateReadOut(config.readout, self.encoder.out_dim)
                        if config.readout is not None else None)
        embed_dim = (self.readout.out_dim if self.readout is not None
                     else self.encoder.out_dim * config.frames)
        self.rssm = RSSM(config.rssm, config.action_dim, embed_dim)
        if self.readout is not None:  # the teacher's filter (copy_teacher_filter), kept fixed
            self.readout.encoder.requires_grad_(False)
            self.rssm.requires_grad_(False)
        # A training target only (the ``dense`` recipe): linear, so that what it reads must be
        # plainly present in the embedding the posterior head reads.
        self.state_head = nn.Linear(embed_dim, config.state_dim) if config.state_dim else None

    def embed(self, image: torch.Tensor, is_first: torch.Tensor,
              before: torch.Tensor | None = None) -> torch.Tensor:
        """What the posterior reads along windows: image uint8 [B, T, H, W, 3], is_first
        [B, T] -> [B, T, frames * E] (see :func:`stack_frames`), or for a read-out student
        the teacher's embedding of the state read along them [B, T, E'], the first step's
        velocities from the frame ``before`` each window (uint8 [B, H, W, 3]) where given."""
        if self.readout is not None:
            positions = self.read_positions(image)
            previous = None if before is None else self.read_positions(before)
            return self._embed_state(self.readout.window_state(positions, is_first, previous))
        return stack_frames(self.encoder(image), is_first, self.config.frames)

    def step_embed(self, image: torch.Tensor, history: torch.Tensor | None
                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`embed` one step at a time: image uint8 [N, H, W, 3] and the history the
        previous step returned (None at an episode's first step) -> (posterior input, next
        history): the embeddings of earlier frames (:func:`step_frames`), or a read-out
        student's last read-out [N, R]."""
        if self.readout is not None:
            positions = self.read_positions(image)
            previous = positions if history is None else history
            return self._embed_state(self.readout.state(positions, previous)), positions
        return step_frames(self.encoder(image), history, self.config.frames)

    def read_positions(self, image: torch.Tensor) -> torch.Tensor:
        """A read-out student's reading of uint8 images [..., H, W, 3] -> [..., R]: what its
        filter is handed before the velocities are derived."""
        # A background never seen biases one reading and its mirror image's differently: the
        # mean of both errs less (cartpole's held-out scenes: 0.50 -> 0.36 degrees of bias on
        # the pole; docs/findings.md, "Does reading the mirror image too hold the lost
        # scenes?").
        mirrored = (self.encoder(image.flip(-2)) if self.readout.config.mirror else None)
        return self.readout.positions(self.encoder(image), mirrored)

    def _embed_state(self, state: torch.Tensor) -> torch.Tensor:
        # In float32 whatever autocast the CNN ran under: this is the teacher's encoder.
        with torch.autocast(state.device.type, enabled=False):
            return self.readout.encoder(state.float())

    def observe(self, image: torch.Tensor, action: torch.Tensor, is_first: torch.Tensor,
                uniform: torch.Tensor | None = None, read: str = "sample"
                ) -> tuple[State, State]:
        """Filter windows of images: image uint8 [B, T, H, W, 3], action [B, T, A],
        is_first [B, T] -> (posterior, prior) states {k: [B, T, ...]}; ``read`` as in
        :meth:`~twist_models.rssm.RSSM.post_step`."""
        return self.rssm.observe(self.embed(image, is_first), action, is_first,
                                 uniform=uniform, read=read)

    def read_state(self, embed: torch.Tensor) -> torch.Tensor:
        """The state head's read-out: embed [..., frames * E] -> [..., state_dim]."""
        if self.state_head is None:
            raise ConfigError("this student has no state head (StudentConfig.state_dim is 0)")
        return self.state_head(embed)


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


@torch.no_grad()
def copy_teacher_dynamics(student: Student, teacher_rssm: RSSM) -> None:
    """Start the student's RSSM from the teacher's: the GRU and its input layer, the prior
    head, and the posterior head except the columns that read the observation embedding (the
    student's embedding is a CNN's, not the state MLP's, so those stay freshly initialised).

    With the teacher's transition function the student's h and prior already agree with the
    teacher's wherever their z samples do, so Eq. 3 and 4 are left to teach mainly the image ->
    posterior mapping; the copied weights still train."""
    if student.rssm.config != teacher_rssm.config:
        raise ConfigError(f"the student's RSSM sizes {student.rssm.config} differ from the "
                          f"teacher's {teacher_rssm.config}; its dynamics cannot be copied")
    for name in TRANSITION:
        getattr(student.rssm, name).load_state_dict(getattr(teacher_rssm, name).state_dict())
    deter = teacher_rssm.config.deter
    student_in, teacher_in = student.rssm.obs_out[0], teacher_rssm.obs_out[0]
    student_in.weight[:, :deter].copy_(teacher_in.weight[:, :deter])
    student_in.bias.copy_(teacher_in.bias)
    student.rssm.obs_out[2].load_state_dict(teacher_rssm.obs_out[2].state_dict())


@torch.no_grad()
def copy_teacher_filter(student: Student, teacher: nn.Module) -> None:
    """Give a read-out student the teacher's whole filter: its state encoder and its RSSM
    (posterior head included, since the student's posterior reads the same embedding), which
    the student keeps fixed, so that distillation trains only the CNN and its read-out head.
    ``teacher`` is the teacher's world model."""
    if student.readout is None:
        raise ConfigError("only a read-out student (StudentConfig.readout) reads the teacher's "
                          "state embedding")
    if student.rssm.config != teacher.rssm.config:
        raise ConfigError(f"the student's RSSM sizes {student.rssm.config} differ from the "
                          f"teacher's {teacher.rssm.config}; its filter cannot be copied")
    student.readout.encoder.load_state_dict(teacher.encoder.state_dict())
    student.rssm.load_state_dict(teacher.rssm.state_dict())


def freeze_dynamics(student: Student) -> None:
    """Stop training the student's transition: the GRU, its input layer and the prior head
    (what :func:`copy_teacher_dynamics` copies whole); the encoder and posterior head train."""
    for name in TRANSITION:
        getattr(student.rssm, name).requires_grad_(False)
