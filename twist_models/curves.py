"""Learning-curve plots (PNG) from the collector's ``eval.csv`` files."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import pandas as pd


def plot_learning_curves(runs: Mapping[str, str | os.PathLike[str]],
                         out: str | os.PathLike[str], title: str = "",
                         references: Mapping[str, float] | None = None) -> Path:
    """Plot evaluation return against environment frames for each ``label: eval.csv`` (mean
    with a ±1 std band over the evaluation episodes) and dashed lines for ``references``
    (e.g. the paper's returns). Writes ``out`` (PNG) and returns its path."""
    import matplotlib

    matplotlib.use("Agg")  # files only; never a display
    from matplotlib import pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    try:
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
        fig.tight_layout()
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out)
    finally:
        plt.close(fig)
    return out
