"""Writer: validation, commit protocol, resume, locking and file counts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import zarr

from twist_data.errors import InvalidEpisodeError, NotADatasetError, ShardLockedError
from twist_data.reader import open_dataset
from twist_data.schema import EpisodeInfo
from twist_data.storage import StorageLayout
from twist_data.synth import SynthConfig, synth_episode, synth_spec, synthetic_episode
from twist_data.verify import verify_dataset
from twist_data.writer import ShardWriter

SPEC = synth_spec(views=2, image_size=16)


def tree_snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "writer.lock"}


def test_invalid_episode_lists_every_problem_and_changes_nothing(tmp_path: Path) -> None:
    ep, info = synth_episode(SPEC, seed=1, length=10)
    with ShardWriter.create(tmp_path, "s", SPEC) as w:
        w.append(ep, info)
        before = tree_snapshot(tmp_path)
        bad_state = ep.state.copy()
        bad_state[3, 0] = np.nan
        first = ep.is_first.copy()
        first[4] = True
        bad = dataclasses.replace(ep, state=bad_state, is_first=first,
                                  reward=ep.reward.astype(np.float64))
        with pytest.raises(InvalidEpisodeError) as exc:
            w.append(bad, info)
        message = str(exc.value)
        assert "'reward' has dtype float64, expected float32" in message
        assert "'state' contains NaN" in message
        assert w.n_episodes == 1
    assert tree_snapshot(tmp_path) == before
    assert verify_dataset(tmp_path).ok


def test_flag_rules_are_enforced(tmp_path: Path) -> None:
    ep, info = synth_episode(SPEC, seed=1, length=10)
    first = ep.is_first.copy()
    first[4] = True
    action = ep.action.copy()
    action[0] = 0.5
    with ShardWriter.create(tmp_path, "s", SPEC) as w:
        with pytest.raises(InvalidEpisodeError, match=r"is_first must be true exactly at step 0"):
            w.append(dataclasses.replace(ep, is_first=first), info)
        with pytest.raises(InvalidEpisodeError, match="action and reward at the first step"):
            w.append(dataclasses.replace(ep, action=action), info)
        with pytest.raises(InvalidEpisodeError, match="episode DR parameters"):
            w.append(ep, EpisodeInfo(seed=1, policy="random"))
    with pytest.raises(InvalidEpisodeError, match="unknown policy 'human'"):
        EpisodeInfo(seed=1, policy="human")


def test_uncommitted_episode_is_invisible_and_discarded_on_resume(tmp_path: Path,
                                                                  monkeypatch) -> None:
    a, info_a = synth_episode(SPEC, seed=1, length=12)
    b, info_b = synth_episode(SPEC, seed=2, length=15)
    c, info_c = synth_episode(SPEC, seed=3, length=9)
    w = ShardWriter.create(tmp_path, "s", SPEC)
    w.append(a, info_a)

    def crash(*args, **kwargs):
        raise KeyboardInterrupt  # the process dies between writing data and committing

    monkeypatch.setattr(ShardWriter, "_commit", crash)
    with pytest.raises(KeyboardInterrupt):
        w.append(b, info_b)
    w.close()
    monkeypatch.undo()
    ds = open_dataset(tmp_path)
    assert (ds.n_episodes, ds.n_steps) == (1, 12)
    report = verify_dataset(tmp_path)
    assert report.ok and any("uncommitted" in n for n in report.notes)
    with ShardWriter.resume(tmp_path / "s.zarr") as w:
        assert (w.n_episodes, w.n_steps) == (1, 12)
        w.append(c, info_c)
    ds = open_dataset(tmp_path)
    assert ds.n_steps == 21
    np.testing.assert_array_equal(ds.episode(1).image, c.image)
    assert verify_dataset(tmp_path).notes == []


def test_one_writer_per_shard_and_no_overwrite(tmp_path: Path) -> None:
    with ShardWriter.create(tmp_path, "s", SPEC), pytest.raises(ShardLockedError,
                                                                 match="already being written"):
        ShardWriter.resume(tmp_path / "s.zarr")
    with pytest.raises(NotADatasetError, match="already exists"):
        ShardWriter.create(tmp_path, "s", SPEC)
    with pytest.raises(NotADatasetError, match="must not contain"):
        ShardWriter.create(tmp_path, "a/b", SPEC)
    ShardWriter.resume(tmp_path / "s.zarr").close()  # the lock died with the first writer


def test_image_file_count_is_one_per_thousand_steps(tmp_path: Path) -> None:
    config = SynthConfig(episodes=5, steps=500, image_size=16)
    with ShardWriter.create(tmp_path, "s", SPEC, StorageLayout(steps_per_file=1000)) as w:
        for i in range(config.episodes):
            w.append(*synthetic_episode(config, i))
    shard = tmp_path / "s.zarr"
    for array in ("image", "state", "reward"):
        chunks = [p for p in (shard / "data" / array / "c").rglob("*") if p.is_file()]
        assert len(chunks) == 3, (array, chunks)  # 2,500 steps -> files for 0-999, -1999, -2499


@pytest.mark.parametrize("codec", ["blosc-lz4", "zstd", "none"])
def test_frames_written_directly_are_what_zarr_reads(tmp_path: Path, codec: str) -> None:
    # The writer builds image shard files itself; zarr's own sharding decoder is the
    # independent judge. Episodes straddle files (8 steps per file) and one uncommitted
    # attempt leaves stale frames that the next append must replace.
    episodes = [synth_episode(SPEC, seed=s, length=n) for s, n in ((5, 20), (6, 7), (7, 11))]
    layout = StorageLayout(image_codec=codec, steps_per_file=8)
    with ShardWriter.create(tmp_path, "s", SPEC, layout) as w:
        w.append(*episodes[0])
        w._commit = lambda *a: (_ for _ in ()).throw(KeyboardInterrupt)  # dies before commit
        with pytest.raises(KeyboardInterrupt):
            w.append(*synth_episode(SPEC, seed=99, length=13))
    with ShardWriter.resume(tmp_path / "s.zarr") as w:
        for episode in episodes[1:]:
            w.append(*episode)
    expected = np.concatenate([e.image for e, _ in episodes])
    stored = zarr.open_array(tmp_path / "s.zarr" / "data" / "image", mode="r")
    np.testing.assert_array_equal(stored[:], expected)
    dataset = open_dataset(tmp_path)
    for i, (episode, _) in enumerate(episodes):
        np.testing.assert_array_equal(dataset.episode(i).image, episode.image)
    assert not list((tmp_path / "s.zarr").rglob("*.partial"))
