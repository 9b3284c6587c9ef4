"""Train the state teacher online and write the matching dataset D while it trains.

One collector owns one shard of D and the run folder ``<out>/collect/<shard>/``:
``config.json`` (the resolved configs), ``metrics.csv`` (one row per episode), ``eval.csv``
and its plot ``learning-curve.png``,
``latest.pt`` (after every episode), ``teacher-<frames>.pt`` (every ``snapshot_every``
frames) and ``teacher.pt`` (the final teacher, which ``twist-distil`` picks by default).

Decisions (docs/cli.md, "twist-collect", says more):

* **The teacher's replay is D itself.** Its windows come from a :class:`WindowSampler` on its
  own shard, low-dimensional keys only, refreshed after each commit. What the teacher trained
  on is exactly what D holds, the student's sampler and the teacher's replay are one code
  path, and resuming needs no replay file. Only committed episodes are replayed, as
  DreamerV2 adds whole episodes to its replay.
* **Updates between episodes, at DreamerV2's ratio.** After each committed episode the
  teacher trains until it has made ``pretrain_updates + (agent steps - prefill) /
  train_every`` updates. Every episode is thus acted by one teacher, named in its provenance
  (``teacher_step``), and a checkpoint taken between episodes is consistent with D.
* **Resume = checkpoint + D.** ``latest.pt`` holds the teacher, its optimisers, the torch and
  replay RNG states and the evaluation schedule. Episodes committed after it (a kill between
  commit and checkpoint) stay in D; the resumed teacher replays them and makes up the
  updates it owes. Uncommitted episodes are dropped by the writer. Nothing is duplicated or
  lost.
* **Evaluation** runs the teacher's mode action on the privileged state, nominal dynamics,
  fixed seeds, without rendering; evaluation episodes are not written to D (they would cost
  renders and add off-distribution, noise-free behaviour to the training data).
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import os
import time
import zlib
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from twist_data.errors import ConfigError, TwistError
from twist_data.reader import ShardReader, open_dataset
from twist_data.sampler import SamplerConfig, WindowSampler
from twist_data.schema import Episode
from twist_data.seeding import derived_seed
from twist_data.writer import ShardWriter, shard_path
from twist_models.agent import Agent
from twist_models.config import (
    LEARNING_PRESETS,
    PRESETS,
    TeacherConfig,
    from_json,
    replace_fields,
    require_choice,
    require_non_negative,
    require_positive,
    teacher_preset,
    to_json,
)
from twist_models.device import COMPILE_SETTINGS, compile_mode, resolve_device
from twist_models.networks import single_threaded
from twist_models.teacher import BEST_TEACHER, FINAL_TEACHER, Teacher, load_teacher, save_teacher
from twist_pipeline.acting import ImageAgent, RandomPushes, StateAgent
from twist_pipeline.curves import plot_learning_curves
from twist_pipeline.runlog import (
    RunFolder,
    TensorBoardLog,
    append_csv,
    check_output,
    record_section,
    resume_conflicts,
)
from twist_sim.randomisation import DR_PRESETS, TRAINING_DR, Dynamics, dr_preset
from twist_sim.render import DRRenderer, FrameRenderer
from twist_sim.render_process import RenderProcess
from twist_sim.rerender import pair_instant
from twist_sim.rollout import Policy, random_policy, record_episode, simulated_spec
from twist_sim.tasks import DEFAULT_ACTION_REPEAT, DEFAULT_TASK, TaskEnv, task_spec

log = logging.getLogger(__name__)

REPLAY_KEYS = ("state", "action", "reward", "is_first", "is_terminal")
TIMED_PARTS = ("physics", "render", "policy", "write", "learn", "eval", "checkpoint")
#: metrics.csv columns; training metrics are means over the updates after each episode.
METRIC_COLUMNS = (
    "frames", "episodes", "updates", "return", "wall_s",
    *(f"seconds_{part}" for part in TIMED_PARTS),
    "model_loss", "kl", "recon_loss", "reward_loss", "discount_loss", "model_grad_norm",
    "actor_loss", "critic_loss", "imagined_return", "imagined_reward", "actor_entropy",
    "overshoot_loss")


class CollectError(TwistError):
    """Collection cannot start or continue (output folder, disk, resume state)."""


#: The most frames one collector run takes: 2,000 times the ``paper`` preset's 500K, beyond
#: which a typo is likelier than a plan.
MAX_FRAMES = 1_000_000_000


#: Teacher settings a collect config once held under names of its own, and ``--set`` still
#: takes: each one's place in the teacher's config (``CollectConfig.teacher``).
TEACHER_ALIASES = {
    "imag_starts": "actor_critic.imag_starts", "horizon": "actor_critic.horizon",
    "explore_noise": "explore_noise", "actor_entropy": "actor_critic.entropy",
    "actor_grad": "actor_critic.actor_grad", "return_norm": "actor_critic.return_norm",
    "critic_head": "actor_critic.critic_head", "actor_lr": "actor_critic.actor_lr",
    "critic_lr": "actor_critic.critic_lr", "slow_target_every": "actor_critic.slow_target_every",
    "model_lr": "world_model.model_lr", "overshoot": "world_model.overshoot",
    "state_noise": "world_model.state_noise", "discount": "actor_critic.discount",
    "imagination_precision": "actor_critic.precision",
}


@dataclass(frozen=True)
class TeacherEvalConfig:
    """The collector's evaluations of its teacher on states (:class:`TeacherEvaluation`)."""

    every: int = 10_000
    """Frames between evaluations."""
    episodes: int = 5
    """Episodes per evaluation (0: none)."""

    def __post_init__(self) -> None:
        require_positive(self, "every")
        require_non_negative(self, "episodes")


@dataclass(frozen=True)
class CollectConfig:
    """One collector run: task, rendering, teacher sizes and the training schedule."""

    #: Fields that moved into a nested config (stored runs and ``--set`` reach them there).
    MOVED: ClassVar[dict[str, str]] = {"eval_every": "evaluation.every",
                                       "eval_episodes": "evaluation.episodes"}
    #: Short names ``--set`` and :meth:`with_settings` take for the teacher's fields.
    ALIASES: ClassVar[dict[str, str]] = {name: f"teacher.{path}"
                                         for name, path in TEACHER_ALIASES.items()}

    task: str = DEFAULT_TASK
    """DMC task (``twist-data tasks``)."""
    model: str = "quick"
    """Teacher size preset (``tiny``, ``quick``, ``paper``)."""
    learning: str = "dreamerv2"
    """How the teacher learns over its size preset (``LEARNING_PRESETS``: ``dreamerv2``, or
    ``cpu``, the settings that learned fastest on a 2-core CPU)."""
    frames: int = 100_000
    """Environment frames to collect (agent steps x action repeat), prefill included."""
    learn_frames: int | None = None
    """Frames after which the teacher stops learning and, frozen, goes on acting (sampling its
    actions) until ``frames``: more of D at the cost of acting alone, without the updates each
    episode costs while the teacher learns; None: it learns until ``frames``."""
    learn_until_return: float | None = None
    """Evaluation return at which the teacher stops learning, if one reaches it before
    ``learn_frames``; from the next episode on it acts frozen (with ``freeze_best``, the best
    evaluated teacher, which is then this one), as after ``learn_frames``: a teacher at the
    task's ceiling has little left to learn, and on a CPU its updates are most of a
    collection's time. It also changes D, more of which the frozen teacher plays
    (docs/findings.md, "Can the teacher stop at an evaluation of 990?"). None: learning ends
    at ``learn_frames`` (or ``frames``) only."""
    freeze_best: bool = False
    """At ``learn_frames`` the teacher of the best evaluation so far (``best.pt``), not the
    last one, acts frozen for the rest of D: a Dreamer's evaluation return swings from one
    evaluation to the next (993 then 817 in one cartpole run), and the frozen teacher is the
    one whose actor the student will serve."""
    frozen_noise: float = 0.0
    """Std of Gaussian noise added to the frozen teacher's actions (after ``learn_frames``;
    clipped to [-1, 1]; D records the executed action): states off the teacher's own path
    from which it recovers, for the student to learn from, as DART (Laskey et al., 2017)
    injects noise into an expert's demonstrations; 0: none."""
    push_every: int = 0
    """Mean agent steps between pushes of the frozen teacher (after ``learn_frames``): a push
    overrides its actions for 1..``push_steps`` steps with one action drawn uniform in
    [-1, 1], then the teacher recovers. Per-step noise (``frozen_noise``) averages out and
    barely moves a balancing teacher's states; pushes put into D the larger excursions an
    imperfect student meets, with the teacher's latents for them; 0: none."""
    push_steps: int = 10
    """Longest push, in agent steps (see ``push_every``)."""
    pairs: bool = False
    """Store each step's frame pair (datasets.md, ``pair_image``: the step before drawn under
    the step's draw) as it collects, from which the ``readout`` recipe reads the speeds no
    single frame shows; D then needs no ``twist-data render --reproduce --pairs``. Each
    episode's pairs are drawn when it ends (~1.6 s an episode on one core). False: none."""
    student: str = ""
    """An agent bundle (``agent.pt`` from twist-distil) that acts instead of the frozen teacher
    (after ``learn_frames``), on its own render of each step: D then holds the states the
    student itself meets, and distillation gives it the teacher's latents on them, as DAgger
    (Ross et al., 2011) labels a learner's own states with the expert's; "": the teacher
    acts. Its episodes are recorded with policy ``student``."""
    views: int = 2
    """K randomised renders per step."""
    image_size: int = 64
    """Render side in pixels."""
    supersample: int = 1
    """Render at this multiple of ``image_size`` and area-downsample: anti-aliasing, without
    which thin geoms (cartpole's pole and rail, the cup's string) break into stray pixels."""
    dr: str = TRAINING_DR
    """DR preset of the renders (``twist-data`` lists them). ``train-wide`` (five texture
    families) rather than the paper-like ``train`` (three): its students read backgrounds of
    kinds they never saw better (docs/findings.md, "Does a wider bank of training textures
    help?")."""
    backgrounds: str | None = None
    """Folder of background images/videos replacing the procedural bank; None: procedural."""
    action_repeat: int = DEFAULT_ACTION_REPEAT
    """Simulator steps per agent step (DreamerV2 DMC: 2)."""
    max_steps: int | None = None
    """Agent steps per episode; None: the task's own limit (1000 frames)."""
    seed: int = 0
    """Run seed; each shard derives its own teacher, episode and replay seeds from it."""
    prefill_frames: int = 2_000
    """Frames of uniform random actions before the teacher acts (DreamerV2 DMC: 5000 agent
    steps = 10K frames)."""
    pretrain_updates: int = 100
    """Teacher updates on the prefill data before it first acts (DreamerV2: 100)."""
    train_every: int = 5
    """Agent steps per teacher update (DreamerV2: 5)."""
    batch_size: int = 16
    """Replay windows per update."""
    batch_length: int = 50
    """Steps per replay window."""
    evaluation: TeacherEvalConfig = field(default_factory=lambda: TeacherEvalConfig())
    """How often and how long the teacher is evaluated on states while it learns."""
    snapshot_every: int = 100_000
    """Frames between kept teacher checkpoints (``latest.pt`` is written every episode)."""
    behaviour_from: int = 0
    """Teacher updates that train the world model alone before the actor-critic joins in: its
    imagination is only worth learning from once the model predicts something (and such
    updates cost a third of a full one)."""
    teacher: TeacherConfig | None = None
    """The teacher's whole config, its sizes included; None: the ``model`` preset's for the
    task, learning as ``learning`` says. ``--set teacher.<field>=...`` (e.g.
    ``teacher.world_model.rssm.deter=256``, ``teacher.actor_critic.actor_lr=1e-4``) starts it
    from there (:meth:`with_settings`); the names in :data:`TEACHER_ALIASES` reach it too."""
    compile: str = "auto"
    """Teacher updates through ``torch.compile`` (``auto``: with CUDA graphs on a CUDA device,
    eager on a CPU, where it saves too little; ``on``: on a CPU the loops in pieces;
    ``off``: eager, the reference; :func:`~twist_models.device.compile_mode`)."""

    def __post_init__(self) -> None:
        task_spec(self.task)  # raises UnknownTaskError naming the valid tasks
        require_choice(self, "compile", COMPILE_SETTINGS)
        require_choice(self, "learning", tuple(LEARNING_PRESETS))
        if self.model not in PRESETS:
            raise ConfigError(f"unknown model preset {self.model!r}; valid: {', '.join(PRESETS)}")
        if self.dr not in DR_PRESETS:
            raise ConfigError(f"unknown DR preset {self.dr!r}; valid: {', '.join(DR_PRESETS)}")
        if self.frames > MAX_FRAMES:
            raise ConfigError(f"frames {self.frames} is more than {MAX_FRAMES:,} (years of "
                              "simulation on one machine); collect in shards instead")
        require_positive(self, "frames", "views", "image_size", "supersample", "action_repeat",
                         "train_every", "batch_size", "batch_length", "snapshot_every")
        require_non_negative(self, "prefill_frames", "pretrain_updates",
                             "behaviour_from", "frozen_noise", "push_every")
        require_positive(self, "push_steps")
        if self.learn_frames is not None and self.learn_frames <= self.prefill_frames:
            raise ConfigError(f"learn_frames {self.learn_frames} ends learning before the "
                              f"teacher first acts (prefill_frames {self.prefill_frames})")
        for name in ("frozen_noise", "push_every", "student"):
            if getattr(self, name) and self.learn_frames is None:
                raise ConfigError(f"{name} changes who acts once the teacher is frozen; it "
                                  "needs learn_frames")
        if self.freeze_best and (self.learn_frames is None or self.evaluation.episodes < 1):
            raise ConfigError("freeze_best needs learn_frames and evaluation.episodes >= 1 (it "
                              "freezes the best evaluated teacher when learning ends)")
        if self.learn_until_return is not None and self.evaluation.episodes < 1:
            raise ConfigError(f"learn_until_return {self.learn_until_return} needs "
                              "evaluation.episodes >= 1: it stops learning on an evaluation's "
                              "return")
        if self.max_steps is not None and self.max_steps < self.batch_length:
            raise ConfigError(f"max_steps {self.max_steps} is shorter than one replay window "
                              f"(batch_length {self.batch_length})")

    def with_settings(self, settings: Mapping[str, Any]) -> CollectConfig:
        """This config with ``settings`` replaced (dotted keys reach nested configs; the names
        of :data:`TEACHER_ALIASES` the teacher's fields). A ``teacher.<field>`` key on a config
        without a teacher config first gets the ``model`` and ``learning`` presets' for the
        task (as they stand after the other settings) to change."""
        settings = {self.ALIASES.get(k, k): v for k, v in settings.items()}
        own = {k: v for k, v in settings.items() if not k.startswith("teacher.")}
        config = replace_fields(self, own)
        teacher = {k: v for k, v in settings.items() if k.startswith("teacher.")}
        if teacher and config.teacher is None:
            env = TaskEnv(config.task, config.action_repeat)
            config = dataclasses.replace(config, teacher=teacher_preset(
                config.model, env.state_dim, env.action_dim, config.learning))
        return replace_fields(config, teacher)

    @classmethod
    def record_section(cls, record: Mapping[str, Any]) -> dict[str, Any]:
        """The ``collect`` section of a run's ``config.json``, as this version stores it: a run
        recorded while the teacher's settings had names of their own here
        (:data:`TEACHER_ALIASES`) holds them in its teacher config, which the record keeps
        whole beside them (``teacher``), so it loads, resumes and compares as it ran."""
        section = dict(record["collect"])
        if any(name in section for name in TEACHER_ALIASES):
            for name in TEACHER_ALIASES:
                section.pop(name, None)
            if "teacher" not in record:
                raise ConfigError("a collect config that names teacher settings by their "
                                  f"former names ({', '.join(TEACHER_ALIASES)}) needs the "
                                  "teacher config its run recorded beside it")
            # The teacher that ran: the settings applied over the collect config's own teacher,
            # with the fields added since at their defaults, which keep its behaviour.
            section["teacher"] = to_json(from_json(TeacherConfig, record["teacher"]))
        return section

    def teacher_config(self, state_dim: int, action_dim: int) -> TeacherConfig:
        if self.teacher is not None:
            wm = self.teacher.world_model
            if (wm.state_dim, wm.action_dim) != (state_dim, action_dim):
                raise ConfigError(f"the teacher config reads states of {wm.state_dim} and acts "
                                  f"in {wm.action_dim} dimensions, but {self.task} has "
                                  f"{state_dim} and {action_dim}")
            return self.teacher
        return teacher_preset(self.model, state_dim, action_dim, self.learning)

    def learns_at(self, frames: int) -> bool:
        """Whether the teacher still learns (or has just learned) once ``frames`` are in D."""
        return self.learn_frames is None or frames <= self.learn_frames

    def acts_frozen(self, frames: int) -> bool:
        """Whether the episode that starts once ``frames`` are in D is the frozen teacher's."""
        return not self.learns_at(frames + 1)

    def updates_due(self, frames: int) -> int:
        """Teacher updates owed once ``frames`` frames are in D (DreamerV2's train ratio); none
        are owed for frames past ``learn_frames``."""
        if self.learn_frames is not None:
            frames = min(frames, self.learn_frames)
        if frames < self.prefill_frames:
            return 0
        steps_after_prefill = (frames - self.prefill_frames) // self.action_repeat
        return self.pretrain_updates + steps_after_prefill // self.train_every


COLLECT_PRESETS: dict[str, CollectConfig] = {
    # DreamerV2 DMC (configs.yaml `dmc_proprio`/`dmc_vision`): pretrain 100, train_every 5;
    # 500K frames, eval every 10K frames. Its prefill is 1,000 agent steps (2K frames); this
    # preset's 10K frames is a departure that runs recorded with it keep.
    # Rendered anti-aliased (supersample 2), as dm_control's own 4x multisampled render is:
    # without it cartpole's pole breaks into stray pixels at 64x64; the same holds for quick.
    "paper": CollectConfig(model="paper", frames=500_000, evaluation=TeacherEvalConfig(10_000, 10),
                           snapshot_every=100_000, prefill_frames=10_000, supersample=2),
    # CPU-sized teacher: the settings that learned fastest on a 2-core CPU, each a change from
    # DreamerV2's (action repeat 4, a warm-up of world-model updates, and the teacher's `cpu`
    # learning: a faster actor, a two-hot critic, open-loop overshooting). It learns
    # to 100K frames or its first evaluation of 990, then its best evaluated snapshot acts
    # frozen to 300 episodes, since the student needs the final teacher's trajectories
    # (docs/findings.md, "The teacher on states").
    "quick": CollectConfig(model="quick", learning="cpu", frames=300_000, learn_frames=100_000,
                           freeze_best=True, learn_until_return=990.0,
                           supersample=2, evaluation=TeacherEvalConfig(2_000, 10),
                           snapshot_every=20_000, action_repeat=4, prefill_frames=10_000,
                           pretrain_updates=2_000, behaviour_from=2_000, train_every=4,
                           batch_size=32),
    # Tests and smoke runs: seconds, learns nothing.
    "tiny": CollectConfig(model="tiny", frames=400, max_steps=50,
                          evaluation=TeacherEvalConfig(200, 1), snapshot_every=200, prefill_frames=100,
                          pretrain_updates=2, train_every=25, batch_size=4, batch_length=16),
}


def collect_preset(name: str, **overrides: Any) -> CollectConfig:
    """Preset ``name`` with fields replaced by ``overrides`` (None values are ignored)."""
    if name not in COLLECT_PRESETS:
        raise ConfigError(f"unknown preset {name!r}; valid presets are: "
                          f"{', '.join(COLLECT_PRESETS)}")
    return COLLECT_PRESETS[name].with_settings(_given(**overrides))


def _given(**values: Any) -> dict[str, Any]:
    """The keyword arguments that are not None (the overrides a user actually set)."""
    return {k: v for k, v in values.items() if v is not None}


def shard_seed(seed: int, shard: str) -> int:
    """Each shard's own seed: shard ``collect-007`` (or any name) gets a distinct stream."""
    return derived_seed(seed, zlib.crc32(shard.encode()))


# -- progress and results ---------------------------------------------------------------------
@dataclass(frozen=True)
class Progress:
    """Reported after every committed episode."""

    frames: int
    total_frames: int
    episodes: int
    updates: int
    episode_return: float
    eval_return: float | None
    frames_per_second: float


@dataclass
class CollectSummary:
    """What a collector run did."""

    shard: Path
    run_dir: Path
    teacher: Path
    episodes: int
    frames: int
    updates: int
    last_return: float | None
    best_eval_return: float | None
    last_eval_return: float | None
    zero_action_return: float | None
    """The evaluation episodes' mean return with every action 0: the floor (on
    cartpole-balance a pole left alone spins through the top and scores ~750)."""
    learned_until: int | None
    """Frames at which an evaluation reached ``learn_until_return`` and learning stopped;
    None: it did not."""
    frozen_from: dict[str, Any] | None
    """With ``freeze_best``: frames, updates and evaluation return of the teacher that acts
    frozen (and is saved as ``teacher.pt``)."""
    dataset_bytes: int
    seconds: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {k: str(v) if isinstance(v, Path) else v
                for k, v in dataclasses.asdict(self).items()}


# -- the collector ----------------------------------------------------------------------------
def load_acting_student(config: CollectConfig, device: torch.device) -> Agent:
    """``config.student``'s bundle, refused unless it acts on this run's task and repeat."""
    path = Path(config.student)
    if not path.is_file():
        raise CollectError(f"the student agent {config.student!r} does not exist; pass an "
                           "agent.pt written by twist-distil")
    agent = Agent.load(path, device)
    for name, want in (("task", config.task), ("action_repeat", config.action_repeat)):
        have = agent.info.get(name)
        if have != want:
            raise CollectError(f"the student agent {config.student!r} has {name} {have!r}, "
                               f"but this run collects with {want!r}")
    return agent


def run_dir(out: str | os.PathLike[str], shard: str) -> Path:
    return Path(out) / "collect" / shard


def collect(out: str | os.PathLike[str], config: CollectConfig, shard: str = "collect-000",
            resume: bool = False, device: str = "cpu",
            on_progress: Callable[[Progress], None] | None = None,
            render_process: bool = True) -> CollectSummary:
    """Collect ``config.frames`` frames into shard ``shard`` of the dataset at ``out`` while
    training a teacher on them; ``resume`` continues an interrupted run of the same config.

    ``render_process`` renders in a child process, overlapped with physics and acting (the
    same pixels; False renders in this process, e.g. to profile or debug the renderer)."""
    torch_device = resolve_device(device)
    out = Path(out)
    path = shard_path(out, shard)
    folder = run_dir(out, shard)
    _check_output(out, path, folder, config, resume)
    if resume and (finished := _finished_run(folder, path, config)) is not None:
        log.info("%s already holds the %d frames asked for; nothing to do", path, finished.frames)
        return finished
    seed = shard_seed(config.seed, shard)
    env = TaskEnv(config.task, config.action_repeat, seed=seed, max_steps=config.max_steps)
    dr_config = dr_preset(config.dr, config.backgrounds)
    teacher_config = config.teacher_config(env.state_dim, env.action_dim)
    make_renderer = RenderProcess if render_process else DRRenderer
    with ExitStack() as stack:
        renderer = stack.enter_context(make_renderer(config.task, dr_config, config.image_size,
                                                     config.views, config.supersample))
        student = None
        if config.student:
            agent = load_acting_student(config, torch_device)
            # The student sees what evaluation shows it: its own image size and supersampling,
            # the run's DR drawn once per episode.
            own_view = stack.enter_context(DRRenderer(
                config.task, dataclasses.replace(dr_config, resample="episode"),
                agent.info.get("image_size") or config.image_size, views=1,
                supersample=agent.info.get("supersample") or 1))
            student = (agent, own_view)
        folder.mkdir(parents=True, exist_ok=True)
        if path.exists():
            writer = ShardWriter.resume(path)
        else:
            extra = {"collect": to_json(config), "teacher": to_json(teacher_config)}
            writer = ShardWriter.create(out, shard, simulated_spec(env, renderer, extra),
                                        pairs=config.pairs)
        with writer:
            run = Collector(out, path, folder, config, teacher_config, env, renderer, writer, seed,
                       torch_device, student)
            try:
                return run.loop(on_progress)
            finally:
                run.board.close()


def episode_pairs(renderer: FrameRenderer, episode: Episode) -> np.ndarray:
    """Every step's pair frames [T, K, H, W, 3] of a recorded ``episode``, drawn by the
    collection's own renderer, queued together and gathered once (the rule of
    :func:`twist_sim.rerender.pair_frames`, which rebuilds them from D)."""
    for t in range(len(episode)):
        renderer.submit(episode.physics[pair_instant(t)],
                        {k: v[t] for k, v in episode.dr.items()})
    return renderer.gather()


def _check_output(out: Path, path: Path, folder: Path, config: CollectConfig,
                  resume: bool) -> None:
    """Refuse, before anything is written, every output that would mix incompatible data."""
    check_output(out, CollectError)  # created once every input is known good
    if (out / "zarr.json").exists():
        raise CollectError(f"{str(out)!r} is a single shard; give the dataset folder above it")
    if any(out.glob("*.zarr")):
        spec = open_dataset(out).spec
        for name, have, want in (("task", spec.task, config.task),
                                 ("views", spec.views, config.views),
                                 ("image size", spec.image_height, config.image_size),
                                 ("supersample", spec.supersample, config.supersample),
                                 ("action repeat", spec.action_repeat, config.action_repeat),
                                 ("frame pairs", open_dataset(out).has_pairs, config.pairs)):
            if have != want:
                raise CollectError(f"{str(out)!r} holds a dataset with {name} {have!r}, but this "
                                   f"run asks for {want!r}; use another --out")
        # A D from before a change to the task's reward or dynamics reads as revision 1.
        have, want = spec.extra.get("task_revision", 1), task_spec(config.task).revision
        if have != want:
            raise CollectError(f"{str(out)!r} holds {spec.task} revision {have}, but this "
                               f"library's {spec.task} is revision {want} (its reward or "
                               "dynamics changed since); use another --out")
    if path.exists() and not resume:
        raise CollectError(f"shard {path.name!r} already exists in {str(out)!r}; pass --resume "
                           "to continue it, or --shard to add another")
    # compile is how, not what, the run computes: a resumed run may move to another device;
    # how often and how long the teacher is evaluated may change in a long run.
    extendable = ("frames", "learn_frames", "learn_until_return", "freeze_best", "frozen_noise",
                  "push_every", "push_steps", "student", "compile", "evaluation.every",
                  "evaluation.episodes")
    # The shard, not the config, marks an existing run here (checked above).
    if resume:
        _run_folder(folder).open(config, True, extendable,
                                 "--frames and --set " + ", ".join(extendable[1:]))


def _finished_run(folder: Path, path: Path, config: CollectConfig) -> CollectSummary | None:
    """The summary a finished run left in ``folder`` if resuming it with ``config`` would do
    nothing (the same config but for ``compile`` and ``frames`` no more than it collected,
    its shard holding the episodes it summed up): then no simulator, renderer or teacher
    starts only to find so."""
    record = _run_folder(folder).stored()
    if record is None or not (folder / "summary.json").exists() or not path.exists():
        return None
    done = json.loads((folder / "summary.json").read_text())
    before = record_section(record, "collect", CollectConfig)
    if (resume_conflicts(before, config, ("frames", "compile")) or config.frames > done["frames"]
            or ShardReader(path).n_episodes != done["episodes"]):
        return None
    return CollectSummary(**{**done, **{k: Path(done[k]) for k in ("shard", "run_dir", "teacher")}})


def _run_folder(folder: Path) -> RunFolder:
    return RunFolder(folder, "collect", CollectError, "a collector run")


class TeacherEvaluation:
    """The collector's evaluations of its teacher on states: episodes of nominal dynamics
    with its mode action (random actions before it first acts), every ``evaluation.every`` frames,
    beside doing nothing on the same episodes (deterministic: played once); ``eval.csv``, the
    learning curve and the best return so far."""

    def __init__(self, config: CollectConfig, seed: int, shard: str, folder: Path,
                 board: TensorBoardLog) -> None:
        self.config, self.seed, self.shard, self.folder, self.board = (config, seed, shard,
                                                                       folder, board)
        self.env = TaskEnv(config.task, config.action_repeat, seed=seed,
                           max_steps=config.max_steps)
        self.next_eval = config.evaluation.every
        self.evaluated_at = -1
        self.returns: list[float] = []
        self.best: float | None = None
        self.zero_action_return: float | None = None

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps of the evaluations (:meth:`restore` reads it back)."""
        return {"next_eval": self.next_eval, "evaluated_at": self.evaluated_at,
                "eval_returns": self.returns, "best_teacher_return": self.best}

    def restore(self, extra: Mapping[str, Any]) -> None:
        self.next_eval, self.evaluated_at = extra["next_eval"], extra["evaluated_at"]
        self.returns = extra.get("eval_returns", [])
        self.best = extra.get("best_teacher_return")

    @property
    def last(self) -> float | None:
        return self.returns[-1] if self.returns else None

    def run(self, teacher: Teacher, frames: int, device: torch.device, wall_s: float) -> float:
        """Evaluate ``teacher`` once ``frames`` are in D: the episodes' mean return, also
        appended to ``eval.csv`` and plotted."""
        c = self.config
        acting = frames >= c.prefill_frames
        returns = [self.episode(j, StateAgent(teacher, None, device) if acting else
                                random_policy(self.env.action_dim, j))
                   for j in range(c.evaluation.episodes)]
        floor = self._zero_action_return()
        self.returns.append(float(np.mean(returns)))
        self.evaluated_at = frames
        while self.next_eval <= frames:
            self.next_eval += c.evaluation.every
        row = {"frames": frames, "updates": int(teacher.step),
               "return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)),
               "episodes": len(returns), "wall_s": wall_s, "zero_action_return": floor}
        append_csv(self.folder / "eval.csv", row, tuple(row))
        self.board.scalar("eval/return", row["return_mean"], frames)
        plot = plot_learning_curves(
            {f"{self.shard} (seed {c.seed})": self.folder / "eval.csv"},
            self.folder / "learning-curve.png",
            f"{c.task}, {c.model} teacher on state, mode action", {"zero actions": floor})
        self.board.image("eval/learning-curve", plot, frames)
        log.info("eval at %d frames: return %.1f (zero actions: %.1f)", frames, self.returns[-1],
                 floor)
        return row["return_mean"]

    def _zero_action_return(self) -> float:
        if self.zero_action_return is None:
            zero = np.zeros(self.env.action_dim, np.float32)
            self.zero_action_return = float(np.mean(
                [self.episode(j, lambda step: zero)
                 for j in range(self.config.evaluation.episodes)]))
        return self.zero_action_return

    def episode(self, index: int, policy: Policy) -> float:
        """The return of evaluation episode ``index`` (nominal dynamics) of ``policy``."""
        step = self.env.reset(seed=derived_seed(self.seed, 1 << 30, index), dynamics=Dynamics())
        total = 0.0
        with single_threaded():
            while not step.is_last:
                step = self.env.step(policy(step))
                total += step.reward
        return total


class Collector:
    """The state of one collector run; :meth:`loop` drives it."""

    def __init__(self, out: Path, path: Path, folder: Path, config: CollectConfig,
                 teacher_config: TeacherConfig, env: TaskEnv, renderer: FrameRenderer,
                 writer: ShardWriter, seed: int, device: torch.device,
                 student: tuple[Agent, DRRenderer] | None = None) -> None:
        self.out, self.path, self.folder, self.config = out, path, folder, config
        self.student = student
        self.env, self.renderer, self.writer, self.seed, self.device = (env, renderer, writer,
                                                                        seed, device)
        self.dr_sampler = renderer.sampler(seed)
        self.seconds = dict.fromkeys(TIMED_PARTS, 0.0)
        self.replay: WindowSampler | None = None
        self.replay_state: dict | None = None
        self.next_snapshot = config.snapshot_every
        self.train_metrics: dict[str, float] = {}
        self.frozen_from: dict[str, Any] | None = None
        self.learned_until: int | None = None
        self.last_return: float | None = None
        self.board = TensorBoardLog(folder)
        self.evaluation = TeacherEvaluation(config, seed, path.name, folder, self.board)
        self._load_or_create_teacher(teacher_config)
        _run_folder(folder).write_config(config, teacher=teacher_config, shard=path.name,
                                         seed=seed)

    # -- state -------------------------------------------------------------------------------
    def _load_or_create_teacher(self, teacher_config: TeacherConfig) -> None:
        latest = _run_folder(self.folder).latest
        if latest.exists():
            self.teacher, checkpoint = load_teacher(latest, self.env.state_dim,
                                                    self.env.action_dim)
            if to_json(self.teacher.config) != to_json(teacher_config):
                raise CollectError(f"{str(latest)!r} was written for another teacher config")
            extra = checkpoint.extra
            torch.set_rng_state(torch.tensor(extra["torch_rng"], dtype=torch.uint8))
            self.replay_state = extra.get("replay_rng")
            self.next_snapshot = extra["next_snapshot"]
            self.evaluation.restore(extra)
            self.seconds.update(extra.get("seconds", {}))
            self.frozen_from = extra.get("frozen_from")
            self.learned_until = extra.get("learned_until")
            log.info("resumed the teacher at update %d from %s; D holds %d episodes (%d "
                     "frames)", int(self.teacher.step), latest, self.writer.n_episodes,
                     self.frames)
        else:
            torch.manual_seed(self.seed)
            self.teacher = Teacher(teacher_config)
        self.teacher.to_device(self.device)
        self.teacher.compile_update(compile_mode(self.config.compile, self.device))

    @property
    def schedule(self) -> CollectConfig:
        """The config whose ``learn_frames`` is where learning ends for this run: earlier than
        the config's once an evaluation reached ``learn_until_return``."""
        if self.learned_until is None:
            return self.config
        return dataclasses.replace(self.config, learn_frames=self.learned_until)

    @property
    def frames(self) -> int:
        shard = self.writer
        return (shard.n_steps - shard.n_episodes) * self.config.action_repeat

    # -- one iteration -----------------------------------------------------------------------
    def loop(self, on_progress: Callable[[Progress], None] | None) -> CollectSummary:
        c = self.config
        started, start_frames = time.perf_counter(), self.frames
        self._train()  # updates owed by episodes committed after the last checkpoint
        while self.frames < c.frames:
            self._freeze_best_if_due()
            episode_return = self._collect_episode()
            self._train()
            if self.frames >= self.evaluation.next_eval and self._changed_since_evaluation():
                self._evaluate()
            self._checkpoint()
            self._log_metrics(episode_return)
            if on_progress is not None:
                elapsed = max(time.perf_counter() - started, 1e-9)
                on_progress(Progress(self.frames, c.frames, self.writer.n_episodes,
                                     int(self.teacher.step), episode_return,
                                     self.evaluation.last,
                                     (self.frames - start_frames) / elapsed))
        if self.evaluation.evaluated_at != self.frames and self._changed_since_evaluation():
            self._evaluate()
        final = self._checkpoint(final=True)
        summary = CollectSummary(
            shard=self.path, run_dir=self.folder, teacher=final,
            episodes=self.writer.n_episodes, frames=self.frames, updates=int(self.teacher.step),
            last_return=self.last_return,
            best_eval_return=max(self.evaluation.returns) if self.evaluation.returns else None,
            last_eval_return=self.evaluation.last,
            zero_action_return=self.evaluation.zero_action_return,
            learned_until=self.learned_until,
            frozen_from=self.frozen_from,
            dataset_bytes=ShardReader(self.path).disk_bytes(),
            seconds={k: round(v, 2) for k, v in self.seconds.items()})
        (self.folder / "summary.json").write_text(json.dumps(summary.to_json(), indent=2))
        return summary

    def _collect_episode(self) -> float:
        c = self.config
        index, frames = self.writer.n_episodes, self.frames
        episode_seed = derived_seed(self.seed, index)
        frozen = self.schedule.acts_frozen(frames)
        if frames < c.prefill_frames:
            policy, name, step = random_policy(self.env.action_dim, episode_seed), "random", -1
        elif frozen and self.student is not None:
            agent, own_view = self.student
            policy = ImageAgent(agent).rendering(own_view, derived_seed(episode_seed, 8))
            name, step = "student", -1
        else:
            pushes = (RandomPushes(c.push_every, c.push_steps, self.env.action_dim,
                             derived_seed(episode_seed, 7)) if frozen and c.push_every else None)
            policy = StateAgent(self.teacher, None, self.device, explore=True,
                                noise=c.frozen_noise if frozen else 0.0, pushes=pushes)
            name, step = "teacher", int(self.teacher.step)
        with single_threaded():
            episode, info = record_episode(self.env, self.renderer, self.dr_sampler, policy,
                                           seed=episode_seed, policy_name=name,
                                           teacher_step=step, env_step=frames,
                                           timings=self.seconds)
        if c.pairs:
            tick = time.perf_counter()
            episode = dataclasses.replace(episode, pair_image=episode_pairs(self.renderer, episode))
            self.seconds["render"] += time.perf_counter() - tick
        tick = time.perf_counter()
        try:
            self.writer.append(episode, info)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise CollectError(
                    f"disk full while writing episode {index} to {str(self.path)!r}; the "
                    f"partial episode was dropped and the {index} committed episodes are "
                    "intact: free space and run again with --resume") from None
            raise CollectError(f"writing episode {index} to {str(self.path)!r} failed: "
                               f"{exc}") from None
        self.seconds["write"] += time.perf_counter() - tick
        self.last_return = float(episode.reward.sum())
        return self.last_return

    def _freeze_best_if_due(self) -> None:
        """With ``freeze_best``, once learning is over: evaluate the last teacher if it has
        not been, then let ``best.pt`` act from here on (a resumed run repeats this harmlessly
        until its first frozen episode is checkpointed)."""
        c = self.config
        if (not c.freeze_best or self.frozen_from is not None
                or not self.schedule.acts_frozen(self.frames)):
            return
        if self._changed_since_evaluation():
            self._evaluate()
        teacher, checkpoint = load_teacher(self.folder / BEST_TEACHER, self.env.state_dim,
                                           self.env.action_dim)
        self.teacher = teacher.to_device(self.device)  # frozen: it only acts from here on
        self.frozen_from = {"frames": checkpoint.counters["frames"],
                            "updates": int(teacher.step),
                            "eval_return": checkpoint.extra["eval_return"]}
        log.info("learning over at %d frames: the teacher of %d frames (evaluation return "
                 "%.1f) acts frozen from here on", self.frames, self.frozen_from["frames"],
                 self.frozen_from["eval_return"])

    def _train(self) -> None:
        c = self.config
        due = self.schedule.updates_due(self.frames)
        # A best teacher put in place has fewer updates than are due; it is frozen all the same.
        if int(self.teacher.step) >= due or self.frozen_from is not None:
            return
        tick = time.perf_counter()
        if self.replay is None:
            self.replay = WindowSampler(self.path, SamplerConfig(
                length=c.batch_length, batch_size=c.batch_size, keys=REPLAY_KEYS,
                cache_bytes=0, seed=self.seed))
            if self.replay_state is not None:
                self.replay.rng_state = self.replay_state
        else:
            self.replay.refresh()
        metrics: dict[str, list[float]] = {}
        while int(self.teacher.step) < due:
            batch = {k: torch.as_tensor(v, device=self.device)
                     for k, v in self.replay.batch().items() if k in REPLAY_KEYS}
            behaviour = int(self.teacher.step) >= c.behaviour_from
            for k, v in self.teacher.train_step(batch, behaviour).items():
                metrics.setdefault(k, []).append(v)
        self.train_metrics = {k: float(np.mean(v)) for k, v in metrics.items()}
        self.seconds["learn"] += time.perf_counter() - tick

    def _changed_since_evaluation(self) -> bool:
        """Whether the teacher may have changed since its last evaluation: not once it froze
        and was evaluated (at the first evaluation due after its last update)."""
        return self.schedule.learns_at(self.evaluation.evaluated_at + 1)

    def _evaluate(self) -> None:
        c = self.config
        tick = time.perf_counter()
        mean = self.evaluation.run(self.teacher, self.frames, self.device,
                                   round(sum(self.seconds.values()), 1))
        self.seconds["eval"] += time.perf_counter() - tick
        teacher_acted = self.frames >= c.prefill_frames
        if teacher_acted and (self.evaluation.best is None or mean > self.evaluation.best):
            self._save_best(mean)
        if (c.learn_until_return is not None and mean >= c.learn_until_return
                and self.frames > c.prefill_frames and self.schedule.learns_at(self.frames + 1)):
            self.learned_until = self.frames
            log.info("learning over at %d frames: the evaluation return %.1f reached "
                     "learn_until_return %.1f", self.frames, mean, c.learn_until_return)

    def _save_best(self, eval_return: float) -> None:
        """Keep the teacher of the best evaluation so far as ``best.pt``. Its return is saved
        in the run's state (``latest.pt``), so a resumed run compares against it; an
        evaluation repeated after a crash may replace it with the repeat's teacher."""
        tick = time.perf_counter()
        self.evaluation.best = eval_return
        save_teacher(self.folder / BEST_TEACHER, self.teacher, self._counters(),
                     {**self._provenance(), "eval_return": eval_return})
        self.seconds["checkpoint"] += time.perf_counter() - tick

    def _provenance(self) -> dict[str, Any]:
        # A teacher checkpoint names the task and action repeat it acts at, so that
        # `twist-eval --agent oracle=teacher.pt` needs neither --task nor a student beside it,
        # and never acts at another repeat than it learnt at.
        return {"collect": to_json(self.config)}

    def _counters(self) -> dict[str, int]:
        return {"frames": self.frames, "episodes": self.writer.n_episodes}

    def _checkpoint(self, final: bool = False) -> Path:
        tick = time.perf_counter()
        # A frozen teacher's snapshots would all be copies of teacher.pt.
        snapshot = self.next_snapshot <= self.frames and self.schedule.learns_at(self.frames)
        while self.next_snapshot <= self.frames:
            self.next_snapshot += self.config.snapshot_every
        extra = {**self._provenance(), "torch_rng": torch.get_rng_state().tolist(),
                 "replay_rng": self.replay.rng_state if self.replay is not None
                 else self.replay_state,
                 **self.evaluation.state(), "next_snapshot": self.next_snapshot,
                 "seconds": self.seconds,
                 "frozen_from": self.frozen_from, "learned_until": self.learned_until}
        counters = self._counters()
        latest = save_teacher(_run_folder(self.folder).latest, self.teacher, counters, extra)
        if snapshot:
            save_teacher(self.folder / f"teacher-{self.frames:08d}.pt", self.teacher, counters,
                         extra)
        if final:
            latest = save_teacher(self.folder / FINAL_TEACHER, self.teacher, counters, extra)
        self.seconds["checkpoint"] += time.perf_counter() - tick
        return latest

    def _log_metrics(self, episode_return: float) -> None:
        row = {**self._counters(), "updates": int(self.teacher.step), "return": episode_return,
               "wall_s": round(sum(self.seconds.values()), 2),
               **{f"seconds_{k}": round(v, 3) for k, v in self.seconds.items()},
               **self.train_metrics}
        append_csv(self.folder / "metrics.csv", row, METRIC_COLUMNS)
        self.board.scalar("train/return", episode_return, self.frames)
        for key, value in self.train_metrics.items():
            self.board.scalar(f"teacher/{key}", value, self.frames)
        self.train_metrics = {}


def stored_config(out: str | os.PathLike[str], shard: str) -> CollectConfig:
    """The collect config a run in ``out`` was started with."""
    data = json.loads(_run_folder(run_dir(out, shard)).config_file.read_text())
    return from_json(CollectConfig, CollectConfig.record_section(data))
