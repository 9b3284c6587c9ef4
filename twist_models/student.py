"""The TWIST student: a vision world model that maps randomised images into the teacher's
latent space. Only an encoder and an RSSM: it is trained by latent matching, never by
reconstruction or reward prediction, so it needs no decoder or heads."""

from __future__ import annotations

import torch
from torch import nn

from twist_data.errors import ConfigError
from twist_models.config import StudentConfig
from twist_models.perception import build_perception
from twist_models.rssm import RSSM, State

#: The RSSM's transition modules (the GRU's input layer, the GRU, the prior head): what the
#: student can copy whole from the teacher, and what freezing its dynamics keeps fixed.
TRANSITION = ("img_in", "gru", "img_out")


class Student(nn.Module):
    """A perception part (:mod:`twist_models.perception`, chosen by the recipe) and an RSSM
    with the teacher's sizes that filters what it reads."""

    def __init__(self, config: StudentConfig) -> None:
        super().__init__()
        self.config = config
        self.perception = build_perception(config)
        embed_dim = self.perception.out_dim
        self.rssm = RSSM(config.rssm, config.action_dim, embed_dim)
        if not self.perception.trains_filter:  # the teacher's filter (copy_teacher_filter)
            self.rssm.requires_grad_(False)
        # A training target only (the ``dense`` recipe): linear, so that what it reads must be
        # plainly present in the embedding the posterior head reads.
        self.state_head = nn.Linear(embed_dim, config.state_dim) if config.state_dim else None
        self.register_load_state_dict_pre_hook(_rename_former_keys)

    def embed(self, image: torch.Tensor, is_first: torch.Tensor,
              before: torch.Tensor | None = None, pair: torch.Tensor | None = None
              ) -> torch.Tensor:
        """What the posterior reads along windows (:meth:`Perception.window
        <twist_models.perception.Perception.window>`): image uint8 [B, T, H, W, 3], is_first
        [B, T] -> [B, T, E]."""
        return self.perception.window(image, is_first, before, pair)

    def step_embed(self, image: torch.Tensor, history: torch.Tensor | None
                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`embed` one step at a time (:meth:`Perception.step
        <twist_models.perception.Perception.step>`): image uint8 [N, H, W, 3] and the history
        the previous step returned (None at an episode's first step) -> (posterior input,
        next history)."""
        return self.perception.step(image, history)

    def observe(self, image: torch.Tensor, action: torch.Tensor, is_first: torch.Tensor,
                uniform: torch.Tensor | None = None, read: str = "sample",
                pair: torch.Tensor | None = None) -> tuple[State, State]:
        """Filter windows of images: image uint8 [B, T, H, W, 3], action [B, T, A],
        is_first [B, T] (and each step's pair frame [B, T, H, W, 3] where the perception reads
        pairs) -> (posterior, prior) states {k: [B, T, ...]}; ``read`` as in
        :meth:`~twist_models.rssm.RSSM.post_step`."""
        return self.rssm.observe(self.embed(image, is_first, pair=pair), action, is_first,
                                 uniform=uniform, read=read)

    def read_state(self, embed: torch.Tensor) -> torch.Tensor:
        """The state head's read-out: embed [..., E] -> [..., state_dim]."""
        if self.state_head is None:
            raise ConfigError("this student has no state head (StudentConfig.state_dim is 0)")
        return self.state_head(embed)


#: Where a student's perception weights were kept before perception was a part of its own:
#: bundles and checkpoints saved then hold the CNN and the read-out at the top level.
FORMER_PREFIXES = {"encoder.": "perception.encoder.", "readout.": "perception.readout."}


def _rename_former_keys(module: nn.Module, state_dict: dict, prefix: str, *_: object) -> None:
    for key in [k for k in state_dict if k.startswith(prefix)]:
        rest = key[len(prefix):]
        for old, new in FORMER_PREFIXES.items():
            if rest.startswith(old):
                state_dict[prefix + new + rest[len(old):]] = state_dict.pop(key)
                break


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
    if student.perception.readout is None:
        raise ConfigError("only a read-out student (StudentConfig.readout) reads the teacher's "
                          "state embedding")
    if student.rssm.config != teacher.rssm.config:
        raise ConfigError(f"the student's RSSM sizes {student.rssm.config} differ from the "
                          f"teacher's {teacher.rssm.config}; its filter cannot be copied")
    reads, fits = student.perception.readout.encoder.symlog, teacher.encoder.symlog
    if reads != fits:
        raise ConfigError(f"the read-out embeds its reading with symlog={reads}, but the "
                          f"teacher's encoder reads the state with symlog={fits}")
    student.perception.readout.encoder.load_state_dict(teacher.encoder.state_dict())
    student.rssm.load_state_dict(teacher.rssm.state_dict())


def freeze_dynamics(student: Student) -> None:
    """Stop training the student's transition: the GRU, its input layer and the prior head
    (what :func:`copy_teacher_dynamics` copies whole); the encoder and posterior head train."""
    for name in TRANSITION:
        getattr(student.rssm, name).requires_grad_(False)
