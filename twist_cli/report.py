"""``twist-report``: the reproduction report (collect -> distil -> baselines -> eval for tasks x
seeds, then Table I and the IQM plot). Re-running continues an interrupted report."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from twist_cli.common import new_app, out, parse_list, run_app
from twist_pipeline.report import AGENTS, ReportConfig, build_report, run_reproduction

app = new_app()


@app.command()
def main(
    out_dir: Annotated[Path, typer.Option("--out", help="Report folder.")] = Path("runs/report"),
    tasks: Annotated[str, typer.Option(help="Comma-separated tasks.")] = "cartpole-balance,cup-catch",
    seeds: Annotated[str, typer.Option(help="Comma-separated pipeline seeds.")] = "0,1,2",
    preset: Annotated[str, typer.Option(help="Scale: tiny, quick, paper.")] = "quick",
    agents: Annotated[str, typer.Option(help=f"Comma-separated agents of {', '.join(AGENTS)}.")
                      ] = ",".join(AGENTS),
    dr: Annotated[str, typer.Option(help="DR preset of the evaluation scenes.")] = "heldout",
    factors: Annotated[str, typer.Option(
        help="Comma-separated DR presets every agent is also evaluated under, on the same "
             "episodes (e.g. heldout-camera,heldout-light,heldout-full); report.md then "
             "shows what each agent keeps of its --dr return under each.")] = "",
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per agent and seed.")] = 10,
    max_steps: Annotated[int | None, typer.Option(help="Agent steps per evaluation episode.")
                         ] = None,
    frames: Annotated[int | None, typer.Option(
        help="Frames the teacher learns for [the preset's].")] = None,
    updates: Annotated[int | None, typer.Option(
        help="Student updates, also the baselines' budget [the preset's].")] = None,
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    table_only: Annotated[bool, typer.Option(
        "--table-only", help="Only aggregate the evaluations already under --out.")] = False,
) -> None:
    """Run the whole pipeline for every task and seed, then write report.md (Table I),
    results.csv and iqm.png to --out."""
    config = ReportConfig(tasks=tuple(parse_list(tasks, str, "--tasks")),
                          seeds=tuple(parse_list(seeds, int, "--seeds")), preset=preset,
                          agents=tuple(parse_list(agents, str, "--agents")), eval_dr=dr,
                          factor_drs=tuple(parse_list(factors, str, "--factors")),
                          eval_episodes=episodes, eval_max_steps=max_steps, frames=frames,
                          updates=updates)
    if table_only:
        build_report(out_dir, config)
    else:
        run_reproduction(out_dir, config, device, on_stage=lambda s: out.print(f"[bold]{s}"))
    out.print((out_dir / "report.md").read_text(), markup=False, soft_wrap=True)
    out.print(f"report: {out_dir / 'report.md'}, plot: {out_dir / 'iqm.png'}")


def entry() -> None:
    run_app(app, log_level=logging.INFO)


if __name__ == "__main__":
    entry()
