"""A distillation run's learning curve: every deployable snapshot it kept
(``agent-<updates>.pt``), its teacher on states and the zero-action floor, evaluated on the
same held-out episodes, as a table (``curve.csv``) and a plot (``curve.png``).

A distiller never touches a simulator, so the curve is an evaluation of its snapshots, made
while it runs or after (``twist-eval --snapshots RUN``), and resumable like any evaluation:
snapshots already evaluated are not run again. Why a curve and not one figure: the return
need not rise with the updates while every held-out latent metric improves
(docs/findings.md), so an update count is chosen by evaluating the snapshots.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from twist_data.errors import TwistError
from twist_data.seeding import evaluation_episode_seed
from twist_models.agent import AgentState
from twist_pipeline.acting import ImageAgent, StateAgent, load_agent
from twist_pipeline.curves import figure
from twist_pipeline.evaluation import EvalConfig, evaluation_envs, run_evaluation

SNAPSHOT = re.compile(r"agent-(\d{8})\.pt")
ORACLE, FLOOR = "oracle", "zero"
CURVE_COLUMNS = ("agent", "updates", "frame_updates", "progress", "episodes", "mean", "std",
                 "sem", "paired_vs_oracle", "paired_vs_oracle_sem", "closed_loop_h_explained",
                 "closed_loop_action_corr")
#: Each snapshot's closed-loop agreement, kept beside the curve so that a resumed curve
#: measures only new snapshots.
AGREEMENT = "agreement.csv"


class CurveError(TwistError):
    """A run folder without snapshots, or a teacher to compare them with that cannot be found."""


def snapshots(run: str | os.PathLike[str]) -> dict[str, Path]:
    """The run's deployable snapshots by agent name (``u<window updates>``), in training
    order; a run whose first stage trains on single frames has ``u00000000``, the student
    after that stage alone."""
    found = sorted((m.group(1), p) for p in Path(run).glob("agent-*.pt")
                   if (m := SNAPSHOT.fullmatch(p.name)))
    if not found:
        raise CurveError(f"{str(run)!r} holds no agent snapshot (agent-<updates>.pt); set "
                         "schedule.snapshot_every lower than the run's steps")
    return {f"u{updates}": path for updates, path in found}


def run_teacher(run: str | os.PathLike[str]) -> Path:
    """The teacher a distillation run was distilled from (its ``config.json``)."""
    config = Path(run) / "config.json"
    if not config.exists():
        raise CurveError(f"{str(run)!r} is not a distillation run (no config.json)")
    teacher = Path(json.loads(config.read_text())["teacher"])
    if not teacher.exists():
        raise CurveError(f"the run's teacher {str(teacher)!r} is gone; pass the teacher")
    return teacher


def evaluate_snapshots(run: str | os.PathLike[str], config: EvalConfig,
                       out: str | os.PathLike[str], teacher: str | os.PathLike[str] | None = None,
                       seeds: Sequence[int] = (0,), device: str = "cpu", resume: bool = False,
                       batch: int = 1, workers: int = 1, agreement_episodes: int = 3,
                       on_progress: Callable[[int, int], None] | None = None) -> pd.DataFrame:
    """Evaluate every snapshot of the distillation run ``run``, its teacher (``teacher``: the
    run's own by default) and the zero-action floor on the same episodes into ``out``
    (:func:`~twist_pipeline.evaluation.run_evaluation`'s files), measure each snapshot's
    :func:`closed_loop_agreement` over the first ``agreement_episodes`` of them (0: none), then
    write ``curve.csv`` (:data:`CURVE_COLUMNS`: per agent its mean, spread and, for
    snapshots, the paired difference from the teacher and the agreement) and ``curve.png``;
    returns the curve."""
    if agreement_episodes < 0:
        raise CurveError(f"agreement episodes must be >= 0, got {agreement_episodes}")
    found = snapshots(run)
    teacher = Path(teacher) if teacher is not None else run_teacher(run)
    agents: dict[str, Any] = {ORACLE: teacher, FLOOR: FLOOR, **found}
    summary = run_evaluation(agents, config, seeds, out, device=device, against=ORACLE,
                             resume=resume, batch=batch, workers=workers,
                             on_progress=on_progress)
    agreement = _agreement(found, teacher, config, Path(out), agreement_episodes, seeds[0],
                           device)
    rows = []
    for name, stats in summary["agents"].items():
        row: dict[str, Any] = {"agent": name, "episodes": stats["episodes"],
                               "mean": stats["mean"], "std": stats["std_over_episodes"],
                               "sem": stats["std_over_episodes"] / np.sqrt(max(stats["episodes"]
                                                                               - 1, 1))}
        if name in found:
            info = _bundle_info(found[name])
            row.update(updates=info["student_updates"],
                       frame_updates=info.get("frame_updates", 0),
                       progress=info["student_updates"] + info.get("frame_updates", 0),
                       paired_vs_oracle=stats["paired"]["mean"],
                       paired_vs_oracle_sem=stats["paired"]["standard_error"],
                       **agreement.get(name, {}))
        rows.append(row)
    curve = pd.DataFrame(rows, columns=list(CURVE_COLUMNS))
    curve.to_csv(Path(out) / "curve.csv", index=False)
    plot_curve(curve, Path(out) / "curve.png", f"{config.task}, DR {config.dr}, "
               f"{config.episodes} episodes x {len(seeds)} seed(s)")
    return curve


def _agreement(found: dict[str, Path], teacher: Path, config: EvalConfig, out: Path,
               episodes: int, seed: int, device: str) -> dict[str, dict[str, float]]:
    """Each snapshot's closed-loop agreement, measured once and kept in :data:`AGREEMENT`."""
    if episodes == 0:
        return {}
    path = out / AGREEMENT
    kept: dict[str, dict[str, float]] = {}
    if path.exists():
        kept = {row.pop("agent"): row for row in pd.read_csv(path).to_dict(orient="records")
                if row["episodes"] == episodes}
    oracle = load_agent(teacher, device, config.task)
    for name, bundle in found.items():
        if name not in kept:
            kept[name] = {"episodes": episodes, **closed_loop_agreement(
                load_agent(bundle, device, config.task, config.posterior), oracle, config,
                episodes, seed)}
            pd.DataFrame([{"agent": n, **v} for n, v in kept.items()]).to_csv(path, index=False)
    return {name: {k: v for k, v in values.items() if k != "episodes"}
            for name, values in kept.items()}


@torch.no_grad()
def closed_loop_agreement(student: ImageAgent, oracle: StateAgent, config: EvalConfig,
                          episodes: int, seed: int = 0) -> dict[str, float]:
    """How closely the student's latent follows its teacher's over whole episodes in which the
    student acts: the first ``episodes`` of the evaluation's scenes (``seed``), the student on
    its rendered view, the teacher's filter on the same states and executed actions in its
    shadow, each sampling its latents with draws of its own (as deployment does, unlike the
    distiller's held-out windows: shared draws, 50 steps from h = 0). Returns
    ``closed_loop_h_explained`` (1 - the mean squared error of the student's h over the
    variance of the teacher's h along the episode, averaged over episodes; 1: on the
    teacher's path, 0: no closer than the path's own spread) and ``closed_loop_action_corr``
    (the correlation, over every step, of the teacher's actor on the student's latent with
    the same actor on the teacher's latent)."""
    teacher = oracle.teacher
    explained, on_student, on_teacher = [], [], []
    with evaluation_envs(student, config) as envs, \
            torch.random.fork_rng(devices=range(torch.cuda.device_count())):
        for i in range(episodes):
            episode_seed = evaluation_episode_seed(seed, i)
            torch.manual_seed(episode_seed)
            ((step, image),) = envs.reset([episode_seed])
            acting: AgentState | None = None
            shadow = None
            previous = torch.zeros(1, teacher.config.world_model.action_dim,
                                   device=oracle.device)
            h_student, h_teacher = [], []
            while not step.is_last:
                action, acting = student.agent.act(image, acting, posterior=config.posterior)
                state = torch.as_tensor(step.state, dtype=torch.float32,
                                        device=oracle.device)[None]
                _, shadow = teacher.policy(state, shadow, previous,
                                           torch.tensor([step.is_first], device=oracle.device),
                                           explore=False)
                latent = {k: v.to(oracle.device) for k, v in acting.latent.items()}
                on_student.append(teacher.act_on_latent(latent).cpu().numpy().ravel())
                on_teacher.append(teacher.act_on_latent(shadow).cpu().numpy().ravel())
                h_student.append(latent["deter"][0].cpu().numpy())
                h_teacher.append(shadow["deter"][0].cpu().numpy())
                executed = np.clip(np.asarray(action, np.float32), -1.0, 1.0)
                previous = torch.as_tensor(executed, device=oracle.device).reshape(1, -1)
                ((step, image),) = envs.step([0], [executed])
            h_s, h_t = np.stack(h_student), np.stack(h_teacher)
            variance = max(float(h_t.var(0).mean()), 1e-12)
            explained.append(1.0 - float(((h_s - h_t) ** 2).mean()) / variance)
    a, b = np.concatenate(on_student), np.concatenate(on_teacher)
    return {"closed_loop_h_explained": float(np.mean(explained)),
            "closed_loop_action_corr": float(np.corrcoef(a, b)[0, 1])}


def _bundle_info(path: Path) -> dict[str, Any]:
    from twist_models.checkpoint import read_checkpoint

    return read_checkpoint(path, kind="agent").extra


def plot_curve(curve: pd.DataFrame, out: Path, title: str) -> Path:
    """Held-out return (mean ± standard error) against the student's updates (single-frame
    plus window updates), with the teacher's and the zero-action floor's returns as lines."""
    students = curve[curve["progress"].notna()].sort_values("progress")
    with figure(out, (6, 3.6)) as (_, ax):
        x = students["progress"].to_numpy(float)
        mean, sem = students["mean"].to_numpy(float), students["sem"].to_numpy(float)
        ax.plot(x, mean, marker="o", markersize=3, label="student")
        ax.fill_between(x, mean - sem, mean + sem, alpha=0.2)
        for name, style in ((ORACLE, "--"), (FLOOR, ":")):
            reference = curve[curve["agent"] == name]
            if len(reference):
                value = float(reference["mean"].iloc[0])
                ax.axhline(value, linestyle=style, color="grey", linewidth=1)
                ax.annotate(f"{'teacher' if name == ORACLE else 'doing nothing'} {value:.0f}",
                            (0, value), xycoords=("axes fraction", "data"),
                            textcoords="offset points", xytext=(4, 3), fontsize=7, color="grey")
        ax.set_xlabel("student updates (single frames, then windows)")
        ax.set_ylabel("held-out return")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    return out
