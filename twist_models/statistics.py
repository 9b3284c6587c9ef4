"""Aggregate statistics of evaluation returns (the method of Agarwal et al., 2021).

* the interquartile mean (IQM): the mean of the middle 50% of scores, robust to outlier runs;
* oracle-normalised scores: an agent's return divided by the oracle's on the same setting;
* a stratified percentile bootstrap confidence interval: each stratum (a task, or a seed) is
  resampled on its own, so every resample keeps the design's composition.

scipy's ``trim_mean`` and ``bootstrap`` do the work (``bootstrap`` with several samples and
``paired=False`` resamples each one independently: exactly a stratified bootstrap).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from twist_data.errors import ConfigError


def iqm(scores: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean along ``axis``: the mean after trimming 25% from each end."""
    return stats.trim_mean(np.asarray(scores, np.float64), 0.25, axis=axis)


@dataclass(frozen=True)
class Interval:
    """A point estimate with its confidence interval."""

    estimate: float
    low: float
    high: float


def stratified_bootstrap(strata: Sequence[np.ndarray], confidence: float = 0.95,
                         resamples: int = 2000, seed: int = 0) -> Interval:
    """IQM of all scores pooled over ``strata`` (1-D arrays, e.g. one per task) with a
    stratified percentile bootstrap interval at ``confidence``."""
    groups = tuple(np.asarray(s, np.float64).ravel() for s in strata)
    if not groups or any(g.size == 0 for g in groups):
        raise ConfigError("every stratum needs at least one score")
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence must be in (0, 1), got {confidence}")

    # A stratum of one score resamples to itself every time (and scipy refuses samples of one
    # observation), so such strata join every resample as constants.
    fixed = np.concatenate([g for g in groups if g.size == 1] or [np.empty(0)])
    varying = tuple(g for g in groups if g.size > 1)

    def pooled_iqm(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        constants = np.broadcast_to(fixed, samples[0].shape[:-1] + fixed.shape)
        return iqm(np.concatenate([*samples, constants], axis=-1), axis=-1)

    estimate = float(iqm(np.concatenate(groups)))
    if not varying or np.ptp(np.concatenate(groups)) == 0:
        return Interval(estimate, estimate, estimate)  # nothing to resample
    result = stats.bootstrap(varying, pooled_iqm, n_resamples=resamples, vectorized=True,
                             paired=False, confidence_level=confidence, method="percentile",
                             rng=np.random.default_rng(seed))
    ci = result.confidence_interval
    return Interval(estimate, float(ci.low), float(ci.high))
