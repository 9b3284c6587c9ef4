"""Damage that must never be read silently: each case is made on a synthetic dataset, found by
``verify`` with the right episode, refused by every reader with DatasetCorruptError (never
wrong data or fill values), while the undamaged episodes still read."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from tests.conftest import run_command
from twist_data.errors import DatasetCorruptError
from twist_data.reader import open_dataset
from twist_data.sampler import SamplerConfig, WindowSampler
from twist_data.schema import FORMAT_VERSION
from twist_data.storage import FrameFile, StorageLayout
from twist_data.synth import SynthConfig, synthetic_episode, write_synthetic_dataset
from twist_data.verify import verify_dataset

# 5 episodes of 12 steps, 8 steps per file: data/state has 8 chunks, so a damaged chunk
# names a range of two episodes at most.
DATA = SynthConfig(episodes=5, steps=12, views=2, image_size=16, seed=7)
LAYOUT = StorageLayout(steps_per_file=8)


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    return write_synthetic_dataset(tmp_path / "ds", DATA, LAYOUT)


def shard_of(dataset: Path) -> Path:
    return next(dataset.glob("*.zarr"))


def flip(path: Path, offset: int, count: int = 1) -> None:
    data = bytearray(path.read_bytes())
    for i in range(offset, offset + count):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def frame_location(shard: Path, step: int, view: int) -> tuple[Path, int, int]:
    """(file, offset, size) of a frame's encoded bytes, from the shard file's own index."""
    per_file = LAYOUT.steps_per_file
    path = shard / "data" / "image" / "c" / str(step // per_file) / "0" / "0" / "0" / "0"
    frames = FrameFile(path, per_file * DATA.views)
    j = (step % per_file) * DATA.views + view
    offset, size = frames.offsets[j], frames.nbytes[j]
    frames.close()
    return path, offset, size


def episodes_that_read(dataset: Path) -> list[int]:
    data = open_dataset(dataset)
    readable = []
    for e in range(data.n_episodes):
        try:
            got = data.episode(e)
        except DatasetCorruptError:
            continue
        expected, _ = synthetic_episode(DATA, e)
        for key, value in expected.arrays().items():  # never wrong data
            np.testing.assert_array_equal(got.arrays()[key], value, err_msg=key)
        readable.append(e)
    return readable


def test_new_shards_carry_checksums(dataset: Path) -> None:
    meta = zarr.open_group(shard_of(dataset), mode="r").attrs["twist"]
    assert meta["format_version"] == FORMAT_VERSION == 2 and meta["layout"]["checksums"]
    assert verify_dataset(dataset).ok
    assert episodes_that_read(dataset) == list(range(DATA.episodes))


@pytest.mark.parametrize("count", [1, 64])
def test_flipped_bytes_in_a_frame(dataset: Path, count: int) -> None:
    step, view = 14, 1  # episode 1 (steps 12-23), its step 2
    path, offset, size = frame_location(shard_of(dataset), step, view)
    flip(path, offset + (size // 2 if count == 1 else 0), min(count, size))
    (problem,) = verify_dataset(dataset).problems
    assert (problem.array, problem.episode) == ("data/image", 1)
    assert "between its steps 2 and 2" in problem.message
    data = open_dataset(dataset)
    with pytest.raises(DatasetCorruptError, match=r"episode 1 \(its step 2\), data/image"):
        data.episode(1)
    out = np.empty((1, 16, 16, 3), np.uint8)
    with pytest.raises(DatasetCorruptError, match="view 1 cannot be decoded"):
        data.read_frames(np.array([step]), np.array([view]), out)
    data.read_frames(np.array([step]), np.array([0]), out)  # the other view is intact
    assert episodes_that_read(dataset) == [0, 2, 3, 4]


def test_flipped_byte_in_a_state_chunk(dataset: Path) -> None:
    chunk = shard_of(dataset) / "data" / "state" / "c" / "3" / "0"  # steps 24-31
    flip(chunk, chunk.stat().st_size // 2)
    (problem,) = verify_dataset(dataset).problems
    assert problem.array == "data/state"
    assert "steps 24-31 (episodes 2-2)" in problem.message and "CRC32C mismatch" in problem.message
    with pytest.raises(DatasetCorruptError, match=r"steps 24-31 \(episodes 2-2\), data/state"):
        open_dataset(dataset).column("state")
    assert episodes_that_read(dataset) == [0, 1, 3, 4]


def test_a_deleted_state_chunk_is_never_read_as_zeros(dataset: Path) -> None:
    (shard_of(dataset) / "data" / "state" / "c" / "1" / "0").unlink()  # steps 8-15
    (problem,) = verify_dataset(dataset).problems
    assert problem.array == "data/state" and "steps 8-15 (episodes 0-1)" in problem.message
    assert "missing" in problem.message
    with pytest.raises(DatasetCorruptError, match="chunk file is missing"):
        WindowSampler(dataset, SamplerConfig(length=4, batch_size=2)).batch()
    assert episodes_that_read(dataset) == [2, 3, 4]


def test_a_truncated_state_chunk(dataset: Path) -> None:
    chunk = shard_of(dataset) / "data" / "state" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-7])
    (problem,) = verify_dataset(dataset).problems
    assert problem.array == "data/state" and "steps 0-7 (episodes 0-0)" in problem.message
    assert episodes_that_read(dataset) == [1, 2, 3, 4]


def test_a_deleted_image_shard_file(dataset: Path) -> None:
    path, _, _ = frame_location(shard_of(dataset), 40, 0)  # steps 40-47: episodes 3
    path.unlink()
    (problem,) = verify_dataset(dataset).problems
    assert problem.array == "data/image" and "steps 40-47 (episodes 3-3)" in problem.message
    assert "missing" in problem.message
    with pytest.raises(DatasetCorruptError, match=r"episode 3 \(its step 4\).*missing"):
        open_dataset(dataset).episode(3)
    assert episodes_that_read(dataset) == [0, 1, 2, 4]


def test_every_damaged_chunk_is_reported(dataset: Path) -> None:
    shard = shard_of(dataset)
    flip(shard / "data" / "state" / "c" / "0" / "0", 5)
    (shard / "data" / "state" / "c" / "6" / "0").unlink()  # steps 48-55
    path, offset, _ = frame_location(shard, 50, 0)  # episode 4, its step 2
    flip(path, offset)
    path, offset, _ = frame_location(shard, 51, 1)  # and its step 3
    flip(path, offset)
    problems = verify_dataset(dataset).problems
    located = sorted((p.array, p.episode, p.message.split(":")[0]) for p in problems)
    assert located == [
        ("data/image", 4, "2 step(s) between its steps 2 and 3 cannot be decoded (CRC32C mismatch)"),
        ("data/state", None, "steps 0-7 (episodes 0-0)"),
        ("data/state", None, "steps 48-55 (episodes 4-4)"),
    ]


def test_a_damaged_meta_chunk(dataset: Path) -> None:
    flip(shard_of(dataset) / "meta" / "episode_seed" / "c" / "0", 3)
    with pytest.raises(DatasetCorruptError, match="episodes 0-4, meta/episode_seed: cannot be "
                                                  "decoded"):
        open_dataset(dataset)
    (problem,) = verify_dataset(dataset).problems
    assert "meta/episode_seed" in str(problem) and "CRC32C mismatch" in str(problem)


def test_format_1_shards_still_read(tmp_path: Path) -> None:
    old = write_synthetic_dataset(tmp_path / "old", DATA,
                                  StorageLayout(steps_per_file=8, checksums=False))
    meta_path = shard_of(old) / "zarr.json"
    doc = json.loads(meta_path.read_text())
    doc["attributes"]["twist"]["format_version"] = 1
    del doc["attributes"]["twist"]["layout"]["checksums"]
    meta_path.write_text(json.dumps(doc))
    assert not open_dataset(old).shards[0].layout.checksums
    assert verify_dataset(old).ok
    assert episodes_that_read(old) == list(range(DATA.episodes))
    shutil.rmtree(old)


def test_salvage_keeps_every_intact_episode_and_names_the_rest(dataset: Path,
                                                               tmp_path: Path) -> None:
    shard = shard_of(dataset)
    path, offset, _ = frame_location(shard, 14, 0)  # episode 1
    flip(path, offset)
    (shard / "data" / "state" / "c" / "6" / "0").unlink()  # steps 48-55: episode 4
    result = run_command("data", "salvage", str(dataset), str(tmp_path / "kept"))
    assert result.returncode == 0, result.stderr
    assert "kept 3 of 5 episodes" in result.stdout
    left = [line for line in result.stderr.splitlines() if line.startswith("left behind")]
    assert [line.split(":")[0] for line in left] == ["left behind episode 1",
                                                     "left behind episode 4"]
    assert verify_dataset(tmp_path / "kept").ok
    copy = open_dataset(tmp_path / "kept")
    for new, old in enumerate([0, 2, 3]):
        expected, info = synthetic_episode(DATA, old)
        got = copy.episode(new)
        for key, value in expected.arrays().items():
            np.testing.assert_array_equal(got.arrays()[key], value, err_msg=key)
        assert copy.episode_info(new).seed == info.seed
    assert copy.spec.extra["salvaged_from"] == str(dataset)
    refused = run_command("data", "salvage", str(dataset), str(tmp_path / "kept"))
    assert refused.returncode == 2 and "is not an empty folder" in refused.stderr


def test_verify_applies_the_writers_own_episode_rules(dataset: Path) -> None:
    """Data that decodes cleanly but breaks the format (a checksum cannot catch a valid
    chunk written wrong) is found by the same rules the writer enforces."""
    shard = shard_of(dataset)
    is_first = zarr.open_array(shard / "data" / "is_first", mode="r+")
    is_first[12 + 3] = True  # episode 1, its step 3
    reward = zarr.open_array(shard / "data" / "reward", mode="r+")
    reward[24 + 5] = reward[24 + 5] + 1.0  # episode 2's stored return no longer adds up
    problems = sorted((p.episode, p.message) for p in verify_dataset(dataset).problems)
    assert problems == [
        (1, "is_first must be true exactly at step 0, got steps [0, 3]"),
        (2, problems[1][1]),
    ]
    assert problems[1][1].startswith("stored return") and "sum of rewards" in problems[1][1]


def test_a_shard_with_no_committed_episode_verifies(tmp_path: Path) -> None:
    """What a collection leaves when its disk fills before the first commit: a shard that
    exists, with nothing committed, beside an intact one."""
    from twist_data.writer import ShardWriter

    dataset = write_synthetic_dataset(tmp_path / "ds", DATA, LAYOUT)
    spec = open_dataset(dataset).spec
    ShardWriter.create(dataset, "zz-empty", spec, LAYOUT).close()
    report = verify_dataset(dataset)
    assert report.ok and report.shards == 2 and report.episodes == DATA.episodes
    assert open_dataset(dataset).shards[1].episode_starts.size == 0


def test_exports_refuse_a_shard_that_lost_an_arrays_metadata(dataset: Path,
                                                             tmp_path: Path) -> None:
    from twist_data.export import export_hdf5, export_video

    (shard_of(dataset) / "data" / "state" / "zarr.json").unlink()  # images still read
    for export, out in ((lambda o: export_video(dataset, 0, o), tmp_path / "e.gif"),
                        (lambda o: export_hdf5(dataset, o), tmp_path / "d.h5")):
        with pytest.raises(DatasetCorruptError, match=r"refuses dataset .*data/state.*"
                                                      r"twist-data verify .* lists every"):
            export(out)
        assert not out.exists()


def _rewrite(shard: Path, array: str, change) -> None:
    """Rewrite the rows of ``array`` of ``shard`` that ``change`` changes, through zarr: every
    checksum stays valid (and no chunk of zeros is dropped, as a whole rewrite would)."""
    target = zarr.open_array(shard / array, mode="r+").with_config({"write_empty_chunks": True})
    values = target[:]
    changed = values.copy()
    change(changed)
    rows = np.flatnonzero((changed != values).reshape(len(values), -1).any(1)
                          | np.isnan(changed.astype(float)).reshape(len(values), -1).any(1))
    for row in rows.tolist():
        target[row] = changed[row]


@pytest.mark.parametrize(("array", "change", "rule"), [
    ("data/is_first", lambda v: v.__setitem__(12 + 3, True),
     r"episode 1 \(global 1\): is_first is set at its step 3"),
    ("data/is_last", lambda v: v.__setitem__(12 + 11, False),
     r"episode 1 \(global 1\): is_last is not set at its step 11"),
    ("data/state", lambda v: v.__setitem__((24 + 5, 0), np.nan),
     r"episode 2 \(global 2\): state is not finite at its step 5"),
    ("data/action", lambda v: v.__setitem__((36 + 2, 0), 3.0),
     r"episode 3 \(global 3\): action is not finite or outside \[-1, 1\] at its step 2"),
    ("data/reward", lambda v: v.__setitem__(24 + 5, v[24 + 5] + 1.0),
     r"episode 2 \(global 2\): stored return .* differs from the sum of rewards"),
    ("meta/episode_ends", lambda v: v.__setitem__(0, 14),  # episode 0 swallows 1's start
     r"episode 0 \(global 0\): is_first is set at its step 12"),
])
def test_the_sampler_refuses_damage_under_valid_checksums(dataset: Path, array: str, change,
                                                          rule: str) -> None:
    from twist_data.sampler import SamplerConfig, WindowSampler

    _rewrite(shard_of(dataset), array, change)
    keys = ("image", "state", "action", "reward", "is_first")
    with pytest.raises(DatasetCorruptError, match=rf"shard synth-000, {rule}.*twist-data verify"):
        WindowSampler(dataset, SamplerConfig(length=4, batch_size=2, keys=keys))
    assert not verify_dataset(dataset).ok  # verify names it too


def test_the_distiller_refuses_damage_under_valid_checksums_writing_nothing(
        tmp_path: Path) -> None:
    import torch

    from twist_models.config import teacher_preset
    from twist_models.distillation import distil_preset
    from twist_models.teacher import Teacher, save_teacher
    from twist_pipeline.distil import distil

    data = write_synthetic_dataset(tmp_path / "ds", SynthConfig(episodes=8, steps=30, seed=5))
    _rewrite(next(data.glob("*.zarr")), "data/reward", lambda v: v.__setitem__(45, v[45] + 1))
    torch.manual_seed(0)
    teacher = save_teacher(tmp_path / "t.pt", Teacher(teacher_preset("tiny", 5, 1)))
    for recipe in ("paper", "readout"):
        with pytest.raises(DatasetCorruptError, match=r"episode 1 \(global 1\): stored return"):
            distil(data, tmp_path / recipe, distil_preset("tiny", recipe), teacher=teacher)
        assert not (tmp_path / recipe).exists()


def test_exports_refuse_a_broken_episode_rule(dataset: Path, tmp_path: Path) -> None:
    from twist_data.export import export_video

    _rewrite(shard_of(dataset), "data/is_first", lambda v: v.__setitem__(12 + 3, True))
    with pytest.raises(DatasetCorruptError, match=r"export-video refuses dataset .*episode 1 "
                                                  r"\(global 1\): is_first is set at its step 3"):
        export_video(dataset, 0, tmp_path / "e.gif")  # episode 0 itself is intact
    assert not (tmp_path / "e.gif").exists()


def test_verify_names_a_frame_of_zeros_written_under_a_valid_checksum(dataset: Path) -> None:
    images = zarr.open_array(shard_of(dataset) / "data" / "image", mode="r+")
    images[14, 1] = 0  # episode 1, its step 2: rewritten through zarr, checksum and all
    (problem,) = verify_dataset(dataset).problems
    assert (problem.array, problem.episode) == ("data/image", 1)
    assert "the frame of its step 2 view 1 is all zeros" in problem.message


def test_a_frame_of_zeros_in_a_drawn_dataset_is_never_served(dataset: Path) -> None:
    images = zarr.open_array(shard_of(dataset) / "data" / "image", mode="r+")
    images[14, 1] = 0  # rewritten through zarr: its checksum is valid
    data = open_dataset(dataset)
    out = np.empty((1, 16, 16, 3), np.uint8)
    with pytest.raises(DatasetCorruptError, match=r"episode 1 \(its step 2\), data/image: .*"
                                                  r"view 1 cannot be decoded \(it is all zeros"):
        data.read_frames(np.array([14]), np.array([1]), out)
    data.read_frames(np.array([14]), np.array([0]), out)  # the other view is served
