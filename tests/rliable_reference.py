"""rliable's aggregate statistics of the scores in a JSON file, in the reference environment
(scripts/reference_env.sh), for tests/test_eval.py to compare with twist_pipeline.statistics:

    python tests/rliable_reference.py IN.json OUT.json

IN holds {"x": [[run scores of task 0], ...], "y": [...], "tau": [...], "reps": R}: two agents'
runs (rows: runs, as rliable lays them out after transposing) on the same tasks.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from rliable import library, metrics


def main(source: str, out: str) -> None:
    with open(source) as f:
        given = json.load(f)
    x = np.array(given["x"], np.float64).T  # rliable: [runs, tasks]
    y = np.array(given["y"], np.float64).T
    reps = int(given["reps"])
    np.random.seed(0)  # rliable's bootstraps draw from NumPy's global generator
    iqm, iqm_ci = library.get_interval_estimates(
        {"x": x}, lambda s: np.array([metrics.aggregate_iqm(s)]), reps=reps)
    improvement, improvement_ci = library.get_interval_estimates(
        {"xy": [x, y]}, lambda a, b: np.array([metrics.probability_of_improvement(a, b)]),
        reps=reps)
    profile = library.score_distributions(x, np.array(given["tau"]))
    result = {"iqm": float(iqm["x"][0]), "iqm_ci": iqm_ci["x"][:, 0].tolist(),
              "improvement": float(improvement["xy"][0]),
              "improvement_ci": improvement_ci["xy"][:, 0].tolist(),
              "profile": np.asarray(profile).tolist()}
    with open(out, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main(*sys.argv[1:3])
