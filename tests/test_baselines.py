"""Offline image baselines from D: they learn, keep the student's held-out split, and end in
the same agent bundle as the student."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

from tests.conftest import board_events
from twist_data.sampler import SamplerConfig, WindowSampler
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.agent import Agent
from twist_models.checkpoint import read_checkpoint
from twist_models.config import (
    ActorCriticConfig,
    DreamerConfig,
    MLPConfig,
    from_json,
    to_json,
)
from twist_models.dreamer import Dreamer
from twist_pipeline.baselines import (
    KEYS,
    BaselineConfig,
    BaselineError,
    behaviour_config,
    train_baseline,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("bl") / "ds",
                                   SynthConfig(episodes=8, steps=30, image_size=64, seed=2))


@pytest.mark.parametrize("kind", ["dreamer", "state-recon"])
def test_baseline_learns_and_bundles_its_own_encoder_and_actor(dataset, tmp_path, kind) -> None:
    config = BaselineConfig(kind=kind, model="tiny", steps=60, batch_size=4, length=8,
                            imag_starts=16, log_every=20, checkpoint_every=30, holdout_every=4)
    summary = train_baseline(dataset, tmp_path / kind, config)
    assert summary["updates"] == 60
    metrics = pd.read_csv(tmp_path / kind / "metrics.csv")
    assert list(metrics["updates"]) == [20, 40, 60]
    scalars, _ = board_events(tmp_path / kind)
    assert scalars["train/model_loss"] == [
        (s, pytest.approx(v)) for s, v in zip(metrics["updates"], metrics["model_loss"],
                                               strict=True)]

    checkpoint = read_checkpoint(tmp_path / kind / "latest.pt", kind="dreamer")
    model_config = from_json(DreamerConfig, checkpoint.config)
    # State Recon decodes the 5-dim privileged state; Dreamer decodes the image.
    assert model_config.world_model.decodes_state == (kind == "state-recon")
    model = Dreamer(model_config)
    model.load_state_dict(checkpoint.weights)
    torch.manual_seed(config.seed)
    initial = Dreamer(model_config)  # the run's initialisation
    batch = {k: torch.as_tensor(v) for k, v in WindowSampler(dataset, SamplerConfig(
        length=8, batch_size=16, keys=KEYS, seed=9)).batch().items() if k in KEYS}
    with torch.no_grad():
        losses = []
        for m in (initial, model):
            torch.manual_seed(1)
            losses.append(m.world_model.loss(batch)[2])
    # Both the reconstruction and the reward prediction improved on a fixed batch.
    assert losses[1]["recon_loss"] < losses[0]["recon_loss"]
    assert losses[1]["reward_loss"] < losses[0]["reward_loss"]
    agent = Agent.load(summary["agent"])
    assert agent.info["baseline"] == kind
    image = torch.randint(0, 256, (2, 64, 64, 3), dtype=torch.uint8)
    with torch.no_grad():
        assert torch.equal(agent.student.perception.encoder(image), model.world_model.encoder(image))
        feature = torch.randn(3, model_config.world_model.rssm.feature_dim)
        assert torch.equal(agent.actor(feature).mean, model.actor_critic.actor(feature).mean)


def test_baseline_refuses_to_overwrite_a_run(dataset, tmp_path) -> None:
    config = BaselineConfig(model="tiny", steps=2, batch_size=2, length=8, imag_starts=4,
                            holdout_every=4)
    train_baseline(dataset, tmp_path / "run", config)
    with pytest.raises(BaselineError, match="already holds a baseline run"):
        train_baseline(dataset, tmp_path / "run", config)
    resumed = train_baseline(dataset, tmp_path / "run",
                             BaselineConfig(model="tiny", steps=4, batch_size=2, length=8,
                                            imag_starts=4, holdout_every=4), resume=True)
    assert resumed["updates"] == 4


def test_a_time_limit_stops_a_baseline_resumably(dataset, tmp_path) -> None:
    config = BaselineConfig(model="tiny", steps=10_000, batch_size=2, length=8, imag_starts=4,
                            holdout_every=4, checkpoint_every=10_000)
    first = train_baseline(dataset, tmp_path / "run", config, time_limit=0.5)
    assert first["stopped"] == "time limit" and 0 < first["updates"] < 10_000
    stored = read_checkpoint(tmp_path / "run" / "latest.pt", kind="dreamer")
    assert stored.counters["updates"] == first["updates"]  # kept where the limit stopped it
    # The limit is the run's: a resumed call with the same limit has no time left.
    again = train_baseline(dataset, tmp_path / "run", config, resume=True, time_limit=0.5)
    assert again["updates"] == first["updates"] and again["stopped"] == "time limit"
    assert again["seconds"] >= first["seconds"] >= 0.5
    more = train_baseline(dataset, tmp_path / "run", config, resume=True, time_limit=2.0)
    assert more["updates"] > first["updates"]
    assert Agent.load(more["agent"]).info["updates"] == more["updates"]
    with pytest.raises(BaselineError, match="positive number of seconds, got 0"):
        train_baseline(dataset, tmp_path / "other", config, time_limit=0)
    assert not (tmp_path / "other").exists()


def test_baseline_learns_behaviour_with_the_teachers_settings_and_its_own_sizes() -> None:
    preset = ActorCriticConfig(actor=MLPConfig(layers=2, units=32), critic=MLPConfig(2, 32))
    teacher = ActorCriticConfig(discount=0.98, actor_lr=1e-3, critic_head="twohot",
                                return_norm=True, actor=MLPConfig(4, 400))
    chosen = behaviour_config({"teacher": {"actor_critic": to_json(teacher)}}, preset)
    assert (chosen.discount, chosen.actor_lr, chosen.critic_head, chosen.return_norm) == \
        (0.98, 1e-3, "twohot", True)
    assert (chosen.actor, chosen.critic) == (preset.actor, preset.critic)
    # A dataset that records no teacher (synthetic, or written by hand) keeps the preset.
    assert behaviour_config({}, preset) == preset


def test_a_damaged_dataset_is_refused_with_nothing_left_behind(tmp_path) -> None:
    from twist_data.errors import DatasetCorruptError

    damaged = write_synthetic_dataset(tmp_path / "ds", SynthConfig(episodes=4, steps=20,
                                                                   image_size=64, seed=3))
    chunk = next(damaged.glob("*.zarr")) / "data" / "state" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-7])  # a truncated state chunk: only reading finds it
    config = BaselineConfig(model="tiny", steps=2, batch_size=2, length=8, imag_starts=4,
                            workers=0)
    with pytest.raises(DatasetCorruptError, match="data/state"):
        train_baseline(damaged, tmp_path / "run", config)
    assert not (tmp_path / "run").exists()
