"""The TWIST teacher: a DreamerV2 agent whose world model sees privileged state.

Library level only: no environment code. The collector feeds :meth:`Teacher.train_step` with
window batches from the matching dataset and acts with :meth:`Teacher.policy`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from twist_data.errors import TwistError
from twist_data.reader import open_dataset
from twist_models.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointMismatchError,
    read_checkpoint,
    restore,
    save_checkpoint,
)
from twist_models.config import TeacherConfig, from_json
from twist_models.dreamer import Dreamer
from twist_models.rssm import State

#: The final teacher's file name in a collector's run folder (what ``twist-distil`` finds).
FINAL_TEACHER = "teacher.pt"
#: The teacher at its best evaluation so far, beside the final one: a short CPU run's
#: evaluations swing by hundreds between neighbouring points (docs/findings.md, "The teacher
#: on states"), so the last teacher is not always the one to distil from.
BEST_TEACHER = "best.pt"


class Teacher(Dreamer):
    """The state teacher: a Dreamer on privileged state that acts in the simulator."""

    config: TeacherConfig

    # inference_mode: ~15% less per-call overhead than no_grad on this batch-1 path.
    @torch.inference_mode()
    def policy(self, state: torch.Tensor, latent: State | None, prev_action: torch.Tensor,
               is_first: torch.Tensor | None, explore: bool = True, read: str = "sample",
               uniform: torch.Tensor | None = None) -> tuple[torch.Tensor, State]:
        """Act on privileged ``state`` [N, S] given the previous latent (None at the start),
        previous action [N, A] and is_first [N] (None: no episode starts at this step).
        Returns (action [N, A] in [-1, 1], latent).

        ``explore`` samples the actor (plus ``explore_noise``); otherwise the actor's mode.
        ``read`` is how z is taken from the posterior (see ``RSSM.post_step``); ``uniform``
        [N, S, 1] its sampling draws (fresh when None).
        """
        rssm = self.world_model.rssm
        if latent is None:
            latent = rssm.initial(state.shape[0], state.device)
        latent = rssm.post_step(latent, prev_action, self.world_model.embed(state), is_first,
                                read=read, uniform=uniform)
        dist = self.actor_critic.actor(rssm.feature(latent))
        if explore:
            action = dist.rsample()
            if self.config.explore_noise:
                action = action + self.config.explore_noise * torch.randn_like(action)
        else:
            action = dist.mode
        return action.clamp(-1.0, 1.0), latent

    def act_on_latent(self, latent: State, explore: bool = False) -> torch.Tensor:
        """The teacher's actor on any model state with the teacher's sizes (e.g. the student's)."""
        dist = self.actor_critic.actor(self.world_model.rssm.feature(latent))
        return (dist.rsample() if explore else dist.mode).clamp(-1.0, 1.0)


def save_teacher(path: str | os.PathLike[str], teacher: Teacher,
                 counters: dict[str, int] | None = None,
                 extra: dict[str, Any] | None = None) -> Path:
    """Checkpoint a teacher with its optimisers, update count and any JSON ``extra``."""
    return save_checkpoint(path, "teacher", teacher, teacher.config, teacher.optimisers(),
                           {"updates": int(teacher.step), **(counters or {})}, extra)


def load_teacher(path: str | os.PathLike[str], state_dim: int | None = None,
                 action_dim: int | None = None) -> tuple[Teacher, Checkpoint]:
    """Rebuild a teacher from its checkpoint; ``state_dim``/``action_dim`` (e.g. a dataset's)
    must match the checkpoint's, else the error names both values."""
    checkpoint = read_checkpoint(path, kind="teacher")
    return teacher_from_checkpoint(checkpoint, state_dim, action_dim, str(path)), checkpoint


def teacher_from_checkpoint(checkpoint: Checkpoint, state_dim: int | None = None,
                            action_dim: int | None = None, source: str = "") -> Teacher:
    """:func:`load_teacher` for a checkpoint already read (``source`` names it in errors)."""
    config = from_json(TeacherConfig, checkpoint.config)
    wm = config.world_model
    for name, wanted in (("state_dim", state_dim), ("action_dim", action_dim)):
        have = getattr(wm, name)
        if wanted is not None and wanted != have:
            raise CheckpointMismatchError(f"teacher checkpoint {source!r} has {name} {have}, "
                                          f"but the data has {name} {wanted}")
    teacher = Teacher(config)
    restore(checkpoint, teacher, config)
    teacher.restore_optimisers(checkpoint.optimisers)
    return teacher


def find_teacher(out: str | os.PathLike[str]) -> Path:
    """The final teacher of the collector run in ``out`` (the one ``twist-distil`` uses by
    default), or, for a D re-rendered from another (``twist-data render``), that one's; an
    error lists the candidates when there are several or none."""
    found = sorted((Path(out) / "collect").glob(f"*/{FINAL_TEACHER}"))
    source = None if found else _rendered_from(Path(out))  # D opened only when it holds none
    if source is not None:
        return find_teacher(source)
    if len(found) != 1:
        have = ", ".join(str(p) for p in found) or "none"
        raise CheckpointError(f"expected one final teacher under "
                              f"{str(Path(out) / 'collect')!r}, found {have}; name one "
                              "explicitly")
    read_checkpoint(found[0], kind="teacher")
    return found[0]


def _rendered_from(dataset: Path) -> Path | None:
    """The folder ``dataset`` was re-rendered from, where it records one that still holds a
    dataset: as recorded (relative to the working folder then) or beside ``dataset``."""
    try:
        recorded = open_dataset(dataset).spec.extra.get("rerendered_from")
    except TwistError:
        return None
    if not recorded:
        return None
    for candidate in (Path(recorded), dataset.parent / Path(recorded).name):
        if candidate.resolve() != dataset.resolve() and (candidate / "collect").is_dir():
            return candidate
    return None
