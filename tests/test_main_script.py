"""scripts/main.sh, the main job, at test sizes: every stage runs and its seconds, with the
machine's eager teacher update, reach timings.json; a second run resumes without redoing the
collection or the distillation."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import run_script

STAGES = ("setup", "machine_speed", "collect", "check_dataset", "distil", "eval")


@pytest.mark.slow
@pytest.mark.usefixtures("gl")
def test_the_main_job_times_every_stage_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "demo"

    def run() -> subprocess.CompletedProcess[str]:
        return run_script("main.sh", out, PRESET="tiny")

    first = run()
    assert first.returncode == 0, first.stderr[-2000:]
    timings = json.loads((out / "timings.json").read_text())
    assert (timings["task"], timings["preset"], timings["seed"]) == ("cartpole-balance", "tiny", 0)
    assert [key for key in timings if key.endswith("_s") and key != "total_s"
            and key != "eager_teacher_update_s"] == [f"{stage}_s" for stage in STAGES]
    assert timings["total_s"] == sum(timings[f"{stage}_s"] for stage in STAGES)
    speed = json.loads((out / "machine-speed.json").read_text())
    assert timings["eager_teacher_update_s"] == speed["eager_s"] > 0
    assert sorted(pd.read_csv(out / "eval" / "episodes.csv")["agent"].unique()) \
        == ["oracle", "student", "zero"]
    for made in ("dataset.h5", "episode-last.mp4", "contact-sheet.png", "latent-agreement.png"):
        assert (out / made).stat().st_size > 0, made
    collected = (out / "dataset" / "collect" / "collect-000" / "metrics.csv").read_text()
    distilled = (out / "student" / "summary.json").read_text()

    second = run()
    assert second.returncode == 0, second.stderr[-2000:]
    assert (out / "dataset" / "collect" / "collect-000" / "metrics.csv").read_text() == collected
    assert json.loads((out / "student" / "summary.json").read_text())["updates"] \
        == json.loads(distilled)["updates"]
