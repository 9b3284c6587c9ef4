"""The ``twist-distil`` stage: offline teacher -> student distillation from a matching dataset,
with the objective of :mod:`twist_models.distillation`.

Never touches a simulator: it reads D and a frozen teacher checkpoint and writes a run folder
``<out>/``: ``config.json``, ``metrics.csv`` (training terms, updates/s, data-wait share),
``heldout.csv`` and its plot ``latent-agreement.png``, ``latest.pt`` (resume point),
``student-<updates>.pt`` snapshots each with its deployable ``agent-<updates>.pt`` (and
``agent-00000000.pt`` after a first stage on single frames), the final
``student.pt``, the deployable ``agent.pt`` (:class:`twist_models.agent.Agent`) and
``summary.json``.

* **Held-out agreement** is measured on a fixed batch of windows from the held-out episodes
  (every ``schedule.holdout_every``-th episode, never trained on), with fixed draws, so its curve
  moves only because the student changes.
* **Resume** restores the student, its optimiser and the torch RNG from ``latest.pt``; the
  window stream restarts from a seed derived from (seed, update), so a resumed run is
  reproducible but not bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.profiler import record_function
from torch.utils.data import DataLoader

from twist_data.errors import SamplerConfigError, TwistError
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.sampler import (
    ResidentWindows,
    WindowDataset,
    WindowSampler,
    heldout_episodes,
    image_problem,
    resident_bytes,
    resident_images,
    window_problem,
)
from twist_data.schema import PAIR_IMAGE
from twist_data.seeding import derived_seed
from twist_data.staging import removed_on_failure, require_memory
from twist_models.agent import Agent
from twist_models.checkpoint import (
    move_optimiser_state,
    read_checkpoint,
    restore,
    save_checkpoint,
)
from twist_models.config import (
    StudentConfig,
    from_json,
    student_preset,
    to_json,
)
from twist_models.device import compile_mode, precision_autocast, resolve_device
from twist_models.distillation import (
    KEYS,
    DistilConfig,
    Distillation,
    compiled_objective,
    frame_loss,
    latent_agreement,
    split_context,
)
from twist_models.frame_targets import (
    FrameBatches,
    FrameRows,
    TeacherTargets,
    frame_terms,
    teacher_latent_before,
    teacher_targets,
)
from twist_models.student import (
    Student,
    copy_teacher_dynamics,
    freeze_dynamics,
)
from twist_models.teacher import Teacher, find_teacher, load_teacher
from twist_pipeline import readout_recipe
from twist_pipeline.curves import plot_agreement
from twist_pipeline.runlog import (
    RunFolder,
    TensorBoardLog,
    append_csv,
    record_section,
    resume_conflicts,
)

log = logging.getLogger(__name__)

TERMS = ("h", "prior_kl", "post_kl", "imagined_h", "imagined_prior_kl", "action",
         "frame_post_kl", "state")
METRIC_COLUMNS = ("updates", "wall_s", "updates_per_s", "data_wait_share", "loss", *TERMS,
                  "grad_norm")
HELDOUT_COLUMNS = ("updates", "frame_updates", "h_mse", "h_explained", "post_kl", "prior_kl",
                   "imagined_h_mse", "frame_post_kl", "frame_action_rmse", "frame_action_corr",
                   "read_error", "read_error_typical")
FRAME_METRIC_COLUMNS = ("frame_updates", "wall_s", "updates_per_s", "loss", "frame_post_kl",
                        "state", "readout", "grad_norm")
#: Evaluations between redrawn agreement plots: on the 2-core CPU a redraw cost about what the
#: evaluation itself does (0.8 s each under a profiler), and the `quick` read-out stage
#: evaluates 90 times.
PLOT_EVERY_EVALUATIONS = 10
FINAL_STUDENT = "student.pt"
AGENT = "agent.pt"


class DistilError(TwistError):
    """Distillation cannot start or continue (inputs, output folder, resume state)."""


# -- the run ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Progress:
    """Reported every ``schedule.eval_every`` updates."""

    updates: int
    total: int
    updates_per_second: float
    data_wait_share: float
    loss: float
    heldout_h_mse: float


@dataclass
class DistilSummary:
    """What a distillation run did."""

    out: Path
    student: Path
    agent: Path
    teacher: Path
    updates: int
    seconds: float
    """Wall time of the run (every invocation of a resumed run), evaluation included."""
    updates_per_second: float
    """Updates per second of training time (data wait + update) since this invocation started."""
    data_wait_share: float
    """Share of this invocation's training time spent waiting for data."""
    heldout_first: dict[str, float]
    heldout_last: dict[str, float]
    stopped: str = "done"
    """``done`` (every update the config asks for) or ``time limit`` (resumable)."""
    frame_updates: int = 0
    """Single-frame updates of a first stage (:attr:`DistilConfig.frame_steps`)."""
    frame_updates_per_second: float = 0.0
    """Single-frame updates per second of training time since this invocation started (0
    where it ran none)."""

    def to_json(self) -> dict[str, Any]:
        return {k: str(v) if isinstance(v, Path) else v
                for k, v in dataclasses.asdict(self).items()}


def distil(dataset: str | os.PathLike[str], out: str | os.PathLike[str], config: DistilConfig,
           teacher: str | os.PathLike[str] | None = None, resume: bool = False,
           device: str = "cpu", on_progress: Callable[[Progress], None] | None = None,
           time_limit: float | None = None) -> DistilSummary:
    """Distil a student from the matching dataset ``dataset`` and a frozen ``teacher``
    checkpoint (default: the dataset's final teacher) into the run folder ``out``.

    ``time_limit``: seconds this call may train; past them the run stops after the update in
    progress and writes what a finished run writes (the metrics and held-out agreement of
    its last updates, ``latest.pt``, ``student.pt``, ``agent.pt``, ``summary.json`` with
    ``stopped`` = ``"time limit"``), so that a short slot ends with a deployable student and
    ``--resume`` continues to ``steps``."""
    if time_limit is not None and not time_limit > 0:
        raise DistilError(f"the time limit must be a positive number of seconds, got {time_limit}")
    torch_device = resolve_device(device)
    out, dataset_path = Path(out), Path(dataset)
    if resume and (finished := _finished_run(out, dataset_path, teacher, config)) is not None:
        log.info("%s already holds the %d updates asked for; nothing to do", out,
                 finished.updates)
        return finished
    data = _open_inputs(dataset_path, config)
    teacher_path = Path(teacher) if teacher is not None else find_teacher(dataset_path)
    teacher_model, _ = load_teacher(teacher_path, data.spec.state_dim, data.spec.action_dim)
    rows = readout_recipe.training_rows(data, config) if config.readout else None
    readout = (readout_recipe.pair_readout(data, rows, teacher_model,
                                           readout_recipe.mirror_mode(config, data),
                                           config.readout_stage)
               if rows is not None else None)
    student_config = student_preset(config.student, teacher_model.config, data.spec.image_height,
                                    config.frames, config.encoder_norm,
                                    state_head=config.weights.state > 0, readout=readout)
    spec = data.spec
    require_memory(config.batch_size * (config.length + config.window_context)
                   * int(np.prod(spec.image_shape)) * 4,
                   f"a batch of {config.batch_size} windows of {config.length} steps (its "
                   "images as float32 alone)")
    rank, world = _rank_and_world()
    with removed_on_failure(out):  # a refused set-up leaves no config, log or plot behind
        student_config = _check_output(out, config, student_config, resume)
        run = Distiller(dataset_path, data, out, config, teacher_model, teacher_path,
                   student_config, torch_device, rank, world, rows)
    try:
        return run.loop(on_progress, None if time_limit is None
                        else time.perf_counter() + time_limit)
    finally:
        if run.board is not None:
            run.board.close()


def _open_inputs(path: Path, config: DistilConfig) -> MatchingDataset:
    if not path.exists():
        raise DistilError(f"dataset {str(path)!r} does not exist")
    data = open_dataset(path)
    data.require_images("twist-distil")
    spec = data.spec
    if spec.views < 1 or spec.image_height < 1:
        raise DistilError(f"dataset {str(path)!r} has no images (views={spec.views}); the "
                          "student learns from images")
    problem = window_problem(data, config.length, config.view)
    if problem is not None:
        raise DistilError(f"{str(path)!r}: {problem}")
    problem = image_problem(data)
    if problem is not None:
        raise DistilError(f"dataset {str(path)!r}: {problem}; the student learns from images")
    return data


def _run_folder(out: Path) -> RunFolder:
    return RunFolder(out, "distil", DistilError, "a distillation run")


def _finished_run(out: Path, dataset: Path, teacher: str | os.PathLike[str] | None,
                  config: DistilConfig) -> DistilSummary | None:
    """The summary a finished run left in ``out`` if resuming it would do nothing: it did every
    update of the same config (``compute.compile`` aside) on the same D and teacher. Returned
    as it was written, without reading D or the teacher (nor rewriting the summary)."""
    record = _run_folder(out).stored()
    if record is None or not (out / "summary.json").exists():
        return None
    done = json.loads((out / "summary.json").read_text())
    same_inputs = (Path(record.get("dataset", "")) == dataset
                   and (teacher is None or Path(record.get("teacher", "")) == Path(teacher)))
    before = record_section(record, "distil", DistilConfig)
    if (done.get("stopped") != "done" or not same_inputs
            or resume_conflicts(before, config, ("compute.compile",))):
        return None
    paths = ("out", "student", "agent", "teacher")
    return DistilSummary(**{**done, **{k: Path(done[k]) for k in paths}})


def _check_output(out: Path, config: DistilConfig, student: StudentConfig, resume: bool
                  ) -> StudentConfig:
    """Open the run folder; on resume, refuse a student of other sizes and return the stored
    student's config (its read-out gains as first measured), else ``student``."""
    folder = _run_folder(out)
    before = folder.stored() if resume else None
    stored = from_json(StudentConfig, before["student"]) if before and "student" in before else None
    changed = (["the student's sizes differ"] if before is not None
               and (stored is None or not same_student(stored, student)) else [])
    # frame_steps may grow on resume: the first stage's loss still falls where a preset stops
    # it, and continuing costs only the added updates (docs/findings.md).
    folder.open(config, resume, ("steps", "frame_steps", "compute.compile"),
                "--steps and --set frame_steps, compute.compile",
                also=changed)
    return stored if stored is not None else student


def same_student(a: StudentConfig, b: StudentConfig) -> bool:
    """Whether two student configs are the same but for the read-out's gains in their last
    digits: measured on D in float64, they change with BLAS's thread count (a run begun on
    one thread and resumed on two measured 24.992443279866706 and 24.99244327986691)."""
    if a.readout is None or b.readout is None:
        return a == b
    close = (len(a.readout.gains) == len(b.readout.gains)
             and np.allclose(a.readout.gains, b.readout.gains, rtol=1e-9, atol=0.0))
    return close and dataclasses.replace(
        a, readout=dataclasses.replace(a.readout, gains=b.readout.gains)) == b


def _rank_and_world() -> tuple[int, int]:
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _to_device(batch: Mapping[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(batch[k]).to(device, non_blocking=True) for k in (*KEYS, PAIR_IMAGE)
            if k in batch}


class DistilInputs:
    """What a distillation run reads: the teacher's targets on D's training steps (recipes
    that need them), D's held-out windows, its training windows and single frames, decoded
    or from a copy of D on the device (``compute.resident_data``)."""

    def __init__(self, dataset_path: Path, data: MatchingDataset, config: DistilConfig,
                 teacher: Teacher, device: torch.device, rank: int, world: int,
                 pairs: bool) -> None:
        self.dataset_path, self.data, self.config, self.teacher = dataset_path, data, config, teacher
        self.device, self.rank, self.world, self.pairs = device, rank, world, pairs
        self.targets: TeacherTargets | None = None
        if config.needs_teacher_targets:
            train = np.flatnonzero(~heldout_episodes(data.n_episodes,
                                                     config.schedule.holdout_every))
            self.targets = teacher_targets(teacher, data, train, seed=derived_seed(config.seed, 6))

    def heldout_batch(self) -> dict[str, torch.Tensor]:
        """The held-out windows every evaluation reads (every ``holdout_every``-th episode)."""
        c = self.config
        try:
            sampler = WindowSampler(self.data, c.sampler("heldout", derived_seed(c.seed, 1),
                                                         c.schedule.heldout_windows, self.pairs))
        except SamplerConfigError as exc:  # damage is its own error, not "no windows"
            raise DistilError(f"no held-out windows (every {c.schedule.holdout_every}th episode is held "
                              f"out): {exc}; lower schedule.holdout_every or the window length") from None
        return split_context(_to_device(sampler.batch(), self.device), c.window_context)

    def windows(self, updates: int) -> Iterator[dict[str, torch.Tensor]]:
        """Training windows; a resumed run draws from a stream seeded by its update count."""
        c = self.config
        sampler = c.sampler("train", derived_seed(c.seed, 3, updates), pairs=self.pairs)
        try:
            if self.resident(sampler.keys):
                return iter(ResidentWindows(self.data, sampler, self.device, self.rank,
                                            self.world))
            windows = WindowDataset(self.dataset_path, sampler)
            loader = DataLoader(windows, batch_size=None, num_workers=c.compute.workers,
                                pin_memory=self.device.type == "cuda",
                                persistent_workers=c.compute.workers > 0,
                                prefetch_factor=4 if c.compute.workers else None)
        except SamplerConfigError as exc:
            raise DistilError(f"no training windows: {exc}") from None
        return iter(loader)

    def window_batch(self, windows: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """A training batch of ``windows`` on the device, split at the context, with the
        teacher's latent before each window where it starts the student's."""
        context = self.config.window_context
        batch = split_context(_to_device(windows, self.device), context)
        if self.config.window_start == "teacher":
            starts = torch.as_tensor(windows["start"]).cpu().numpy() + context
            start = teacher_latent_before(self.teacher, self.targets, starts)
            batch.update(start_deter=start["deter"], start_stoch=start["stoch"])
        return batch

    def frame_batches(self, rows: FrameRows, frame_updates: int) -> FrameBatches:
        """The first stage's batches of single frames of ``rows``, seeded by the updates
        done."""
        c = self.config
        resident = self.resident(("image", PAIR_IMAGE) if self.pairs else ("image",))
        images = resident_images(self.data, self.device) if resident else None
        pair_images = (resident_images(self.data, self.device, PAIR_IMAGE)
                       if resident and self.pairs else None)
        return FrameBatches(self.data, rows, c.frame_batch, c.frames, c.view,
                            seed=derived_seed(c.seed, 7, frame_updates, self.rank),
                            images=images, pairs=self.pairs, pair_images=pair_images)

    def resident(self, keys: tuple[str, ...]) -> bool:
        """Whether training windows or frames come from a copy of D on the device
        (``resident_data``)."""
        choice = self.config.compute.resident_data
        if choice != "auto":
            return choice == "on"
        if self.device.type != "cuda":
            return False
        free, _ = torch.cuda.mem_get_info(self.device)
        need = resident_bytes(self.data, keys)
        log.info("D's copy needs %.2f GiB on %s, %.2f GiB free", need / 2**30, self.device,
                 free / 2**30)
        return need <= free / 2


class _Meter:
    """A stage's training time and metric sums: per evaluation interval and for the run
    (evaluation and checkpoints excluded, so updates/s is the steady-state rate)."""

    def __init__(self) -> None:
        self.run = {"train": 0.0, "wait": 0.0, "done": 0}
        self.wall = time.perf_counter()
        self.synced = 0.0
        self.restart()

    def restart(self) -> None:
        self.interval = {"train": 0.0, "wait": 0.0, "done": 0}
        self.sums: dict[str, torch.Tensor] = {}

    def add(self, spent: float, waited: float) -> None:
        for record in (self.interval, self.run):
            record["train"] += spent
            record["wait"] += waited
            record["done"] += 1

    def means(self) -> dict[str, float]:
        """The interval's mean of each metric; the wait for the device to finish counts as
        training time."""
        tick = time.perf_counter()
        means = {k: float(v) / self.interval["done"] for k, v in self.sums.items()}
        self.synced = time.perf_counter() - tick
        for record in (self.interval, self.run):
            record["train"] += self.synced
        return means


def _optimiser(student: Student, config: DistilConfig) -> torch.optim.Optimizer:
    o = config.optim
    return torch.optim.AdamW(student.parameters(), config.lr, eps=o.eps,
                             weight_decay=o.weight_decay)


def _start_student(config: DistilConfig, student_config: StudentConfig, teacher: Teacher,
                   rows: FrameRows | None, latest: Path, rank: int
                   ) -> tuple[Student, torch.optim.Optimizer, dict[str, Any]]:
    """The run's student and optimiser, restored from ``latest`` where it exists (its update
    counters, seconds, first held-out figures and torch's stream as recorded), else new (a
    read-out student from the teacher's own filter; ``copy_dynamics``: the teacher's RSSM)."""
    torch.manual_seed(config.seed)
    student = Student(student_config)
    optimiser = _optimiser(student, config)
    counters: dict[str, Any] = {"updates": 0, "frame_updates": 0, "seconds": 0.0,
                                "heldout_first": {}}
    if latest.exists():
        checkpoint = read_checkpoint(latest, kind="student")
        restore(checkpoint, student, student_config, {"student": optimiser})
        counters = {"updates": checkpoint.counters["updates"],
                    "frame_updates": checkpoint.counters.get("frame_updates", 0),
                    "seconds": float(checkpoint.extra.get("seconds", 0.0)),
                    "heldout_first": checkpoint.extra.get("heldout_first", {})}
        torch.set_rng_state(torch.tensor(checkpoint.extra["torch_rng"], dtype=torch.uint8))
        log.info("resumed the student at %d frame updates and %d window updates from %s",
                 counters["frame_updates"], counters["updates"], latest)
        if counters["updates"] > 0 and counters["frame_updates"] < config.frame_steps:
            raise DistilError(
                f"the run's first stage ended at {counters['frame_updates']} frame updates and "
                f"{counters['updates']} updates on windows followed; frame_steps="
                f"{config.frame_steps} cannot extend it now")
    else:
        if student.perception.readout is not None:
            readout_recipe.start(student, teacher, rows, student_config)
        elif config.copy_dynamics:
            copy_teacher_dynamics(student, teacher.world_model.rssm)
        # Ranks start from one student but draw their own latent samples and noise.
        torch.manual_seed(derived_seed(config.seed, 5, rank))
    if student.perception.readout is not None and config.readout_stage.units == "teacher":
        readout_recipe.weigh_by_teacher(student.perception.readout, rows, config.seed)
    if config.freeze_dynamics:
        freeze_dynamics(student)
    return student, optimiser, counters


class Distiller:
    """State of one distillation run; :meth:`loop` drives it."""

    def __init__(self, dataset_path: Path, data: MatchingDataset, out: Path,
                 config: DistilConfig, teacher: Teacher, teacher_path: Path,
                 student_config: StudentConfig, device: torch.device, rank: int,
                 world: int, rows: FrameRows | None = None) -> None:
        self.dataset_path, self.data, self.out, self.config = dataset_path, data, out, config
        self.teacher_path, self.device, self.rank, self.world = teacher_path, device, rank, world
        self.teacher = teacher.to_device(device).eval().requires_grad_(False)
        self.writes = rank == 0
        self.deadline: float | None = None  # set by loop()
        self.run_folder = _run_folder(out)
        self.student, self.optimiser, counters = _start_student(
            config, student_config, self.teacher, rows, self.run_folder.latest, rank)
        self.updates, self.frame_updates = counters["updates"], counters["frame_updates"]
        self.seconds, self.heldout_first = counters["seconds"], counters["heldout_first"]
        self.student.to(device)
        self._frame_timing = [0, 0.0]  # this invocation's single-frame updates, training seconds
        move_optimiser_state(self.optimiser, device)
        # Whether the student reads frame pairs (a read-out's moving velocities).
        pairs = bool(student_config.readout is not None and student_config.readout.moving)
        self.inputs = DistilInputs(dataset_path, data, config, self.teacher, device, rank, world,
                                   pairs)
        targets = self.inputs.targets
        # What the first stage draws frames from: the teacher's targets, or for a read-out
        # student the states alone, of D's typical frames (``readout_stage``).
        self.rows = targets if targets is not None else rows
        if self.student.perception.readout is not None:
            self.rows = readout_recipe.stage_rows(self.student.perception.readout, self.rows,
                                                  config.readout_stage)
        self.objective: nn.Module = Distillation(
            self.student, self.teacher, config,
            targets.scale if targets is not None else 1.0)
        if world > 1:
            self.objective = nn.parallel.DistributedDataParallel(
                self.objective, device_ids=[device.index] if device.type == "cuda" else None)
        # A whole graph is for training only: evaluation runs other shapes and would recompile.
        self.compiled_mode = compile_mode("on" if config.compute.compile else "off", device)
        self.train_objective: Callable[..., Any] = compiled_objective(self.objective,
                                                                      self.compiled_mode)
        self.heldout = self.inputs.heldout_batch()
        self.heldout_last: dict[str, float] = {}
        self.board = TensorBoardLog(out) if self.writes else None
        if self.writes:
            _run_folder(out).write_config(config, student=student_config, teacher=teacher_path,
                                          dataset=dataset_path, world_size=world)

    @property
    def progress(self) -> int:
        """Updates so far, single-frame and on windows: TensorBoard's step and the plot's x."""
        return self.frame_updates + self.updates

    def evaluate(self, plot: bool = True) -> dict[str, float]:
        """Held-out agreement, appended to ``heldout.csv`` and TensorBoard; ``plot`` redraws
        ``latent-agreement.png`` from the whole table as well."""
        self.student.eval()
        metrics = latent_agreement(self.student, self.teacher, self.heldout, self.config,
                                   derived_seed(self.config.seed, 4))
        self.student.train()
        if not self.heldout_first:
            self.heldout_first = metrics
        self.heldout_last = metrics
        if self.writes:
            append_csv(self.out / "heldout.csv", {"updates": self.updates,
                                                  "frame_updates": self.frame_updates, **metrics},
                       HELDOUT_COLUMNS)
            for key, value in metrics.items():
                self.board.scalar(f"heldout/{key}", value, self.progress)
            if plot:
                path = plot_agreement(self.out / "heldout.csv", self.out / "latent-agreement.png")
                self.board.image("heldout/latent-agreement", path, self.progress)
        return metrics

    def loop(self, on_progress: Callable[[Progress], None] | None,
             deadline: float | None = None) -> DistilSummary:
        """Train to the config's updates, or until ``deadline`` (``time.perf_counter``)."""
        c = self.config
        self.deadline = deadline
        if self.updates == 0 and not (self.out / "heldout.csv").exists():
            self.evaluate(plot=False)  # a plot of one point; each stage's last redraws it
        if self.frame_updates < c.frame_steps and self.updates == 0:
            self.frame_stage(on_progress)
            if self.frame_updates == c.frame_steps:
                # The first stage's student, deployable: the ablation without Eq. 3/4 after it.
                self._bundle(self.out / f"agent-{0:08d}.pt")
        first_stage_done = self.frame_updates >= c.frame_steps
        if (first_stage_done and c.frame_steps and self.updates == 0 and self.updates < c.steps
                and c.stage_optimiser == "reset"):
            self.optimiser = _optimiser(self.student, c)
        windows = (self.inputs.windows(self.updates) if self.updates < c.steps and first_stage_done
                   else iter(()))
        params = list(self.student.parameters())
        meter = _Meter()
        while self.updates < c.steps and first_stage_done and not self._out_of_time():
            tick = time.perf_counter()
            batch = self.inputs.window_batch(next(windows))
            waited = time.perf_counter() - tick
            if self.compiled_mode == "reduce-overhead":
                torch.compiler.cudagraph_mark_step_begin()
            loss, terms = self.train_objective(batch)
            self._step("window", loss, terms, params, meter.sums)
            meter.add(time.perf_counter() - tick, waited)
            self.updates += 1
            if (self.updates % c.schedule.eval_every == 0 or self.updates == c.steps
                    or self._out_of_time()):
                row = self._report(meter, "updates", self.updates, c.steps,
                                   c.schedule.eval_every, on_progress)
                if self.writes:
                    append_csv(self.out / "metrics.csv", row, METRIC_COLUMNS)
                    for key in (*TERMS, "loss"):
                        if key in row:
                            self.board.scalar(f"train/{key}", row[key], self.progress)
            if (self.updates % c.schedule.checkpoint_every == 0 or self.updates == c.steps
                    or self._out_of_time()):
                self._checkpoint(self.run_folder.latest)
            if self.updates % c.schedule.snapshot_every == 0:
                self._snapshot()
        self.seconds += time.perf_counter() - meter.wall
        stopped_early = self.updates < c.steps or not first_stage_done
        if stopped_early and self.updates and self.updates % c.schedule.snapshot_every:
            self._snapshot()  # where a time limit stopped it is a point of its curve too
        student = self._checkpoint(self.out / FINAL_STUDENT)
        agent = self._bundle(self.out / AGENT)
        run = meter.run
        summary = DistilSummary(
            out=self.out, student=student, agent=agent, teacher=self.teacher_path,
            updates=self.updates, seconds=round(self.seconds, 2),
            updates_per_second=round(run["done"] / run["train"], 3) if run["done"] else 0.0,
            data_wait_share=round(run["wait"] / run["train"], 4) if run["done"] else 0.0,
            heldout_first=self.heldout_first, heldout_last=self.heldout_last,
            stopped="time limit" if stopped_early else "done",
            frame_updates=self.frame_updates,
            frame_updates_per_second=(round(self._frame_timing[0] / self._frame_timing[1], 3)
                                      if self._frame_timing[0] else 0.0))
        if summary.stopped != "done":
            log.info("stopped at the time limit after %d single-frame and %d window updates; "
                     "--resume continues", self.frame_updates, self.updates)
        if self.writes:
            (self.out / "summary.json").write_text(json.dumps(summary.to_json(), indent=2))
        return summary

    def frame_stage(self, on_progress: Callable[[Progress], None] | None) -> None:
        """The first stage: the per-frame terms alone on single training frames, for
        ``frame_steps`` updates; resumable at its evaluation points."""
        c = self.config
        batches = self.inputs.frame_batches(self.rows, self.frame_updates)
        params = [p for p in self.student.parameters() if p.requires_grad]
        flips = torch.Generator().manual_seed(derived_seed(c.seed, 9, self.frame_updates,
                                                           self.rank))
        mirror = (torch.tensor(readout_recipe.task_mirror(self.data), device=self.device)
                  if readout_recipe.mirror_mode(c, self.data) == "augment" else None)
        meter = _Meter()
        log.info("frame stage: %d of %d updates of %d frames to go", c.frame_steps - self.frame_updates,
                 c.frame_steps, c.frame_batch)
        while self.frame_updates < c.frame_steps and not self._out_of_time():
            tick = time.perf_counter()
            # Named ranges for a profiler (benchmarks/readout_profile.py); ~1 us when none runs.
            with record_function("frame/data"):
                batch = {k: v.to(self.device, non_blocking=True) for k, v in batches.batch().items()}
                if mirror is not None:  # each frame mirrored with probability 1/2, with its state
                    flip = (torch.rand(len(batch["state"]), generator=flips) < 0.5).to(self.device)
                    batch["image"][flip] = batch["image"][flip].flip(-2)
                    batch["state"][flip] = batch["state"][flip] * mirror
                    if "pair" in batch:
                        batch["pair"][flip] = batch["pair"][flip].flip(-2)
            with record_function("frame/forward"):
                loss, terms = self._frame_loss(batch)
            self._step("frame", loss, terms, params, meter.sums)
            meter.add(time.perf_counter() - tick, 0.0)
            self.frame_updates += 1
            if (self.frame_updates % c.schedule.frame_eval_every == 0
                    or self.frame_updates == c.frame_steps or self._out_of_time()):
                done, spent = meter.interval["done"], meter.interval["train"]
                row = self._report(meter, "frame_updates", self.frame_updates, c.frame_steps,
                                   c.schedule.frame_eval_every, on_progress)
                if self.writes:
                    append_csv(self.out / "frame-metrics.csv", row, FRAME_METRIC_COLUMNS)
                self._frame_timing = [self._frame_timing[0] + done,
                                      self._frame_timing[1] + spent + meter.synced]
                self._checkpoint(self.run_folder.latest)
        self.seconds += time.perf_counter() - meter.wall

    def _frame_loss(self, batch: Mapping[str, torch.Tensor]
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The first stage's loss on a batch of single frames and its terms."""
        c = self.config
        with precision_autocast(c.compute.precision, self.device):  # most recent frame first:
            embed = self.student.perception.encoder(batch["image"]).flatten(1).float()
            motion = (self.student.perception.motion_features(batch["pair"],
                                                              batch["image"][:, 0]).float()
                      if "pair" in batch else None)
        if self.student.perception.readout is not None:
            terms = {"readout": self.student.perception.readout.loss(
                embed, batch["state"], c.readout_stage.huber_delta, motion)}
            return terms["readout"], terms
        terms = frame_terms(self.student, self.teacher, embed, batch["deter"], batch["state"],
                            batch["sensitivity"])
        return frame_loss(terms, c), terms

    def _step(self, stage: str, loss: torch.Tensor, terms: Mapping[str, torch.Tensor],
              params: list[nn.Parameter], sums: dict[str, torch.Tensor]) -> None:
        """One optimiser step of ``stage`` (``frame`` or ``window``) on ``loss``, its terms
        and gradient norm summed into ``sums`` on the device: a read-back per update would
        stall a GPU's queue."""
        with record_function(f"{stage}/backward"):
            self.optimiser.zero_grad(set_to_none=True)
            loss.backward()
            if stage == "frame" and self.world > 1:  # outside DistributedDataParallel
                for p in params:
                    if p.grad is not None:
                        torch.distributed.all_reduce(p.grad)
                        p.grad /= self.world
        with record_function(f"{stage}/step"):
            grad_norm = nn.utils.clip_grad_norm_(params, self.config.optim.grad_clip)
            self.optimiser.step()
        for key, value in {"loss": loss, "grad_norm": grad_norm, **terms}.items():
            sums[key] = sums.get(key, 0.0) + value.detach().double()

    def _report(self, meter: _Meter, counter: str, done: int, last: int, every: int,
                on_progress: Callable[[Progress], None] | None) -> dict[str, float]:
        """An evaluation point of a stage: the interval's mean metrics (the wait for the
        device counted as training time), held-out agreement, progress; the meter restarts."""
        c = self.config
        means = meter.means()
        now = time.perf_counter()
        self.seconds, meter.wall = self.seconds + now - meter.wall, now
        interval = meter.interval
        row = {counter: done, "wall_s": round(self.seconds, 2),
               "updates_per_s": interval["done"] / interval["train"],
               **({"data_wait_share": interval["wait"] / interval["train"]}
                  if counter == "updates" else {}), **means}
        heldout = self.evaluate(plot=_plots_at(done, every, last) or self._out_of_time())
        if on_progress is not None:
            on_progress(Progress(self.progress if counter == "updates" else done,
                                 c.frame_steps + c.steps, row["updates_per_s"],
                                 row.get("data_wait_share", 0.0), row["loss"], heldout["h_mse"]))
        meter.restart()
        return row

    def _snapshot(self) -> None:
        """The student and its agent bundle at this update count: a learning-curve point."""
        self._checkpoint(self.out / f"student-{self.updates:08d}.pt")
        self._bundle(self.out / f"agent-{self.updates:08d}.pt")

    def _out_of_time(self) -> bool:
        return self.deadline is not None and time.perf_counter() >= self.deadline

    def _bundle(self, path: Path) -> Path:
        # Every snapshot is deployable too: the return need not rise with the updates while
        # the latents improve (docs/findings.md, "TWIST's objective, long"), so the update
        # count is worth choosing by evaluating the snapshots on other episodes.
        if self.writes:
            info = {**self.data.spec.image_agent_info(), "dataset": str(self.dataset_path),
                    "teacher": str(self.teacher_path), "student_updates": self.updates,
                    "recipe": self.config.recipe, "frame_updates": self.frame_updates}
            Agent.from_models(self.student, self.teacher, info).save(path)
        return path

    def _checkpoint(self, path: Path) -> Path:
        if self.writes:
            extra = {"torch_rng": torch.get_rng_state().tolist(), "seconds": self.seconds,
                     "heldout_first": self.heldout_first, "distil": to_json(self.config),
                     "teacher": str(self.teacher_path), "dataset": str(self.dataset_path)}
            save_checkpoint(path, "student", self.student, self.student.config,
                            {"student": self.optimiser},
                            {"updates": self.updates, "frame_updates": self.frame_updates}, extra)
        return path


def _plots_at(done: int, every: int, last: int) -> bool:
    """Whether the evaluation after ``done`` of a stage's ``last`` updates, one every
    ``every``, redraws the plot: every :data:`PLOT_EVERY_EVALUATIONS`-th, and the stage's
    last (and, :meth:`Distiller._report`, the last before a time limit)."""
    return done == last or (done // every) % PLOT_EVERY_EVALUATIONS == 0


def load_student(path: str | os.PathLike[str]) -> tuple[Student, dict[str, Any]]:
    """A student checkpoint's model and its run record (``extra``)."""
    checkpoint = read_checkpoint(path, kind="student")
    config = from_json(StudentConfig, checkpoint.config)
    student = Student(config)
    restore(checkpoint, student, config)
    return student, checkpoint.extra


def initialise_distributed(device: str) -> str:
    """Join the process group ``torchrun`` describes (WORLD_SIZE > 1) and return this rank's
    device (``cuda`` becomes ``cuda:<local rank>``); a no-op for single-process runs."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return device
    backend = "nccl" if device.startswith("cuda") else "gloo"
    torch.distributed.init_process_group(backend)
    if device == "cuda":
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
        torch.cuda.set_device(device)
    return device



def stored_config(out: str | os.PathLike[str]) -> DistilConfig:
    """The distil config the run in ``out`` was started with."""
    data = json.loads(_run_folder(Path(out)).config_file.read_text())
    return from_json(DistilConfig, data["distil"])
