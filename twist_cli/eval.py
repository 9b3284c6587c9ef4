"""``twist-eval``: evaluate teachers (on states) and distilled students (on images) in the
simulator, on held-out scenes by default."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer
from rich.table import Table

from twist_cli.common import new_app, out, parse_list, print_json, progress_bar, run_app
from twist_data.errors import ConfigError
from twist_data.staging import require_writable
from twist_models.device import resolve_device
from twist_models.rssm import require_posterior_read
from twist_pipeline.acting import EvalAgent, PolicyAgent, StateAgent, is_reference, load_agent
from twist_pipeline.evaluation import EvalConfig, agents_setting, run_evaluation
from twist_pipeline.factors import evaluate_factors
from twist_pipeline.learning_curve import FLOOR, ORACLE, evaluate_snapshots
from twist_pipeline.learning_curve import snapshots as snapshot_agents
from twist_pipeline.statistics import format_paired
from twist_sim.tasks import DEFAULT_ACTION_REPEAT

app = new_app()


def parse_agents(specs: list[str], device: str, posterior: str = "sample"
                 ) -> dict[str, EvalAgent | str]:
    """``NAME=SPEC`` or ``SPEC`` (named after its kind and file, or a policy's attribute) ->
    {name: loaded agent}; a reference agent stays a name (it is sized for the task once that
    is known)."""
    agents: dict[str, EvalAgent | str] = {}
    for spec in specs:
        name, _, path = spec.rpartition("=")
        if is_reference(path):
            agent: EvalAgent | str = path
            name = name or path
        else:
            agent = load_agent(path, device, posterior=posterior)
        if not name and isinstance(agent, PolicyAgent):
            name = path.rpartition(":")[2]
        elif not name:
            kind = "oracle" if isinstance(agent, StateAgent) else "student"
            name = f"{kind}-{Path(path).stem}"
        if name in agents:
            raise ConfigError(f"two agents are named {name!r}; use NAME=PATH")
        agents[name] = agent
    return agents


@app.command()
def main(
    agent: Annotated[list[str] | None, typer.Option(
        help="Teacher checkpoint (the oracle, on states), agent bundle (agent.pt, on "
             "images), a reference agent (zero, random) or module:function, a policy of "
             "the Gymnasium observations, as SPEC or NAME=SPEC; repeat for several.")] = None,
    snapshots: Annotated[Path | None, typer.Option(
        help="A twist-distil run folder: evaluate every snapshot it kept (agent-<updates>.pt), "
             "its teacher and the zero floor on the same episodes, and write the learning "
             "curve (curve.csv, curve.png) instead of --agent.")] = None,
    teacher: Annotated[Path | None, typer.Option(
        help="With --snapshots: the teacher to compare with [the run's].")] = None,
    agreement_episodes: Annotated[int, typer.Option(
        help="With --snapshots: episodes over which each snapshot acts while the teacher's "
             "filter follows it on the states (closed-loop agreement; 0: none).")] = 3,
    task: Annotated[str | None, typer.Option(help="Task [the first agent's].")] = None,
    dr: Annotated[str, typer.Option(
        help="DR preset of the scenes; several, comma-separated, evaluate every agent under "
             "each on the same episodes and tabulate what each keeps of its return under the "
             "first (factors.csv; e.g. heldout,heldout-camera,heldout-light,heldout-full).")
    ] = "heldout",
    backgrounds: Annotated[Path | None, typer.Option(
        help="Folder of your own background images/videos.")] = None,
    episodes: Annotated[int, typer.Option(help="Episodes per seed.")] = 100,
    seeds: Annotated[str, typer.Option(help="Comma-separated evaluation seeds.")] = "0",
    video: Annotated[int, typer.Option(help="Episodes per agent and seed to film.")] = 0,
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("eval"),
    device: Annotated[str, typer.Option(help="torch device.")] = "cpu",
    max_steps: Annotated[int | None, typer.Option(help="Agent steps per episode.")] = None,
    action_repeat: Annotated[int | None, typer.Option(
        help="Simulator steps per agent step [the agents' own; 2 if none says].")] = None,
    supersample: Annotated[int | None, typer.Option(
        help="Render at this multiple and downsample [each agent's training data's].")] = None,
    paired_with: Annotated[str | None, typer.Option(
        help="Agent NAME to compare every other agent with, episode by episode.")] = None,
    posterior: Annotated[str, typer.Option(
        help="How students take z from their posterior: sample (the paper), mode or mean "
             "(class probabilities).")] = "sample",
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue the evaluation in --out: episodes it holds are kept, "
                         "not run again.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
    batch: Annotated[int, typer.Option(
        help="Episodes stepped together, one batched call of each trained agent per step "
             "(the same episodes, up to float rounding).")] = 1,
    workers: Annotated[int, typer.Option(
        help="Processes that simulate and render a batch's environments (with --batch; "
             "the same episodes as 1).")] = 1,
    save_trajectories: Annotated[bool, typer.Option(
        "--save-trajectories", help="Write each episode's states, actions and rewards to "
                                    "--out/trajectories/NAME-seedS-episodeE.npz.")] = False,
) -> None:
    """Evaluate agents on the same episodes; write episodes.csv, summary.json, returns.png."""
    require_posterior_read(posterior, "--posterior")
    resolve_device(device)
    require_writable(out_dir, "output folder")
    if (snapshots is None) == (not agent):
        raise ConfigError("give either --agent (one or more) or --snapshots RUN")
    if teacher is not None and snapshots is None:
        raise ConfigError("--teacher names the teacher of --snapshots; give --agent instead")
    if snapshots is not None:
        found = snapshot_agents(snapshots)
        agents = parse_agents([str(path) for path in list(found.values())[-1:]], device,
                              posterior)
    else:
        agents = parse_agents(agent, device, posterior)
    presets = parse_list(dr, str, "--dr")
    if not presets:
        raise ConfigError("--dr names no DR preset")
    if len(presets) > 1 and (snapshots is not None or paired_with or video
                             or save_trajectories):
        raise ConfigError(f"several DR presets ({dr}) pair each agent with itself under "
                          f"{presets[0]}; --snapshots, --paired-with, --video and "
                          "--save-trajectories take one preset")
    if task is None:
        task = agents_setting(agents, "task")
        if task is None:
            raise ConfigError("no agent names its task; pass --task")
    if action_repeat is None:
        action_repeat = agents_setting(agents, "action_repeat") or DEFAULT_ACTION_REPEAT
    config = EvalConfig(task=task, dr=presets[0], episodes=episodes, max_steps=max_steps,
                        action_repeat=action_repeat, supersample=supersample,
                        posterior=posterior,
                        backgrounds=None if backgrounds is None else str(backgrounds))
    seed_list = parse_list(seeds, int, "--seeds")
    if snapshots is not None:
        with progress_bar(quiet, "evaluating snapshots", describe) as report:
            curve = evaluate_snapshots(snapshots, config, out_dir, teacher, seed_list, device,
                                       resume, batch, workers, agreement_episodes,
                                       on_progress=None if report is None
                                       else lambda done, total: report((done, total)))
        table = Table(title=f"{task}, DR {dr}, {episodes} episodes x {len(seed_list)} seeds: "
                            "the run's snapshots")
        for column in ("agent", "updates", "mean ± s.e.", "paired vs oracle ± s.e.",
                       "closed loop: h explained, action corr"):
            table.add_column(column)
        for row in curve.itertuples():
            student = row.agent not in (ORACLE, FLOOR)
            measured = student and pd.notna(row.closed_loop_h_explained)
            table.add_row(row.agent, f"{int(row.progress)}" if student else "",
                          f"{row.mean:.1f} ± {row.sem:.1f}",
                          f"{row.paired_vs_oracle:+.1f} ± {row.paired_vs_oracle_sem:.1f}"
                          if student else "",
                          f"{row.closed_loop_h_explained:.2f}, {row.closed_loop_action_corr:.2f}"
                          if measured else "")
        out.print(table)
        print_json(json.loads(curve.to_json(orient="records")), indent=None)
        return
    if len(presets) > 1:
        with progress_bar(quiet, "evaluating", describe) as report:
            factors = evaluate_factors(agents, config, presets, seed_list, out_dir, device,
                                       resume, batch, workers,
                                       on_progress=None if report is None
                                       else lambda done, total: report((done, total)))
        out.print(factor_table_view(factors, presets, task, episodes, len(seed_list)))
        print_json(json.loads(factors.to_json(orient="records")), indent=None)
        return
    with progress_bar(quiet, "evaluating", describe) as report:
        summary = run_evaluation(agents, config, seed_list, out_dir, video, device,
                                 against=paired_with, resume=resume, batch=batch,
                                 trajectories=save_trajectories, workers=workers,
                                 on_progress=None if report is None
                                 else lambda done, total: report((done, total)))
    table = Table(title=f"{task}, DR {dr}, {episodes} episodes x {len(seed_list)} seeds")
    columns = ["agent", "kind", "mean ± std (seeds)", "normalised IQM [95% CI]"]
    if paired_with is not None:
        columns.append(f"paired vs {paired_with}: mean ± s.e. (better)")
    for column in columns:
        table.add_column(column)
    for name, s in summary["agents"].items():
        iqm = ("" if "normalised_iqm" not in s else
               f"{s['normalised_iqm']:.3f} [{s['normalised_iqm_ci95'][0]:.3f}, "
               f"{s['normalised_iqm_ci95'][1]:.3f}]")
        cells = [name, s["kind"], f"{s['mean']:.1f} ± {s['std_over_seeds']:.1f}", iqm]
        if paired_with is not None:
            cells.append(format_paired(s["paired"]) if "paired" in s else "")
        table.add_row(*cells)
    out.print(table)
    print_json(summary, indent=None)


def factor_table_view(factors: pd.DataFrame, presets: list[str], task: str, episodes: int,
                      seeds: int) -> Table:
    """The factor table as the terminal shows it: an agent per row, a preset per column, each
    cell the mean return ± its standard error and, beside the first, its share of the first
    preset's return and the paired difference."""
    table = Table(title=f"{task}, {episodes} episodes x {seeds} seeds under each DR preset; "
                        f"share of {presets[0]}'s return, paired difference (better)")
    table.add_column("agent")
    for name in presets:
        table.add_column(name)
    for agent, rows in factors.groupby("agent", sort=False):
        cells = [agent]
        for row in rows.itertuples():
            cell = f"{row.mean:.1f} ± {row.sem:.1f}"
            if row.dr != presets[0]:
                cell += (f"\n{row.ratio:.2f}, {row.paired:+.1f} ± {row.paired_sem:.1f} "
                         f"({int(row.better)}/{row.episodes})")
            cells.append(cell)
        table.add_row(*cells)
    return table


def describe(progress: tuple[int, int]) -> tuple[int, int, str]:
    """The bar's figures: episodes done of those asked for."""
    done, total = progress
    return done, total, f"{done}/{total} episodes"


def entry() -> None:
    run_app(app, log_level=logging.INFO)


if __name__ == "__main__":
    entry()
