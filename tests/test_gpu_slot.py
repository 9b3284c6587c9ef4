"""The GPU-slot kit at test sizes on the CPU: a carry folder built by scripts/gpu_carry.py from
a collected D, then scripts/gpu_slot.sh rebuilds D from it, distils, evaluates the snapshots
and packs its results; a second run resumes without redoing work."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import run_script_main

ROOT = Path(__file__).resolve().parent.parent


def carry(dataset: Path, out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``python scripts/gpu_carry.py DATASET OUT ARGS``, in this process."""
    return run_script_main(ROOT / "scripts" / "gpu_carry.py", str(dataset), str(out), *args)


@pytest.fixture(scope="module")
def carried(collected_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A carry folder built by the kit from the tiny collected D (read-only: the slots only
    read it)."""
    out = tmp_path_factory.mktemp("carried") / "carry"
    built = carry(collected_tiny, out)
    assert built.returncode == 0, built.stderr
    return out


def test_the_slot_runs_from_a_carry_and_resumes(collected_tiny: Path, carried: Path,
                                                tmp_path: Path) -> None:
    assert sorted(p.name for p in carried.iterdir()) == ["dataset", "teacher.pt"]
    teacher = (collected_tiny / "collect" / "collect-000" / "teacher.pt").stat().st_size
    assert (carried / "teacher.pt").stat().st_size < teacher  # no optimiser states

    out = tmp_path / "slot"

    # One rebuild worker: a rebuild in several processes is tested in tests/test_strip.py.
    def slot() -> subprocess.CompletedProcess[str]:
        result = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_slot.sh"),
                                 str(carried), str(out)],
                                env={**os.environ,
                                     "TWIST_VENV": sys.prefix, "PRESET": "tiny",
                                     "DEVICE": "cpu", "STEPS": "4", "SNAPSHOT_EVERY": "2",
                                     "EVAL_EPISODES": "2", "WORKERS": "1"},
                                capture_output=True, text=True, timeout=900)
        assert result.returncode == 0, result.stderr[-3000:]
        return result

    slot()
    results = sorted(p.name for p in (out / "results").iterdir())
    assert results == ["curve.csv", "curve.png", "episodes.csv", "heldout.csv", "metrics.csv",
                       "slot.json"]
    record = json.loads((out / "results" / "slot.json").read_text())
    rebuilt = record["rebuild"]
    assert rebuilt["identical"] == rebuilt["episodes"] > 0  # the same machine: the same GL
    curve = pd.read_csv(out / "results" / "curve.csv")
    assert list(curve["agent"]) == ["oracle", "zero", "u00000002", "u00000004"]
    timings = record["timings"]
    assert timings["updates"] == record["distil"]["updates"] == 4
    assert {"rebuild_s", "distil_s", "curve_s"} <= set(timings)

    slot()  # a later slot: everything found done
    assert json.loads((out / "distil-summary.json").read_text())["updates"] == 4
    assert len(pd.read_csv(out / "curve" / "episodes.csv")) == 8


def test_a_readout_slot_trains_on_frames_alone_and_evaluates_each_factor(
        carried: Path, tmp_path: Path) -> None:
    out = tmp_path / "slot"
    result = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_slot.sh"), str(carried),
                             str(out)],
                            env={**os.environ, "TWIST_VENV": sys.prefix, "PRESET": "tiny",
                                 "DEVICE": "cpu", "RECIPE": "readout", "EVAL_EPISODES": "2",
                                 "WORKERS": "1", "FACTORS": "heldout,heldout-camera"},
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    results = sorted(p.name for p in (out / "results").iterdir())
    assert results == ["curve.csv", "curve.png", "episodes.csv", "factors.csv",
                       "frame-metrics.csv", "heldout.csv", "slot.json"]
    from twist_models.distillation import distil_preset

    frames = pd.read_csv(out / "results" / "frame-metrics.csv")
    assert frames["frame_updates"].iloc[-1] == distil_preset("tiny", "readout").frame_steps
    assert json.loads((out / "results" / "slot.json").read_text())["distil"]["updates"] == 0
    factors = pd.read_csv(out / "results" / "factors.csv")
    assert list(factors["dr"]) == ["heldout", "heldout-camera"]
    assert set(factors["agent"]) == {"student"} and (factors["episodes"] == 2).all()


def test_a_carry_over_the_limit_is_refused_and_removed(collected_tiny: Path,
                                                       tmp_path: Path) -> None:
    result = carry(collected_tiny, tmp_path / "carry", "--limit-mib", "0.5")
    assert result.returncode == 2 and "over the limit of 0.5 MiB" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "carry").exists()
    result = carry(tmp_path / "nowhere", tmp_path / "carry")
    assert result.returncode == 2 and "does not exist" in result.stderr
    assert not (tmp_path / "carry").exists()
    # A teacher of another task.
    import torch

    from twist_models.config import teacher_preset
    from twist_models.teacher import Teacher, save_teacher

    other = save_teacher(tmp_path / "cup.pt", Teacher(teacher_preset("tiny", 8, 2)),
                         extra={"collect": {"task": "cup-catch"}})
    torch.manual_seed(0)
    result = carry(collected_tiny, tmp_path / "carry", "--teacher", str(other))
    assert result.returncode == 2 and "learned 'cup-catch'" in result.stderr
    assert not (tmp_path / "carry").exists()


def test_the_gl_loaders_travel_in_the_carry_and_count(collected_tiny: Path,
                                                      tmp_path: Path) -> None:
    loaders = tmp_path / "gl"
    loaders.mkdir()
    result = carry(collected_tiny, tmp_path / "carry", "--gl", str(loaders))
    assert result.returncode == 2 and "holds no package (*.deb)" in result.stderr
    assert not (tmp_path / "carry").exists()
    package = bytes(range(256)) * 4096  # 1 MiB standing in for libegl1's package
    (loaders / "libegl1_1.6.0-1_amd64.deb").write_bytes(package)
    (loaders / "notes.txt").write_text("not a package")
    result = carry(collected_tiny, tmp_path / "carry", "--gl", str(loaders))
    assert result.returncode == 0, result.stderr
    assert [p.name for p in (tmp_path / "carry" / "gl").iterdir()] == ["libegl1_1.6.0-1_amd64.deb"]
    assert (tmp_path / "carry" / "gl" / "libegl1_1.6.0-1_amd64.deb").read_bytes() == package
    sizes = dict(part.split("=") for part in result.stdout.split())
    assert sizes["gl"] == "1.00MiB"
    parts = ("tree", "dataset", "teacher", "wheels", "gl")
    assert abs(sum(float(sizes[k][:-3]) for k in parts) - float(sizes["total"][:-3])) < 0.03
