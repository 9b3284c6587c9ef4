"""The episode rules every reader applies to what it serves (datasets.md, §3 "Episode rules").

A checksum proves that bytes are the ones written, not that what was written is an episode:
an array rewritten through zarr keeps valid checksums. These rules are what D's episodes must
satisfy for a window never to span a reset or serve values no collector wrote; ``verify``,
the window sampler (when it indexes D) and the exports apply them, from the columns they
read anyway, so they cost a few vector operations over D's low-dimensional arrays.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

#: How far a stored episode return may differ from the sum of its rewards (relative and
#: absolute): float64 sums of float32 rewards, summed in another order.
RETURN_TOLERANCE = 1e-6
#: How far an action may lie outside [-1, 1]: float32 rounding of a clipped action.
ACTION_TOLERANCE = 1e-6


def rule_problems(starts: np.ndarray, ends: np.ndarray, columns: Mapping[str, np.ndarray],
                  returns: np.ndarray | None = None) -> list[tuple[int, str]]:
    """(episode, the rule it breaks) for every episode of ``columns`` (per-step arrays over
    the episodes ``[starts[e], ends[e])``, concatenated) that breaks one, first rule first:
    ``is_first`` exactly at each start, ``is_last`` exactly at each last step, finite
    ``state``, ``action`` finite and within [-1, 1], and ``returns[e]`` (the stored
    ``episode_return``) equal to the sum of ``reward`` over the episode. Only the columns
    given are checked."""
    found: dict[int, str] = {}
    n = int(ends[-1]) if len(ends) else 0
    if n == 0:
        return []

    def episode_of(step: int) -> int:
        return int(np.searchsorted(ends, step, side="right"))

    def flags(name: str, expected: np.ndarray, where: str) -> None:
        if name not in columns:
            return
        flag = np.asarray(columns[name][:n], bool)
        should = np.zeros(n, bool)
        should[expected] = True
        for step in np.flatnonzero(flag != should)[:64].tolist():
            e = episode_of(step)
            local = step - int(starts[e])
            state = "set" if flag[step] else "not set"
            found.setdefault(e, f"{name} is {state} at its step {local} ({where})")

    flags("is_first", np.asarray(starts, np.int64), "only an episode's first step has it")
    flags("is_last", np.asarray(ends, np.int64) - 1, "only an episode's last step has it")
    for name in ("state", "action"):
        if name not in columns:
            continue
        values = np.asarray(columns[name][:n]).reshape(n, -1)
        bad = ~np.isfinite(values).all(1)
        if name == "action":
            bad |= (np.abs(np.nan_to_num(values)) > 1 + ACTION_TOLERANCE).any(1)
        for step in np.flatnonzero(bad)[:64].tolist():
            e = episode_of(step)
            what = "is not finite" if name == "state" else "is not finite or outside [-1, 1]"
            found.setdefault(e, f"{name} {what} at its step {step - int(starts[e])}")
    if returns is not None and "reward" in columns and len(starts):
        rewards = np.asarray(columns["reward"][:n], np.float64)
        sums = np.add.reduceat(rewards, np.asarray(starts, np.int64))
        stored = np.asarray(returns, np.float64)
        off = ~np.isclose(sums, stored, rtol=RETURN_TOLERANCE, atol=RETURN_TOLERANCE)
        for e in np.flatnonzero(off).tolist():
            found.setdefault(e, f"stored return {stored[e]:.6g} differs from the sum of rewards "
                                f"{sums[e]:.6g}")
    return sorted(found.items())
