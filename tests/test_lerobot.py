"""twist-data export-lerobot: D as a LeRobotDataset v3.0 folder, read back by LeRobot's own
loader in the reference environment (scripts/reference_env.sh)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import reference_python
from tests.test_bad_input import cli
from twist_data.errors import ImagesStrippedError, MissingExtraError
from twist_data.lerobot_export import (
    QUANTILES,
    LeRobotExportError,
    export_lerobot,
    stat_frames,
    view_key,
)
from twist_data.reader import open_dataset
from twist_data.synth import SynthConfig, write_synthetic_dataset

av = pytest.importorskip("av")
pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

ROOT = Path(__file__).resolve().parents[1]
SYNTH = SynthConfig(episodes=11, steps=14, views=2, image_size=16, shards=2, length_jitter=4, seed=4)


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("lerobot") / "d", SYNTH)


@pytest.fixture(scope="module")
def exported(synth: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The CLI's export of the synthetic D (it keeps no clock, so --fps is given)."""
    out = tmp_path_factory.mktemp("lerobot-out") / "export"
    result = cli("export-lerobot", synth, out, "--fps", "25")
    assert result.returncode == 0, result.stderr
    return out


def rgb(frame: av.VideoFrame) -> np.ndarray:
    """A decoded frame as RGB [H, W, 3]: a lossless frame's planes as they are (PyAV orders
    them RGB), without the ~7 ms per frame its conversion to rgb24 costs."""
    return frame.to_ndarray() if frame.format.name == "gbrp" else frame.to_ndarray(format="rgb24")


def decoded(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of an MP4 and its time in seconds."""
    with av.open(str(path)) as container:
        frames = [(float(f.pts * f.time_base), rgb(f))
                  for f in container.decode(video=0)]
    return np.array([t for t, _ in frames]), np.stack([f for _, f in frames])


def test_rows_and_frames_are_ds_steps_in_lerobots_convention(synth: Path, exported: Path) -> None:
    data = open_dataset(synth)
    info = json.loads((exported / "meta" / "info.json").read_text())
    lengths = data.episode_lengths - 1
    assert info["codebase_version"] == "v3.0" and info["fps"] == 25
    assert info["total_episodes"] == data.n_episodes and info["total_frames"] == lengths.sum()
    rows = pq.read_table(exported / "data" / "chunk-000" / "file-000.parquet")
    # The Parquet columns are exactly the features that are not videos, in their order.
    assert rows.column_names == [k for k, v in info["features"].items() if v["dtype"] != "video"]
    assert np.array_equal(rows.column("index").to_numpy(), np.arange(lengths.sum()))
    times = {k: decoded(exported / "videos" / view_key(k) / "chunk-000" / "file-000.mp4")
             for k in range(data.spec.views)}
    episodes = pq.read_table(exported / "meta" / "episodes" / "chunk-000" /
                             "file-000.parquet").to_pylist()
    start = 0
    for i in range(data.n_episodes):
        d, n = data.episode(i), int(lengths[i])
        mine = rows.slice(start, n)
        column = {name: np.array(mine.column(name).to_pylist()) for name in mine.column_names}
        # A feature of shape [1] (the one action here) is a scalar column, as LeRobot types it.
        column["action"] = column["action"].reshape(n, -1)
        # Frame t: D's observation t and the action taken from it, which D stores at t + 1.
        assert np.array_equal(column["observation.environment_state"], d.state[:-1])
        assert np.array_equal(column["observation.physics"], d.physics[:-1])
        assert np.array_equal(column["action"], d.action[1:])
        assert np.array_equal(column["next.reward"], d.reward[1:])
        assert np.array_equal(column["next.done"], d.is_last[1:]) and column["next.done"][-1]
        assert np.array_equal(column["next.terminal"], d.is_terminal[1:])
        assert np.array_equal(column["frame_index"], np.arange(n))
        assert np.allclose(column["timestamp"], np.arange(n) / 25)
        assert np.array_equal(column["dr.agent_rgb"], d.dr["agent_rgb"][:-1].reshape(n, -1))
        row = episodes[i]
        assert (row["episode_index"], row["length"]) == (i, n)
        assert (row["dataset_from_index"], row["dataset_to_index"]) == (start, start + n)
        assert row["twist/episode"] == i and row["twist/seed"] == data.episode_info(i).seed
        assert row["twist/heldout"] == (i == 9)  # every 10th episode, as the distiller splits
        for k in range(data.spec.views):
            when, frames = times[k]
            begin = row[f"videos/{view_key(k)}/from_timestamp"]
            assert row[f"videos/{view_key(k)}/to_timestamp"] == pytest.approx(begin + n / 25)
            # Lossless: the frame at each row's time is D's, byte for byte.
            at = np.abs(when[:, None] - (begin + np.arange(n) / 25)[None]).argmin(0)
            assert np.abs(when[at] - (begin + np.arange(n) / 25)).max() < 1e-4
            assert np.array_equal(frames[at], d.image[:-1, k])
        start += n


def test_stats_are_the_rows_statistics(synth: Path, exported: Path) -> None:
    data = open_dataset(synth)
    stats = json.loads((exported / "meta" / "stats.json").read_text())
    info = json.loads((exported / "meta" / "info.json").read_text())
    assert set(stats) == set(info["features"])
    state = np.concatenate([data.episode(i).state[:-1] for i in range(data.n_episodes)])
    entry = {k: np.array(v) for k, v in stats["observation.environment_state"].items()}
    # Pooled over episodes by count, mean and std are those of all rows at once.
    assert np.allclose(entry["mean"], state.mean(0)) and np.allclose(entry["std"], state.std(0))
    assert np.array_equal(entry["min"], state.min(0)) and entry["count"].tolist() == [len(state)]
    assert set(entry) == {"min", "max", "mean", "std", "count",
                          *(f"q{round(q * 100):02d}" for q in QUANTILES)}
    # A view: per channel in [0, 1], from the frames LeRobot samples of each episode.
    frames = [data.episode(i).image[:-1, 0] for i in range(data.n_episodes)]
    sampled = np.concatenate([f[stat_frames(len(f))] for f in frames]).reshape(-1, 3) / 255
    view = {k: np.array(v) for k, v in stats[view_key(0)].items()}
    assert view["mean"].shape == (3, 1, 1)
    assert np.allclose(view["mean"].ravel(), sampled.mean(0))
    assert np.allclose(view["std"].ravel(), sampled.std(0))


def test_episodes_and_views_are_chosen_and_ds_clock_gives_the_rate(
        collected_tiny: Path, tmp_path: Path) -> None:
    from twist_sim.tasks import TaskEnv

    data = open_dataset(collected_tiny)
    out = export_lerobot(collected_tiny, tmp_path / "e", episodes=[-1, 0], views=[1])
    info = json.loads((out / "meta" / "info.json").read_text())
    env = TaskEnv(data.spec.task, data.spec.action_repeat)
    assert info["fps"] == round(1 / env.seconds_per_step)
    assert [k for k in info["features"] if k.startswith("observation.images")] == [view_key(1)]
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert episodes.column("twist/episode").to_pylist() == [0, data.n_episodes - 1]  # D's order
    assert info["features"]["dr.colour"]["shape"][0] == int(np.prod(
        data.episode(0).dr["colour"].shape[2:]))


@pytest.mark.parametrize("case", ["not-empty", "not-lerobot", "stripped", "view", "episode",
                                  "twice", "clock", "extra"])
def test_bad_input_writes_nothing(case: str, synth: Path, exported: Path, tmp_path: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    out, kwargs, error = tmp_path / "out", {"fps": 25}, LeRobotExportError
    source = synth
    if case == "not-empty":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    elif case == "not-lerobot":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
        kwargs["overwrite"] = True
    elif case == "stripped":
        from twist_data.strip import strip_dataset

        source, error = strip_dataset(synth, tmp_path / "stripped"), ImagesStrippedError
    elif case == "view":
        kwargs["views"] = [2]
    elif case == "episode":
        kwargs["episodes"] = [11]
    elif case == "twice":
        kwargs["episodes"] = [1, -10]
    elif case == "clock":
        kwargs = {}
    else:
        monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
        error = MissingExtraError
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(error) as raised:
        export_lerobot(source, out, **kwargs)
    message = str(raised.value)
    expected = {"not-empty": "--overwrite", "not-lerobot": "not a LeRobot dataset",
                "stripped": "--reproduce", "view": "view 2", "episode": "episode 11",
                "twice": "twice", "clock": "--fps", "extra": "twist[lerobot]"}[case]
    assert expected in message and "\n" not in message
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no staging folder left
    if out.exists():
        assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.parametrize("fails", ["videos", "parquet"])
def test_a_failure_while_writing_leaves_the_former_export(fails: str, synth: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from twist_data import lerobot_export

    out = export_lerobot(synth, tmp_path / "e", fps=25, episodes=[0])
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def broken(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    if fails == "videos":
        monkeypatch.setattr(lerobot_export._Videos, "write", broken)
    else:
        monkeypatch.setattr(pq, "write_table", broken)
    with pytest.raises(LeRobotExportError, match=r"cannot write.*No space left on device"):
        export_lerobot(synth, out, fps=25, episodes=[1, 2], overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e"]  # no staging left beside it
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_overwrite_replaces_an_export(synth: Path, exported: Path, tmp_path: Path) -> None:
    out = tmp_path / "e"
    export_lerobot(synth, out, fps=25, episodes=[0])
    refused = cli("export-lerobot", synth, out, "--fps", "25")
    assert refused.returncode != 0 and "Traceback" not in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    export_lerobot(synth, out, fps=25, episodes=[1, 2], overwrite=True)
    assert json.loads((out / "meta" / "info.json").read_text())["total_episodes"] == 2


def test_lerobots_own_loader_reads_every_array_and_frame(collected_tiny: Path,
                                                         tmp_path: Path) -> None:
    python = reference_python()
    out = export_lerobot(collected_tiny, tmp_path / "e")
    result = subprocess.run([str(python), str(ROOT / "tests" / "lerobot_readback.py"), str(out),
                             str(tmp_path / "read.npz")], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    read = np.load(tmp_path / "read.npz")
    summary = json.loads(str(read["summary"]))
    data = open_dataset(collected_tiny)
    lengths = data.episode_lengths - 1
    assert summary["num_episodes"] == data.n_episodes
    assert summary["num_frames"] == lengths.sum()
    features = summary["features"]
    assert features["observation.environment_state"]["shape"] == [data.spec.state_dim]
    assert features[view_key(0)]["shape"] == [*data.spec.image_shape]
    assert summary["video_keys"] == [view_key(k) for k in range(data.spec.views)]
    episodes = [data.episode(i) for i in range(data.n_episodes)]
    assert np.array_equal(read["observation.environment_state"],
                          np.concatenate([e.state[:-1] for e in episodes]))
    actions = np.concatenate([e.action[1:] for e in episodes])
    assert np.array_equal(read["action"].reshape(actions.shape), actions)  # [1]: a scalar
    assert np.array_equal(read["next.reward"], np.concatenate([e.reward[1:] for e in episodes]))
    assert np.array_equal(read["next.done"], np.concatenate([e.is_last[1:] for e in episodes]))
    # The physics rows keep float64 (LeRobot's items hand out float32).
    assert np.array_equal(read["rows.observation.physics"],
                          np.concatenate([e.physics[:-1] for e in episodes]))
    assert set(read["task"].tolist()) == {data.spec.task}
    for k in range(data.spec.views):  # lossless: D's bytes at the times LeRobot asks for
        assert np.array_equal(read[f"frames.{view_key(k)}"],
                              np.concatenate([e.image[:-1, k] for e in episodes]))
    # stats.json against LeRobot's own statistics of the same rows and frames: equal, and
    # each quantile within one of its 5,000 histogram bins.
    for feature, theirs in summary["lerobot_stats"].items():
        ours = summary["stats"][feature]
        for key in ("min", "max", "mean", "std", "count"):
            assert np.allclose(ours[key], theirs[key], rtol=1e-5, atol=1e-7), (feature, key)
        width = (np.array(ours["max"], float) - np.array(ours["min"], float)) / 5000
        for q in QUANTILES:
            key = f"q{round(q * 100):02d}"
            assert np.all(np.abs(np.array(ours[key]) - np.array(theirs[key])) <= width + 1e-9), \
                (feature, key)
