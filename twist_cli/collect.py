"""``twist-collect``: train the state teacher online and write the matching dataset D."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from twist_cli.common import new_app, parse_settings, print_json, progress_bar, run_app
from twist_data.errors import ConfigError
from twist_models.device import resolve_device
from twist_pipeline.collect import (
    COLLECT_PRESETS,
    CollectConfig,
    collect,
    collect_preset,
    run_dir,
    stored_config,
)
from twist_pipeline.collect import Progress as CollectProgress
from twist_pipeline.runlog import recorded_config
from twist_sim.randomisation import TRAINING_DR
from twist_sim.tasks import DEFAULT_TASK

app = new_app()


def shard_name(shard: str) -> str:
    """``--shard 3`` means ``collect-003``; any other value is the shard's name."""
    return f"collect-{int(shard):03d}" if shard.isdigit() else shard


@app.command()
def main(
    out_dir: Annotated[Path, typer.Option("--out", help="Dataset folder (created if needed).")],
    task: Annotated[str | None, typer.Option(
        help=f"DMC task (see `twist-data tasks`) [{DEFAULT_TASK}].")] = None,
    preset: Annotated[str | None, typer.Option(
        help=f"Sizes and schedule: {', '.join(COLLECT_PRESETS)}; a resumed run keeps its "
             "own [quick].")] = None,
    config_file: Annotated[Path | None, typer.Option(
        "--config", help="Start from the config a collector run recorded (its config.json "
                         "or folder) instead of --preset; options and --set apply on top.")
    ] = None,
    frames: Annotated[int | None, typer.Option(
        help="Environment frames to collect, learning and frozen (default: the preset's).")
    ] = None,
    views: Annotated[int | None, typer.Option("--views", help="K renders per step [2].")] = None,
    image_size: Annotated[int | None, typer.Option(help="Render side in pixels [64].")] = None,
    dr: Annotated[str | None, typer.Option(
        help=f"DR preset of the renders [{TRAINING_DR}].")] = None,
    backgrounds: Annotated[Path | None, typer.Option(
        help="Folder of images/videos to use as backgrounds.")] = None,
    seed: Annotated[int | None, typer.Option(help="Run seed [0].")] = None,
    shard: Annotated[str, typer.Option(
        help="Shard index (N -> collect-00N) or name; one per concurrent collector.")] = "0",
    device: Annotated[str, typer.Option(help="torch device of the teacher.")] = "cpu",
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue an interrupted run of this shard.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
    settings: Annotated[list[str] | None, typer.Option(
        "--set", help="Override any CollectConfig field, KEY=VALUE (repeatable), e.g. "
                      "--set behaviour_from=2000; the teacher's by dotted keys, e.g. "
                      "--set teacher.actor_critic.actor_lr=1e-4.")] = None,
) -> None:
    """Train a DreamerV2 teacher on privileged state while recording K randomised renders of
    every step it takes into a matching dataset, crash-safe and resumable."""
    name = shard_name(shard)
    overrides = {"task": task, "frames": frames, "views": views, "image_size": image_size,
                 "dr": dr, "backgrounds": None if backgrounds is None else str(backgrounds),
                 "seed": seed}
    given = {k: v for k, v in overrides.items() if v is not None}
    given.update(parse_settings(settings or [], CollectConfig))
    if resume and (run_dir(out_dir, name) / "config.json").exists():
        # A resumed run keeps its stored config; flags given again must agree with it
        # (collect() refuses any difference but --frames).
        config = stored_config(out_dir, name).with_settings(given)
    elif config_file is not None:
        if preset is not None:
            raise ConfigError("--config gives the preset; change its fields with --set "
                              "instead of passing --preset")
        config = recorded_config(config_file, "collect", CollectConfig).with_settings(given)
    else:
        # Settings replace the preset's fields as given: `--set learn_until_return=null` clears
        # one (collect_preset's keywords would ignore a None).
        config = collect_preset(preset or "quick").with_settings(given)
    resolve_device(device)  # before the bar: a refusal is then the only line printed
    with progress_bar(quiet, "collecting", describe) as report:
        summary = collect(out_dir, config, shard=name, resume=resume, device=device,
                          on_progress=report)
    print_json(summary.to_json())


def describe(p: CollectProgress) -> tuple[int, int, str]:
    """The bar's figures: frames/s, the last episode return and the latest evaluation."""
    evaluation = "" if p.eval_return is None else f", eval {p.eval_return:.0f}"
    return p.frames, p.total_frames, (f"{p.frames_per_second:.0f} frames/s, return "
                                      f"{p.episode_return:.0f}{evaluation}, {p.updates} updates")


def entry() -> None:
    run_app(app, log_level=logging.INFO)


if __name__ == "__main__":
    entry()
