"""The ``readout`` recipe's set-up on a D: what its student reads and derives (measured on D's
training steps), the mirror it reads through, its first weights (the teacher's own filter and
the read-out's standardisation), the units its loss counts errors in, and which of D's frames
its first stage trains on. :mod:`twist_pipeline.distil` calls these; the student's own parts
are in :mod:`twist_models.readout`."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from twist_data.errors import ConfigError
from twist_data.reader import MatchingDataset
from twist_data.sampler import heldout_episodes
from twist_data.seeding import derived_seed
from twist_models.config import ReadOutConfig, StudentConfig
from twist_models.distillation import AUTO_MIRROR, DistilConfig, ReadOutStage
from twist_models.frame_targets import FrameRows
from twist_models.readout import (
    StateReadOut,
    episode_constants,
    motion_standardisation,
    pair_velocities,
    robust_standardisation,
    training_frames,
    typical,
)
from twist_models.student import Student, copy_teacher_filter
from twist_models.teacher import Teacher
from twist_sim.tasks import state_mirror

log = logging.getLogger(__name__)

#: States the teacher's sensitivity is averaged over (``readout_stage.units=teacher``).
UNITS_SAMPLE = 2048


def training_rows(data: MatchingDataset, config: DistilConfig) -> FrameRows:
    """D's steps outside the held-out episodes: what the read-out is measured and trained on."""
    return FrameRows.of(data, np.flatnonzero(~heldout_episodes(data.n_episodes,
                                                               config.schedule.holdout_every)))


def pair_readout(data: MatchingDataset, rows: FrameRows, teacher: Teacher, mirror: str,
                 stage: ReadOutStage) -> ReadOutConfig:
    """What a read-out student reads and derives, measured on D's training steps (velocities
    paired at ``stage.min_pairing``; components constant within episodes pooled where
    ``stage.pool`` asks), the mirror signs of what it reads where ``mirror``
    (:func:`mirror_mode`) asks for them, and how far it leans the angles it reads
    (``stage.lean``)."""
    wm = teacher.config.world_model
    states, is_first = rows.state.numpy(), rows.steps == rows.episode_start
    readout = pair_velocities(states, is_first, data.spec.state_layout, wm.state_mlp,
                              data.spec.task, hidden=wm.state_hidden,
                              min_pairing=stage.min_pairing)
    pooled = (episode_constants(states, is_first, readout.poolable()) if stage.pool == "constant"
              else ())
    if pooled:
        log.info("the read-out pools components %s over each episode: D's episodes never "
                 "change them", list(pooled))
    readout = dataclasses.replace(readout, lean=stage.lean, pooled=pooled, symlog=wm.symlog)
    if readout.moving:  # refused before anything is written, naming the command that adds them
        # No lower bar is offered: cheetah's root speed correlates at 0.43 with a change that
        # is not its rate, panda-push's block height at 0.47 with its own.
        data.require_pairs(f"the readout recipe on {data.spec.task} (velocity components "
                           f"{list(readout.moving)} pair with no component one frame shows: "
                           f"best correlations {list(readout.moving_pairing)}, below "
                           f"readout_stage.min_pairing {stage.min_pairing})")
    if mirror == "none":
        return readout
    signs = task_mirror(data)
    return dataclasses.replace(readout, mirror=tuple(signs[i] for i in readout.read))


def mirror_mode(config: DistilConfig, data: MatchingDataset) -> str:
    """``readout_stage.mirror`` for this D: ``auto`` resolved by whether its task declares a
    mirror."""
    if config.readout_stage.mirror == "auto":
        return AUTO_MIRROR if state_mirror(data.spec.task) else "none"
    return config.readout_stage.mirror


def task_mirror(data: MatchingDataset) -> tuple[float, ...]:
    """The sign of each of D's state components in the mirrored view (``TaskSpec.mirror``);
    a task that declares none, or one whose state D records at another length, is refused."""
    task = data.spec.task
    signs = state_mirror(task)
    if len(signs) != data.spec.state_dim:
        raise ConfigError(f"task {task!r} declares no mirror symmetry for its "
                          f"{data.spec.state_dim}-component state; set readout_stage.mirror=none")
    return signs


def start(student: Student, teacher: Teacher, rows: FrameRows, config: StudentConfig) -> None:
    """A new read-out student's first weights: the teacher's own state encoder and filter,
    and the read-out's standardisation of D's states."""
    copy_teacher_filter(student, teacher.world_model)
    states = rows.state.numpy()
    student.perception.readout.set_standardisation(
        *robust_standardisation(states, config.readout),
        motion_standardisation(states, config.readout))


def weigh_by_teacher(readout: StateReadOut, rows: FrameRows, seed: int) -> None:
    """Count each read error in units the teacher is sensitive to (``readout_stage.units=
    teacher``), averaged over a seeded draw of D's states, the same on resume."""
    drawn = np.random.default_rng(derived_seed(seed, 11)).choice(
        len(rows.state), min(UNITS_SAMPLE, len(rows.state)), replace=False)
    readout.weigh_by_teacher(rows.state[torch.as_tensor(np.sort(drawn))])
    log.info("the read-out's loss counts each error in units of %s (state units)",
             [round(float(u), 4) for u in readout.scale / readout.loss_weight])


def stage_rows(readout: StateReadOut, rows: FrameRows, stage: ReadOutStage) -> FrameRows:
    """The frames the first stage trains on: D's typical ones (``readout_stage.frames``)."""
    usual = typical(rows.state.cpu().numpy(), readout.config, readout.mean.cpu().numpy(),
                    readout.scale.cpu().numpy(), stage.typical_spreads)
    keep = training_frames(usual, stage.frames, stage.max_atypical_share)
    log.info("the read-out trains on %d of %d frames (%d within %.0f robust spreads; "
             "readout_stage.frames=%s)", keep.sum(), keep.size, usual.sum(),
             stage.typical_spreads, stage.frames)
    return rows.subset(keep)
