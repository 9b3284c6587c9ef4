"""``twist-data``: inspect, verify, export, re-render and synthesise matching datasets."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn
from rich.table import Table

from twist_cli.common import SIM_MODULES, err, new_app, out, parse_list, run_app
from twist_data.errors import ConfigError, TwistError
from twist_data.export import export_hdf5, export_video
from twist_data.reader import open_dataset
from twist_data.staging import human_bytes, require_new_file
from twist_data.summary import dataset_info
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_data.verify import quick_problems, verify_dataset

try:  # for the DR options' help; the commands that simulate import twist_sim themselves
    from twist_sim.randomisation import DR_PRESETS, TRAINING_DR
except ModuleNotFoundError as missing:  # without the sim extra D is still read and exported
    if (missing.name or "").split(".")[0] not in SIM_MODULES:
        raise
    DR_PRESETS, TRAINING_DR = {}, "train-wide"

app = new_app(help="Inspect, verify, export, re-render and synthesise TWIST matching datasets.",
              no_args_is_help=True)

DatasetArg = Annotated[Path, typer.Argument(help="Dataset folder (or one shard folder).")]
Overwrite = Annotated[bool, typer.Option("--overwrite", help="Replace the output file if it exists.")]


@contextmanager
def progress_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A Rich progress bar on stderr, exposed as an ``on_progress(done, total)`` callback."""
    with Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                  TimeRemainingColumn(), console=err, transient=True) as bar:
        task = bar.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update


@app.command()
def info(dataset: DatasetArg,
         as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False) -> None:
    """Shards, episodes, steps, views, shapes, dimensions, bytes and compression; exit 1, with
    what it saw, when a look without decoding already finds damage (verify checks every byte)."""
    seen = quick_problems(dataset)
    if seen:
        for problem in seen:
            err.print(f"problem: {problem}", markup=False, highlight=False, soft_wrap=True)
        err.print(f"{len(seen)} problem(s) seen without decoding; run `twist-data verify "
                  f"{dataset}` for every one", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(1)
    summary = dataset_info(dataset)
    if as_json:
        out.print_json(json.dumps(summary))
        return
    table = Table(title=f"twist dataset {summary['path']}", show_header=False)
    rows = [
        ("format version", summary["format_version"]), ("task", summary["task"]),
        ("shards", len(summary["shards"])), ("episodes", summary["episodes"]),
        ("steps", summary["steps"]), ("views K", summary["views"]),
        ("image shape", "x".join(map(str, summary["image_shape"]))),
        ("frame pairs", "stored" if summary["frame_pairs"] else "-"),
        ("state / action / physics dims",
         f"{summary['state_dim']} / {summary['action_dim']} / {summary['physics_dim']}"),
        ("DR parameters", ", ".join(summary["dr_params"]) or "-"),
        ("bytes on disk", human_bytes(summary["bytes_on_disk"])),
        ("uncompressed", human_bytes(summary["bytes_uncompressed"])),
        ("compression ratio", f"{summary['compression_ratio']:.2f}"
         if summary["compression_ratio"] else "-"),
    ]
    if summary["episode_return"]:
        r = summary["episode_return"]
        rows.append(("episode return min/mean/max", f"{r['min']:.1f} / {r['mean']:.1f} / "
                                                    f"{r['max']:.1f}"))
    for key, value in rows:
        table.add_row(key, str(value))
    out.print(table)
    out.print(f"checked without decoding a chunk: shards, arrays and their files; `twist-data "
              f"verify {dataset}` decodes and checksums every byte", soft_wrap=True,
              markup=False, highlight=False)


@app.command()
def episodes(dataset: DatasetArg,
             csv: Annotated[Path | None, typer.Option(help="Write the table to this CSV file.")]
             = None, overwrite: Overwrite = False) -> None:
    """Per-episode table: shard, length, return, seed and provenance."""
    if csv is not None:
        require_new_file(csv, overwrite, "CSV file")
    table = open_dataset(dataset).episodes()
    if csv is not None:
        table.to_csv(csv)
        err.print(f"wrote {len(table)} episodes to {csv}")
        return
    shown = table.assign(committed=table["committed"].dt.strftime("%Y-%m-%d %H:%M:%S"))
    with pd.option_context("display.max_rows", None, "display.width", 200,
                           "display.float_format", "{:.3f}".format):
        out.print(shown.to_string(), markup=False, highlight=False, soft_wrap=True)


#: Steps ``verify`` re-renders unless told otherwise, where D can be re-rendered: a few
#: seconds, most of them the renderer's start.
DEFAULT_RERENDER = 8


@app.command()
def verify(
    dataset: DatasetArg,
    rerender: Annotated[int | None, typer.Option(
        help=f"Also re-render this many random steps from their physics state and DR "
             f"parameters and require pixel-identical images (simulated datasets only; 0: "
             f"none) [default: {DEFAULT_RERENDER} where D can be re-rendered].",
        show_default=False)] = None,
) -> None:
    """Full integrity check; exit 0 when clean, 1 with one line per problem otherwise."""
    if rerender is not None and rerender < 0:
        raise ConfigError(f"--rerender takes a number of steps >= 0, got {rerender}")
    with progress_bar("verifying") as update:
        report = verify_dataset(dataset, on_progress=update)
    if rerender is None:  # a checksum cannot tell a frame rewritten whole: a redraw can
        data = open_dataset(dataset)
        rerender = DEFAULT_RERENDER if data.has_images and "render" in data.spec.extra else 0
    if rerender > 0 and report.ok:
        from twist_sim.rerender import check_reproduction

        with progress_bar("re-rendering"):
            report.problems.extend(check_reproduction(open_dataset(dataset), rerender))
            report.notes.append(f"{rerender} random steps re-rendered and compared")
    for note in report.notes:
        err.print(f"note: {note}")
    if report.ok:
        out.print(f"OK: {report.shards} shard(s), {report.episodes} episodes, "
                  f"{report.steps} steps verified")
        return
    for problem in report.problems:
        err.print(f"problem: {problem}", markup=False, highlight=False, soft_wrap=True)
    err.print(f"FAILED: {len(report.problems)} problem(s) in {dataset}")
    raise typer.Exit(1)


@app.command("export-video")
def export_video_cmd(
    dataset: DatasetArg,
    out_path: Annotated[Path, typer.Argument(metavar="OUT", help="Output .mp4 or .gif file.")],
    episode: Annotated[int, typer.Option(help="Global episode index (-1: the last).")] = 0,
    fps: Annotated[int, typer.Option(help="Frames per second.")] = 25,
    scale: Annotated[int, typer.Option(help="Pixel upscaling factor.")] = 4,
    overwrite: Overwrite = False,
) -> None:
    """Write one episode's K views side by side as a video."""
    path = export_video(dataset, episode, out_path, fps=fps, scale=scale, overwrite=overwrite)
    out.print(f"wrote {path}")


@app.command()
def salvage(
    dataset: DatasetArg,
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="New dataset folder to create.")],
) -> None:
    """Copy every episode of a damaged dataset that still reads cleanly into OUT, and list
    the episodes left behind (see `verify`)."""
    from twist_data.salvage import salvage_dataset

    with progress_bar("salvaging") as update:
        report = salvage_dataset(dataset, out_dir, on_episode=update)
    for name, why in report.dropped_shards.items():
        err.print(f"left behind shard {name}: {why}", markup=False, highlight=False,
                  soft_wrap=True)
    for index, why in report.dropped.items():
        err.print(f"left behind episode {index}: {why}", markup=False, highlight=False,
                  soft_wrap=True)
    whole = " of the shards that open" if report.dropped_shards else ""
    out.print(f"kept {len(report.kept)} of {len(report.kept) + len(report.dropped)} episodes"
              f"{whole} in {out_dir}")


@app.command("export-hdf5")
def export_hdf5_cmd(
    dataset: DatasetArg,
    out_path: Annotated[Path, typer.Argument(metavar="OUT", help="Output .h5 file.")],
    overwrite: Overwrite = False,
) -> None:
    """Write every committed episode into one HDF5 file (layout in datasets.md)."""
    with progress_bar("exporting") as update:
        path = export_hdf5(dataset, out_path, on_progress=update, overwrite=overwrite)
    out.print(f"wrote {path}")


@app.command("export-minari")
def export_minari_cmd(
    dataset: DatasetArg,
    dataset_id: Annotated[str, typer.Argument(
        metavar="DATASET_ID", help="Minari dataset ID, [namespace/]name-v<version>, e.g. "
                                   "twist/cartpole-balance-v0.")],
    root: Annotated[Path | None, typer.Option(
        help="Minari's dataset root [$MINARI_DATASETS_PATH, else ~/.minari/datasets].")] = None,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="Replace a Minari dataset of that ID.")] = False,
    jpeg: Annotated[bool, typer.Option(
        "--jpeg", help="Store images as JPEG (smaller, lossy) [lossless].")] = False,
) -> None:
    """Write every committed episode as a Minari dataset (Gymnasium's convention; needs the
    minari extra), for offline-RL libraries that read Minari."""
    from twist_data.minari_export import export_minari

    with progress_bar("exporting") as update:
        path = export_minari(dataset, dataset_id, root=root, overwrite=overwrite, jpeg=jpeg,
                             on_progress=update)
    out.print(f"wrote {path}")


@app.command("export-lerobot")
def export_lerobot_cmd(
    dataset: DatasetArg,
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="LeRobot dataset folder to "
                                                                "create.")],
    episodes: Annotated[str | None, typer.Option(
        help="Comma-separated episode indices, negative from the end (default: all); "
             "exported in D's order.")] = None,
    views: Annotated[str | None, typer.Option(
        help="Comma-separated views to export (default: all).")] = None,
    fps: Annotated[int | None, typer.Option(
        help="Frames per second (default: from the stored physics' clock).")] = None,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="Replace OUT if it holds a LeRobot dataset.")] = False,
) -> None:
    """Write D as a LeRobotDataset v3.0 folder that LeRobot's loader opens: each view a
    lossless video, the privileged state as observation.environment_state, the physics,
    actions, rewards and flags as Parquet rows, DR draws and provenance beside them (needs
    the lerobot extra)."""
    from twist_data.lerobot_export import export_lerobot

    chosen = None if episodes is None else parse_list(episodes, int, "--episodes")
    shown = None if views is None else parse_list(views, int, "--views")
    with progress_bar("exporting") as update:
        path = export_lerobot(dataset, out_dir, episodes=chosen, views=shown, fps=fps,
                              overwrite=overwrite, on_progress=update)
    out.print(f"wrote {path}")


@app.command()
def viz(
    dataset: DatasetArg,
    episode: Annotated[int, typer.Option(help="Global episode index (-1: the last).")] = 0,
    save: Annotated[Path | None, typer.Option(
        help="Write a .rrd file to open later (rerun FILE.rrd) instead of spawning the "
             "viewer.")] = None,
) -> None:
    """Show one episode in the rerun viewer: every view as images on a step timeline, with
    state, action, reward, flags and DR values beside them (needs the viz extra)."""
    from twist_data.viewer import log_episode

    path = log_episode(dataset, episode, save)
    out.print(f"wrote {path}" if path is not None else "sent to the rerun viewer")


@app.command()
def synth(
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="Dataset folder to create.")],
    episodes: Annotated[int, typer.Option(help="Number of episodes.")] = 4,
    steps: Annotated[int, typer.Option(help="Steps per episode.")] = 60,
    views: Annotated[int, typer.Option(help="K renders per step.")] = 2,
    image_size: Annotated[int, typer.Option(help="Image side in pixels.")] = 64,
    shards: Annotated[int, typer.Option(help="Number of shards.")] = 1,
    length_jitter: Annotated[int, typer.Option(help="Shorten episodes by up to this.")] = 0,
    seed: Annotated[int, typer.Option(help="Seed.")] = 0,
) -> None:
    """Write a synthetic dataset (the generator the tests use as fixtures)."""
    try:
        config = SynthConfig(episodes=episodes, steps=steps, views=views, image_size=image_size,
                             shards=shards, length_jitter=length_jitter, seed=seed)
    except ValueError as exc:
        raise TwistError(f"invalid synth options: {exc}") from None
    with progress_bar("writing") as update:
        write_synthetic_dataset(out_dir, config, on_episode=update)
    out.print(f"wrote {episodes} episodes x {steps} steps x {views} views to {out_dir}")


@app.command()
def photos(
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="Folder to create.")],
) -> None:
    """Write the photographs of everyday scenes that installed packages ship (matplotlib's;
    more with scikit-image) as a folder for `twist-eval --backgrounds OUT`: real scenes a
    student never saw, without a download."""
    from twist_sim.backgrounds import shipped_photographs, write_background_folder

    images = shipped_photographs()
    write_background_folder(out_dir, images)
    out.print(f"wrote {len(images)} photographs to {out_dir}: {', '.join(images)}")
    if len(images) == 1:
        out.print("scikit-image is not installed: only matplotlib's photograph was written")


@app.command()
def textures(
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="Folder to create.")],
    bank: Annotated[str, typer.Option(help="Procedural bank whose families to draw: train, "
                                           "wide, leaves or heldout.")] = "wide",
    count: Annotated[int, typer.Option(help="Textures to write.")] = 1024,
    size: Annotated[int, typer.Option(help="Texture side in pixels (256: the bank's for "
                                           "64x64 renders supersampled 2x).")] = 256,
    seed: Annotated[int, typer.Option(help="Seed (the procedural banks draw with 0).")] = 1,
) -> None:
    """Write a procedural bank's textures as a folder a user can edit by hand and render D
    under (`twist-data render D D2 --backgrounds OUT`)."""
    from twist_sim.backgrounds import bank_textures, write_background_folder

    write_background_folder(out_dir, bank_textures(bank, count, size, seed))
    out.print(f"wrote {count} textures of the {bank} bank's families to {out_dir}")


BackgroundsOption = Annotated[Path | None, typer.Option(
    "--backgrounds", help="Folder of images/videos to use as backgrounds instead of the "
                          "procedural bank.")]


@app.command()
def tasks() -> None:
    """The simulated tasks with their state, action and physics dimensions."""
    from twist_sim.tasks import TASKS, TaskEnv, load_task_modules

    load_task_modules()
    table = Table(title="twist tasks (action repeat 2)")
    for column in ("task", "source", "state", "action", "physics", "state layout"):
        table.add_column(column)
    for name, spec in TASKS.items():
        env = TaskEnv(name)
        layout = ", ".join(f"{k}:{n}" for k, n in env.state_layout)
        table.add_row(name, spec.source, str(env.state_dim), str(env.action_dim),
                      str(env.physics_dim), layout)
    out.print(table)


@app.command()
def render(
    dataset: DatasetArg,
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="New dataset folder to create.")],
    reproduce: Annotated[bool, typer.Option(
        help="Rebuild the dataset's own images from its stored physics, DR draws and render "
             "settings (a stripped D too) and check them against the recorded ones, instead "
             "of drawing new DR parameters; the DR options below then do not apply.")] = False,
    workers: Annotated[int, typer.Option(
        help="Processes rebuilding blocks of episodes with --reproduce, each into shards of "
             "its own (global episode order kept).")] = 1,
    accept_other_gl: Annotated[bool, typer.Option(
        help="With --reproduce: exit 0 when rebuilt frames differ from the recorded ones, as "
             "they do where another GL implementation draws them (the count is reported).")
        ] = False,
    dr: Annotated[str, typer.Option(help=f"DR preset: {', '.join(DR_PRESETS)}.")] = TRAINING_DR,
    views: Annotated[int, typer.Option(help="K new views per step.")] = 2,
    image_size: Annotated[int | None, typer.Option(
        help="Image side in pixels (default: the dataset's).")] = None,
    add_views: Annotated[bool, typer.Option(
        help="Keep the dataset's views and append the new ones.")] = False,
    supersample: Annotated[int | None, typer.Option(
        help="Render at this multiple and downsample (default: the dataset's).")] = None,
    backgrounds: BackgroundsOption = None,
    seed: Annotated[int, typer.Option(help="Seed of the new DR parameters.")] = 0,
    episodes: Annotated[str | None, typer.Option(
        help="Comma-separated episode indices to re-render, negative from the end (default: "
             "all); each renders as it would in a full re-render.")] = None,
    pairs: Annotated[bool, typer.Option(
        help="Also store each step's frame pair, the step before drawn in the step's scene "
             "(datasets.md, pair_image), from which the readout recipe reads the speeds no "
             "single frame shows; --reproduce rebuilds the pairs a D stored without it.")
        ] = False,
) -> None:
    """Re-render a simulated dataset's stored physics states under a new DR config into OUT,
    or with --reproduce rebuild its own images exactly."""
    from twist_sim.rerender import reproduce_dataset, rerender_dataset

    chosen = None if episodes is None else parse_list(episodes, int, "--episodes")
    if reproduce:
        with progress_bar("rebuilding") as update:
            report = reproduce_dataset(dataset, out_dir, workers, chosen, on_episode=update,
                                       pairs=True if pairs else None)
        gl = report.gl.get("gl_renderer", "an unknown GL")
        if report.exact:
            out.print(f"wrote {out_dir}: {report.episodes} episodes rebuilt in "
                      f"{report.seconds:.1f} s by {report.workers} worker(s), every frame "
                      f"identical to the recorded ones ({gl})", soft_wrap=True)
            return
        err.print(f"wrote {out_dir}, but {len(report.differing)} of {report.episodes} rebuilt "
                  f"episodes differ from the recorded frames (first: episode "
                  f"{report.differing[0]}); they were drawn by {gl}, and frames are "
                  "bit-identical only under the GL implementation that recorded them",
                  soft_wrap=True)
        if not accept_other_gl:
            raise typer.Exit(1)
        return
    if accept_other_gl:
        raise ConfigError("--accept-other-gl applies to --reproduce alone")
    if workers != 1:
        raise ConfigError(f"--workers {workers} applies to --reproduce alone")
    from twist_sim.randomisation import dr_preset

    config = dr_preset(dr, backgrounds)
    if supersample is None:
        supersample = open_dataset(dataset).spec.supersample or 1
    with progress_bar("rendering") as update:
        rerender_dataset(dataset, out_dir, config, views=views, image_size=image_size,
                         add_views=add_views, supersample=supersample, seed=seed,
                         episodes=chosen, on_episode=update, pairs=pairs)
    out.print(f"wrote {out_dir}")


@app.command()
def strip(
    dataset: DatasetArg,
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="New dataset folder to create.")],
    teacher: Annotated[bool, typer.Option(
        help="Keep each collector's final teacher beside it, its weights alone.")] = False,
) -> None:
    """Copy a dataset without its images (a few MB that `render --reproduce` rebuilds into the
    whole D, bit for bit on the same GL implementation)."""
    from twist_data.strip import strip_dataset
    from twist_models.checkpoint import weights_only

    with progress_bar("stripping") as update:
        strip_dataset(dataset, out_dir, weights_only if teacher else None, on_episode=update)
    out.print(f"wrote {out_dir}: {human_bytes(open_dataset(out_dir).disk_bytes())} "
              f"(from {human_bytes(open_dataset(dataset).disk_bytes())})", soft_wrap=True)


@app.command()
def record(
    task: Annotated[str, typer.Argument(help="Task name (see `twist-data tasks`).")],
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="Dataset folder (a new shard "
                                                               "is added).")],
    episodes: Annotated[int, typer.Option(help="Number of episodes.")] = 2,
    dr: Annotated[str, typer.Option(help=f"DR preset: {', '.join(DR_PRESETS)}.")] = TRAINING_DR,
    views: Annotated[int, typer.Option(help="K views per step.")] = 2,
    image_size: Annotated[int, typer.Option(help="Image side in pixels.")] = 64,
    max_steps: Annotated[int | None, typer.Option(
        help="End episodes after this many agent steps (default: the task's 500).")] = None,
    shard: Annotated[str, typer.Option(help="Name of the shard to create.")] = "random-000",
    backgrounds: BackgroundsOption = None,
    seed: Annotated[int, typer.Option(help="Seed of everything.")] = 0,
) -> None:
    """Record random-policy episodes of a task with K randomised views (prefill, demos)."""
    from twist_sim.randomisation import dr_preset
    from twist_sim.rollout import record_dataset

    config = dr_preset(dr, backgrounds)
    with progress_bar("recording") as update:
        record_dataset(out_dir, task, episodes, config, views=views, image_size=image_size,
                       max_steps=max_steps, seed=seed, shard=shard, on_episode=update)
    out.print(f"wrote {episodes} episodes of {task} to {out_dir}")


@app.command("contact-sheet")
def contact_sheet_cmd(
    task: Annotated[str, typer.Argument(help="Task name (see `twist-data tasks`).")],
    out_path: Annotated[Path, typer.Argument(metavar="OUT", help="Output .png file.")],
    views: Annotated[int, typer.Option(help="Views per row.")] = 6,
    image_size: Annotated[int, typer.Option(help="Image side in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Seed of the state and the DR draws.")] = 0,
    backgrounds: BackgroundsOption = None,
) -> None:
    """PNG of one state: a row of train-distribution views, a row of held-out views."""
    from twist_sim.contact_sheets import contact_sheet, default_rows, write_contact_sheet
    from twist_sim.randomisation import dr_preset

    rows = default_rows()
    if backgrounds is not None:
        rows["user"] = dr_preset("heldout", backgrounds)
    sheet = contact_sheet(task, views=views, image_size=image_size, seed=seed, rows=rows)
    out.print(f"wrote {write_contact_sheet(out_path, sheet)}")


def main() -> None:
    """Entry point: known errors become one line on stderr and exit code 2."""
    run_app(app)


if __name__ == "__main__":
    main()
