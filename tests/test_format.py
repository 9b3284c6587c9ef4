"""The format: time alignment, round trips, the spec in datasets.md, re-rendering from DR data."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import zarr

from tests.conftest import SMALL
from twist_data.reader import open_dataset
from twist_data.sampler import SamplerConfig, WindowSampler
from twist_data.schema import (
    EPISODE_COLUMNS,
    FORMAT_VERSION,
    DatasetSpec,
    Episode,
    EpisodeInfo,
    step_arrays,
)
from twist_data.synth import render_synthetic, synth_spec, synthetic_episode
from twist_data.writer import ShardWriter

ROOT = Path(__file__).resolve().parents[1]


def hand_built_episode(spec: DatasetSpec) -> tuple[Episode, list[float], list[float]]:
    """Integrator s' = s + a, reward = -|s'|, from s_0 = 1 with actions -0.5, -0.25, +1."""
    states, applied, rewards = [1.0], [-0.5, -0.25, 1.0], []
    for a in applied:
        states.append(states[-1] + a)
        rewards.append(-abs(states[-1]))
    t = len(states)
    k, h, w = spec.views, spec.image_height, spec.image_width
    image = np.zeros((t, k, h, w, 3), np.uint8)
    image[:, :, 0, 0, 0] = np.arange(t)[:, None] + 1  # frame t is marked with t + 1
    ep = Episode(
        image=image,
        state=np.array(states, np.float32)[:, None].repeat(spec.state_dim, 1),
        physics=np.array(states, np.float64)[:, None].repeat(spec.physics_dim, 1),
        action=np.array([0.0, *applied], np.float32)[:, None],
        reward=np.array([0.0, *rewards], np.float32),
        discount=np.ones(t, np.float32),
        is_first=np.arange(t) == 0, is_last=np.arange(t) == t - 1, is_terminal=np.zeros(t, bool),
        dr={p.name: np.zeros((t, k, *p.shape), p.dtype) for p in spec.dr_params},
    )
    return ep, states, rewards


def test_time_alignment_matches_a_hand_built_episode(tmp_path: Path) -> None:
    spec = synth_spec(views=2, image_size=16)
    ep, states, rewards = hand_built_episode(spec)
    with ShardWriter.create(tmp_path, "hand", spec) as w:
        w.append(ep, EpisodeInfo(seed=0, policy="scripted", dr={"pole_mass_scale": 1.0}))
    sampler = WindowSampler(tmp_path, SamplerConfig(length=4, batch_size=1, view=1))
    b = sampler.batch()
    s, a, r = b["state"][0, :, 0], b["action"][0, :, 0], b["reward"][0]
    # index t holds o_t/s_t, the action that led to it (a_{t-1}) and the reward for it.
    np.testing.assert_array_equal(s, states)
    np.testing.assert_array_equal(s[1:], s[:-1] + a[1:])
    np.testing.assert_array_equal(r[1:], rewards)
    assert a[0] == 0 and r[0] == 0
    np.testing.assert_array_equal(b["image"][0, :, 0, 0, 0], np.arange(4) + 1)
    assert b["is_first"][0].tolist() == [True, False, False, False]
    assert b["is_last"][0].tolist() == [False, False, False, True]


def test_every_array_round_trips(small_dataset: Path) -> None:
    ds = open_dataset(small_dataset)
    assert ds.n_episodes == SMALL.episodes
    table = ds.episodes()
    for i in range(SMALL.episodes):
        expected, info = synthetic_episode(SMALL, i)
        got = ds.episode(i).arrays()
        assert set(got) == set(expected.arrays())
        for key, value in expected.arrays().items():
            assert got[key].dtype == value.dtype, key
            np.testing.assert_array_equal(got[key], value, err_msg=key)
        row = table.loc[i]
        assert row["length"] == len(expected)
        assert row["seed"] == info.seed and row["policy"] == "synthetic"
        assert row["dr_pole_mass_scale"] == pytest.approx(float(info.dr["pole_mass_scale"]))
        assert row["return"] == pytest.approx(float(expected.reward.astype(np.float64).sum()))


def test_negative_episode_indices_count_from_the_end(small_dataset: Path) -> None:
    dataset = open_dataset(small_dataset)
    n = dataset.n_episodes
    for index in (-1, -n):
        expected = dataset.episode(n + index)
        np.testing.assert_array_equal(dataset.episode(index).state, expected.state)
        assert dataset.episode_info(index) == dataset.episode_info(n + index)


def test_plain_zarr_reads_what_datasets_md_describes(small_dataset: Path) -> None:
    """A reader written from datasets.md alone, with zarr and the standard library: every
    shard's commit record, every episode's every data/ array and meta/ column, the policy
    through the shard's own code table, and the chunk files checked to exist (§5, §7); it
    agrees with the synthetic ground truth on every array."""
    global_episode = 0
    for shard in sorted(p for p in small_dataset.iterdir()
                        if p.name.endswith(".zarr") and not p.name.startswith(".")):
        group = zarr.open_group(shard, mode="r")
        block = group.attrs["twist"]
        assert block["format"] == "twist.matching-dataset"
        assert block["format_version"] == FORMAT_VERSION
        n_episodes, n_steps = block["commit"]["n_episodes"], block["commit"]["n_steps"]
        policy_names = {code: name for name, code in block["policy_codes"].items()}
        for key in ["data/state", "data/image", "meta/episode_ends"]:
            array = group[key]
            rows = array.shards[0] if array.shards else array.chunks[0]
            committed = n_steps if key.startswith("data/") else n_episodes
            for i in range(-(-committed // rows)):
                name = "/".join(["c", str(i)] + ["0"] * (array.ndim - 1))
                assert (shard / key / name).is_file(), (key, i)
        ends = group["meta/episode_ends"][:n_episodes]
        assert ends[-1] == n_steps
        data_keys = [f"data/{k}" for k in ("image", "state", "physics", "action", "reward",
                                             "discount", "is_first", "is_last", "is_terminal")]
        data_keys += [f"data/dr/{p['name']}" for p in block["spec"]["dr_params"]]
        for e in range(n_episodes):
            a, b = (int(ends[e - 1]) if e else 0), int(ends[e])
            expected, info = synthetic_episode(SMALL, global_episode)
            arrays = expected.arrays()
            for key in data_keys:
                np.testing.assert_array_equal(group[key][a:b], arrays[key.removeprefix("data/")],
                                              err_msg=key)
            assert policy_names[int(group["meta/episode_policy"][e])] == info.policy
            assert int(group["meta/episode_seed"][e]) == info.seed
            for p in block["spec"]["episode_dr_params"]:
                np.testing.assert_array_equal(group[f"meta/dr/{p['name']}"][e],
                                              info.dr[p["name"]])
            assert group["meta/episode_return"][e] == pytest.approx(arrays["reward"].sum())
            global_episode += 1
    assert global_episode == SMALL.episodes


def test_datasets_md_documents_every_array() -> None:
    text = (ROOT / "datasets.md").read_text()
    spec = synth_spec()
    core = [a for a in step_arrays(spec) if not a.name.startswith("dr/")]
    for a in core:
        assert re.search(rf"`data/{a.name}`", text), a.name
    for column in EPISODE_COLUMNS:
        assert f"`meta/{column}`" in text, column
    assert f"format_version` = {FORMAT_VERSION}" in text or f"`format_version`: {FORMAT_VERSION}" \
        in text


def test_stored_dr_parameters_reproduce_each_frame(small_dataset: Path) -> None:
    ds = open_dataset(small_dataset)
    ep = ds.episode(2)
    for t in (0, 7, len(ep) - 1):
        for v in range(ds.spec.views):
            frame = render_synthetic(ep.physics[t], ep.dr["background_seed"][t, v],
                                     ep.dr["agent_rgb"][t, v], ep.dr["brightness"][t, v],
                                     ds.spec.image_height)
            np.testing.assert_array_equal(frame, ep.image[t, v])


def test_spec_survives_json() -> None:
    spec = synth_spec(views=3, image_size=32)
    assert DatasetSpec.from_json(spec.to_json()) == spec


def test_spec_tells_how_its_views_were_rendered() -> None:
    spec = synth_spec(views=3, image_size=32)
    assert spec.supersample is None  # synthetic: nothing records a renderer
    blocks = [{"views": [0, 2], "supersample": 2}, {"views": [2, 3], "supersample": 2}]
    rendered = dataclasses.replace(spec, extra={"render": blocks})
    assert rendered.supersample == 2
    assert rendered.image_agent_info() == {"task": spec.task, "action_repeat": spec.action_repeat,
                                           "image_size": 32, "supersample": 2}
    blocks[1] = {"views": [2, 3]}  # a block from before the field: rendered at 1
    assert dataclasses.replace(spec, extra={"render": blocks}).supersample is None
