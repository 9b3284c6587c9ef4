"""The twist-data commands on a synthetic dataset, and the exports' contents."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import pytest

from tests.conftest import SMALL, run_command
from tests.test_bad_input import cli
from twist_data.export import episode_strip, export_hdf5, export_video
from twist_data.reader import open_dataset
from twist_data.synth import episode_length


def test_synth_info_episodes_verify(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    assert cli("synth", ds, "--episodes", "3", "--steps", "12", "--views", "3",
               "--image-size", "16", "--shards", "2").returncode == 0
    info = json.loads(cli("info", ds, "--json").stdout)
    assert (info["episodes"], info["steps"], info["views"]) == (3, 36, 3)
    assert info["image_shape"] == [16, 16, 3] and len(info["shards"]) == 2
    assert info["bytes_on_disk"] > 0 and info["compression_ratio"] > 0
    assert cli("episodes", ds, "--csv", tmp_path / "e.csv").returncode == 0
    table = pd.read_csv(tmp_path / "e.csv")
    assert table["length"].tolist() == [12, 12, 12]
    assert "synth-001" in cli("episodes", ds).stdout
    result = cli("verify", ds)
    assert result.returncode == 0 and "3 episodes, 36 steps verified" in result.stdout


def test_video_shows_every_step_with_views_side_by_side(small_dataset: Path,
                                                        tmp_path: Path) -> None:
    images = open_dataset(small_dataset).episode(1).image
    strip = episode_strip(images, scale=2)
    t, k, h, w, _ = images.shape
    assert strip.shape == (t, 2 * h, 2 * k * w, 3)
    np.testing.assert_array_equal(strip[5, ::2, 2 * w::2], images[5, 1])
    mp4 = export_video(small_dataset, 1, tmp_path / "e.mp4", scale=2)
    capture = cv2.VideoCapture(str(mp4))
    frames = 0
    while capture.read()[0]:
        frames += 1
    assert frames == episode_length(SMALL, 1) == t
    assert capture.get(cv2.CAP_PROP_FRAME_WIDTH) == 2 * k * w
    if importlib.util.find_spec("av") is not None:  # the video extra: H.264, decoded back
        import av

        with av.open(str(mp4)) as container:
            stream = container.streams.video[0]
            decoded = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(stream)])
        assert stream.codec_context.name == "h264" and decoded.shape == strip.shape
        # Each decoded frame is the frame written there (closest to it of all), within a few
        # levels (4:2:0 chroma subsampling costs the synthetic renders' coloured noise most).
        error = np.abs(decoded[:, None].astype(int) - strip[None].astype(int)).mean((2, 3, 4))
        assert np.array_equal(error.argmin(1), np.arange(t))
        assert error.diagonal().mean() < 8
    gif = export_video(small_dataset, 1, tmp_path / "e.gif", scale=2)
    ok, animation = cv2.imreadanimation(str(gif))
    assert ok and len(animation.frames) == t


def test_hdf5_export_holds_every_episode(small_dataset: Path, tmp_path: Path) -> None:
    ds = open_dataset(small_dataset)
    path = export_hdf5(small_dataset, tmp_path / "d.h5")
    with h5py.File(path) as f:
        assert f.attrs["format"] == "twist.matching-dataset.hdf5"
        ends = f["meta/episode_ends"][:]
        np.testing.assert_array_equal(ends, ds.episode_ends)
        assert f["meta/episode_shard"][:].tolist() == [0, 0, 0, 1, 1, 1]
        for i in (0, 4):
            a, b = int(ds.episode_starts[i]), int(ends[i])
            ep = ds.episode(i)
            np.testing.assert_array_equal(f["data/image"][a:b], ep.image)
            np.testing.assert_array_equal(f["data/dr/agent_rgb"][a:b], ep.dr["agent_rgb"])
            np.testing.assert_array_equal(f["data/reward"][a:b], ep.reward)


def test_help_keeps_the_bracketed_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    # Rich markup read "[random per step]" as a style tag and dropped it from the help.
    monkeypatch.setenv("COLUMNS", "200")
    for module, note in (("baseline", "[random per step]"), ("collect", "[train-wide]"),
                         ("eval", "[the first agent's]")):
        result = run_command(module, "--help")
        assert result.returncode == 0 and note in result.stdout, (module, result.stdout)
