"""Shared fixtures: tiny synthetic datasets written by the library's own synth code."""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import logging
import os
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

# Rendering tests run headless: pick EGL before anything imports MuJoCo (twist_data does the
# same by default; this keeps the tests independent of that).
os.environ.setdefault("MUJOCO_GL", "egl")

from twist_data.synth import SynthConfig, write_synthetic_dataset


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``-n``), each worker and the commands its tests start use one
    thread: two workers of two threads on two cores stall each other at every barrier."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)


#: The modules whose tests run whole pipelines (tens of seconds each), run first so that, with
#: ``-n``, no worker is left with one of them while the others have finished.
PIPELINE_MODULES = ("test_report", "test_gpu_slot", "test_gpu_script", "test_collect",
                    "test_distil", "test_eval", "test_crash", "test_strip", "test_bad_input")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        name = item.path.stem
        return PIPELINE_MODULES.index(name) if name in PIPELINE_MODULES else len(PIPELINE_MODULES)

    items.sort(key=rank)


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


@pytest.fixture(scope="session")
def collected_tiny(tmp_path_factory: pytest.TempPathFactory, gl: None) -> Path:
    """A read-only D that `twist-collect --preset tiny` wrote (cartpole-balance, its teacher
    in collect/collect-000/), in ~15 s: the real pipeline's dataset at toy sizes."""
    from twist_pipeline.collect import collect, collect_preset

    out = tmp_path_factory.mktemp("collected") / "dataset"
    collect(out, collect_preset("tiny"))
    return out


@pytest.fixture(scope="session")
def gl() -> None:
    """Skip rendering tests, with the reason, only if no OpenGL context can be made at all."""
    from twist_sim.errors import RenderUnavailableError
    from twist_sim.randomisation import dr_preset
    from twist_sim.render import DRRenderer

    try:
        DRRenderer("cartpole-balance", dr_preset("none"), 8, 1).close()
    except RenderUnavailableError as exc:
        pytest.skip(f"no offscreen OpenGL on this machine: {exc}")


def board_events(run: Path) -> tuple[dict[str, list[tuple[int, float]]],
                                     dict[str, list[tuple[int, tuple[int, int]]]]]:
    """What a run's TensorBoard files hold, read back through TensorBoard's own reader:
    ({scalar tag: [(step, value)]}, {image tag: [(step, (height, width))]}). Skips the test
    when the tensorboard extra is not installed."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0}).Reload()
    tags = events.Tags()
    scalars = {t: [(e.step, e.value) for e in events.Scalars(t)] for t in tags["scalars"]}
    images = {t: [(e.step, (e.height, e.width)) for e in events.Images(t)]
              for t in tags["images"]}
    return scalars, images


def reference_python() -> Path:
    """The Python of the reference environment, where other projects' own readers live
    (scripts/reference_env.sh), or skip the test saying why it is missing."""
    venv = Path(os.environ.get("TWIST_REFERENCE_VENV",
                               Path(__file__).resolve().parents[1] / ".venv-ref"))
    if not (venv / ".twist-reference").exists():
        pytest.skip(f"no reference environment at {venv} (bash scripts/reference_env.sh "
                    "installs LeRobot's loader and rliable there)")
    return venv / "bin" / "python"


def mask_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean pixel masks."""
    return float((a & b).sum() / (a | b).sum())


def load_script(path: Path) -> ModuleType:
    """The Python script at ``path`` imported as a module (its ``main`` not run)."""
    spec = importlib.util.spec_from_file_location(f"script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: The console script each ``twist_cli`` module installs (pyproject's ``[project.scripts]``).
ENTRY_POINTS = {"data": "main"}


def _show_warning(stream: io.StringIO) -> Callable[..., None]:
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        stream.write(warnings.formatwarning(message, category, filename, lineno, line))

    return show


def _run_in_process(main: Callable[[], None], argv: list[str]
                    ) -> subprocess.CompletedProcess[str]:
    """``main()`` with ``argv`` as ``sys.argv``: its exit code, stdout and stderr."""
    stdout, stderr, code = io.StringIO(), io.StringIO(), 0
    saved = sys.argv
    sys.argv = argv
    try:
        with (contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr),
              warnings.catch_warnings()):
            # The filters a fresh interpreter starts with, printing to the captured stderr
            # (pytest's own capture would otherwise swallow what a user sees).
            warnings.resetwarnings()
            warnings.simplefilter("default")
            for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning,
                             ResourceWarning):
                warnings.simplefilter("ignore", category)
            warnings.showwarning = _show_warning(stderr)
            main()
    except SystemExit as exc:  # as the interpreter exits: None is 0, a message goes to stderr
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
        if not isinstance(exc.code, int | None):
            stderr.write(f"{exc.code}\n")
    finally:
        sys.argv = saved
    return subprocess.CompletedProcess(argv, code, stdout.getvalue(), stderr.getvalue())


def run_command(module: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``twist-<module> ARGS`` run in this process through the entry point its console script
    calls, as ``python -m twist_cli.<module> ARGS`` runs it but without starting an
    interpreter (~3 s with torch): its exit code, stdout and stderr, log lines included (the
    entry point's log level, the format :func:`twist_cli.common.run_app` sets). An error the
    boundary does not turn into one line propagates, failing the test as a traceback would."""
    entry = getattr(importlib.import_module(f"twist_cli.{module}"),
                    ENTRY_POINTS.get(module, "entry"))
    # A subprocess's basicConfig handler writes log lines to its stderr; pytest's own handler
    # on the root logger keeps basicConfig from adding one here, so add it for the call.
    lines = io.StringIO()
    handler = logging.StreamHandler(lines)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    from twist_cli.common import LIBRARY_PACKAGES

    loggers = [logging.getLogger(name) for name in LIBRARY_PACKAGES]
    levels = [logger.level for logger in loggers]
    logging.getLogger().addHandler(handler)
    try:
        result = _run_in_process(entry, [f"twist-{module}", *args])
    finally:
        logging.getLogger().removeHandler(handler)
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)
    result.stderr = lines.getvalue() + result.stderr
    return result


def run_script_main(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """The Python script at ``path`` run in this process with ``args`` as its command line
    (its ``main()``, as ``python PATH ARGS`` runs it): its exit code, stdout and stderr."""
    return _run_in_process(load_script(path).main, [str(path), *args])


def run_script(script: str, out: Path, **settings: str) -> subprocess.CompletedProcess[str]:
    """``bash scripts/<script> <out>`` with ``settings`` in its environment, in the virtual
    environment that runs these tests (so the script installs nothing)."""
    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, **settings, "TWIST_VENV": sys.prefix}
    return subprocess.run(["bash", str(root / "scripts" / script), str(out)], env=env,
                          capture_output=True, text=True, timeout=900)

