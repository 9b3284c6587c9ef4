"""The distillation objective of TWIST (Eq. 3 on windows, Eq. 4 along imagined rollouts) with
its config, recipes and size presets, and the held-out latent agreement: the building block the
``twist-distil`` stage (:mod:`twist_pipeline.distil`) runs.

* **Shared draws.** Teacher and student sample their categorical latents from the *same*
  uniform draws (inverse-CDF sampling): z_t^teacher and z_t^student are equal wherever the
  two distributions agree, so h_t^student is compared with the h_t^teacher that the same
  sample path produced. With independent draws the h target is noisy even for a perfect
  student. ``shared_draws=False`` gives independent samples.
* **Eq. 4** starts from the posterior states of both models at ``imag_starts`` random steps
  of the windows (0: every step, as the paper); the teacher samples its actor plus Gaussian
  noise, the student replays those actions; gradients flow into the student's start states.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import nn

from twist_data.errors import ConfigError
from twist_data.sampler import SamplerConfig
from twist_data.schema import PAIR_IMAGE
from twist_models.config import (
    CNN_NORMS,
    PRECISIONS,
    PRESETS,
    OptimConfig,
    replace_fields,
    require_choice,
    require_non_negative,
    require_positive,
)
from twist_models.device import compiles_whole, precision_autocast
from twist_models.frame_targets import actor_sensitivity, frame_agreement, frame_terms
from twist_models.losses import (
    action_matching_loss,
    distillation_loss,
    frame_posterior_loss,
    imagined_distillation_loss,
)
from twist_models.readout import MIN_PAIRING
from twist_models.rssm import FILTER_CHUNK
from twist_models.student import Student
from twist_models.teacher import Teacher

KEYS = ("image", "state", "action", "is_first")
WINDOW_STARTS = ("zero", "teacher")

@dataclass(frozen=True)
class LossWeights:
    """How the distillation terms are weighed: the paper's objective is Eq. 3's three terms
    and Eq. 4 at 1 and nothing else."""

    h: float = 1.0
    """||h_teacher - h_student||^2 on data (Eq. 3)."""
    prior: float = 1.0
    """KL(prior_student || prior_teacher) on data (Eq. 3)."""
    post: float = 1.0
    """KL(posterior_student || posterior_teacher) on data (Eq. 3)."""
    imagined: float = 1.0
    """The whole imagined term (Eq. 4)."""
    action: float = 0.0
    """Action matching: the teacher's actor on the student's posterior against it on the
    teacher's (not in the paper)."""
    frame_post: float = 0.0
    """The per-frame posterior term: KL of the student's posterior to the teacher's, both at
    the teacher's h (:mod:`twist_models.frame_targets`; not in the paper)."""
    state: float = 0.0
    """The per-frame state read-out term, each state component weighted by the teacher
    actor's sensitivity to it (adds a linear state head to the student; not in the paper)."""

    def __post_init__(self) -> None:
        require_non_negative(self, "h", "prior", "post", "imagined", "action", "frame_post",
                             "state")


@dataclass(frozen=True)
class DistilSchedule:
    """When a distillation run evaluates, checkpoints and snapshots, and on what."""

    holdout_every: int = 10
    """Every n-th episode of D is held out for the agreement metrics and never trained on."""
    heldout_windows: int = 16
    """Windows in the fixed held-out batch."""
    eval_every: int = 1_000
    """Updates between held-out evaluations (and metrics.csv rows)."""
    frame_eval_every: int = 500
    """First-stage updates between held-out evaluations and checkpoints."""
    checkpoint_every: int = 1_000
    """Updates between writes of ``latest.pt``."""
    snapshot_every: int = 10_000
    """Updates between kept ``student-<updates>.pt`` and ``agent-<updates>.pt`` snapshots."""

    def __post_init__(self) -> None:
        require_positive(self, "heldout_windows", "eval_every", "frame_eval_every",
                         "checkpoint_every", "snapshot_every")
        if self.holdout_every < 2:
            raise ConfigError(f"holdout_every must be >= 2, got {self.holdout_every}")


@dataclass(frozen=True)
class DistilCompute:
    """How a distillation run computes: none of it changes the objective."""

    precision: str = "float32"
    """Arithmetic of the student's CNN in training: ``float32``; ``bfloat16`` (autocast: the
    weights stay float32); ``auto``: bfloat16 on CUDA and on CPUs with native bfloat16
    (AVX512-BF16 or AMX, where it trains ~2x the frames per second:
    ``benchmarks/encoder_speed.py``), float32 elsewhere, where it would be slower."""
    compile: bool = False
    """Run the window objective (Eq. 3/4 and the terms beside them, forward and the backward
    through it) through ``torch.compile`` (:func:`compiled_objective`): on a CUDA device whole
    and captured as CUDA graphs, on a CPU its two filters in compiled pieces; the optimiser
    step stays eager. Off by default: it pays on a GPU, barely on a CPU
    (docs/performance.md)."""
    workers: int = 1
    """DataLoader processes decoding windows (0: decode in the training process)."""
    resident_data: str = "auto"
    """Gather training windows, and the first stage's frames, from a copy of D decoded once on
    the training device (:class:`twist_data.sampler.ResidentWindows`, the same stream as
    ``workers=0``; :class:`twist_models.frame_targets.FrameBatches`, the same batches): ``on``,
    ``off``, or ``auto``: on for a CUDA device where the copy takes at most half its free
    memory, off elsewhere (on a CPU the decode is a few percent of an update)."""

    def __post_init__(self) -> None:
        require_choice(self, "precision", PRECISIONS)
        require_choice(self, "resident_data", ("auto", "on", "off"))
        require_non_negative(self, "workers")


#: Ways a read-out student may use the task's mirror symmetry (``ReadOutStage.mirror``).
READOUT_MIRRORS = ("none", "average", "augment", "auto")
#: What ``mirror=auto`` does where the task declares its mirror (elsewhere: none).
AUTO_MIRROR = "augment"


@dataclass(frozen=True)
class ReadOutStage:
    """How a read-out student (``DistilConfig.readout``) reads D and hands on what it reads
    (the ``readout`` recipe; not in the paper)."""

    frames: str = "auto"
    """Which of D's frames its first stage trains on: ``typical`` (every read component
    within ``typical_spreads`` of its median), ``all``, or ``auto``: typical unless more than
    ``max_atypical_share`` of D is not (then all)."""
    typical_spreads: float = 17.0
    """Robust spreads (median and MAD over D) within which a frame's read components make it
    typical: on cartpole with a balancing teacher, the pole within ~20° of upright, so that
    the CNN is not spent on reading a fallen pole through a whole turn."""
    max_atypical_share: float = 0.15
    """Under ``frames=auto``, the share of D beyond which the atypical frames are a phase of
    the task (cup-catch's ball in flight, 28% of D), not rare outliers (cartpole's fallen
    poles, 9%), and every frame trains."""
    huber_delta: float = 17.0
    """Robust spreads up to which the read-out's loss is quadratic (linear beyond): on the
    typical frames it trains on, a squared error."""
    mirror: str = "none"
    """How it uses the task's left-right mirror symmetry (``TaskSpec.mirror``): ``none``;
    ``average``, each image read as the mean of its own reading and its mirror image's,
    mirrored back (acting and windows; twice the CNN passes); ``augment``, that, and the
    first stage trains on each frame mirrored with probability 1/2, its state mirrored with
    it; ``auto``: :data:`AUTO_MIRROR` where the task declares its mirror, ``none`` elsewhere."""
    lean: float = 1.0
    """How much further from its centre (upright on cartpole) each angle it reads is handed
    to the teacher's filter than it is read (``ReadOutConfig.lean``; 1: as read); any
    ``steps`` of Eq. 3/4 train through it. The recipe's value is chosen on held-out scenes of
    another evaluation seed than the reported one (research/log.md, "Does reading the lean
    larger hold the lost scenes?")."""
    min_pairing: float = MIN_PAIRING
    """The least correlation, over D's steps, between a velocity and the difference of
    successive read-outs it is derived from; below it the velocity counts as one no image
    shows and is read from frame pairs (D's ``pair_image``); what each task's velocities
    pair at: docs/findings.md, "Which tasks' velocities are the rate of something one image
    shows?"."""
    units: str = "robust"
    """What the first stage's loss measures each read component's error in: ``robust``, its
    robust spread over D (the error in spreads that ``read_error`` reports); ``teacher``,
    the error that moves the teacher's state embedding by one unit, velocities derived from
    it included (:meth:`~twist_models.readout.StateReadOut.teacher_units`): a robust spread
    of millimetres (a pushed block's height, a hand mostly at the table) would otherwise
    outweigh every centimetre the filter acts on (docs/findings.md). ``huber_delta`` is then
    in those units."""
    first_velocity: str = "zero"
    """Where its velocities at a training window's first step come from, mid-episode:
    ``read`` (the recipe's), the difference with the frame before the window, which the
    sampler draws with it, as when acting; ``zero``: none, the velocities 0 while the
    teacher's filter reads the true ones there, which only training shows."""
    pool: str = "constant"
    """Which read components are handed on as the mean of their readings over the episode
    so far (``ReadOutConfig.pooled``): ``constant``, those no training episode of D changes
    (``panda-push``'s goal marker, ``finger-turn_easy``'s target), so that a frame's error
    averages out with the next; ``none``, every frame read afresh."""

    def __post_init__(self) -> None:
        require_choice(self, "frames", ("auto", "typical", "all"))
        require_choice(self, "pool", ("constant", "none"))
        require_choice(self, "mirror", READOUT_MIRRORS)
        require_choice(self, "first_velocity", ("read", "zero"))
        require_choice(self, "units", ("robust", "teacher"))
        require_positive(self, "typical_spreads", "huber_delta")
        if not 0 <= self.max_atypical_share <= 1:
            raise ConfigError(f"max_atypical_share must lie in [0, 1], got "
                              f"{self.max_atypical_share}")
        if not 0 < self.min_pairing <= 1:
            raise ConfigError(f"min_pairing must lie in (0, 1], got {self.min_pairing}")
        if not 0 < self.lean < 2:
            raise ConfigError(f"lean must lie in (0, 2), got {self.lean}")


@dataclass(frozen=True)
class DistilConfig:
    """One distillation run: student size, batches, the losses and the schedule. The defaults
    are the paper's objective (the ``paper`` recipe); :data:`RECIPES` name other starting
    points."""

    #: Switches no recipe used, removed with the code behind them (what each measured:
    #: docs/findings.md); a run recorded before loads while it left them at these values.
    REMOVED: ClassVar[dict[str, Any]] = {
        "readout_weights": "robust", "frame_augment": "none", "frame_shift": 0.0,
        "frame_roll": 0.0, "rare_states": 0.0, "encoder_depth": None, "encoder_layers": None,
        "encoder_first_stride": 2, "encoder_pool": "flatten", "filter_read": "sample"}
    #: Fields that moved into the nested configs, by their old names (a run recorded before
    #: loads and resumes under them, :func:`~twist_models.config.moved_fields`).
    MOVED: ClassVar[dict[str, str]] = {
        **{f"{w}_weight": f"weights.{w}" for w in ("h", "prior", "post", "imagined", "action",
                                                   "frame_post", "state")},
        **{name: f"schedule.{name}" for name in ("holdout_every", "heldout_windows", "eval_every",
                                                 "frame_eval_every", "checkpoint_every",
                                                 "snapshot_every")},
        **{name: f"compute.{name}" for name in ("precision", "compile", "workers",
                                                "resident_data")},
        **{f"readout_{name}": f"readout_stage.{name}" for name in ("frames", "mirror", "lean",
                                                                  "first_velocity")}}

    recipe: str = "paper"
    """The named recipe this config started from (:data:`RECIPES`), kept as a label with the
    run and its agent bundle; the fields below are what ran."""
    student: str = "quick"
    """Student size preset (its CNN: ``tiny``, ``quick``, ``paper``); the RSSM is the teacher's."""
    steps: int = 50_000
    """Student updates."""
    batch_size: int = 16
    """Windows per update (the paper gives none; DreamerV2's world model takes 50, which did
    no better at equal updates: docs/findings.md)."""
    length: int = 50
    """L, steps per window (the paper: 50)."""
    horizon: int = 15
    """H, imagined steps of Eq. 4 (the paper: 15)."""
    action_noise: float = 0.3
    """Std of the Gaussian noise added to the teacher's actions in Eq. 4 (0: no noise)."""
    imagined: bool = True
    """Train with Eq. 4 too (False: the paper's "without imagined distillation" ablation)."""
    imag_starts: int = 0
    """Posterior states that start Eq. 4's rollouts; 0 = every step of every window."""
    shared_draws: bool = True
    """Teacher and student sample their latents from the same uniform draws."""
    copy_dynamics: bool = True
    """Start the student's RSSM from the teacher's (False: from scratch, as the paper)."""
    freeze_dynamics: bool = False
    """Keep the copied transition (the GRU, its input layer and the prior head) fixed, so
    only the encoder and the posterior head learn: the student's h is then the teacher's
    recurrence run on the student's z (needs ``copy_dynamics``; not in the paper)."""
    window_start: str = "zero"
    """Latent both filters start each training window from: ``zero`` (the paper's: h = 0,
    z = 0 mid-episode) or ``teacher`` (the teacher's own latent at the step before, filtered
    from the episode's start: the student learns to stay on the teacher's long-run path
    rather than to recover from h = 0; not in the paper). Held-out windows start from zero."""
    frames: int = 1
    """Images the student's posterior reads per step, each encoded alone: the current one and
    the ``frames - 1`` before it (1: the paper's single image; 2 shows it motion)."""
    encoder_norm: str = "none"
    """Normalisation in the student's CNN: ``none`` (DreamerV2's, the paper's) or ``layer``
    (see :class:`~twist_models.config.CNNConfig`)."""
    view: int | None = None
    """Camera view shown at every step; None: a random one of the K per step."""
    readout: bool = False
    """The student reads the teacher's state from each image and hands it to the teacher's
    own state encoder and filter, copied and fixed (:mod:`twist_models.readout`); its first
    stage regresses the state one frame shows, and any ``steps`` then train the CNN with
    Eq. 3/4 through the fixed filter (not in the paper)."""
    readout_stage: ReadOutStage = field(default_factory=ReadOutStage)
    """How a read-out student reads D and hands on what it reads."""
    stage_optimiser: str = "keep"
    """What the updates on windows after a first stage (``frame_steps``) start from:
    ``reset`` (the ``readout`` recipe's), a fresh AdamW, since the first stage's moments were
    scaled by another objective's gradients; ``keep``, the first stage's
    (docs/findings.md)."""
    frame_steps: int = 0
    """Updates of a first stage on single frames with the per-frame terms alone, before
    Eq. 3/4 (0: none, the paper): many cheap encoder updates instead of few whole ones."""
    frame_batch: int = 64
    """Frames per update of the first stage."""
    lr: float = 3e-4
    """Adam learning rate of the student (DreamerV2's world-model rate)."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Adam epsilon, gradient clip and weight decay."""
    seed: int = 0
    """Seed of the student's initialisation, the windows and the sampling draws."""
    weights: LossWeights = field(default_factory=LossWeights)
    """How the distillation terms are weighed."""
    schedule: DistilSchedule = field(default_factory=DistilSchedule)
    """When the run evaluates, checkpoints and snapshots, and on what."""
    compute: DistilCompute = field(default_factory=DistilCompute)
    """How the run computes (precision, compiling, data loading)."""

    def __post_init__(self) -> None:
        if self.student not in PRESETS:
            raise ConfigError(f"unknown student preset {self.student!r}; valid presets are: "
                              f"{', '.join(PRESETS)}")
        require_choice(self, "recipe", tuple(RECIPES))
        require_positive(self, "batch_size", "length", "horizon", "frames", "lr", "frame_batch")
        require_non_negative(self, "action_noise", "imag_starts", "frame_steps", "steps")
        if self.steps == 0 and self.frame_steps == 0:
            raise ConfigError("steps must be > 0 unless a first stage trains (frame_steps), "
                              "got steps=0 and frame_steps=0")
        if self.frame_steps and not self.frame_terms:
            raise ConfigError(f"frame_steps={self.frame_steps} trains on the per-frame terms "
                              "alone, but weights.frame_post and weights.state are both 0 and "
                              "the student does not read the state (readout)")
        w = self.weights
        if self.readout and (self.frames != 1 or w.state or w.frame_post
                             or not self.copy_dynamics):
            raise ConfigError("a read-out student reads one frame per step into the teacher's "
                              "copied filter and learns from its read-out alone in the first "
                              f"stage; got frames={self.frames}, weights.state={w.state}, "
                              f"weights.frame_post={w.frame_post}, "
                              f"copy_dynamics={self.copy_dynamics}")
        require_choice(self, "encoder_norm", CNN_NORMS)
        stage = self.readout_stage
        if stage.mirror != "none" and not self.readout:
            raise ConfigError(f"readout_stage.mirror={stage.mirror!r} averages a read-out "
                              "over the mirror image; only a read-out student (readout) has one")
        if stage.lean != 1.0 and not self.readout:
            raise ConfigError(f"readout_stage.lean={stage.lean} leans a read-out's angles; "
                              "only a read-out student (readout) has one")
        require_choice(self, "window_start", WINDOW_STARTS)
        require_choice(self, "stage_optimiser", ("reset", "keep"))
        if self.view is not None and self.view < 0:
            raise ConfigError(f"view must be >= 0, got {self.view}")
        if self.freeze_dynamics and not self.copy_dynamics:
            raise ConfigError("freeze_dynamics keeps the teacher's copied dynamics fixed; it "
                              "needs copy_dynamics")

    @property
    def frame_terms(self) -> bool:
        """Whether per-frame terms train: the ``dense`` ones (which need the teacher's
        targets over D) or a read-out student's."""
        return self.weights.frame_post > 0 or self.weights.state > 0 or self.readout

    @property
    def needs_teacher_targets(self) -> bool:
        """Whether the teacher's filter over D is needed: for the ``dense`` terms, or windows
        started from the teacher's latent."""
        return (self.weights.frame_post > 0 or self.weights.state > 0
                or self.window_start == "teacher")

    @property
    def window_context(self) -> int:
        """Steps drawn before each window for what its first step reads (a read-out
        student's frame before, ``readout_stage.first_velocity``); :func:`split_context` takes
        them off."""
        return int(self.readout and self.readout_stage.first_velocity == "read")

    def sampler(self, split: str, seed: int, batch_size: int | None = None,
                pairs: bool = False) -> SamplerConfig:
        """Windows of ``split`` (with each step's pair frame where ``pairs``: a read-out
        student's moving velocities read them)."""
        return SamplerConfig(length=self.length + self.window_context,
                             batch_size=batch_size or self.batch_size,
                             view=self.view, seed=seed,
                             keys=(*KEYS, PAIR_IMAGE) if pairs else KEYS,
                             holdout_every=self.schedule.holdout_every, split=split)



#: Recipes by name: what each sets on top of a size preset. ``paper``: Eq. 3 and 4 alone
#: (with the student's RSSM started from the teacher's, which every preset does). ``dense``:
#: the same, plus the per-frame targets of :mod:`twist_models.frame_targets`, first alone on
#: single frames for the size preset's ``FRAME_STEPS`` updates, then beside Eq. 3/4; windows
#: that start from the teacher's latent before them; sampling draws of its own (not the
#: teacher's), as when it acts; and a layer-normalised CNN. ``readout``: a student that reads
#: the teacher's state from each image into the teacher's own fixed filter
#: (:mod:`twist_models.readout`), its read-out trained on single frames; Eq. 3/4 through the
#: filter only if ``steps`` asks, reading each image with its mirror image's where the task
#: declares its mirror (docs/design.md, "Recipes", and docs/findings.md for what each part
#: was measured to give).
RECIPES: dict[str, dict[str, Any]] = {
    "paper": {},
    "dense": {"encoder_norm": "layer", "weights.frame_post": 1.0, "weights.state": 1.0,
              "compute.precision": "auto", "window_start": "teacher", "shared_draws": False},
    "readout": {"readout": True, "encoder_norm": "layer", "compute.precision": "auto",
                "readout_stage.mirror": "auto", "readout_stage.lean": 1.25,
                "readout_stage.first_velocity": "read",
                "stage_optimiser": "reset"},
}
#: Updates of each recipe's single-frame stage at each size preset: one update of 64 frames
#: costs ~1/20 of a ``quick`` update on windows, and the read-out student's return still rose
#: from 15,000 to 45,000 (research/findings-full.md, "Do more first-stage updates help?").
FRAME_STEPS = {"dense": {"paper": 20_000, "quick": 10_000, "tiny": 4},
               "readout": {"paper": 90_000, "quick": 45_000, "tiny": 4}}
#: Updates on windows (Eq. 3/4 through the teacher's fixed filter) after the read-out stage:
#: none by default, since they move the read-out away from the state the actor needs
#: (docs/findings.md, "TWIST's objective, long"); ``steps`` adds them.
READOUT_STEPS = {"paper": 0, "quick": 0, "tiny": 0}

DISTIL_PRESETS: dict[str, DistilConfig] = {
    # The paper's batch, window and horizon; Eq. 4 from every posterior state.
    "paper": DistilConfig(student="paper", steps=50_000),
    # CPU demo (~1 s per update on 2 cores, the CNN on 800 frames dominates): quick sizes,
    # Eq. 4 from 256 states per update; windows decoded in-process, since a loader process
    # takes a core from the update on a 2-core machine (benchmarks/distil_update.py).
    "quick": DistilConfig(student="quick", steps=800, imag_starts=256,
                          schedule=DistilSchedule(eval_every=50, checkpoint_every=50,
                                                  snapshot_every=400),
                          compute=DistilCompute(workers=0)),
    # Tests: seconds.
    "tiny": DistilConfig(student="tiny", steps=6, batch_size=2, length=8, horizon=3,
                         imag_starts=8,
                         schedule=DistilSchedule(holdout_every=4, heldout_windows=2, eval_every=3,
                                                 checkpoint_every=2, snapshot_every=4),
                         compute=DistilCompute(workers=0)),
}


def distil_preset(name: str, recipe: str = "paper", **overrides: Any) -> DistilConfig:
    """Size preset ``name`` with ``recipe``'s settings (:data:`RECIPES`), then fields replaced
    by ``overrides`` (None values are ignored; dotted keys reach nested configs, as
    :func:`~twist_models.config.replace_fields`)."""
    if name not in DISTIL_PRESETS:
        raise ConfigError(f"unknown preset {name!r}; valid presets are: "
                          f"{', '.join(DISTIL_PRESETS)}")
    if recipe not in RECIPES:
        raise ConfigError(f"unknown recipe {recipe!r}; valid recipes are: {', '.join(RECIPES)}")
    settings = dict(RECIPES[recipe], recipe=recipe)
    if recipe in FRAME_STEPS:
        settings["frame_steps"] = FRAME_STEPS[recipe][name]
    if recipe == "readout":
        settings["steps"] = READOUT_STEPS[name]
    settings.update({k: v for k, v in overrides.items() if v is not None})
    return replace_fields(DISTIL_PRESETS[name], settings)


def split_context(batch: Mapping[str, torch.Tensor], context: int) -> dict[str, torch.Tensor]:
    """Windows drawn ``context`` steps longer (:attr:`DistilConfig.window_context`), {k:
    [B, context + L, ...]} -> the windows proper {k: [B, L, ...]}, with the frame before each
    as ``image_before`` [B, H, W, 3] and ``start`` moved to the window proper's first step.
    Where a drawn window starts an episode its first frame is the one before: the window
    proper, which starts at the episode's second step, then reads the velocity as acting
    does there."""
    if context == 0:
        return dict(batch)
    out = {k: v[:, context:] if torch.is_tensor(v) and v.dim() >= 2 and k != "image_before"
           else v for k, v in batch.items()}
    out["image_before"] = batch["image"][:, context - 1]
    if "start" in batch:
        out["start"] = batch["start"] + context
    return out


# -- one update ---------------------------------------------------------------------------------
def frame_loss(terms: Mapping[str, torch.Tensor], config: DistilConfig) -> torch.Tensor:
    """The per-frame terms weighted by ``config`` (a student without a state head has no
    ``state`` term)."""
    loss = config.weights.frame_post * terms["frame_post_kl"]
    if "state" in terms:
        loss = loss + config.weights.state * terms["state"]
    return loss


def draws(batch_shape: tuple[int, ...], stoch: int, device: torch.device) -> torch.Tensor:
    """Uniform sampling draws [*batch_shape, S, 1] for :func:`twist_models.rssm.sample_one_hot`."""
    return torch.rand(*batch_shape, stoch, 1, device=device)


class Distillation(nn.Module):
    """The objective as a module around the student (so DistributedDataParallel can wrap it);
    the frozen teacher is held outside the module tree: it is neither trained nor synced."""

    def __init__(self, student: Student, teacher: Teacher, config: DistilConfig,
                 sensitivity_scale: float = 1.0) -> None:
        super().__init__()
        self.student = student
        self._teacher = [teacher.requires_grad_(False)]  # a target: gradients stop at it
        self.config = config
        # The per-frame state weights are divided by D's mean sensitivity (TeacherTargets).
        self.sensitivity_scale = sensitivity_scale

    @property
    def teacher(self) -> Teacher:
        return self._teacher[0]

    def forward(self, batch: Mapping[str, torch.Tensor]
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Total loss [] and every term [] for a batch of windows ({k: [B, L, ...]})."""
        c = self.config
        s_post, t_post, terms, embed = self.filter(batch)
        w = c.weights
        loss = w.h * terms["h"] + w.prior * terms["prior_kl"] + w.post * terms["post_kl"]
        if c.frame_terms:
            frame = self.window_frame_terms(embed, t_post, batch["state"])
            terms.update(frame)
            loss = loss + frame_loss(frame, c)
        if w.action > 0:
            terms["action"] = self.action_term(s_post, t_post)
            loss = loss + w.action * terms["action"]
        if c.imagined and w.imagined > 0:
            imagined = self.imagined_terms(s_post, t_post)
            terms.update({f"imagined_{k}": v for k, v in imagined.items()})
            loss = loss + w.imagined * (imagined["h"] + imagined["prior_kl"])
        return loss, terms

    def filter(self, batch: Mapping[str, torch.Tensor]
               ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor],
                          dict[str, torch.Tensor], torch.Tensor]:
        """Both models' posteriors over the windows (student on images, teacher on states,
        from the same draws when shared) and the Eq. 3 terms: (student posterior, teacher
        posterior, terms, the student's posterior input [B, L, E'])."""
        action, is_first = batch["action"], batch["is_first"]
        # Windows may start from the teacher's latent before them (``window_start``).
        start = ({"deter": batch["start_deter"], "stoch": batch["start_stoch"]}
                 if "start_deter" in batch else None)
        post_draws = None
        if self.config.shared_draws:
            post_draws = draws(action.shape[:2], self.student.config.rssm.stoch, action.device)
        with torch.no_grad():
            wm = self.teacher.world_model
            t_post, t_prior = wm.rssm.observe(wm.embed(batch["state"]), action, is_first,
                                              start, post_draws)
        with precision_autocast(self.config.compute.precision, is_first.device):
            embed = self.student.embed(batch["image"], is_first, batch.get("image_before"),
                                       batch.get(PAIR_IMAGE)).float()
        s_post, s_prior = self.student.rssm.observe(embed, action, is_first, start, post_draws)
        terms = distillation_loss(s_post, s_prior["logits"], t_post, t_prior["logits"])
        return s_post, t_post, terms, embed

    def window_frame_terms(self, embed: torch.Tensor, t_post: dict[str, torch.Tensor],
                           state: torch.Tensor) -> dict[str, torch.Tensor]:
        """The per-frame terms at every step of the windows, at the teacher's h there."""
        sensitivity = actor_sensitivity(self.teacher, t_post["deter"], state)
        return frame_terms(self.student, self.teacher, embed, t_post["deter"], state,
                           sensitivity / self.sensitivity_scale, t_post["logits"])

    def action_term(self, s_post: dict[str, torch.Tensor], t_post: dict[str, torch.Tensor]
                    ) -> torch.Tensor:
        """The teacher's actor (mode) on both posteriors [B, L, ...], matched; the gradient
        reaches the student's latent through the frozen actor."""
        actor = self.teacher.actor_critic.actor
        with torch.no_grad():
            target = actor(self.teacher.world_model.rssm.feature(t_post)).mode
        return action_matching_loss(actor(self.student.rssm.feature(s_post)).mode, target)

    def imagined_terms(self, s_post: dict[str, torch.Tensor], t_post: dict[str, torch.Tensor]
                       ) -> dict[str, torch.Tensor]:
        """Eq. 4 from (a subset of) the posterior states [B, L, ...] of both models."""
        c, teacher = self.config, self.teacher
        flat_s = {k: v.flatten(0, 1) for k, v in s_post.items()}
        flat_t = {k: v.flatten(0, 1) for k, v in t_post.items()}
        n = flat_s["deter"].shape[0]
        if 0 < c.imag_starts < n:
            chosen = torch.randperm(n, device=flat_s["deter"].device)[:c.imag_starts]
            flat_s = {k: v[chosen] for k, v in flat_s.items()}
            flat_t = {k: v[chosen] for k, v in flat_t.items()}
            n = c.imag_starts
        stoch = self.student.config.rssm.stoch
        device = flat_s["deter"].device
        img_draws = draws((n, c.horizon), stoch, device) if c.shared_draws else None
        actor = teacher.actor_critic.actor

        def noisy_actor(feature: torch.Tensor) -> torch.Tensor:
            action = actor(feature).rsample()
            if c.action_noise:
                action = action + c.action_noise * torch.randn_like(action)
            return action.clamp(-1.0, 1.0)

        with torch.no_grad():
            t_states, actions = teacher.world_model.rssm.imagine(
                flat_t, c.horizon, policy=noisy_actor, uniform=img_draws)
        s_states, _ = self.student.rssm.imagine(flat_s, c.horizon, actions=actions,
                                                uniform=img_draws)
        return imagined_distillation_loss(s_states, t_states)


def compiled_objective(objective: nn.Module, mode: str | None, whole: bool | None = None
                       ) -> Callable[..., Any]:
    """What to train with: ``objective`` (a :class:`Distillation`, or one wrapped in
    DistributedDataParallel) compiled in ``mode`` (``reduce-overhead``: also captured as
    CUDA graphs; None: ``objective`` itself, eager).

    ``whole`` (default: with CUDA graphs only, which want the fewest launches) compiles the
    whole objective as one graph. Otherwise the student's and the teacher's filters run
    :data:`~twist_models.rssm.FILTER_CHUNK` steps at a time through compiled pieces and
    the networks between them eager: on a 2-core CPU the ``dense`` recipe's ``quick`` window
    update (bfloat16 CNN) ran 1.16x eager after 54 s of compiling, the whole graph 1.23x after
    352 s, whose extra compiling is repaid only after ~10,000 updates
    (``benchmarks/distil_compile.py``; docs/performance.md). The pieces live on the
    models' RSSMs, so every filter of this student and this teacher runs them from here on,
    the held-out evaluation's included (``RSSM.compile_filter(None)`` undoes it)."""
    whole = compiles_whole(mode, whole)
    if mode is None or whole:
        return objective if mode is None else torch.compile(objective, mode=mode)
    distillation = objective.module if isinstance(
        objective, nn.parallel.DistributedDataParallel) else objective
    distillation.student.rssm.compile_filter(FILTER_CHUNK, mode)
    distillation.teacher.world_model.rssm.compile_filter(FILTER_CHUNK, mode)
    return objective


@torch.no_grad()
def latent_agreement(student: Student, teacher: Teacher, batch: Mapping[str, torch.Tensor],
                     config: DistilConfig, seed: int = 0) -> dict[str, float]:
    """How close the student's latents are to the teacher's on ``batch``: per-element MSE of
    h (``h_mse``), the share of the teacher's h variance over the batch's steps that the
    student reproduces (``h_explained``, R² = 1 - h_mse / variance), posterior and prior KL
    (student || teacher) and the h-MSE along Eq. 4's rollouts. All randomness (draws, starts,
    action noise) comes from ``seed``, so a fixed student on a fixed batch always scores the
    same."""
    device = batch["action"].device
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(seed)
        objective = Distillation(student, teacher, dataclasses.replace(config, shared_draws=True))
        s_post, t_post, terms, embed = objective.filter(batch)
        imagined = objective.imagined_terms(s_post, t_post)
        frames = frame_agreement(student, teacher, embed, t_post["deter"], batch["state"])
        frame_kl = frame_posterior_loss(student.rssm.posterior_logits(t_post["deter"], embed),
                                        t_post["logits"])
        if student.perception.readout is not None:
            features = student.perception.encoder(batch["image"])
            motion = (student.perception.motion_features(batch[PAIR_IMAGE], batch["image"])
                      if PAIR_IMAGE in batch else None)
            frames["read_error"] = student.perception.readout.error(
                features, batch["state"], motion_features=motion)
            frames["read_error_typical"] = student.perception.readout.error(
                features, batch["state"], config.readout_stage.typical_spreads, motion)
    deter = student.config.rssm.deter
    h_mse = float(terms["h"]) / deter
    # An h-MSE means little without the scale of the teacher's h (on cartpole its variance is
    # ~0.06 per dimension): the share of that variance the student reproduces says more.
    h_variance = float(t_post["deter"].flatten(0, -2).var(0).mean())
    return {"h_mse": h_mse, "h_explained": 1.0 - h_mse / max(h_variance, 1e-12),
            "post_kl": float(terms["post_kl"]), "prior_kl": float(terms["prior_kl"]),
            "imagined_h_mse": float(imagined["h"]) / deter, "frame_post_kl": float(frame_kl),
            **frames}
