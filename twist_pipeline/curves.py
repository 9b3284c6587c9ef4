"""PNG plots of runs: the collector's learning curves, the distiller's latent agreement and
twist-eval's returns. Files only; matplotlib never opens a display."""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd


@contextmanager
def figure(out: str | os.PathLike[str], figsize: tuple[float, float], ncols: int = 1
           ) -> Iterator[tuple[Any, Any]]:
    """(figure, axes) to draw on; laid out and written to ``out`` on leaving the block, and
    closed whatever happens."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=figsize, dpi=120)
    try:
        yield fig, axes
        fig.tight_layout()
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out)  # tight_layout keeps long tick labels and the suptitle inside
    finally:
        plt.close(fig)


def plot_learning_curves(runs: Mapping[str, str | os.PathLike[str]],
                         out: str | os.PathLike[str], title: str = "",
                         references: Mapping[str, float] | None = None) -> Path:
    """Plot evaluation return against environment frames for each ``label: eval.csv`` (mean
    with a ±1 std band over the evaluation episodes) and dashed lines for ``references``
    (e.g. the paper's returns). Writes ``out`` (PNG) and returns its path."""
    with figure(out, (6, 3.6)) as (_, ax):
        for label, path in runs.items():
            table = pd.read_csv(path)
            if table.empty:
                continue
            x, mean, std = table["frames"], table["return_mean"], table["return_std"]
            (line,) = ax.plot(x, mean, marker="o", markersize=3, label=label)
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        for label, value in (references or {}).items():
            ax.axhline(value, linestyle="--", linewidth=1, color="grey")
            ax.annotate(label, (0, value), xycoords=("axes fraction", "data"),
                        textcoords="offset points", xytext=(4, 3), fontsize=7, color="grey")
        ax.set_xlabel("environment frames")
        ax.set_ylabel("evaluation return")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        if runs:
            ax.legend(fontsize=7, loc="lower right")
    return Path(out)


def student_progress(table: pd.DataFrame) -> pd.Series:
    """Each row's place in a run of ``heldout.csv``: single-frame updates plus updates on
    windows, since a recipe with a single-frame stage runs it before any window update (the
    ``readout`` recipe runs no window update at all, so ``updates`` alone stays 0)."""
    return table["updates"] + table.get("frame_updates", 0)


def plot_agreement(heldout_csv: str | os.PathLike[str], out: str | os.PathLike[str]) -> Path:
    """Held-out latent agreement (h-MSE and posterior KL, log scale) and, for a student with a
    read-out, its error, against the student's updates (:func:`student_progress`); a dashed
    line marks where updates on windows follow a single-frame stage."""
    table = pd.read_csv(heldout_csv)
    panels = [(("h_mse", "imagined_h_mse"), "h MSE"),
              (("post_kl", "prior_kl"), "KL(student || teacher)")]
    if "read_error" in table and table["read_error"].notna().any():
        panels.append((tuple(c for c in ("read_error", "read_error_typical") if c in table),
                       "read-out error (robust spreads)"))
    x = student_progress(table)
    window_start = (int(table["frame_updates"].max())
                    if "frame_updates" in table and (table["updates"] > 0).any() else 0)
    with figure(out, (4 * len(panels), 3.2), ncols=len(panels)) as (fig, axes):
        for ax, (columns, label) in zip(axes, panels, strict=True):
            for column in columns:
                ax.plot(x, table[column].clip(lower=1e-6), marker="o", markersize=3,
                        label=column)
            if window_start:
                ax.axvline(window_start, linestyle="--", linewidth=1, color="grey")
            ax.set_yscale("log")
            ax.set_xlabel("student updates (single frames, then windows)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.suptitle("held-out latent agreement with the teacher", fontsize=9)
    return Path(out)


def plot_returns(table: pd.DataFrame, out: str | os.PathLike[str], title: str) -> Path:
    """Box plot of episode returns per agent (an ``episodes.csv`` table)."""
    names = list(dict.fromkeys(table["agent"]))
    with figure(out, (1.6 + 1.4 * len(names), 3.4)) as (_, ax):
        ax.boxplot([table.loc[table["agent"] == n, "return"] for n in names], showmeans=True)
        ax.set_xticks(range(1, len(names) + 1), names, fontsize=8)
        ax.set_ylabel("episode return")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    return Path(out)
