"""Aggregate statistics of evaluation returns (the method of Agarwal et al., 2021).

* the interquartile mean (IQM): the mean of the middle 50% of scores, robust to outlier runs;
* oracle-normalised scores: an agent's return divided by the oracle's on the same setting;
* a stratified percentile bootstrap confidence interval: each stratum (a task, or a seed) is
  resampled on its own, so every resample keeps the design's composition;
* paired differences: two agents evaluated on the same seeded episodes differ episode by
  episode, which removes the episodes' own spread from the comparison (an agent's returns vary
  more between episodes than two close agents differ on one).

scipy's ``trim_mean`` and ``bootstrap`` do the work (``bootstrap`` with several samples and
``paired=False`` resamples each one independently: exactly a stratified bootstrap; ``ttest_rel``
gives the paired interval).

rliable (Agarwal et al.'s library) computes the same estimates and intervals, which a test
checks against rliable 1.2.0 itself (scripts/reference_env.sh); it is not a dependency, since
that release pins arch < 8, whose import fails beside pandas 3, and its statsmodels would not
fit a GPU slot's carry.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

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


def _strata(strata: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Each stratum's scores as a flat float64 array; refused when there is none or one is empty."""
    groups = tuple(np.asarray(s, np.float64).ravel() for s in strata)
    if not groups or any(g.size == 0 for g in groups):
        raise ConfigError("every stratum needs at least one score")
    return groups


def _check_confidence(confidence: float) -> None:
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence must be in (0, 1), got {confidence}")


def stratified_bootstrap(strata: Sequence[np.ndarray], confidence: float = 0.95,
                         resamples: int = 2000, seed: int = 0) -> Interval:
    """IQM of all scores pooled over ``strata`` (1-D arrays, e.g. one per task) with a
    stratified percentile bootstrap interval at ``confidence``."""
    groups = _strata(strata)
    _check_confidence(confidence)

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


@dataclass(frozen=True)
class PairedDifference:
    """``a - b`` over episodes both agents met: the mean, its standard error and 95% t interval
    (None with a single pair), how many episodes ``a`` scored higher on, and out of how many."""

    mean: float
    standard_error: float | None
    ci95: tuple[float, float] | None
    better: int
    pairs: int

    def as_dict(self) -> dict[str, object]:
        """JSON-ready fields."""
        return {"mean": self.mean, "standard_error": self.standard_error,
                "ci95": None if self.ci95 is None else list(self.ci95),
                "better": self.better, "pairs": self.pairs}


def paired_difference(a: np.ndarray, b: np.ndarray) -> PairedDifference:
    """Paired comparison of returns ``a`` [N] and ``b`` [N], element i of each being the same
    episode (same task, seed and episode seed)."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    if a.shape != b.shape:
        raise ConfigError(f"paired returns need one value per episode on each side, got "
                          f"{a.size} and {b.size}")
    if a.size == 0:
        raise ConfigError("paired returns need at least one episode, got none")
    diff = a - b
    if diff.size == 1 or np.ptp(diff) == 0:
        # One pair has no spread to estimate; identical differences have no uncertainty left
        # (and scipy's t interval would divide by zero).
        spread = None if diff.size == 1 else 0.0
        ci = None if spread is None else (float(diff[0]), float(diff[0]))
    else:
        spread = float(stats.sem(diff))
        interval = stats.ttest_rel(a, b).confidence_interval(0.95)
        ci = (float(interval.low), float(interval.high))
    return PairedDifference(float(diff.mean()), spread, ci, int((diff > 0).sum()), diff.size)


def format_paired(paired: Mapping[str, Any]) -> str:
    """A :meth:`PairedDifference.as_dict` as the documents write it: ``+12.3 ± 4.5 (7/10)``."""
    spread = paired["standard_error"]
    spread_text = "" if spread is None else f" ± {spread:.1f}"
    return f"{paired['mean']:+.1f}{spread_text} ({paired['better']}/{paired['pairs']})"




def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y) / 2 for scores x [..., N] and y [..., M] along the last axis."""
    greater = (x[..., :, None] > y[..., None, :]).mean((-2, -1))
    ties = (x[..., :, None] == y[..., None, :]).mean((-2, -1))
    return greater + 0.5 * ties


def probability_of_improvement(x: Sequence[np.ndarray], y: Sequence[np.ndarray],
                               confidence: float = 0.95, resamples: int = 2000,
                               seed: int = 0) -> Interval:
    """The probability that a run of agent X scores above a run of agent Y on the same
    stratum (ties count half), averaged over strata (Agarwal et al., 2021): ``x`` and ``y``
    hold one 1-D array of scores per stratum (e.g. per task), in the same order. The interval
    is a stratified percentile bootstrap, resampling each agent's runs within each stratum."""
    xs, ys = _strata(x), _strata(y)
    if len(xs) != len(ys):
        raise ConfigError(f"x has {len(xs)} strata and y {len(ys)}; they must match")
    _check_confidence(confidence)
    estimate = float(np.mean([_improvement(a, b) for a, b in zip(xs, ys, strict=True)]))
    rng = np.random.default_rng(seed)
    draws = np.zeros(resamples)
    for a, b in zip(xs, ys, strict=True):
        ra = a[rng.integers(0, a.size, (resamples, a.size))]
        rb = b[rng.integers(0, b.size, (resamples, b.size))]
        draws += _improvement(ra, rb)
    draws /= len(xs)
    tail = (1 - confidence) / 2
    low, high = np.quantile(draws, [tail, 1 - tail])
    return Interval(estimate, float(low), float(high))


def performance_profile(strata: Sequence[np.ndarray], thresholds: np.ndarray) -> np.ndarray:
    """The share of runs scoring above each threshold, averaged over strata so that each
    stratum counts once (Agarwal et al., 2021, score distributions): ``strata`` one 1-D
    array of (normalised) scores each, ``thresholds`` [T] -> [T]."""
    groups = _strata(strata)
    tau = np.asarray(thresholds, np.float64).ravel()
    return np.mean([(g[None, :] > tau[:, None]).mean(1) for g in groups], axis=0)
