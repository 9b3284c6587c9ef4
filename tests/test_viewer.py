"""twist-data viz: one episode of D as a rerun recording, read back through rerun's reader."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_bad_input import cli
from twist_data.errors import MissingExtraError
from twist_data.reader import open_dataset
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_data.viewer import log_episode, state_series

pytest.importorskip("rerun")


def _read(path: Path) -> dict[str, dict[int, object]]:
    """{entity path: {step: logged value}} of a .rrd file (static entities at step -1)."""
    from rerun.chunk import RrdReader

    logged: dict[str, dict[int, object]] = {}
    for chunk in RrdReader(str(path)).store().stream():
        columns = chunk.to_record_batch().to_pydict()
        steps = columns.get("step", [-1] * chunk.num_rows)
        for row, step in enumerate(steps):
            value = {k: v[row] for k, v in columns.items()
                     if k not in ("step", "log_time", "rerun.controls.RowId")}
            logged.setdefault(chunk.entity_path, {})[step] = value
    return logged


def test_every_step_of_the_episode_reads_back_from_the_file(tmp_path: Path) -> None:
    dataset = write_synthetic_dataset(tmp_path / "d", SynthConfig(
        episodes=3, steps=7, views=2, image_size=16, seed=5))
    out = tmp_path / "episode.rrd"
    result = cli("viz", dataset, "--episode", "-2", "--save", out)  # episode 1
    assert result.returncode == 0, result.stderr
    data = open_dataset(dataset)
    episode, info = data.episode(1), data.episode_info(1)
    logged = _read(out)
    for t in range(len(episode)):
        for k in range(2):
            image = logged[f"/views/{k}"][t]["Image:buffer"][0]
            assert np.array_equal(np.asarray(image, np.uint8).reshape(16, 16, 3),
                                  episode.image[t, k])
        state = np.concatenate([logged[f"/{path}"][t]["Scalars:scalars"]
                                for path, _ in state_series(data)])
        assert np.array_equal(state, episode.state[t].astype(np.float64))
        assert logged["/action"][t]["Scalars:scalars"] == episode.action[t].tolist()
        assert logged["/reward"][t]["Scalars:scalars"] == [float(episode.reward[t])]
        assert logged["/flags"][t]["Scalars:scalars"] == [
            float(episode.is_first[t]), float(episode.is_last[t]), float(episode.is_terminal[t])]
        for name, values in episode.dr.items():
            for k in range(2):
                assert logged[f"/dr/{name}/view{k}"][t]["Scalars:scalars"] == pytest.approx(
                    np.ravel(values[t, k]).tolist()), name
    provenance = json.loads(logged["/episode"][-1]["TextDocument:text"][0])
    assert (provenance["episode"], provenance["seed"], provenance["policy"]) == (
        1, info.seed, info.policy)
    assert not list(tmp_path.glob(".*.partial"))


def test_bad_requests_are_refused_in_one_line(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    dataset = write_synthetic_dataset(tmp_path / "d", SynthConfig(episodes=2, steps=4,
                                                                  image_size=16))
    for args, message in [
            (("--episode", "5", "--save", tmp_path / "a.rrd"),
             "dataset has 2 episodes; index 5 is out of range"),
            (("--save", tmp_path / "a.mp4"), "must end in .rrd")]:
        result = cli("viz", dataset, *args)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and message in lines[0], result.stderr
        assert not list(tmp_path.glob("a.*"))
    # Without --save on a Linux machine with no display: refused before rerun is started.
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = subprocess.run([sys.executable, "-m", "twist_cli.data", "viz", str(dataset)],
                            capture_output=True, text=True, env=headless)
    if sys.platform.startswith("linux"):
        assert result.returncode == 2 and result.stderr.strip().startswith(
            "error: no display to open the rerun viewer on"), result.stderr
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(MissingExtraError, match=r"pip install 'twist\[viz\]'"):
        log_episode(dataset, 0, tmp_path / "b.rrd")
