"""D without its pixels: stripping a dataset of its images and rebuilding them, exactly, from
the stored physics and DR draws, in one process or several."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import run_command
from twist_data.errors import ConfigError, ImagesStrippedError, NotADatasetError
from twist_data.reader import open_dataset
from twist_data.sampler import SamplerConfig, WindowSampler
from twist_data.schema import image_digest, step_arrays
from twist_data.strip import strip_dataset
from twist_data.verify import verify_dataset
from twist_data.writer import ShardWriter
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.rerender import check_reproduction, reproduce_dataset
from twist_sim.rollout import random_policy, record_episode, simulated_spec
from twist_sim.tasks import TaskEnv


def tree(path: Path) -> dict[str, int]:
    """Every file under ``path`` with its size: what a refused command must leave unchanged."""
    return {str(p.relative_to(path)): p.stat().st_size for p in sorted(path.rglob("*"))}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory, gl: None) -> Path:
    """Five short cartpole episodes in two shards (3 + 2), K=2, 24x24 supersampled 2x, DR
    drawn per step: every render setting that a rebuild must read back from D."""
    out = tmp_path_factory.mktemp("rec") / "ds"
    env = TaskEnv("cartpole-balance", max_steps=9)
    with DRRenderer(env.name, dr_preset("train-wide"), 24, 2, supersample=2) as r:
        sampler = r.sampler(0)
        spec = simulated_spec(env, r)
        for name, seeds in (("collect-000", (0, 1, 2)), ("collect-001", (3, 4))):
            with ShardWriter.create(out, name, spec) as writer:
                for seed in seeds:
                    writer.append(*record_episode(env, r, sampler, random_policy(1, seed),
                                                  seed=seed))
    return out


@pytest.fixture(scope="module")
def stripped(recorded: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return strip_dataset(recorded, tmp_path_factory.mktemp("strip") / "stripped")


def assert_same_dataset(a: Path, b: Path) -> None:
    """Every per-step array, every episode's provenance and the global order equal."""
    x, y = open_dataset(a), open_dataset(b)
    assert (x.n_episodes, x.n_steps) == (y.n_episodes, y.n_steps)
    for array in step_arrays(x.spec):
        if array.name != "image":
            np.testing.assert_array_equal(x.column(array.name), y.column(array.name))
    for i in range(x.n_episodes):
        assert x.episode_info(i) == y.episode_info(i)
        np.testing.assert_array_equal(x.episode(i).image, y.episode(i).image)


def test_a_stripped_dataset_keeps_every_array_but_the_images(recorded: Path,
                                                              stripped: Path) -> None:
    src, copy = open_dataset(recorded), open_dataset(stripped)
    assert not copy.has_images and src.has_images
    assert [s.name for s in copy.shards] == ["collect-000", "collect-001"]
    for array in step_arrays(src.spec):
        if array.name != "image":
            np.testing.assert_array_equal(copy.column(array.name), src.column(array.name))
    assert copy.episodes().drop(columns="committed").equals(
        src.episodes().drop(columns="committed"))
    digests = [d for shard in copy.shards for d in shard.images.sha256]
    assert digests == [image_digest(src.episode(i).image) for i in range(src.n_episodes)]
    assert copy.disk_bytes() < src.disk_bytes() / 2
    report = verify_dataset(stripped)
    assert report.ok and report.episodes == 5
    assert any("stripped of its images" in note for note in report.notes)


def test_every_image_reader_refuses_a_stripped_dataset_naming_the_rebuild(
        stripped: Path) -> None:
    data = open_dataset(stripped)
    rebuild = f"twist-data render {stripped} OUT --reproduce"
    with pytest.raises(ImagesStrippedError, match="stripped of them") as caught:
        data.read_frames(np.array([0]), np.array([0]), np.empty((1, 24, 24, 3), np.uint8))
    assert rebuild in str(caught.value)
    with pytest.raises(ImagesStrippedError):
        data.episode(0)
    assert data.episode(0, images=False).image.shape == (10, 0, 24, 24, 3)
    with pytest.raises(ImagesStrippedError):
        WindowSampler(data, SamplerConfig(length=4, batch_size=2)).batch()
    with pytest.raises(ImagesStrippedError, match="comparing re-renders"):
        check_reproduction(data, 3)
    with pytest.raises(NotADatasetError, match="never appended to"):
        ShardWriter.resume(stripped / "collect-000.zarr")


def test_the_distiller_refuses_a_stripped_dataset_before_writing(stripped: Path,
                                                                  tmp_path: Path) -> None:
    from twist_models.distillation import distil_preset
    from twist_pipeline.distil import distil

    with pytest.raises(ImagesStrippedError, match=r"twist-distil needs images, but .* "
                                                  r"twist-data render .* --reproduce"):
        distil(stripped, tmp_path / "student", distil_preset("tiny"))
    assert not (tmp_path / "student").exists()


@pytest.mark.parametrize(("source", "workers"), [("stripped", 2), ("recorded", 1)])
def test_reproduction_rebuilds_every_array_bit_for_bit(source: str, workers: int,
                                                       request: pytest.FixtureRequest,
                                                       recorded: Path, tmp_path: Path) -> None:
    report = reproduce_dataset(request.getfixturevalue(source), tmp_path / "re", workers=workers)
    assert report.exact and report.identical == [0, 1, 2, 3, 4] and report.workers == workers
    assert report.gl.get("gl_vendor")
    rebuilt = open_dataset(tmp_path / "re")
    assert_same_dataset(recorded, tmp_path / "re")
    assert verify_dataset(tmp_path / "re").ok and check_reproduction(rebuilt, 10) == []
    assert rebuilt.spec.extra["versions"]["gl_renderer"] == report.gl["gl_renderer"]
    names = [s.name for s in rebuilt.shards]
    # Blocks of episodes 0-1 | 2-4 (one process each): shards split where both cut.
    assert names == (["collect-000", "collect-001"] if workers == 1 else
                     ["collect-000-000", "collect-000-001", "collect-001-001"])


def test_a_rebuild_that_draws_other_pixels_is_reported(stripped: Path, tmp_path: Path) -> None:
    import shutil

    import zarr

    copy = tmp_path / "copy"
    shutil.copytree(stripped, copy)
    group = zarr.open_group(str(copy / "collect-001.zarr"), mode="r+")
    block = dict(group.attrs["twist"])
    block["images"] = {**block["images"], "sha256": ["0" * 64, *block["images"]["sha256"][1:]]}
    group.attrs["twist"] = block
    report = reproduce_dataset(copy, tmp_path / "re")
    assert report.differing == [3] and report.identical == [0, 1, 2, 4]


def test_bad_requests_are_refused_before_anything_is_written(recorded: Path, stripped: Path,
                                                             small_dataset: Path,
                                                             tmp_path: Path) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    before = tree(tmp_path)
    with pytest.raises(ConfigError, match="workers must be at least 1 process, got 0"):
        reproduce_dataset(stripped, tmp_path / "a", workers=0)
    with pytest.raises(ConfigError, match="exists and is not an empty folder"):
        reproduce_dataset(stripped, tmp_path / "full")
    with pytest.raises(ConfigError, match="not rendered by twist's simulator"):
        reproduce_dataset(small_dataset, tmp_path / "b")
    with pytest.raises(ConfigError, match="stripped of its images already"):
        strip_dataset(stripped, tmp_path / "c")
    with pytest.raises(ConfigError, match="no final teacher"):
        strip_dataset(recorded, tmp_path / "d", copy_teacher=lambda a, b: None)
    assert tree(tmp_path) == before


def test_the_cli_strips_and_rebuilds(recorded: Path, tmp_path: Path) -> None:
    def twist_data(*args: str) -> subprocess.CompletedProcess[str]:
        return run_command("data", *args)

    result = twist_data("strip", str(recorded), str(tmp_path / "s"))
    assert result.returncode == 0, result.stderr
    result = twist_data("render", str(tmp_path / "s"), str(tmp_path / "r"), "--reproduce")
    assert result.returncode == 0, result.stderr
    assert "5 episodes rebuilt" in result.stdout and "every frame identical" in result.stdout
    assert_same_dataset(recorded, tmp_path / "r")
    before = tree(tmp_path)
    for args, message in (
            (("render", str(tmp_path / "s"), str(tmp_path / "x"), "--reproduce", "--workers",
              "0"), "workers must be at least 1 process, got 0"),
            (("render", str(tmp_path / "s"), str(tmp_path / "x"), "--workers", "2"),
             "--workers 2 applies to --reproduce alone"),
            (("export-video", str(tmp_path / "s"), str(tmp_path / "x.gif")),
             "holds none: it was stripped of them"),
            (("verify", str(tmp_path / "s"), "--rerender", "3"), "comparing re-renders")):
        result = twist_data(*args)
        assert result.returncode != 0 and "Traceback" not in result.stderr
        assert message in result.stderr
    assert tree(tmp_path) == before
