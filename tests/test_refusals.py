"""Refusals before any work: absurd sizes against the machine, outputs that cannot be written or
already exist, options checked before a file is created, and a refused set-up undone. Each
case: a project exception (or exit 2 and one line naming the value), and the disk as it was."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import run_command
from tests.test_writer import tree_snapshot
from twist_cli import data
from twist_data.errors import ConfigError, DatasetCorruptError, TwistError
from twist_data.reader import open_dataset
from twist_data.salvage import salvage_dataset
from twist_data.staging import (
    removed_on_failure,
    require_memory,
    require_new_file,
    require_writable,
)
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_data.verify import quick_problems
from twist_models.config import teacher_preset
from twist_models.distillation import distil_preset
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline.baselines import BaselineConfig, train_baseline
from twist_pipeline.collect import MAX_FRAMES, CollectConfig, collect, collect_preset
from twist_pipeline.distil import distil
from twist_pipeline.evaluation import MAX_EPISODES, EvalConfig, run_evaluation

UNWRITABLE = Path("/proc/twist-refusals")  # root cannot create a file under /proc either


def data_cli(*args: object) -> subprocess.CompletedProcess[str]:
    """``twist-data ARGS`` run in this process (a subprocess per case costs seconds of
    imports): its exit code and what it wrote to stderr."""
    stderr, argv = io.StringIO(), sys.argv
    sys.argv = ["twist-data", *map(str, args)]
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            data.main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 0
    finally:
        sys.argv = argv
    return subprocess.CompletedProcess(args, code, "", stderr.getvalue())


def one_line_refusal(result: subprocess.CompletedProcess[str], message: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_outputs_are_probed_without_creating_anything(tmp_path: Path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("mine")
    require_writable(tmp_path / "new" / "deeper", "output")  # creatable: accepted
    assert list(tmp_path.iterdir()) == [afile]  # ...and nothing was made to find out
    with pytest.raises(ConfigError, match=r"'/proc/twist-refusals/x' cannot be written in '/proc'"):
        require_writable(UNWRITABLE / "x", "output")
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        require_writable(afile / "inside", "output")
    with pytest.raises(ConfigError, match=r"exists; pass --overwrite to replace it"):
        require_new_file(afile, overwrite=False)
    require_new_file(afile, overwrite=True)
    with pytest.raises(ConfigError, match="is a folder; name a file"):
        require_new_file(tmp_path, overwrite=True)
    with pytest.raises(ConfigError, match=r"a batch needs 2\.0 GiB of memory; this machine has "
                                          r"1\.0 GiB"):
        require_memory(2 * 2**30, "a batch", available=2**30)
    require_memory(2**30, "a batch", available=2**30)
    assert afile.read_text() == "mine"


@pytest.mark.parametrize("before", ["absent", "empty", "resumed"])
def test_a_refused_set_up_is_undone_but_a_resumed_run_is_kept(tmp_path: Path,
                                                             before: str) -> None:
    out = tmp_path / "run"
    if before != "absent":
        out.mkdir()
    if before == "resumed":
        (out / "latest.pt").write_text("a run's work")
    with pytest.raises(ConfigError), removed_on_failure(out):
        (out / "sub").mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text("{}")
        raise ConfigError("refused")
    # A folder that held a run is not the set-up's to clean: nothing in it is removed.
    expected = {"absent": None, "empty": [],
                "resumed": ["config.json", "latest.pt", "sub"]}[before]
    assert (sorted(p.name for p in out.iterdir()) if out.exists() else None) == expected
    if before == "resumed":
        assert (out / "latest.pt").read_text() == "a run's work"


def test_data_commands_refuse_outputs_and_sizes_up_front(small_dataset: Path,
                                                         tmp_path: Path) -> None:
    existing = tmp_path / "existing.gif"
    existing.write_bytes(b"a user's file")
    before = tree_snapshot(tmp_path)
    cases = [
        (("episodes", small_dataset, "--csv", UNWRITABLE / "e.csv"),
         "CSV file '/proc/twist-refusals/e.csv' cannot be written in '/proc'"),
        (("export-hdf5", small_dataset, UNWRITABLE / "d.h5"), "cannot be written in '/proc'"),
        (("export-hdf5", small_dataset, existing), "exists; pass --overwrite to replace it"),
        (("export-video", small_dataset, existing), "exists; pass --overwrite to replace it"),
        (("export-video", small_dataset, tmp_path / "v.gif", "--scale", "100000"),
         "episode 0's video at scale 100000 needs"),
        (("synth", tmp_path / "s", "--episodes", "3", "--steps", "1000000000000"),
         "a synthetic episode of 1000000000000 steps needs"),
        (("synth", tmp_path / "s", "--image-size", "100000"),
         "a synthetic episode of 60 steps needs"),
        (("synth", tmp_path / "s", "--episodes", "1000000000", "--steps", "1000"),
         "writing 1000000000 synthetic episodes of 1000 steps needs about"),
        (("synth", UNWRITABLE, "--episodes", "1"), "cannot be written in '/proc'"),
        (("synth", tmp_path / "s", "--episodes", "abc"),
         "invalid value 'abc' for --episodes"),
        (("verify", small_dataset, "--rerender", "-1"),
         "--rerender takes a number of steps >= 0, got -1"),
        (("verify", small_dataset, "--rerender", "2"),
         "was not rendered by twist's simulator: it records no dr/background"),
    ]
    for args, message in cases:
        one_line_refusal(data_cli(*args), message)
    assert tree_snapshot(tmp_path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.gif"]
    replaced = data_cli("export-video", small_dataset, existing, "--scale", "1", "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert existing.read_bytes()[:3] == b"GIF"


def test_info_reports_damage_it_sees_without_decoding(fresh_dataset: Path) -> None:
    assert quick_problems(fresh_dataset) == []
    shard = sorted(fresh_dataset.glob("*.zarr"))[1]
    (shard / "data" / "state" / "c" / "0" / "0").unlink()
    image = shard / "data" / "image" / "c" / "0" / "0" / "0" / "0" / "0"
    image.write_bytes(image.read_bytes()[:10])
    image, state = quick_problems(fresh_dataset)
    steps = open_dataset(fresh_dataset).shards[1].n_steps
    assert image.startswith(f"shard {shard.stem}, data/image: steps 0-{steps - 1} (episodes "
                            "0-2): truncated: 10 bytes, its index alone needs")
    assert state == f"shard {shard.stem}, data/state: 1 chunk file(s) missing"
    result = data_cli("info", fresh_dataset)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert f"run `twist-data verify {fresh_dataset}`" in result.stderr


def test_salvage_keeps_the_shards_that_open_and_fails_when_it_keeps_nothing(
        tmp_path: Path) -> None:
    source = write_synthetic_dataset(tmp_path / "ds", SynthConfig(episodes=4, steps=12, shards=2,
                                                                  image_size=16, seed=2))
    (source / "synth-001.zarr" / "zarr.json").unlink()
    report = salvage_dataset(source, tmp_path / "kept")
    assert report.kept == [0, 1] and list(report.dropped_shards) == ["synth-001.zarr"]
    kept = open_dataset(tmp_path / "kept")
    assert [s.name for s in kept.shards] == ["synth-000"] and kept.n_episodes == 2
    for index in range(2):  # both intact shards' episodes, byte for byte
        for key, value in open_dataset(source / "synth-000.zarr").episode(index).arrays().items():
            assert (kept.episode(index).arrays()[key] == value).all(), key
    shutil.rmtree(source / "synth-000.zarr" / "data" / "reward")
    with pytest.raises(DatasetCorruptError, match=r"nothing in .* could be kept, so nothing "
                                                  r"was written"):
        salvage_dataset(source, tmp_path / "none")
    assert not (tmp_path / "none").exists()
    result = data_cli("salvage", source, tmp_path / "none")
    assert result.returncode == 2 and "nothing in" in result.stderr.splitlines()[-1]
    assert not (tmp_path / "none").exists()


def test_evaluation_options_are_refused_before_its_folder_is_made(tmp_path: Path) -> None:
    for settings, message in (({"max_steps": -1}, "max_steps must be >= 1, got -1"),
                              ({"backgrounds": str(tmp_path / "missing")},
                               "background directory .* does not exist"),
                              ({"backgrounds": str(tmp_path)},
                               "background directory .* has no images or videos"),
                              ({"episodes": MAX_EPISODES + 1}, "episodes must lie in")):
        with pytest.raises(ConfigError, match=message):
            EvalConfig(**settings)
    config = EvalConfig(episodes=1, max_steps=2)
    with pytest.raises(ConfigError, match=r"episodes to film .* \(--video\) must be >= 0, got -1"):
        run_evaluation({"zero": "zero"}, config, [0], tmp_path / "eval", videos=-1)
    with pytest.raises(ConfigError, match="cannot be written in '/proc'"):
        run_evaluation({"zero": "zero"}, config, [0], UNWRITABLE)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal is for a torch without CUDA")
def test_evaluation_on_a_missing_gpu_is_one_line(tmp_path: Path) -> None:
    result = run_command("eval", "--agent", "zero", "--task", "cartpole-balance", "--device",
                         "cuda", "--out", str(tmp_path / "e"))
    one_line_refusal(result, "device 'cuda' is not available")
    assert list(tmp_path.iterdir()) == []


def test_collect_creates_nothing_until_its_inputs_are_good(tmp_path: Path, gl: None) -> None:
    with pytest.raises(ConfigError, match=f"frames {MAX_FRAMES + 1} is more than"):
        dataclasses.replace(collect_preset("tiny"), frames=MAX_FRAMES + 1)
    afile = tmp_path / "afile"
    afile.write_text("x")
    for settings in ({"backgrounds": str(tmp_path / "missing")}, {"backgrounds": str(afile)},
                     {"views": 1_000_000}):
        config = dataclasses.replace(collect_preset("tiny"), **settings)
        with pytest.raises(TwistError):
            collect(tmp_path / "out", config)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"], settings
    assert isinstance(collect_preset("tiny"), CollectConfig)


def test_trainers_refuse_before_writing_and_undo_a_refused_set_up(tmp_path: Path) -> None:
    dataset = write_synthetic_dataset(tmp_path / "ds", SynthConfig(episodes=4, steps=30,
                                                                   image_size=64, seed=5))
    teacher = save_teacher(tmp_path / "teacher.pt", Teacher(teacher_preset("tiny", 5, 1)))
    before = tree_snapshot(tmp_path)
    with pytest.raises(ConfigError, match=r"a batch of 1000000000000 windows of 8 steps .* "
                                          r"needs .* this machine has"):
        distil(dataset, tmp_path / "big", distil_preset("tiny", batch_size=10**12),
               teacher=teacher)
    with pytest.raises(ConfigError, match="a batch of 1000000000000 windows of 8 steps"):
        train_baseline(dataset, tmp_path / "big", BaselineConfig(model="tiny", length=8,
                                                                 batch_size=10**12))
    with pytest.raises(TwistError, match="view index 9 is out of range"):
        train_baseline(dataset, tmp_path / "view", BaselineConfig(model="tiny", length=8,
                                                                  view=9))
    # Damage that only the run's own set-up meets: its folder goes with the refusal.
    state = next(dataset.glob("*.zarr")) / "data" / "state" / "c" / "0" / "0"
    state.write_bytes(b"xx")
    with pytest.raises(TwistError):
        distil(dataset, tmp_path / "damaged", distil_preset("tiny"), teacher=teacher)
    assert not (tmp_path / "big").exists() and not (tmp_path / "view").exists()
    assert not (tmp_path / "damaged").exists()
    state.unlink()
    assert set(tree_snapshot(tmp_path)) == set(before) - {state.relative_to(tmp_path).as_posix()}
