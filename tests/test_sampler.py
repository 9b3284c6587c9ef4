"""Window sampler: boundaries, coverage, determinism, stream sharding, cache, live datasets."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest
from torch.utils.data import DataLoader

from tests.conftest import SMALL
from twist_data.errors import SamplerConfigError
from twist_data.reader import _ZarrFrameReader, open_dataset
from twist_data.sampler import SamplerConfig, WindowDataset, WindowSampler
from twist_data.synth import (
    SynthConfig,
    episode_length,
    synth_spec,
    synthetic_episode,
    write_synthetic_dataset,
)
from twist_data.writer import ShardWriter

L = 10


def all_valid_starts(path: Path, length: int) -> set[int]:
    """Independent enumeration: every global step whose window stays inside one episode."""
    ds = open_dataset(path)
    out = set()
    for a, b in zip(ds.episode_starts.tolist(), ds.episode_ends.tolist(), strict=True):
        out.update(range(a, b - length + 1))
    return out


def test_windows_stay_inside_one_episode_and_match_its_data(small_dataset: Path) -> None:
    ds = open_dataset(small_dataset)
    episodes = [synthetic_episode(SMALL, i)[0] for i in range(SMALL.episodes)]
    sampler = WindowSampler(ds, SamplerConfig(length=L, batch_size=8, seed=1))
    for _ in range(20):
        b = sampler.batch()
        for w in range(8):
            e = int(b["episode"][w])
            offset = int(b["start"][w] - ds.episode_starts[e])
            assert offset >= 0 and offset + L <= len(episodes[e])
            ref = episodes[e]
            steps = offset + np.arange(L)
            np.testing.assert_array_equal(b["image"][w], ref.image[steps, b["view"][w]])
            np.testing.assert_array_equal(b["state"][w], ref.state[steps])
            np.testing.assert_array_equal(b["action"][w], ref.action[steps])
            np.testing.assert_array_equal(b["is_last"][w], ref.is_last[steps])


def test_draws_cover_every_valid_start(small_dataset: Path) -> None:
    expected = all_valid_starts(small_dataset, L)
    sampler = WindowSampler(small_dataset, SamplerConfig(length=L, batch_size=64, seed=0))
    assert sampler.total_windows == len(expected)
    seen = set()
    for _ in range(60):
        seen.update(sampler.sample_starts(64)[0].tolist())
    assert seen == expected


def test_same_seed_same_batches_other_seed_other_batches(small_dataset: Path) -> None:
    def draw(seed: int) -> list[np.ndarray]:
        s = WindowSampler(small_dataset, SamplerConfig(length=L, batch_size=4, seed=seed))
        return [np.concatenate([b["start"], b["view"].ravel()]) for b in itertools.islice(s, 5)]

    assert all(np.array_equal(x, y) for x, y in zip(draw(7), draw(7), strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(draw(7), draw(8), strict=True))


def test_streams_are_disjoint_and_together_cover_everything(small_dataset: Path) -> None:
    expected = all_valid_starts(small_dataset, L)
    per_stream = []
    for j in range(3):
        s = WindowSampler(small_dataset, SamplerConfig(length=L, seed=0), stream=j, n_streams=3)
        per_stream.append({int(x) for x in s.sample_starts(3000)[0]})
    for x, y in itertools.combinations(per_stream, 2):
        assert not x & y
    assert set().union(*per_stream) == expected


def test_dataloader_workers_yield_their_own_streams(small_dataset: Path) -> None:
    config = SamplerConfig(length=L, batch_size=4, seed=11)
    loader = DataLoader(WindowDataset(small_dataset, config), batch_size=None, num_workers=2)
    got = [b["start"].numpy() for b in itertools.islice(loader, 6)]
    # DataLoader alternates workers: batches 0, 2, 4 from worker 0 and 1, 3, 5 from worker 1.
    for worker in range(2):
        s = WindowSampler(small_dataset, config, stream=worker, n_streams=2)
        for i in range(3):
            np.testing.assert_array_equal(got[2 * i + worker], s.batch()["start"])


def test_ranks_and_workers_combine_into_disjoint_streams(small_dataset: Path) -> None:
    config = SamplerConfig(length=L, batch_size=32, seed=2)
    starts = {}
    for rank in range(2):
        ds = WindowDataset(small_dataset, config, rank=rank, world_size=2)
        starts[rank] = {int(x) for b in itertools.islice(iter(ds), 10) for x in b["start"]}
    assert starts[0] and starts[1] and not starts[0] & starts[1]


@pytest.mark.parametrize("cache_bytes", [0, 16 * 16 * 3 * 5, 1 << 24])
def test_cache_size_never_changes_the_data(small_dataset: Path, cache_bytes: int) -> None:
    reference = WindowSampler(small_dataset, SamplerConfig(length=L, batch_size=8, seed=4,
                                                           cache_bytes=0))
    sampler = WindowSampler(small_dataset, SamplerConfig(length=L, batch_size=8, seed=4,
                                                         cache_bytes=cache_bytes))
    for _ in range(15):
        np.testing.assert_array_equal(sampler.batch()["image"], reference.batch()["image"])
    assert sampler.cache.capacity * 16 * 16 * 3 <= cache_bytes
    if cache_bytes >= 1 << 24:
        assert sampler.cache.hits > 0


def test_direct_frame_reader_agrees_with_zarr(small_dataset: Path) -> None:
    ds = open_dataset(small_dataset)
    rng = np.random.default_rng(0)
    steps = rng.integers(0, ds.shards[0].n_steps, 50)
    views = rng.integers(0, ds.spec.views, 50)
    fast = np.empty((50, *ds.spec.image_shape), np.uint8)
    slow = np.empty_like(fast)
    ds.shards[0].frames.read_into(steps, views, fast, np.arange(50))
    _ZarrFrameReader(ds.shards[0].array("data/image")).read_into(steps, views, slow,
                                                                 np.arange(50))
    np.testing.assert_array_equal(fast, slow)


def test_fixed_view_and_extra_keys(small_dataset: Path) -> None:
    s = WindowSampler(small_dataset, SamplerConfig(length=L, batch_size=3, view=1,
                                                   keys=("image", "dr/brightness", "physics")))
    b = s.batch()
    assert (b["view"] == 1).all()
    ds = open_dataset(small_dataset)
    steps = b["start"][:, None] + np.arange(L)
    np.testing.assert_array_equal(b["dr/brightness"], ds.column("dr/brightness")[steps, 1])
    assert b["physics"].shape == (3, L, 4) and b["physics"].dtype == np.float64


def test_bad_requests_are_named(small_dataset: Path) -> None:
    longest = max(episode_length(SMALL, i) for i in range(SMALL.episodes))
    with pytest.raises(SamplerConfigError, match=rf"window length 500 is longer than every "
                                                 rf"episode \(the longest has {longest} steps\)"):
        WindowSampler(small_dataset, SamplerConfig(length=500))
    with pytest.raises(SamplerConfigError, match=r"view index 2 is out of range: the dataset "
                                                 r"has 2 views"):
        WindowSampler(small_dataset, SamplerConfig(view=2, length=L))
    with pytest.raises(SamplerConfigError, match="unknown key 'pixels'"):
        WindowSampler(small_dataset, SamplerConfig(keys=("pixels",), length=L))
    with pytest.raises(SamplerConfigError, match="window length must be >= 1"):
        SamplerConfig(length=0)


def test_sampler_picks_up_episodes_committed_while_it_runs(tmp_path: Path) -> None:
    config = SynthConfig(episodes=4, steps=30, image_size=16)
    writer = ShardWriter.create(tmp_path, "live", synth_spec(2, 16))
    writer.append(*synthetic_episode(config, 0))
    sampler = WindowSampler(tmp_path, SamplerConfig(length=L, batch_size=16))
    assert {int(e) for e in sampler.batch()["episode"]} == {0}
    for i in (1, 2):
        writer.append(*synthetic_episode(config, i))
    assert sampler.refresh() == 2
    seen = {int(e) for _ in range(10) for e in sampler.batch()["episode"]}
    assert seen == {0, 1, 2}
    b = sampler.batch()
    ref = [synthetic_episode(config, i)[0] for i in range(3)]
    for w in range(16):
        e, off = int(b["episode"][w]), int(b["start"][w] - 30 * b["episode"][w])
        np.testing.assert_array_equal(b["image"][w], ref[e].image[off + np.arange(L), b["view"][w]])
    # a second collector's shard appears beside the first
    write_synthetic_dataset(tmp_path, SynthConfig(episodes=1, steps=30, image_size=16, seed=9))
    assert sampler.refresh() == 1
    writer.close()


def test_resident_windows_are_the_samplers_windows(small_dataset: Path) -> None:
    from twist_data.sampler import ResidentWindows, resident_bytes

    config = SamplerConfig(length=L, batch_size=5, seed=11,
                           keys=("image", "state", "action", "is_first"))
    reference = WindowSampler(small_dataset, config)
    resident = ResidentWindows(small_dataset, config, device="cpu")
    for _ in range(3):
        want, got = reference.batch(), resident.batch()
        assert set(got) == set(want)
        for key, value in want.items():
            assert np.array_equal(got[key].numpy(), value), key
    data = resident.sampler.dataset
    image_bytes = data.n_steps * data.spec.views * int(np.prod(data.spec.image_shape))
    assert resident_bytes(data, ("image",)) == image_bytes == resident.images.numel()
    with pytest.raises(SamplerConfigError, match="refresh_every must be 0"):
        ResidentWindows(small_dataset, dataclasses.replace(config, refresh_every=4))
