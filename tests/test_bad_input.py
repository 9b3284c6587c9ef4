"""Bad input: one clear sentence, a project exception, exit code != 0, nothing changed on disk."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import zarr

from tests.conftest import run_command
from tests.test_writer import tree_snapshot
from twist_data.errors import FormatVersionError, NotADatasetError, SchemaMismatchError
from twist_data.reader import open_dataset
from twist_data.schema import FORMAT_VERSION
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_data.verify import verify_dataset


def cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return run_command("data", *map(str, args))


def test_not_a_dataset(tmp_path: Path) -> None:
    with pytest.raises(NotADatasetError, match="does not exist"):
        open_dataset(tmp_path / "missing")
    with pytest.raises(NotADatasetError, match=r"holds no shard \(\*\.zarr folder\)"):
        open_dataset(tmp_path)
    zarr.open_group(tmp_path / "other.zarr", mode="w")  # a zarr store, but not ours
    with pytest.raises(NotADatasetError, match="is not a twist dataset shard"):
        open_dataset(tmp_path)


def test_newer_format_version_is_refused(fresh_dataset: Path) -> None:
    meta = next(fresh_dataset.glob("*.zarr")) / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["twist"]["format_version"] = 99
    meta.write_text(json.dumps(doc))
    with pytest.raises(FormatVersionError, match="has format_version 99, but this library reads "
                                                 f"versions up to {FORMAT_VERSION}"):
        open_dataset(fresh_dataset)


def test_missing_array_is_named(fresh_dataset: Path) -> None:
    shard = next(fresh_dataset.glob("*.zarr"))
    shutil.rmtree(shard / "data" / "action")
    report = verify_dataset(fresh_dataset)
    assert [str(p) for p in report.problems] == [
        f"shard {shard.stem}, data/action: array data/action is missing"]


def test_truncated_image_file_is_named(fresh_dataset: Path) -> None:
    shard = sorted(fresh_dataset.glob("*.zarr"))[1]
    chunk = shard / "data" / "image" / "c" / "0" / "0" / "0" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-500])
    report = verify_dataset(fresh_dataset)
    assert len(report.problems) == 1
    problem = report.problems[0]
    assert problem.shard == shard.stem and problem.array == "data/image"
    assert "corrupt index" in problem.message and "(episodes 0-2)" in problem.message
    sampler_reader = open_dataset(fresh_dataset).shards[1].frames
    with pytest.raises(Exception, match="corrupt index"):
        sampler_reader._file(0)


def test_nan_in_stored_data_is_located(fresh_dataset: Path) -> None:
    shard = next(fresh_dataset.glob("*.zarr"))
    state = zarr.open_array(shard / "data" / "state", mode="r+")
    ends = zarr.open_array(shard / "meta" / "episode_ends")[:]
    state[int(ends[0]) + 5, 2] = float("nan")
    (problem,) = verify_dataset(fresh_dataset).problems
    assert problem.episode == 1
    assert "array 'state' contains NaN or inf (first at step 5 of the episode)" in problem.message


def test_shards_with_different_schemas_do_not_mix(tmp_path: Path) -> None:
    write_synthetic_dataset(tmp_path, SynthConfig(episodes=1, steps=10, image_size=16))
    other = tmp_path / "other"
    write_synthetic_dataset(other, SynthConfig(episodes=1, steps=10, image_size=32))
    (other / "synth-000.zarr").rename(tmp_path / "synth-big.zarr")
    with pytest.raises(SchemaMismatchError, match="differ in image_height, image_width"):
        open_dataset(tmp_path)


def test_cli_errors_are_one_line_nonzero_and_change_nothing(fresh_dataset: Path,
                                                            tmp_path: Path) -> None:
    afile = tmp_path / "afile.txt"
    afile.write_text("not a dataset")
    other = tmp_path / "other"
    shutil.copytree(next(fresh_dataset.glob("*.zarr")), other / "collect-000.zarr")
    before = tree_snapshot(fresh_dataset)
    other_before = tree_snapshot(other)
    cases = [
        (("info", tmp_path / "nope"), "does not exist"),
        (("episodes", tmp_path), "holds no shard"),
        (("export-video", fresh_dataset, tmp_path / "v.avi"), "must end in .mp4 or .gif"),
        (("export-video", fresh_dataset, tmp_path / "v.mp4", "--episode", "99"),
         "dataset has 6 episodes; index 99 is out of range"),
        (("export-video", fresh_dataset, tmp_path / "v.mp4", "--episode", "-7"),
         "dataset has 6 episodes; index -7 is out of range"),
        (("synth", tmp_path / "s", "--steps", "1"), "steps must be >= 2, got 1"),
        (("render", fresh_dataset, tmp_path / "r", "--image-size", "0"),
         "image_size must be >= 1 (or omitted for the dataset's), got 0"),
        (("render", fresh_dataset, tmp_path / "r", "--episodes", "0,-9"),
         "dataset has 6 episodes; index -9 is out of range"),
        (("render", fresh_dataset, tmp_path / "r", "--episodes", "last"),
         "--episodes must be a comma-separated list, got 'last'"),
        (("synth", afile, "--episodes", "1"), "exists and is not a folder"),
        (("export-hdf5", fresh_dataset, tmp_path), "is a folder; give the path of the .h5 file"),
        (("synth", other, "--episodes", "1", "--image-size", "32"),
         f"{other} already holds a dataset (shard collect-000) that differs from the new shard "
         "in image_height, image_width"),
    ]
    for args, message in cases:
        result = cli(*args)
        assert result.returncode == 2, (args, result.stderr)
        assert "Traceback" not in result.stderr
        assert message in result.stderr, (args, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert tree_snapshot(fresh_dataset) == before
    assert tree_snapshot(other) == other_before and afile.read_text() == "not a dataset"
    assert not (tmp_path / "v.mp4").exists() and not (tmp_path / "r").exists()


def test_cli_verify_exit_codes(fresh_dataset: Path) -> None:
    assert cli("verify", fresh_dataset).returncode == 0
    shard = next(fresh_dataset.glob("*.zarr"))
    shutil.rmtree(shard / "data" / "reward")
    result = cli("verify", fresh_dataset)
    assert result.returncode == 1
    assert f"shard {shard.stem}, data/reward: array data/reward is missing" in result.stderr
    assert "Traceback" not in result.stderr
