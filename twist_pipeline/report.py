"""The reproduction report: the whole pipeline for a list of tasks and seeds, then a table
shaped like Table I of the TWIST paper and the aggregate IQM plot of its Fig. 2.

Folder layout under ``out`` (every stage is skipped when its result exists, and resumed when
its folder exists without one, so an interrupted report continues where it stopped)::

    <task>/seed-<s>/dataset/        twist-collect (teacher + matching dataset D)
    <task>/seed-<s>/<agent>/        twist-distil / twist-baseline runs, each with agent.pt
    <task>/seed-<s>/dataset-clean/  D re-rendered without DR (for "Dreamer w/o DR")
    <task>/seed-<s>/eval/           twist-eval of every agent on the evaluation scenes
    results.csv, report.md, iqm.png the aggregate

Statistics (Agarwal et al., 2021, as the paper): a run's score is its mean return over the
evaluation episodes; the table gives mean ± std over seeds; normalised scores divide a run's
score by the oracle's mean score on the same task; the aggregate is the IQM of the normalised
run scores over all tasks and seeds with a 95% bootstrap interval stratified by task; and, per
task, every agent's return minus TWIST's on the same evaluation episodes, pooled over seeds.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twist_data.errors import ConfigError, TwistError
from twist_data.staging import require_writable
from twist_models.config import require_positive
from twist_models.device import resolve_device
from twist_models.distillation import DISTIL_PRESETS, DistilConfig, distil_preset
from twist_models.teacher import FINAL_TEACHER
from twist_pipeline.acting import REFERENCE_AGENTS
from twist_pipeline.baselines import BaselineConfig, train_baseline
from twist_pipeline.collect import (
    COLLECT_PRESETS,
    CollectConfig,
    collect,
    collect_preset,
    run_dir,
)
from twist_pipeline.curves import figure
from twist_pipeline.distil import distil
from twist_pipeline.evaluation import EvalConfig, paired_episodes, run_evaluation
from twist_pipeline.factors import FACTOR_TABLE, factor_table
from twist_pipeline.statistics import (
    format_paired,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap,
)
from twist_sim.randomisation import DR_PRESETS, dr_preset
from twist_sim.rerender import rerender_dataset
from twist_sim.tasks import task_spec

log = logging.getLogger(__name__)

#: The report's agents, in the columns' order: name -> heading of Table I.
AGENTS: dict[str, str] = {
    "oracle": "Oracle (teacher on states)",
    "twist": "TWIST",
    "twist-dense": "TWIST, dense recipe (not in the paper)",
    "twist-dense-no-stage": "dense recipe w/o its single-frame stage",
    "twist-dense-no-state": "dense recipe w/o the state read-out",
    "twist-dense-no-frame-kl": "dense recipe w/o the per-frame posterior",
    "twist-dense-no-norm": "dense recipe w/o the layer-normalised CNN",
    "twist-dense-zero-start": "dense recipe with windows from h = 0 (as the paper)",
    "twist-dense-shared-draws": "dense recipe with the teacher's sampling draws (as the paper)",
    "twist-readout": "TWIST, read-out recipe (not in the paper)",
    "twist-readout-eq34": "read-out recipe + Eq. 3/4 through the teacher's filter after it",
    "twist-readout-no-stage": "Eq. 3/4 alone through the teacher's filter (no read-out stage)",
    "twist-readout-no-norm": "read-out recipe w/o the layer-normalised CNN",
    "twist-readout-no-mirror": "read-out recipe w/o the mirror image",
    "twist-readout-no-lean": "read-out recipe handing on the angle as read (lean 1)",
    "twist-scratch": "TWIST, student RSSM from scratch (as the paper)",
    "twist-no-imagined": "TWIST w/o imagined distillation",
    "twist-no-noise": "TWIST w/o action noise",
    "twist-action": "TWIST + action matching (not in the paper)",
    "dreamer-dr": "Dreamer w/ DR",
    "dreamer-no-dr": "Dreamer w/o DR",
    "state-recon": "State Recon",
    "zero": "Zero actions (the floor)",
}
#: Each student column's distillation: a recipe (``twist_models.distillation.RECIPES``) and what it
#: changes. The paper's recipe with its from-scratch start and its two ablations, action
#: matching at the weight measured to help at CPU scale, and the ``dense`` recipe with each
#: of its parts removed in turn, and the ``readout`` recipe likewise. Every student gets the
#: report's ``updates`` on windows, except the read-out recipe's own, which has none
#: (docs/design.md, "Recipes").
STUDENT_VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "twist": ("paper", {}),
    "twist-scratch": ("paper", {"copy_dynamics": False}),
    "twist-no-imagined": ("paper", {"imagined": False}),
    "twist-no-noise": ("paper", {"action_noise": 0.0}),
    "twist-action": ("paper", {"weights.action": 10.0}),
    "twist-dense": ("dense", {}),
    "twist-dense-no-stage": ("dense", {"frame_steps": 0}),
    "twist-dense-no-state": ("dense", {"weights.state": 0.0}),
    "twist-dense-no-frame-kl": ("dense", {"weights.frame_post": 0.0}),
    "twist-dense-no-norm": ("dense", {"encoder_norm": "none"}),
    "twist-dense-zero-start": ("dense", {"window_start": "zero"}),
    "twist-dense-shared-draws": ("dense", {"shared_draws": True}),
    "twist-readout": ("readout", {"steps": 0}),
    "twist-readout-eq34": ("readout", {}),
    "twist-readout-no-stage": ("readout", {"frame_steps": 0}),
    "twist-readout-no-norm": ("readout", {"encoder_norm": "none", "steps": 0}),
    "twist-readout-no-mirror": ("readout", {"readout_stage.mirror": "none", "steps": 0}),
    "twist-readout-no-lean": ("readout", {"readout_stage.lean": 1.0, "steps": 0}),
}
#: Table I of the paper (held-out backgrounds, 500K frames, paper-scale models on GPU): the
#: values as the paper reports them. Blank cells are values not transcribed.
PAPER_TABLE_I: dict[str, dict[str, float]] = {
    "cartpole-balance": {"oracle": 992.9, "twist": 954.5, "dreamer-dr": 590.8},
    "cup-catch": {"oracle": 936.6, "twist": 856.6, "dreamer-dr": 744.3},
}
RESULT_COLUMNS = ("task", "seed", "agent", "score", "episodes")
EPISODE_RESULT_COLUMNS = ("task", "seed", "agent", "episode", "return")
#: The column every other agent is compared with, episode by episode.
PAIRED_AGAINST = "twist"


class ReportError(TwistError):
    """The reproduction report cannot run or has nothing to aggregate."""


@dataclass(frozen=True)
class ReportConfig:
    """Which tasks, seeds and agents the report runs, at which scale."""

    tasks: tuple[str, ...] = ("cartpole-balance", "cup-catch")
    """DMC tasks (rows of the table)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Pipeline seeds: each seed collects its own D and trains every agent on it."""
    preset: str = "quick"
    """Preset of collection, distillation and the baselines (``tiny``, ``quick``, ``paper``)."""
    agents: tuple[str, ...] = tuple(AGENTS)
    """Agents to train and evaluate (the oracle always is)."""
    eval_dr: str = "heldout"
    """DR preset of the evaluation scenes (the paper: held-out backgrounds)."""
    factor_drs: tuple[str, ...] = ()
    """DR presets every agent is also evaluated under, on the same episodes as ``eval_dr``
    (e.g. ``heldout-camera``, ``heldout-light``: one factor each); ``report.md`` then shows
    what each agent keeps of its ``eval_dr`` return under each (:mod:`~twist_pipeline.
    factors`)."""
    eval_episodes: int = 10
    """Evaluation episodes per agent and seed (the paper: 100)."""
    eval_max_steps: int | None = None
    """Agent steps per evaluation episode; None: the task's own limit."""
    frames: int | None = None
    """Override of the frames the teacher learns for (the collection preset's ``learn_frames``,
    or its ``frames`` where it has none; D keeps the preset's frames where they are more);
    None keeps the preset's."""
    updates: int | None = None
    """Override of the student's updates; the baselines always get the student's budget."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "tasks", tuple(self.tasks))
        object.__setattr__(self, "seeds", tuple(self.seeds))
        object.__setattr__(self, "factor_drs", tuple(self.factor_drs))
        agents = ("oracle", *(a for a in self.agents if a != "oracle"))
        object.__setattr__(self, "agents", agents)
        if not self.tasks or not self.seeds:
            raise ConfigError("the report needs at least one task and one seed")
        for task in self.tasks:
            task_spec(task)  # raises UnknownTaskError naming the valid tasks
        for agent in self.agents:
            if agent not in AGENTS:
                raise ConfigError(f"unknown agent {agent!r}; valid agents are: "
                                  f"{', '.join(AGENTS)}")
        if self.preset not in COLLECT_PRESETS or self.preset not in DISTIL_PRESETS:
            raise ConfigError(f"unknown preset {self.preset!r}; valid presets are: "
                              f"{', '.join(COLLECT_PRESETS)}")
        for name in (self.eval_dr, *self.factor_drs):
            if name not in DR_PRESETS:
                raise ConfigError(f"unknown DR preset {name!r}; valid presets are: "
                                  f"{', '.join(DR_PRESETS)}")
        if len({self.eval_dr, *self.factor_drs}) != 1 + len(self.factor_drs):
            raise ConfigError(f"each factor DR preset must differ from the others and from "
                              f"eval_dr ({self.eval_dr}), got {','.join(self.factor_drs)}")
        require_positive(self, "eval_episodes")
        for name in ("frames", "updates", "eval_max_steps"):
            if getattr(self, name) is not None:
                require_positive(self, name)

    def collect_config(self, task: str, seed: int) -> CollectConfig:
        """The collector config of one (task, seed) of the report."""
        config = collect_preset(self.preset, task=task, seed=seed)
        learn = self.frames
        if learn is None:
            return config
        if config.learn_frames is None:
            return dataclasses.replace(config, frames=learn)
        return dataclasses.replace(config, learn_frames=learn, frames=max(config.frames, learn))


def run_reproduction(out: str | os.PathLike[str], config: ReportConfig, device: str = "cpu",
                     on_stage: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run every stage of every (task, seed) that is not done yet, then aggregate: returns
    :func:`build_report`'s summary and writes ``results.csv``, ``report.md`` and ``iqm.png``."""
    out = Path(out)
    if out.exists() and not out.is_dir():  # before any stage logs that it starts
        raise ConfigError(f"report folder {str(out)!r} is a file; name a folder")
    resolve_device(device)
    require_writable(out, "report folder")
    for task in config.tasks:
        for seed in config.seeds:
            _Pipeline(out / task / f"seed-{seed}", task, seed, config, device, on_stage).run()
    return build_report(out, config)


class _Pipeline:
    """The stages of one (task, seed)."""

    def __init__(self, root: Path, task: str, seed: int, config: ReportConfig, device: str,
                 on_stage: Callable[[str], None] | None) -> None:
        self.root, self.task, self.seed, self.config, self.device = root, task, seed, config, device
        self.on_stage = on_stage
        self.dataset = root / "dataset"
        self.distil_config = distil_preset(config.preset, seed=seed, steps=config.updates)

    def student_config(self, name: str) -> DistilConfig:
        """The distillation config of student column ``name``."""
        recipe, changes = STUDENT_VARIANTS[name]
        steps = self.config.updates or DISTIL_PRESETS[self.config.preset].steps
        return distil_preset(self.config.preset, recipe,
                             **{"seed": self.seed, "steps": steps, **changes})

    def run(self) -> None:
        self._collect()
        agents = {"oracle": run_dir(self.dataset, "collect-000") / FINAL_TEACHER}
        for name in self.config.agents[1:]:
            # A reference agent is only evaluated; run_evaluation sizes it for the task.
            agents[name] = name if name in REFERENCE_AGENTS else self._train(name)
        c = self.config
        for dr in (c.eval_dr, *c.factor_drs):
            eval_dir = self.root / eval_folder(dr, c)
            episodes = eval_dir / "episodes.csv"
            # Done only if it covers every agent asked for now (a report may add agents later).
            if episodes.exists() and set(agents) <= set(pd.read_csv(episodes)["agent"]):
                continue
            self._announce("evaluating" if dr == c.eval_dr else f"evaluating under {dr}")
            eval_config = EvalConfig(task=self.task, dr=dr, episodes=c.eval_episodes,
                                     max_steps=c.eval_max_steps,
                                     action_repeat=self._collect_config().action_repeat)
            run_evaluation(agents, eval_config, [self.seed], eval_dir, device=self.device,
                           resume=True)

    def _announce(self, stage: str) -> None:
        log.info("%s seed %d: %s", self.task, self.seed, stage)
        if self.on_stage is not None:
            self.on_stage(f"{self.task} seed {self.seed}: {stage}")

    def _collect(self) -> None:
        if (run_dir(self.dataset, "collect-000") / FINAL_TEACHER).exists():
            return
        self._announce("collecting D and training the teacher")
        collect(self.dataset, self._collect_config(), resume=self.dataset.exists(),
                device=self.device)

    def _collect_config(self) -> CollectConfig:
        return self.config.collect_config(self.task, self.seed)

    def _train(self, name: str) -> Path:
        folder = self.root / name
        agent = folder / "agent.pt"
        if agent.exists():
            return agent
        self._announce(f"training {AGENTS[name]}")
        resume = (folder / "config.json").exists()
        if name in STUDENT_VARIANTS:
            distil(self.dataset, folder, self.student_config(name), resume=resume,
                   device=self.device)
        else:
            kind = "state-recon" if name == "state-recon" else "dreamer"
            dataset = self._clean_dataset() if name == "dreamer-no-dr" else self.dataset
            # The same budget of updates, batch shape and held-out split as the student.
            d = self.distil_config
            baseline = BaselineConfig(kind=kind, model=self.config.preset, steps=d.steps,
                                      batch_size=d.batch_size, length=d.length, seed=self.seed,
                                      holdout_every=d.schedule.holdout_every)
            train_baseline(dataset, folder, baseline, resume=resume, device=self.device)
        return agent

    def _clean_dataset(self) -> Path:
        """D's trajectories re-rendered in the nominal scene, one view: the paper's
        "Dreamer w/o DR" data."""
        clean = self.root / "dataset-clean"
        done = self.root / "dataset-clean.done"
        if done.exists():
            return clean
        self._announce("re-rendering D without DR")
        if clean.exists():
            # An interrupted re-render; re-rendering is deterministic, so start it again.
            shutil.rmtree(clean)
        rerender_dataset(self.dataset, clean, dr_preset("none"), views=1, seed=self.seed)
        done.write_text("dataset-clean holds D re-rendered without DR\n")
        return clean


def eval_folder(dr: str, config: ReportConfig) -> str:
    """The folder of a (task, seed) that holds its evaluation under DR preset ``dr``:
    ``eval`` for the report's own scenes, ``eval-<preset>`` for a factor's."""
    return "eval" if dr == config.eval_dr else f"eval-{dr}"


# -- aggregation ------------------------------------------------------------------------------
def collect_episodes(out: str | os.PathLike[str],
                     config: ReportConfig | None = None, folder: str = "eval") -> pd.DataFrame:
    """One row per evaluation episode (:data:`EPISODE_RESULT_COLUMNS`), read from every
    ``<task>/seed-<s>/<folder>/episodes.csv`` under ``out`` (only ``config``'s tasks and
    seeds when given)."""
    frames = []
    for path in sorted(Path(out).glob(f"*/seed-*/{folder}/episodes.csv")):
        task, seed = path.parents[2].name, int(path.parents[1].name.removeprefix("seed-"))
        if config is not None and (task not in config.tasks or seed not in config.seeds):
            continue
        frames.append(pd.read_csv(path).assign(task=task, seed=seed))
    if not frames:
        return pd.DataFrame(columns=EPISODE_RESULT_COLUMNS)
    return pd.concat(frames, ignore_index=True)[list(EPISODE_RESULT_COLUMNS)]


def run_scores(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per (task, seed, agent) of :func:`collect_episodes`' table: the run's score,
    i.e. its mean evaluation return (:data:`RESULT_COLUMNS`)."""
    runs = (episodes.groupby(["task", "seed", "agent"], sort=False)["return"]
            .agg(score="mean", episodes="size").reset_index())
    runs["score"] = runs["score"].astype(float)
    return runs[list(RESULT_COLUMNS)]


def paired_with(episodes: pd.DataFrame, against: str = PAIRED_AGAINST
                ) -> dict[str, dict[str, dict[str, Any]]]:
    """Per task and agent: the agent's returns minus ``against``'s over the episodes both met
    (same seed and episode), pooled over seeds; tasks without ``against`` are left out."""
    paired: dict[str, dict[str, dict[str, Any]]] = {}
    for task, rows in episodes.groupby("task", sort=False):
        if against not in set(rows["agent"]):
            continue
        paired[str(task)] = {
            str(agent): paired_episodes(rows, str(agent), against).as_dict()
            for agent in rows["agent"].unique() if agent != against}
    return paired


def aggregate(results: pd.DataFrame) -> dict[str, Any]:
    """Per task and agent: mean and std over seeds of the run scores; per agent: the IQM of
    oracle-normalised run scores over tasks and seeds with its 95% interval stratified by
    task, and the probability that a TWIST run scores above one of the agent's on the same
    task (``improvement``). ``results`` has :data:`RESULT_COLUMNS`; every task needs an oracle. A task whose
    oracle's mean score is not positive (a teacher that never learned it) has no ratio to
    normalise by: it keeps its row of raw scores, stays out of the IQM and is listed under
    ``unnormalised_tasks``."""
    if results.empty:
        raise ReportError("no evaluation results to aggregate")
    per_task: dict[str, dict[str, dict[str, float]]] = {}
    normalised: dict[str, dict[str, list[float]]] = {}
    unnormalised: list[str] = []
    for task, rows in results.groupby("task", sort=False):
        oracle = rows.loc[rows["agent"] == "oracle", "score"]
        if oracle.empty:
            raise ReportError(f"task {task!r} has no oracle results to normalise by")
        oracle_mean = float(oracle.mean())
        if oracle_mean <= 0:
            log.warning("task %s: the oracle's mean score is %.1f, so its scores are not "
                        "normalised and stay out of the IQM", task, oracle_mean)
            unnormalised.append(str(task))
        per_task[task] = {}
        for agent, group in rows.groupby("agent", sort=False):
            scores = group["score"].to_numpy()
            per_task[task][agent] = {"mean": float(scores.mean()),
                                     "std": float(scores.std(ddof=0)), "seeds": len(scores)}
            if oracle_mean > 0:
                normalised.setdefault(agent, {})[task] = list(scores / oracle_mean)
    iqm = {}
    for agent, by_task in normalised.items():
        interval = stratified_bootstrap(list(by_task.values()))
        iqm[agent] = {"iqm": interval.estimate, "ci95": [interval.low, interval.high],
                      "runs": sum(len(v) for v in by_task.values()), "tasks": len(by_task)}
    improvement = {}
    base = normalised.get(PAIRED_AGAINST, {})
    for agent, by_task in normalised.items():
        tasks = [t for t in by_task if t in base]
        if agent != PAIRED_AGAINST and tasks:
            p = probability_of_improvement([base[t] for t in tasks], [by_task[t] for t in tasks])
            improvement[agent] = {"probability": p.estimate, "ci95": [p.low, p.high],
                                  "tasks": len(tasks)}
    return {"per_task": per_task, "normalised_iqm": iqm, "improvement": improvement,
            "normalised_runs": normalised, "unnormalised_tasks": unnormalised}


def markdown_table(summary: dict[str, Any], config: ReportConfig | None = None) -> str:
    """Table I in Markdown: one row per task with our mean ± std over seeds, a row with the
    paper's values beneath it, then the aggregate IQM of normalised scores and, when the
    summary has them (``paired``), the paired differences from TWIST."""
    per_task = summary["per_task"]
    agents = [a for a in AGENTS if any(a in row for row in per_task.values())]
    lines = [f"| Task | {' | '.join(AGENTS[a] for a in agents)} |",
             "|" + "---|" * (len(agents) + 1)]
    for task, row in per_task.items():
        # Seeds per task, not the config's: tasks of one report may have been run apart.
        scale = ("" if config is None else
                 f", `{config.preset}` preset, {max(r['seeds'] for r in row.values())} "
                 f"seed(s), {config.eval_episodes} {config.eval_dr} episodes per run")
        cells = [f"{row[a]['mean']:.1f} ± {row[a]['std']:.1f}" if a in row else "–"
                 for a in agents]
        lines.append(f"| {task} (ours{scale}) | {' | '.join(cells)} |")
        paper = PAPER_TABLE_I.get(task, {})
        paper_cells = [f"{paper[a]:.1f}" if a in paper else "" for a in agents]
        lines.append(f"| {task} (paper, `paper` scale) | {' | '.join(paper_cells)} |")
    lines += ["", "| Agent | IQM of oracle-normalised return [95% CI] | runs |", "|---|---|---|"]
    for agent in agents:
        s = summary["normalised_iqm"].get(agent)
        if s is not None:
            lines.append(f"| {AGENTS[agent]} | {s['iqm']:.3f} [{s['ci95'][0]:.3f}, "
                         f"{s['ci95'][1]:.3f}] | {s['runs']} |")
    if summary.get("improvement"):
        lines += ["", f"| Agent | P({AGENTS[PAIRED_AGAINST]} > agent) over runs [95% CI] | tasks |",
                  "|---|---|---|"]
        for agent in [a for a in AGENTS if a in summary["improvement"]]:
            p = summary["improvement"][agent]
            lines.append(f"| {AGENTS[agent]} | {p['probability']:.2f} [{p['ci95'][0]:.2f}, "
                         f"{p['ci95'][1]:.2f}] | {p['tasks']} |")
    if summary.get("unnormalised_tasks"):
        lines += ["", "Not normalised, because the oracle's mean score is not positive: "
                  f"{', '.join(summary['unnormalised_tasks'])}."]
    if summary.get("paired"):
        lines += ["", f"Paired by episode against {AGENTS[PAIRED_AGAINST]} (same seed and "
                  "evaluation episode): mean ± standard error of the return differences, "
                  "(episodes better / pairs), [95% t interval].", "",
                  "| Task | Agent | difference (better/pairs) | 95% CI |", "|---|---|---|---|"]
        for task, by_agent in summary["paired"].items():
            for agent in [a for a in AGENTS if a in by_agent]:
                p = by_agent[agent]
                ci = ("–" if p["ci95"] is None else
                      f"[{p['ci95'][0]:+.1f}, {p['ci95'][1]:+.1f}]")
                lines.append(f"| {task} | {AGENTS[agent]} | {format_paired(p)} | {ci} |")
    return "\n".join(lines) + "\n"


def report_factors(out: Path, config: ReportConfig, episodes: pd.DataFrame) -> pd.DataFrame:
    """Per task, the factor table (:func:`~twist_pipeline.factors.factor_table`) of the
    evaluations under ``config.eval_dr`` (``episodes``) and each factor preset, pooled over
    seeds, with a ``task`` column first."""
    presets = [config.eval_dr, *config.factor_drs]
    every = pd.concat([episodes.assign(dr=config.eval_dr)] + [
        collect_episodes(out, config, eval_folder(dr, config)).assign(dr=dr)
        for dr in config.factor_drs])
    tables = [factor_table(rows, presets).assign(task=task)
              for task, rows in every.groupby("task", sort=False)]
    if not tables:
        raise ReportError("no evaluation results to tabulate under the factor presets")
    table = pd.concat(tables, ignore_index=True)
    return table[["task", *table.columns.drop("task")]]


def factor_markdown(factors: pd.DataFrame, config: ReportConfig) -> str:
    """The factor table in Markdown: per task and agent, the mean return under
    ``eval_dr`` and, under each factor preset, the share of it the agent keeps and the
    paired difference (episodes better / pairs)."""
    presets = [config.eval_dr, *config.factor_drs]
    lines = [f"Each agent under one factor at a time, on the same episodes as {config.eval_dr}: "
             f"mean return, then the share of its {config.eval_dr} return and the paired "
             "difference ± its standard error (episodes better / pairs).", "",
             f"| Task | Agent | {' | '.join(presets)} |", "|" + "---|" * (len(presets) + 2)]
    for (task, agent), rows in factors.groupby(["task", "agent"], sort=False):
        cells = []
        for row in rows.itertuples():
            cell = f"{row.mean:.1f}"
            if row.dr != config.eval_dr:
                cell += (f": {row.ratio:.2f}, {row.paired:+.1f} ± {row.paired_sem:.1f} "
                         f"({int(row.better)}/{row.episodes})")
            cells.append(cell)
        lines.append(f"| {task} | {AGENTS.get(agent, agent)} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def plot_iqm(summary: dict[str, Any], out: str | os.PathLike[str]) -> Path:
    """The aggregate IQM of normalised returns per agent with its 95% interval (Fig. 2)."""
    iqm = summary["normalised_iqm"]
    agents = [a for a in AGENTS if a in iqm][::-1]
    with figure(out, (6.0, 0.5 + 0.45 * max(len(agents), 1))) as (_, ax):
        if not agents:
            ax.text(0.5, 0.5, "no task could be normalised (every oracle scored <= 0)",
                    ha="center", va="center", transform=ax.transAxes)
        for y, agent in enumerate(agents):
            low, high = iqm[agent]["ci95"]
            ax.plot([low, high], [y, y], color="tab:blue", lw=6, alpha=0.4, solid_capstyle="butt")
            # A dot as well as the bar: with one run per agent the interval has no width.
            ax.plot([iqm[agent]["iqm"]], [y], "ko", markersize=4)
        ax.set_yticks(range(len(agents)), [AGENTS[a] for a in agents], fontsize=8)
        ax.axvline(1.0, color="grey", ls="--", lw=0.8)
        ax.set_xlim(left=min(0.0, ax.get_xlim()[0]))
        ax.set_xlabel("IQM of oracle-normalised return\n(bar: 95% stratified bootstrap CI)")
        ax.grid(alpha=0.3, axis="x")
    return Path(out)


def plot_profiles(summary: dict[str, Any], out: str | os.PathLike[str]) -> Path:
    """Performance profiles: per agent, the share of runs above each oracle-normalised score,
    each task counting once (Agarwal et al., 2021)."""
    runs = summary["normalised_runs"]
    agents = [a for a in AGENTS if a in runs]
    top = max([1.0, *(max(max(v) for v in runs[a].values()) for a in agents)])
    tau = np.linspace(0.0, top, 101)
    with figure(out, (6.0, 4.0)) as (_, ax):
        for agent in agents:
            ax.plot(tau, performance_profile(list(runs[agent].values()), tau), label=AGENTS[agent])
        ax.set_xlabel("oracle-normalised return τ")
        ax.set_ylabel("share of runs scoring above τ")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    return Path(out)


def build_report(out: str | os.PathLike[str], config: ReportConfig | None = None
                 ) -> dict[str, Any]:
    """Aggregate the evaluations under ``out`` into ``results.csv``, ``report.md``,
    ``iqm.png`` and ``profiles.png``; returns the summary of :func:`aggregate` with the paired
    differences from TWIST of :func:`paired_with` under ``paired``."""
    out = Path(out)
    episodes = collect_episodes(out, config)
    results = run_scores(episodes)
    summary = aggregate(results)
    summary["paired"] = paired_with(episodes)
    results.to_csv(out / "results.csv", index=False)
    text = markdown_table(summary, config)
    if config is not None and config.factor_drs:
        factors = report_factors(out, config, episodes)
        factors.to_csv(out / FACTOR_TABLE, index=False)
        summary["factors"] = json.loads(factors.to_json(orient="records"))
        text += "\n" + factor_markdown(factors, config)
    (out / "report.md").write_text(text)
    plot_iqm(summary, out / "iqm.png")
    plot_profiles(summary, out / "profiles.png")
    return summary

