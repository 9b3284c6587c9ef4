"""twist-data export-minari: D as a Minari dataset, read back through Minari and torchrl."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_bad_input import cli
from twist_data.errors import MissingExtraError
from twist_data.minari_export import MinariExportError, export_minari
from twist_data.reader import MatchingDataset, open_dataset
from twist_data.synth import SynthConfig, write_synthetic_dataset

minari = pytest.importorskip("minari")

DATASET_ID = "twist/synth-v0"


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(D, Minari root): a two-shard synthetic D of uneven episodes, exported by the CLI."""
    root = tmp_path_factory.mktemp("minari")
    dataset = write_synthetic_dataset(root / "d", SynthConfig(
        episodes=5, steps=14, views=2, image_size=16, shards=2, length_jitter=4, seed=4))
    result = cli("export-minari", dataset, DATASET_ID, "--root", root / "datasets")
    assert result.returncode == 0, result.stderr
    return dataset, root / "datasets"


def test_every_array_and_the_provenance_read_back_through_minari(
        exported: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    dataset, root = exported
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    data = open_dataset(dataset)
    loaded = minari.load_dataset(DATASET_ID)
    assert loaded.total_episodes == data.n_episodes
    assert loaded.total_steps == int((data.episode_lengths - 1).sum())  # transitions
    metadata = list(loaded.storage.get_episode_metadata(range(data.n_episodes)))
    for i, episode in enumerate(loaded.iterate_episodes()):
        d, info = data.episode(i), data.episode_info(i)
        # Gymnasium's convention: T observations, the T - 1 transitions between them; D's row
        # t holds the action that led to step t and the reward received on arriving there.
        for k in range(data.spec.views):
            assert np.array_equal(episode.observations[f"image_{k}"], d.image[:, k])  # lossless
        assert np.array_equal(episode.observations["state"], d.state)
        assert np.array_equal(episode.actions, d.action[1:])
        assert np.array_equal(episode.rewards, d.reward[1:])
        assert np.array_equal(episode.terminations, d.is_terminal[1:])
        assert np.array_equal(episode.truncations, d.is_last[1:] & ~d.is_terminal[1:])
        assert episode.truncations[-1] or episode.terminations[-1]
        assert np.array_equal(episode.infos["physics"], d.physics)
        assert set(episode.infos["dr"]) == set(d.dr)
        for name, values in d.dr.items():
            assert np.array_equal(episode.infos["dr"][name], values), name
        meta = metadata[i]
        assert meta["seed"] == info.seed and meta["options"]["policy"] == info.policy
        assert meta["options"]["teacher_step"] == info.teacher_step
        assert meta["options"]["twist_episode"] == i
        assert meta["options"]["twist_shard"] == ("synth-000" if i < 3 else "synth-001")
        for name, value in info.dr.items():
            assert meta["options"]["dr"][name] == pytest.approx(value)


def _check_transitions(batch: object, data: MatchingDataset, slice_len: int) -> None:
    """Each sampled row is one of D's transitions: a state, the action taken there, the next
    state and the reward on arriving, all of one episode, and the image of view 1 there."""
    states = batch["observation", "state"].numpy()
    following = batch["next", "observation", "state"].numpy()
    for j in range(len(states)):
        matches = [(i, t) for i in range(data.n_episodes)
                   for t in np.flatnonzero((data.episode(i).state[:-1] == states[j]).all(1))]
        assert len(matches) == 1, f"row {j} is not one of D's states"
        i, t = matches[0]
        d = data.episode(i)
        assert int(batch["episode"][j]) == i
        assert np.array_equal(following[j], d.state[t + 1])
        assert np.array_equal(batch["action"][j].numpy(), d.action[t + 1])
        assert float(batch["next", "reward"][j]) == pytest.approx(float(d.reward[t + 1]))
        # torchrl's SliceSampler also marks each slice's last step done (no bootstrapping
        # across a slice's end), so done is D's last step or the end of a slice.
        assert bool(batch["next", "done"][j]) == (bool(d.is_last[t + 1])
                                                  or (j + 1) % slice_len == 0)
        assert np.array_equal(batch["observation", "image_1"][j].numpy(), d.image[t, 1])
        assert np.array_equal(batch["next", "info", "physics"][j].numpy(), d.physics[t + 1])


def test_torchrl_samples_slices_of_the_export(exported: tuple[Path, Path]) -> None:
    pytest.importorskip("torchrl")
    from twist_data.torchrl_replay import minari_replay_buffer

    dataset, root = exported
    data = open_dataset(dataset)
    buffer = minari_replay_buffer(DATASET_ID, root=root, slice_len=4, batch_size=12)
    assert len(buffer) == int((data.episode_lengths - 1).sum())
    batch = buffer.sample()
    _check_transitions(batch, data, slice_len=4)
    # Three slices of four consecutive steps, each within one episode.
    episodes = batch["episode"].reshape(3, 4)
    assert (episodes == episodes[:, :1]).all()
    with pytest.raises(MinariExportError, match="no Minari dataset 'twist/other-v0' in"):
        minari_replay_buffer("twist/other-v0", root=root)


@pytest.mark.xfail(strict=True, reason="torchrl 0.14.1's MinariExperienceReplay returns "
                                       "memmap_like(data): the shapes without the contents")
def test_torchrls_own_minari_reader_fills_the_export(exported: tuple[Path, Path],
                                                     tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("torchrl")
    from torchrl.data.datasets import MinariExperienceReplay
    from torchrl.data.replay_buffers import SliceSampler

    dataset, root = exported
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    buffer = MinariExperienceReplay(DATASET_ID, batch_size=12, root=tmp_path / "torchrl",
                                    download=False, load_from_local_minari=True,
                                    sampler=SliceSampler(slice_len=4))
    _check_transitions(buffer.sample(), open_dataset(dataset), slice_len=4)


def test_an_existing_id_is_refused_unless_overwritten(
        exported: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    dataset, root = exported
    main_data = root / DATASET_ID / "data" / "main_data.hdf5"
    before = main_data.read_bytes()
    refused = cli("export-minari", dataset, DATASET_ID, "--root", root)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert refused.stderr.strip() == (f"error: Minari dataset '{DATASET_ID}' already exists in "
                                      f"{root}; pass overwrite (--overwrite) to replace it")
    assert main_data.read_bytes() == before
    for bad in ("../outside-v0", "no-version", "a name-v0", "/abs-v0"):
        with pytest.raises(MinariExportError, match="is not a Minari ID"):
            export_minari(dataset, bad, root=root)
    # Overwriting writes the new dataset aside first: no staging folder or old copy remains.
    small = write_synthetic_dataset(root.parent / "small", SynthConfig(
        episodes=2, steps=6, views=2, image_size=16, seed=9))
    export_minari(small, DATASET_ID, root=root, overwrite=True)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    assert minari.load_dataset(DATASET_ID).total_episodes == 2
    assert sorted(p.name for p in root.iterdir()) == ["twist"]
    assert sorted(p.name for p in (root / "twist").iterdir()) == [
        "namespace_metadata.json", "synth-v0"]


def test_without_the_extra_the_export_names_the_install(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "minari", None)  # import minari now raises ImportError
    dataset = write_synthetic_dataset(tmp_path / "d", SynthConfig(episodes=1, steps=4,
                                                                  image_size=16))
    with pytest.raises(MissingExtraError, match=r"pip install 'twist\[minari\]'"):
        export_minari(dataset, DATASET_ID, root=tmp_path / "root")
    assert not (tmp_path / "root").exists()
