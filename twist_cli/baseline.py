"""``twist-baseline``: train an offline image baseline (Dreamer, State Recon) from D."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from twist_cli.common import new_app, print_json, progress_bar, run_app
from twist_models.device import resolve_device
from twist_pipeline.baselines import KINDS, BaselineConfig, train_baseline
from twist_pipeline.baselines import Progress as BaselineProgress

app = new_app()


@app.command()
def main(
    dataset: Annotated[Path, typer.Option(help="Matching dataset folder.")],
    kind: Annotated[str, typer.Option(help=f"Baseline: {', '.join(KINDS)}.")] = "dreamer",
    out_dir: Annotated[Path | None, typer.Option(
        "--out", help="Run folder [<dataset>/baseline-<kind>].")] = None,
    preset: Annotated[str, typer.Option(help="Model sizes: tiny, quick, paper.")] = "quick",
    steps: Annotated[int, typer.Option(help="Updates (the student's budget).")] = 800,
    batch: Annotated[int, typer.Option(help="Windows per update.")] = 16,
    length: Annotated[int, typer.Option(help="Steps per window.")] = 50,
    view: Annotated[int | None, typer.Option(help="Camera view [random per step].")] = None,
    seed: Annotated[int, typer.Option(help="Run seed.")] = 0,
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    resume: Annotated[bool, typer.Option("--resume", help="Continue a run in --out.")] = False,
    time_limit: Annotated[float | None, typer.Option(
        help="Seconds the run may train in all, resumed calls included: it stops after the "
             "update in progress, checkpointed, e.g. at the wall clock a student took.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
) -> None:
    """Train a Dreamer (image reconstruction) or State Recon baseline offline on D, ending in
    an agent bundle that twist-eval evaluates like the student."""
    config = BaselineConfig(kind=kind, model=preset, steps=steps, batch_size=batch,
                            length=length, view=view, seed=seed)
    folder = out_dir if out_dir is not None else dataset / f"baseline-{kind}"
    resolve_device(device)  # before the bar: a refusal is then the only line printed
    with progress_bar(quiet, "training", describe) as report:
        summary = train_baseline(dataset, folder, config, resume=resume, device=device,
                                 on_progress=report, time_limit=time_limit)
    print_json(summary)


def describe(p: BaselineProgress) -> tuple[int, int, str]:
    """The bar's figures: updates/s and the world-model loss."""
    return p.updates, p.total, f"{p.updates_per_second:.2f} updates/s, loss {p.model_loss:.3f}"


def entry() -> None:
    run_app(app, log_level=logging.INFO)


if __name__ == "__main__":
    entry()
