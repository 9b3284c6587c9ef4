"""Shared fixtures: tiny synthetic datasets written by the library's own synth code."""

from __future__ import annotations

from pathlib import Path

import pytest

from twist_data.synth import SynthConfig, write_synthetic_dataset

SMALL = SynthConfig(episodes=6, steps=40, views=2, image_size=16, shards=2, length_jitter=12,
                    seed=3)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A read-only two-shard dataset of six episodes of varying length (do not modify)."""
    return write_synthetic_dataset(tmp_path_factory.mktemp("small") / "ds", SMALL)


@pytest.fixture
def fresh_dataset(tmp_path: Path) -> Path:
    """A private copy-sized dataset a test may damage."""
    return write_synthetic_dataset(tmp_path / "ds", SMALL)
