"""A distillation run's learning curve: every deployable snapshot it kept
(``agent-<updates>.pt``), its teacher on states and the zero-action floor, evaluated on the
same held-out episodes, as a table (``curve.csv``) and a plot (``curve.png``).

A distiller never touches a simulator, so the curve is an evaluation of its snapshots, made
while it runs or after (``twist-eval --snapshots RUN``), and resumable like any evaluation:
snapshots already evaluated are not run again. Why a curve and not one figure: the return
need not rise with the updates while every held-out latent metric improves
(docs/results.md), so an update count is chosen by evaluating the snapshots.
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

from twist_data.errors import TwistError
from twist_models.curves import figure
from twist_models.stages.evaluation import EvalConfig, run_evaluation

SNAPSHOT = re.compile(r"agent-(\d{8})\.pt")
ORACLE, FLOOR = "oracle", "zero"
CURVE_COLUMNS = ("agent", "updates", "frame_updates", "progress", "episodes", "mean", "std",
                 "sem", "paired_vs_oracle", "paired_vs_oracle_sem")


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
                         "snapshot_every lower than the run's steps")
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
                       batch: int = 1, workers: int = 1,
                       on_progress: Callable[[int, int], None] | None = None) -> pd.DataFrame:
    """Evaluate every snapshot of the distillation run ``run``, its teacher (``teacher``: the
    run's own by default) and the zero-action floor on the same episodes into ``out``
    (:func:`~twist_models.stages.evaluation.run_evaluation`'s files), then write
    ``curve.csv`` (:data:`CURVE_COLUMNS`: per agent its mean, spread and, for snapshots, the
    paired difference from the teacher) and ``curve.png``; returns the curve."""
    found = snapshots(run)
    teacher = Path(teacher) if teacher is not None else run_teacher(run)
    agents: dict[str, Any] = {ORACLE: teacher, FLOOR: FLOOR, **found}
    summary = run_evaluation(agents, config, seeds, out, device=device, against=ORACLE,
                             resume=resume, batch=batch, workers=workers,
                             on_progress=on_progress)
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
                       paired_vs_oracle_sem=stats["paired"]["standard_error"])
        rows.append(row)
    curve = pd.DataFrame(rows, columns=list(CURVE_COLUMNS))
    curve.to_csv(Path(out) / "curve.csv", index=False)
    plot_curve(curve, Path(out) / "curve.png", f"{config.task}, DR {config.dr}, "
               f"{config.episodes} episodes x {len(seeds)} seed(s)")
    return curve


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
