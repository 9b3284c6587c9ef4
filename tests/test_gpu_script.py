"""scripts/gpu.sh, the one-lease paper-scale run, at test sizes on the CPU: every stage runs,
records its seconds, and a second run of the same command resumes without redoing work."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import run_script


@pytest.mark.usefixtures("gl")
def test_the_lease_script_runs_every_stage_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "lease"

    def run() -> subprocess.CompletedProcess[str]:
        return run_script("gpu.sh", out, PRESET="tiny", DEVICE="cpu", STUDENT_STEPS="4")

    first = run()
    assert first.returncode == 0, first.stderr[-2000:]
    timings = json.loads((out / "timings.json").read_text())
    assert (timings["preset"], timings["device"]) == ("tiny", "cpu")
    assert all(isinstance(timings[f"{s}_s"], int) for s in ("collect", "distil", "eval"))
    episodes = pd.read_csv(out / "eval" / "episodes.csv")
    assert sorted(episodes["agent"].unique()) == ["oracle", "student", "zero"]
    assert len(episodes) == 6
    assert json.loads((out / "student" / "summary.json").read_text())["updates"] == 4
    collected = (out / "dataset" / "collect" / "collect-000" / "metrics.csv").read_text()

    second = run()  # a later lease: every stage finds its work done
    assert second.returncode == 0, second.stderr[-2000:]
    assert (out / "dataset" / "collect" / "collect-000" / "metrics.csv").read_text() == collected
    assert len(pd.read_csv(out / "eval" / "episodes.csv")) == 6
    assert json.loads((out / "student" / "summary.json").read_text())["updates"] == 4
