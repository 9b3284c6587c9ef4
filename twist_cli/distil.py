"""``twist-distil``: distil a vision student from a matching dataset and its frozen teacher."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from twist_cli.common import new_app, parse_settings, print_json, progress_bar, run_app
from twist_data.errors import ConfigError
from twist_models.config import replace_fields
from twist_models.device import resolve_device
from twist_models.distillation import DISTIL_PRESETS, RECIPES, DistilConfig, distil_preset
from twist_pipeline.distil import Progress as DistilProgress
from twist_pipeline.distil import distil, initialise_distributed, stored_config
from twist_pipeline.runlog import recorded_config

app = new_app()


@app.command()
def main(
    dataset: Annotated[Path, typer.Option(help="Matching dataset folder (from twist-collect).")],
    out_dir: Annotated[Path | None, typer.Option(
        "--out", help="Run folder [<dataset>/distil].")] = None,
    teacher: Annotated[Path | None, typer.Option(
        help="Teacher checkpoint [the dataset's final teacher].")] = None,
    preset: Annotated[str | None, typer.Option(
        help=f"Student sizes and schedule: {', '.join(DISTIL_PRESETS)} [quick].")] = None,
    recipe: Annotated[str | None, typer.Option(
        help=f"Distillation recipe: {', '.join(RECIPES)} (docs/design.md, 'Recipes') "
             "[paper].")] = None,
    config_file: Annotated[Path | None, typer.Option(
        "--config", help="Start from the config a distillation run recorded (its "
                         "config.json or folder) instead of --preset and --recipe; options "
                         "and --set apply on top.")] = None,
    steps: Annotated[int | None, typer.Option(help="Student updates.")] = None,
    batch: Annotated[int | None, typer.Option(help="Windows per update [the preset's].")] = None,
    length: Annotated[int | None, typer.Option(help="Steps per window L [the preset's].")] = None,
    horizon: Annotated[int | None, typer.Option(help="Imagined steps H of Eq. 4 [the preset's].")] = None,
    action_noise: Annotated[float | None, typer.Option(
        help="Std of the noise on the teacher's imagined actions [the preset's].")] = None,
    no_imagined: Annotated[bool, typer.Option(
        "--no-imagined", help="Ablation: train without imagined distillation (Eq. 4).")] = False,
    scratch_dynamics: Annotated[bool, typer.Option(
        "--scratch-dynamics", help="Start the student's RSSM from random weights, as the "
                                   "paper [from the teacher's].")] = False,
    view: Annotated[int | None, typer.Option(
        help="Use this camera view only [a random view per step].")] = None,
    workers: Annotated[int | None, typer.Option(help="Data-loading processes [the preset's].")] = None,
    seed: Annotated[int | None, typer.Option(help="Run seed [0].")] = None,
    device: Annotated[str, typer.Option(help="torch device (cuda under torchrun: one per "
                                             "rank).")] = "cpu",
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue an interrupted run in --out.")] = False,
    time_limit: Annotated[float | None, typer.Option(
        help="Seconds to train in this call; then stop after the update in progress, write "
             "the student, agent.pt and the last metrics, and leave the run to --resume.")
        ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
    settings: Annotated[list[str] | None, typer.Option(
        "--set", help="Override any DistilConfig field, KEY=VALUE (repeatable), e.g. "
                      "--set weights.action=10 --set lr=1e-3.")] = None,
) -> None:
    """Train a student world model to put domain-randomised images into the teacher's latent
    space (TWIST Eq. 3 and Eq. 4), offline, and write a deployable agent bundle."""
    folder = out_dir if out_dir is not None else dataset / "distil"
    given = {k: v for k, v in {
        "steps": steps, "batch_size": batch, "length": length, "horizon": horizon,
        "action_noise": action_noise, "imagined": False if no_imagined else None,
        "copy_dynamics": False if scratch_dynamics else None,
        "view": view, "workers": workers, "seed": seed}.items() if v is not None}
    given.update(parse_settings(settings or [], DistilConfig))
    if config_file is not None and (preset is not None or recipe is not None):
        raise ConfigError("--config gives the preset and the recipe; change its fields with "
                          "--set instead of passing --preset or --recipe")
    if resume and (folder / "config.json").exists():
        config = replace_fields(stored_config(folder), given)
    elif config_file is not None:
        config = replace_fields(recorded_config(config_file, "distil", DistilConfig), given)
    else:
        config = distil_preset(preset or "quick", recipe or "paper", **given)
    device = initialise_distributed(device)
    resolve_device(device)  # before the bar: a refusal is then the only line printed
    with progress_bar(quiet, "distilling", describe) as report:
        summary = distil(dataset, folder, config, teacher=teacher, resume=resume, device=device,
                         on_progress=report, time_limit=time_limit)
    print_json(summary.to_json())


def describe(p: DistilProgress) -> tuple[int, int, str]:
    """The bar's figures: updates/s, data-wait share, loss and held-out h-MSE."""
    return p.updates, p.total, (f"{p.updates_per_second:.2f} updates/s, data wait "
                                f"{100 * p.data_wait_share:.1f}%, loss {p.loss:.3f}, held-out "
                                f"h-MSE {p.heldout_h_mse:.4f}")


def entry() -> None:
    run_app(app, log_level=logging.INFO)


if __name__ == "__main__":
    entry()
