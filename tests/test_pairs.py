"""Frame pairs in D (``data/pair_image``): the step before drawn in each step's scene, rebuilt
from the stored physics and DR draws, kept through verify, strip, rebuild and salvage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from tests.conftest import run_command
from twist_data.errors import ImagesStrippedError, PairsMissingError, SchemaMismatchError
from twist_data.reader import open_dataset
from twist_data.schema import PAIR_IMAGE
from twist_data.strip import strip_dataset
from twist_data.verify import verify_dataset
from twist_data.writer import ShardWriter
from twist_sim.randomisation import VIEW_PARAMS, dr_preset
from twist_sim.render import DRRenderer
from twist_sim.rerender import (
    check_reproduction,
    render_blocks,
    renderer_for_block,
    reproduce_dataset,
    reproduce_pairs,
    rerender_dataset,
)
from twist_sim.rollout import random_policy, record_episode, simulated_spec
from twist_sim.tasks import TaskEnv


def tree(path: Path) -> dict[str, int]:
    return {str(p.relative_to(path)): p.stat().st_size for p in sorted(path.rglob("*"))}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory, gl: None) -> Path:
    """Three short cheetah episodes in two shards, K=2, 24x24, a new scene every step: its
    camera tracks the body, so a step's frame and the one before differ by the framing too."""
    out = tmp_path_factory.mktemp("rec") / "ds"
    env = TaskEnv("cheetah-run", max_steps=6)
    with DRRenderer(env.name, dr_preset("train-wide"), 24, 2) as r:
        sampler = r.sampler(0)
        spec = simulated_spec(env, r)
        for name, seeds in (("collect-000", (0, 1)), ("collect-001", (2,))):
            with ShardWriter.create(out, name, spec) as writer:
                for seed in seeds:
                    writer.append(*record_episode(env, r, sampler, random_policy(6, seed),
                                                  seed=seed))
    return out


@pytest.fixture(scope="module")
def paired(recorded: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("paired") / "ds"
    report = reproduce_dataset(recorded, out, pairs=True)
    assert report.exact
    return out


def direct_pairs(data_path: Path) -> np.ndarray:
    """Every step's pair frames drawn here, one render per view set, with nothing of the
    library's pair code: the physics of the step before (the step itself at an episode's
    start) under the step's stored draw -> [N, K, H, W, 3]."""
    data = open_dataset(data_path)
    physics, first = data.column("physics"), data.column("is_first").astype(bool)
    params = {p.name: data.column(f"dr/{p.name}") for p in VIEW_PARAMS}
    out = np.empty((data.n_steps, data.spec.views, *data.spec.image_shape), np.uint8)
    for block in render_blocks(data.spec):
        a, b = block["views"]
        with renderer_for_block(data.spec.task, block) as renderer:
            for t in range(data.n_steps):
                before = physics[t] if first[t] else physics[t - 1]
                renderer.render(before, {k: v[t, a:b] for k, v in params.items()},
                                out=out[t, a:b])
    return out


def stored_pairs(data_path: Path) -> np.ndarray:
    data = open_dataset(data_path)
    k, n = data.spec.views, data.n_steps
    out = np.empty((n * k, *data.spec.image_shape), np.uint8)
    data.read_frames(np.repeat(np.arange(n), k), np.tile(np.arange(k), n), out, key=PAIR_IMAGE)
    return out.reshape(n, k, *data.spec.image_shape)


def test_stored_pairs_are_direct_renders_of_the_step_before_in_the_steps_scene(
        recorded: Path, paired: Path) -> None:
    data, source = open_dataset(paired), open_dataset(recorded)
    assert data.has_pairs and not source.has_pairs
    pairs = stored_pairs(paired)
    np.testing.assert_array_equal(pairs, direct_pairs(recorded))
    for i in range(data.n_episodes):  # the images are D's own, bit for bit
        episode = data.episode(i)
        np.testing.assert_array_equal(episode.image, source.episode(i).image)
        np.testing.assert_array_equal(episode.pair_image[0], episode.image[0])  # nothing before
        np.testing.assert_array_equal(episode.pair_image, pairs[data.episode_starts[i]:
                                                                data.episode_ends[i]])
    # In the same scene, the pair differs from its step by the motion only, far less than
    # two consecutive frames of D, each in its own scene.
    image = np.stack([data.episode(i).image for i in range(data.n_episodes)]).astype(np.int32)
    pair = np.stack([data.episode(i).pair_image for i in range(data.n_episodes)])
    motion = np.abs(pair[:, 1:] - image[:, 1:]).mean()
    scenes = np.abs(image[:, :-1] - image[:, 1:]).mean()
    assert 0 < motion < scenes / 2
    np.testing.assert_array_equal(reproduce_pairs(source, np.arange(source.n_steps)), pairs)
    assert verify_dataset(paired).ok and check_reproduction(data, 8) == []


def test_a_redrawn_pair_that_differs_is_reported(paired: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(paired, copy)
    group = zarr.open_group(str(copy / "collect-000.zarr"), mode="r+")
    pairs = group[f"data/{PAIR_IMAGE}"]
    frame = pairs[3, 1]
    pairs[3, 1] = 255 - frame  # rewritten whole, checksums and all: only a redraw tells
    problems = check_reproduction(open_dataset(copy), open_dataset(copy).n_steps)
    assert problems and all("step 3 view 1: the redrawn pair frame differs" in p
                            for p in problems)


def test_a_stripped_paired_dataset_rebuilds_its_pairs(paired: Path,
                                                      tmp_path: Path) -> None:
    stripped = strip_dataset(paired, tmp_path / "s")
    data = open_dataset(stripped)
    assert not data.has_pairs and data.shards[0].images.pairs
    assert not (stripped / "collect-000.zarr" / "data" / PAIR_IMAGE).exists()
    assert verify_dataset(stripped).ok
    with pytest.raises(ImagesStrippedError):
        data.require_pairs("the readout recipe")
    report = reproduce_dataset(stripped, tmp_path / "r", workers=2)
    assert report.exact
    assert open_dataset(tmp_path / "r").has_pairs
    np.testing.assert_array_equal(stored_pairs(tmp_path / "r"), stored_pairs(paired))


def test_a_dataset_without_pairs_names_the_command_that_adds_them(recorded: Path) -> None:
    data = open_dataset(recorded)
    with pytest.raises(PairsMissingError, match=r"the readout recipe needs frame pairs .* "
                                                 r"twist-data render .* OUT --reproduce --pairs"):
        data.require_pairs("the readout recipe")
    with pytest.raises(PairsMissingError):
        data.read_frames(np.array([0]), np.array([0]), np.empty((1, 24, 24, 3), np.uint8),
                         key=PAIR_IMAGE)


def test_verify_names_a_damaged_pair_frame(paired: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(paired, copy)
    folder = copy / "collect-001.zarr" / "data" / PAIR_IMAGE
    chunk = max((p for p in folder.rglob("*") if p.is_file() and p.name != "zarr.json"),
                key=lambda p: p.stat().st_size)
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 3] ^= 0xFF
    chunk.write_bytes(bytes(raw))
    report = verify_dataset(copy)
    assert not report.ok
    assert {p.array for p in report.problems} == {f"data/{PAIR_IMAGE}"}
    assert all(p.shard == "collect-001" for p in report.problems)


def test_shards_with_and_without_pairs_form_no_dataset(recorded: Path, paired: Path,
                                                       tmp_path: Path) -> None:
    import shutil

    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copytree(paired / "collect-000.zarr", mixed / "collect-000.zarr")
    shutil.copytree(recorded / "collect-001.zarr", mixed / "collect-001.zarr")
    with pytest.raises(SchemaMismatchError, match="collect-000 stores frame pairs and "
                                                  "collect-001 does not"):
        open_dataset(mixed)
    # A shard that lost its pairs' metadata is damage verify names, not a quiet difference.
    lost = tmp_path / "lost"
    shutil.copytree(paired, lost)
    (lost / "collect-001.zarr" / "data" / PAIR_IMAGE / "zarr.json").unlink()
    report = verify_dataset(lost)
    assert [(p.shard, p.array) for p in report.problems] == [("collect-001",
                                                              f"data/{PAIR_IMAGE}")]
    assert "lacks the frame pairs" in report.problems[0].message


def test_new_renders_and_added_views_carry_pairs(recorded: Path, paired: Path,
                                                 tmp_path: Path) -> None:
    rerender_dataset(recorded, tmp_path / "new", dr_preset("train"), views=1, pairs=True)
    new = open_dataset(tmp_path / "new")
    assert new.has_pairs and new.spec.views == 1
    np.testing.assert_array_equal(stored_pairs(tmp_path / "new"), direct_pairs(tmp_path / "new"))
    rerender_dataset(paired, tmp_path / "more", dr_preset("train"), views=1, add_views=True)
    more = open_dataset(tmp_path / "more")
    assert more.has_pairs and more.spec.views == 3
    pairs = stored_pairs(tmp_path / "more")
    np.testing.assert_array_equal(pairs[:, :2], stored_pairs(paired))
    np.testing.assert_array_equal(pairs, direct_pairs(tmp_path / "more"))
    before = tree(tmp_path)
    with pytest.raises(PairsMissingError, match="adding views with frame pairs"):
        rerender_dataset(recorded, tmp_path / "x", dr_preset("train"), views=1,
                         add_views=True, pairs=True)
    assert tree(tmp_path) == before


def test_the_cli_adds_pairs(recorded: Path, tmp_path: Path) -> None:
    result = run_command("data", "render", str(recorded), str(tmp_path / "p"), "--reproduce",
                         "--pairs")
    assert result.returncode == 0, result.stderr
    assert open_dataset(tmp_path / "p").has_pairs
    group = zarr.open_group(str(tmp_path / "p" / "collect-000.zarr"), mode="r")
    assert group[f"data/{PAIR_IMAGE}"].shape == group["data/image"].shape
    result = run_command("data", "info", str(tmp_path / "p"))
    assert result.returncode == 0 and "frame pairs" in result.stdout
    assert f"twist-data verify {tmp_path / 'p'}` decodes and checksums" in result.stdout


def test_verify_redraws_a_sample_by_default_and_finds_frames_rewritten_whole(
        recorded: Path, tmp_path: Path) -> None:
    import shutil

    assert run_command("data", "verify", str(recorded)).returncode == 0
    copy = tmp_path / "copy"
    shutil.copytree(recorded, copy)
    for shard in copy.glob("*.zarr"):
        images = zarr.open_group(str(shard), mode="r+")["data/image"]
        images[:, 0] = 255 - images[:, 0]  # through zarr: every checksum stays valid
    result = run_command("data", "verify", str(copy))
    assert result.returncode == 1 and "re-render differs" in result.stderr
    assert run_command("data", "verify", str(copy), "--rerender", "0").returncode == 0


def test_a_collection_stores_the_pairs_that_d_rebuilds(tmp_path: Path, gl: None) -> None:
    from twist_pipeline.collect import CollectError, collect, collect_preset

    out = tmp_path / "dataset"
    collect(out, collect_preset("tiny", pairs=True))
    data = open_dataset(out)
    assert data.has_pairs and data.n_episodes > 1
    stored = stored_pairs(out)
    for i in range(data.n_episodes):  # nothing before an episode's first step: the step itself
        np.testing.assert_array_equal(stored[data.episode_starts[i]], data.episode(i).image[0])
    # Drawn by the collection's render process, equal to a rebuild from D's physics and draws.
    np.testing.assert_array_equal(reproduce_pairs(data, np.arange(data.n_steps)), stored)
    assert verify_dataset(out).ok
    # A shard without pairs would leave D unreadable: refused before anything is written.
    with pytest.raises(CollectError, match="frame pairs True, but this run asks for False"):
        collect(out, collect_preset("tiny"), shard="collect-001")
    assert sorted(p.name for p in out.glob("*.zarr")) == ["collect-000.zarr"]
