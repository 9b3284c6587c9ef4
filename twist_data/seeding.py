"""Seeds derived from a run's seed: one mixing rule for every stage, so that (run seed,
episode), (run seed, purpose, rank) and the like never collide or correlate."""

from __future__ import annotations

import numpy as np


def derived_seed(*keys: int) -> int:
    """A well-mixed 32-bit seed from integer keys, e.g. (run seed, episode index)."""
    return int(np.random.SeedSequence(list(keys)).generate_state(1)[0])


#: The key that separates evaluation episodes' seeds from every other derived seed.
EVALUATION_EPISODES = 1 << 20


def evaluation_episode_seed(seed: int, episode: int) -> int:
    """The seed of evaluation episode ``episode`` of evaluation seed ``seed``: its initial
    state, dynamics and DR draws (``twist-eval`` and the Gymnasium environments alike)."""
    return derived_seed(seed, EVALUATION_EPISODES, episode)
