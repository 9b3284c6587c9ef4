"""twist-distil: the Eq. 3/4 losses against independent computations, the frozen teacher, a
short run that clearly improves latent agreement, resume after SIGKILL, the agent bundle,
bad inputs, and that distillation never imports a simulator."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
from torch.utils.data import DataLoader

from tests.conftest import board_events, run_command
from twist_cli.common import parse_settings
from twist_data.errors import ConfigError
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.agent import Agent
from twist_models.config import (
    field_types,
    from_json,
    replace_fields,
    student_preset,
    teacher_preset,
    to_json,
)
from twist_models.distillation import DistilConfig, Distillation, distil_preset, latent_agreement
from twist_models.losses import distillation_loss, imagined_distillation_loss
from twist_models.perception import stack_frames, step_frames
from twist_models.student import Student, copy_teacher_dynamics
from twist_models.teacher import Teacher, load_teacher, save_teacher
from twist_pipeline.distil import DistilError, distil, load_student, stored_config
from twist_pipeline.runlog import append_csv, recorded_config, resume_conflicts

# Images are deterministic drawings of the state (plus randomised backgrounds), so the
# image -> teacher-latent mapping is learnable.
DATA = SynthConfig(episodes=8, steps=30, views=2, image_size=64, seed=5)


@pytest.fixture(scope="module")
def distil_inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(dataset, teacher checkpoint): synthetic data and a small random-weights teacher."""
    root = tmp_path_factory.mktemp("distil")
    dataset = write_synthetic_dataset(root / "ds", DATA)
    torch.manual_seed(1)
    teacher = Teacher(teacher_preset("tiny", 5, 1))
    return dataset, save_teacher(root / "teacher.pt", teacher)


def _np_kl(p_logits: np.ndarray, q_logits: np.ndarray) -> np.ndarray:
    """KL(p || q) of independent categoricals [..., S, C] summed over S, in float64."""
    def log_softmax(x: np.ndarray) -> np.ndarray:
        x = x - x.max(-1, keepdims=True)
        return x - np.log(np.exp(x).sum(-1, keepdims=True))

    lp, lq = log_softmax(p_logits.astype(np.float64)), log_softmax(q_logits.astype(np.float64))
    return (np.exp(lp) * (lp - lq)).sum((-2, -1))


def test_losses_match_an_independent_computation() -> None:
    g = torch.Generator().manual_seed(0)
    b, t, d, s, c = 3, 7, 6, 4, 5
    student = {"deter": torch.randn(b, t, d, generator=g),
               "logits": torch.randn(b, t, s, c, generator=g)}
    teacher = {"deter": torch.randn(b, t, d, generator=g),
               "logits": torch.randn(b, t, s, c, generator=g)}
    s_prior, t_prior = torch.randn(b, t, s, c, generator=g), torch.randn(b, t, s, c, generator=g)
    terms = distillation_loss(student, s_prior, teacher, t_prior)
    sd, td = student["deter"].numpy(), teacher["deter"].numpy()
    expected_h = np.mean([np.sum((td[i, j] - sd[i, j]) ** 2) for i in range(b) for j in range(t)])
    assert float(terms["h"]) == pytest.approx(expected_h, rel=1e-5)
    assert float(terms["prior_kl"]) == pytest.approx(
        _np_kl(s_prior.numpy(), t_prior.numpy()).mean(), rel=1e-5)
    assert float(terms["post_kl"]) == pytest.approx(
        _np_kl(student["logits"].numpy(), teacher["logits"].numpy()).mean(), rel=1e-5)
    # Eq. 4 leaves out the start state (index 0), which Eq. 3 already matches.
    imagined = imagined_distillation_loss(student, teacher)
    expected = np.mean(((td[:, 1:] - sd[:, 1:]) ** 2).sum(-1))
    assert float(imagined["h"]) == pytest.approx(expected, rel=1e-5)
    assert float(imagined["prior_kl"]) == pytest.approx(
        _np_kl(student["logits"][:, 1:].numpy(), teacher["logits"][:, 1:].numpy()).mean(),
        rel=1e-5)
    # Identical latents cost nothing.
    same = distillation_loss(teacher, t_prior, teacher, t_prior)
    assert all(float(v) == pytest.approx(0.0, abs=1e-6) for v in same.values())


def _objective(imagined: bool = True, **weights: float
               ) -> tuple[Distillation, dict[str, torch.Tensor]]:
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset("tiny", 5, 1))
    student = Student(student_preset("tiny", teacher.config, image_size=64))
    config = distil_preset("tiny", imagined=imagined, **weights)
    g = torch.Generator().manual_seed(0)
    is_first = torch.zeros(2, 8, dtype=torch.bool)
    is_first[:, 0] = True
    batch = {"image": torch.randint(0, 256, (2, 8, 64, 64, 3), dtype=torch.uint8, generator=g),
             "state": torch.randn(2, 8, 5, generator=g), "action": torch.rand(2, 8, 1, generator=g),
             "is_first": is_first}
    return Distillation(student, teacher, config), batch


def test_no_gradient_reaches_the_teacher_and_eq4_is_optional() -> None:
    objective, batch = _objective()
    loss, terms = objective(batch)
    loss.backward()
    assert {"h", "prior_kl", "post_kl", "imagined_h", "imagined_prior_kl"} == set(terms)
    assert all(p.grad is None for p in objective.teacher.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0
               for p in objective.student.parameters())
    # The teacher is no submodule of the objective: an optimiser (or DDP) never sees it.
    teacher_ids = {id(p) for p in objective.teacher.parameters()}
    assert not teacher_ids & {id(p) for p in objective.parameters()}

    plain, batch = _objective(imagined=False)
    loss, terms = plain(batch)
    assert set(terms) == {"h", "prior_kl", "post_kl"}
    total = terms["h"] + terms["prior_kl"] + terms["post_kl"]
    assert float(loss.detach()) == pytest.approx(float(total.detach()))


def test_action_matching_compares_the_actors_modes_and_trains_only_the_student() -> None:
    objective, batch = _objective(imagined=False, h_weight=0.0, prior_weight=0.0,
                                  post_weight=0.0, action_weight=2.0)
    torch.manual_seed(1)  # the sampling draws of the filter
    loss, terms = objective(batch)
    torch.manual_seed(1)
    s_post, t_post, _, _ = objective.filter(batch)
    actor, teacher = objective.teacher.actor_critic.actor, objective.teacher
    with torch.no_grad():
        a_student = actor(objective.student.rssm.feature(s_post)).mode
        a_teacher = actor(teacher.world_model.rssm.feature(t_post)).mode
    # An independent computation of the term: mean over [B, L] of the summed squares.
    by_hand = float(((a_student - a_teacher) ** 2).sum(-1).mean())
    assert by_hand > 0
    assert float(terms["action"].detach()) == pytest.approx(by_hand, rel=1e-5)
    assert float(loss.detach()) == pytest.approx(2.0 * by_hand, rel=1e-5)
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0
               for p in objective.student.perception.encoder.parameters())
    assert all(p.grad is None for p in teacher.parameters())


def test_shared_draws_give_equal_samples_to_equal_distributions() -> None:
    """A student that is an exact copy of the teacher's RSSM, fed the teacher's embeddings,
    reproduces the teacher's latents exactly with shared draws (and only with them)."""
    objective, batch = _objective()
    teacher = objective.teacher
    rssm = teacher.world_model.rssm
    embed = teacher.world_model.embed(batch["state"])
    draws = torch.rand(2, 8, rssm.config.stoch, 1)
    with torch.no_grad():
        a, _ = rssm.observe(embed, batch["action"], batch["is_first"], uniform=draws)
        b, _ = rssm.observe(embed, batch["action"], batch["is_first"], uniform=draws)
        c, _ = rssm.observe(embed, batch["action"], batch["is_first"])
    assert torch.equal(a["deter"], b["deter"]) and torch.equal(a["stoch"], b["stoch"])
    assert not torch.equal(a["stoch"], c["stoch"])


def test_copied_dynamics_imagine_like_the_teacher() -> None:
    """After copy_teacher_dynamics the student's prior is the teacher's transition function;
    its posterior differs from the teacher's only through the embedding it reads."""
    objective, batch = _objective()
    teacher, student = objective.teacher.world_model.rssm, objective.student
    start = {k: v[:, 3] for k, v in teacher.observe(
        objective.teacher.world_model.embed(batch["state"]), batch["action"],
        batch["is_first"])[0].items()}
    actions = torch.rand(2, 5, 1) * 2 - 1
    draws = torch.rand(2, 5, teacher.config.stoch, 1)
    scratch = latent_agreement(student, objective.teacher, batch, objective.config)
    with torch.no_grad():
        expected, _ = teacher.imagine(start, 5, actions=actions, uniform=draws)
        before, _ = student.rssm.imagine(start, 5, actions=actions, uniform=draws)
        copy_teacher_dynamics(student, teacher)
        after, _ = student.rssm.imagine(start, 5, actions=actions, uniform=draws)
        # With no embedding both posteriors see only h: the copied columns make them equal.
        t_post = teacher.post_step(start, actions[:, 0], torch.zeros(2, teacher.obs_out[0]
                                   .in_features - teacher.config.deter), uniform=draws[:, 0])
        s_post = student.rssm.post_step(start, actions[:, 0],
                                        torch.zeros(2, student.perception.encoder.out_dim),
                                        uniform=draws[:, 0])
    assert not torch.allclose(before["deter"], expected["deter"], atol=1e-3)
    copied = latent_agreement(student, objective.teacher, batch, objective.config)
    assert copied["h_mse"] < 0.5 * scratch["h_mse"]
    assert copied["imagined_h_mse"] < 0.5 * scratch["imagined_h_mse"]
    for key in ("deter", "logits", "stoch"):
        torch.testing.assert_close(after[key], expected[key])
        torch.testing.assert_close(s_post[key], t_post[key])
    # The copied weights still train (they are copies, not the teacher's tensors).
    assert all(p.requires_grad for p in student.rssm.parameters())
    assert not {id(p) for p in student.parameters()} & {id(p) for p in teacher.parameters()}


def test_short_run_improves_agreement_and_writes_an_agent(distil_inputs, tmp_path) -> None:
    dataset, teacher = distil_inputs
    # From scratch, as the paper: copied dynamics would start it close to the target.
    config = distil_preset("tiny", steps=40, eval_every=20, checkpoint_every=20,
                           snapshot_every=20, copy_dynamics=False)
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher)
    first, last = summary.heldout_first, summary.heldout_last
    assert summary.updates == 40
    assert last["h_mse"] < 0.7 * first["h_mse"]
    assert last["imagined_h_mse"] < 0.7 * first["imagined_h_mse"]
    assert first["h_explained"] < last["h_explained"] <= 1.0
    heldout = pd.read_csv(tmp_path / "run" / "heldout.csv")
    assert list(heldout["updates"]) == [0, 20, 40]
    metrics = pd.read_csv(tmp_path / "run" / "metrics.csv")
    assert list(metrics["updates"]) == [20, 40] and (metrics["data_wait_share"] < 1).all()
    assert (tmp_path / "run" / "latent-agreement.png").stat().st_size > 0
    # The TensorBoard record (the tensorboard extra) holds what the CSV files hold, and the plot.
    scalars, images = board_events(tmp_path / "run")
    assert [s for s, _ in scalars["heldout/h_mse"]] == [0, 20, 40]
    assert [v for _, v in scalars["heldout/h_mse"]] == pytest.approx(list(heldout["h_mse"]))
    assert [v for _, v in scalars["train/loss"]] == pytest.approx(list(metrics["loss"]))
    plot = cv2.imread(str(tmp_path / "run" / "latent-agreement.png"))
    # Drawn at every tenth evaluation and the last, not at each (nor at the first: one point).
    assert [step for step, _ in images["heldout/latent-agreement"]] == [40]
    assert images["heldout/latent-agreement"][-1][1] == plot.shape[:2]

    # The teacher file is untouched, and the bundle acts like student filter + teacher actor.
    student, extra = load_student(summary.student)
    assert extra["teacher"] == str(teacher)
    agent = Agent.load(summary.agent)
    assert agent.info["task"] == "synthetic-cartpole"
    frames = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    torch.manual_seed(3)
    state, actions = None, []
    for frame in frames:
        action, state = agent.act(frame, state)
        actions.append(action)
    assert np.asarray(actions).shape == (3, 1) and np.all(np.abs(actions) <= 1)
    # The same chain from the separately saved student and the teacher's own actor.
    actor = load_teacher(teacher)[0].actor_critic.actor
    torch.manual_seed(3)
    rssm, latent, previous = student.rssm, student.rssm.initial(1), torch.zeros(1, 1)
    with torch.no_grad():
        for i, frame in enumerate(frames):
            embed = student.perception.encoder(torch.as_tensor(frame)[None])
            latent = rssm.post_step(latent, previous, embed, torch.tensor([i == 0]))
            previous = actor(rssm.feature(latent)).mode.clamp(-1, 1)
            np.testing.assert_allclose(actions[i], previous[0].numpy(), atol=1e-6)

    # Each snapshot comes with a deployable bundle of that snapshot's student.
    for updates in (20, 40):
        snapshot = load_student(tmp_path / "run" / f"student-{updates:08d}.pt")[0].state_dict()
        bundled = Agent.load(tmp_path / "run" / f"agent-{updates:08d}.pt")
        assert bundled.info["student_updates"] == updates
        weights = bundled.student.state_dict()
        assert weights.keys() == snapshot.keys()
        assert all(torch.equal(weights[k], snapshot[k]) for k in snapshot)
    early = Agent.load(tmp_path / "run" / "agent-00000020.pt").student.state_dict()
    assert not all(torch.equal(early[k], student.state_dict()[k]) for k in early)


def test_heldout_metrics_are_fixed_for_a_fixed_student(distil_inputs) -> None:
    dataset, teacher_path = distil_inputs
    from twist_data.sampler import WindowSampler

    teacher, _ = load_teacher(teacher_path)
    config = distil_preset("tiny")
    student = Student(student_preset("tiny", teacher.config, image_size=64))
    batch = {k: torch.as_tensor(v) for k, v in
             WindowSampler(dataset, config.sampler("heldout", 0)).batch().items()}
    once = latent_agreement(student, teacher, batch, config, 7)
    torch.rand(5)  # the global stream moves on; the metric must not
    again = latent_agreement(student, teacher, batch, config, 7)
    assert once == again and once["h_mse"] > 0
    assert latent_agreement(student, teacher, batch, config, 8) != once


def _fresh_cli(*args: str) -> subprocess.CompletedProcess:
    """``twist-distil ARGS`` through a fresh interpreter, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "twist_cli.distil", *args], text=True,
                          capture_output=True, timeout=300)


def _rows(csv: Path) -> int:
    """Rows a CSV that another process is writing holds so far (0 before its header lands)."""
    try:
        return len(pd.read_csv(csv))
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return 0


def test_a_time_limit_stops_with_a_deployable_student_and_the_run_resumes(
        distil_inputs, tmp_path, monkeypatch) -> None:
    """The clock is the module's own, advanced one minute per update: the limit of 3.5 minutes
    passes during the fourth update, whatever the machine's speed."""
    import twist_pipeline.distil as stage

    dataset, teacher = distil_inputs
    config = distil_preset("tiny", steps=10, eval_every=5, checkpoint_every=5, snapshot_every=5)
    clock = {"now": 0.0}

    class Clock:
        @staticmethod
        def perf_counter() -> float:
            return clock["now"]

    monkeypatch.setattr(stage, "time", Clock)
    real_step = torch.optim.AdamW.step

    def step(self, *args, **kwargs):
        clock["now"] += 60.0
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", step)
    run = tmp_path / "run"
    summary = distil(dataset, run, config, teacher=teacher, time_limit=210.0)
    assert summary.stopped == "time limit" and summary.updates == 4
    assert json.loads((run / "summary.json").read_text())["stopped"] == "time limit"
    assert list(pd.read_csv(run / "metrics.csv")["updates"]) == [4]  # the last updates logged
    assert list(pd.read_csv(run / "heldout.csv")["updates"]) == [0, 4]
    assert Agent.load(run / "agent.pt").info["student_updates"] == 4
    # Where it stopped is a snapshot of the learning curve, beside the regular ones.
    assert Agent.load(run / "agent-00000004.pt").info["student_updates"] == 4
    assert torch.load(run / "latest.pt", weights_only=True)["counters"]["updates"] == 4
    resumed = distil(dataset, run, config, teacher=teacher, resume=True)
    assert resumed.stopped == "done" and resumed.updates == 10
    assert list(pd.read_csv(run / "metrics.csv")["updates"]) == [4, 5, 10]
    # Resumed once more with nothing to do: its summary as written, D never opened.
    written = (run / "summary.json").read_text()
    monkeypatch.setattr(stage, "_open_inputs", None)
    assert distil(dataset, run, config, teacher=teacher, resume=True) == resumed
    assert (run / "summary.json").read_text() == written
    with pytest.raises(TypeError):  # more updates: the run goes on
        distil(dataset, run, dataclasses.replace(config, steps=12), teacher=teacher, resume=True)
    with pytest.raises(DistilError, match="time limit must be a positive number of seconds, "
                                          "got 0"):
        distil(dataset, tmp_path / "never", config, teacher=teacher, time_limit=0)
    assert not (tmp_path / "never").exists()


def test_cli_resumes_after_sigkill_and_continues_the_count(distil_inputs, tmp_path) -> None:
    dataset, teacher = distil_inputs
    run = tmp_path / "run"
    args = ["--dataset", str(dataset), "--teacher", str(teacher), "--out", str(run),
            "--preset", "tiny", "--quiet"]
    process = subprocess.Popen([sys.executable, "-m", "twist_cli.distil", *args,
                                "--steps", "100000"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    try:
        while _rows(run / "metrics.csv") < 2:
            assert time.monotonic() < deadline and process.poll() is None
            time.sleep(0.2)
    finally:  # also when the wait fails: a distiller left running slows everything after it
        process.send_signal(signal.SIGKILL)
        process.wait()
    done = load_student(run / "latest.pt")[0]
    killed_at = int(torch.load(run / "latest.pt", weights_only=True)["counters"]["updates"])
    assert killed_at >= 2 and done is not None

    result = run_command("distil", *args, "--resume", "--steps", str(killed_at + 4))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["updates"] == killed_at + 4
    metrics = pd.read_csv(run / "metrics.csv")
    assert metrics["updates"].is_monotonic_increasing and metrics["updates"].iloc[-1] == killed_at + 4
    # Resuming with another config is refused, naming the field.
    refused = run_command("distil", *args, "--resume", "--length", "6")
    assert refused.returncode == 2 and "length was 8, now 6" in refused.stderr


def test_a_run_starts_from_a_recorded_config_with_overrides(distil_inputs, tmp_path) -> None:
    dataset, teacher = distil_inputs
    base = ["--dataset", str(dataset), "--teacher", str(teacher), "--quiet"]
    first = tmp_path / "first"
    done = run_command("distil", *base, "--out", str(first), "--preset", "tiny", "--recipe",
                       "dense", "--steps", "2")
    assert done.returncode == 0, done.stderr
    recorded = stored_config(first)
    second = tmp_path / "second"
    result = run_command("distil", *base, "--out", str(second), "--config",
                         str(first / "config.json"), "--steps", "3", "--set", "optim.grad_clip=7",
                         "--set", "lr=0.001")
    assert result.returncode == 0, result.stderr
    # Every recorded field carries over (the dense recipe's included); the nested override
    # changes one field of the optimiser's config and keeps the others.
    expected = dataclasses.replace(recorded, steps=3, lr=1e-3, optim=dataclasses.replace(
        recorded.optim, grad_clip=7.0))
    assert stored_config(second) == expected and expected.recipe == "dense"
    assert json.loads(result.stdout)["updates"] == 3

    other_kind = tmp_path / "collect.json"
    other_kind.write_text(json.dumps({"collect": {"task": "cartpole-balance"}}))
    refusals = {
        "is a collect run's config; this command starts from a distil run's":
            ["--config", str(other_kind)],
        "--config gives the preset and the recipe": ["--config", str(first), "--recipe",
                                                     "paper"],
    }
    for i, (expected_text, args) in enumerate(refusals.items()):
        out = tmp_path / f"refused-{i}"
        refused = run_command("distil", *base, "--out", str(out), *args)
        lines = [line for line in refused.stderr.splitlines() if line.strip()]
        assert refused.returncode == 2 and len(lines) == 1, refused.stderr
        assert expected_text in lines[0], lines[0]
        assert not out.exists()
    with pytest.raises(ConfigError, match=r"missing\.json' does not exist"):
        recorded_config(tmp_path / "missing.json", "distil", DistilConfig)
    with pytest.raises(ConfigError, match=r"KEY one of .*optim\.grad_clip.*got 'optim\.nope=1'"):
        parse_settings(["optim.nope=1"], DistilConfig)


def test_bad_inputs_are_refused_clearly(distil_inputs, tmp_path) -> None:
    dataset, teacher = distil_inputs
    base = ["--dataset", str(dataset), "--preset", "tiny", "--quiet"]

    wrong = Teacher(teacher_preset("tiny", 7, 1))
    wrong_path = save_teacher(tmp_path / "wrong.pt", wrong)
    cases = {
        "state_dim 7": ["--teacher", str(wrong_path), "--out", str(tmp_path / "a")],
        "does not exist": ["--teacher", str(tmp_path / "missing.pt"), "--out",
                           str(tmp_path / "b")],
        "longer than every episode": ["--teacher", str(teacher), "--length", "500", "--out",
                                      str(tmp_path / "c")],
        "one final teacher": ["--out", str(tmp_path / "d")],  # synthetic data has none
        "LossWeights.action must be >= 0, got -1": ["--teacher", str(teacher), "--set",
                                                    "weights.action=-1", "--out",
                                                    str(tmp_path / "g")],
        "encoder_norm must be one of none, layer, got 'batch'": [
            "--teacher", str(teacher), "--set", "encoder_norm=batch", "--out", str(tmp_path / "i")],
        "KEY one of": ["--teacher", str(teacher), "--set", "nope=1", "--out",
                       str(tmp_path / "h")],
    }
    # One case through a fresh interpreter, as a user runs it; the rest through the same
    # error boundary in this process.
    result = _fresh_cli(*base, *cases["state_dim 7"])
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "but the data has state_dim 5" in result.stderr
    for expected, args in cases.items():
        result = run_command("distil", *base, *args)
        assert result.returncode == 2, (expected, result.stderr)
        assert expected in result.stderr and "Traceback" not in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr

    no_images = tmp_path / "no-images"
    shutil.copytree(dataset, no_images)
    for shard in no_images.glob("*.zarr"):
        shutil.rmtree(shard / "data" / "image")
    result = run_command("distil", "--dataset", str(no_images), "--teacher", str(teacher),
                         "--preset", "tiny", "--out", str(tmp_path / "e"), "--quiet")
    assert result.returncode == 2 and "no readable images" in result.stderr, result.stderr
    with pytest.raises(DistilError, match="already holds a distillation run"):
        (tmp_path / "f").mkdir()
        (tmp_path / "f" / "config.json").write_text("{}")
        distil(dataset, tmp_path / "f", distil_preset("tiny"), teacher=teacher)


def test_distillation_never_imports_a_simulator(distil_inputs, tmp_path) -> None:
    dataset, teacher = distil_inputs
    code = (
        "import sys\n"
        "from twist_models.distillation import distil_preset\n"
        "from twist_pipeline.distil import distil\n"
        f"distil({str(dataset)!r}, {str(tmp_path / 'run')!r}, distil_preset('tiny', steps=2),"
        f" teacher={str(teacher)!r})\n"
        "import twist_cli.distil\n"
        "loaded = [m for m in sys.modules if m.split('.')[0] in "
        "('mujoco', 'dm_control', 'dm_env')]\n"
        "assert not loaded, loaded\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=300, env={**os.environ})
    assert result.returncode == 0, result.stderr


@pytest.mark.slow
def test_torchrun_data_parallel_on_cpu(distil_inputs, tmp_path) -> None:
    """Two gloo ranks train one student: rank 0 writes, the count is the global one."""
    dataset, teacher = distil_inputs
    result = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
         "-m", "twist_cli.distil", "--dataset", str(dataset), "--teacher", str(teacher),
         "--out", str(tmp_path / "ddp"), "--preset", "tiny", "--steps", "4", "--quiet"],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    config = json.loads((tmp_path / "ddp" / "config.json").read_text())
    assert config["world_size"] == 2
    assert dataclasses.asdict(distil_preset("tiny"))["batch_size"] == 2
    assert len(pd.read_csv(tmp_path / "ddp" / "metrics.csv")) >= 1


def test_a_csv_log_keeps_its_own_columns_when_a_newer_version_appends(tmp_path) -> None:
    log = tmp_path / "metrics.csv"
    append_csv(log, {"updates": 1, "h": 0.5}, ("updates", "h"))
    append_csv(log, {"updates": 2, "h": 0.25, "action": 0.1}, ("updates", "h", "action"))
    table = pd.read_csv(log)
    assert list(table.columns) == ["updates", "h"]
    assert table.to_dict("list") == {"updates": [1, 2], "h": [0.5, 0.25]}


def test_a_run_stored_before_a_config_field_existed_resumes_under_its_default() -> None:
    config = distil_preset("tiny", steps=20)
    stored = to_json(config)
    del stored["weights"]["action"]  # as a run saved before the field was added stores it
    assert resume_conflicts(stored, dataclasses.replace(config, steps=40), ("steps",)) == []
    changed = resume_conflicts(stored, distil_preset("tiny", steps=20, **{"weights.action": 2.0}),
                               ("steps",))
    assert changed == ["weights.action was 0.0, now 2.0"]
    stored["length"] = 9
    assert resume_conflicts(stored, config, ("steps",)) == [
        f"length was 9, now {config.length}"]


def test_a_run_recorded_before_fields_moved_loads_resumes_and_takes_old_settings() -> None:
    config = distil_preset("tiny", "dense", steps=20)
    stored = to_json(config)
    flat = {k: v for k, v in stored.items() if k not in ("weights", "schedule", "compute")}
    flat.update({f"{k}_weight": v for k, v in stored["weights"].items()})
    flat.update(stored["schedule"])
    flat.update(stored["compute"])  # as a run recorded before the groups existed stores it
    assert from_json(DistilConfig, flat) == config
    assert resume_conflicts(flat, config, ("steps",)) == []
    changed = replace_fields(config, {"snapshot_every": 7, "state_weight": 0.5})
    assert (changed.schedule.snapshot_every, changed.weights.state) == (7, 0.5)
    assert resume_conflicts(flat, changed, ("steps",)) == [
        "weights.state was 1.0, now 0.5", "schedule.snapshot_every was 4, now 7"]
    assert parse_settings(["snapshot_every=7"], DistilConfig) == {"schedule.snapshot_every": 7}


def test_a_run_recorded_with_a_removed_switch_loads_only_where_it_was_off() -> None:
    config = distil_preset("tiny")
    stored = to_json(config)
    stored["frame_shift"] = 0.0  # removed since, at the value that meant "off"
    assert from_json(DistilConfig, stored) == config
    assert resume_conflicts(stored, config, ("steps",)) == []
    stored["frame_shift"] = 8.0  # a run the removed code trained
    with pytest.raises(ConfigError, match=r"DistilConfig\.frame_shift was removed .*sets it "
                                          r"to 8\.0"):
        from_json(DistilConfig, stored)
    assert resume_conflicts(stored, config, ("steps",)) == [
        "frame_shift was 8.0 and has been removed"]
    stored["frame_shift"] = 0.0
    stored["frame_tilt"] = 1.0  # never a field
    with pytest.raises(ConfigError, match=r"unknown fields \['frame_tilt'\] for DistilConfig"):
        from_json(DistilConfig, stored)


def test_frozen_dynamics_train_only_the_encoder_and_posterior(distil_inputs, tmp_path) -> None:
    dataset, teacher_path = distil_inputs
    rssm = load_teacher(teacher_path)[0].world_model.rssm.state_dict()

    def changed(freeze: bool) -> set[str]:
        config = distil_preset("tiny", steps=4, freeze_dynamics=freeze)
        summary = distil(dataset, tmp_path / str(freeze), config, teacher=teacher_path)
        student = load_student(summary.student)[0].rssm.state_dict()
        return {k.split(".")[0] for k, v in student.items()
                if v.shape == rssm[k].shape and not torch.equal(v, rssm[k])}

    assert changed(freeze=True) == {"obs_out"}  # the posterior head trains, nothing else
    assert {"img_in", "gru", "img_out"} <= changed(freeze=False)
    with pytest.raises(ConfigError, match="needs copy_dynamics"):
        distil_preset("tiny", freeze_dynamics=True, copy_dynamics=False)


def test_stacked_frames_repeat_at_episode_starts_and_agree_step_by_step() -> None:
    embed = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0]).reshape(1, 5, 1)
    is_first = torch.tensor([[True, False, True, False, False]])
    # Most recent first; before an episode's first step its own image stands in.
    expected = [[1, 1, 1], [2, 1, 1], [3, 3, 3], [4, 3, 3], [5, 4, 3]]
    assert stack_frames(embed, is_first, 3)[0].tolist() == expected
    assert torch.equal(stack_frames(embed, is_first, 1), embed)

    sequence = torch.randn(2, 6, 4)
    starts = torch.tensor([[True, False, False, True, False, False]] * 2)
    history, steps = None, []
    for t in range(6):
        if starts[0, t]:
            history = None
        stacked, history = step_frames(sequence[:, t], history, 3)
        steps.append(stacked)
    torch.testing.assert_close(torch.stack(steps, 1), stack_frames(sequence, starts, 3))


@pytest.mark.parametrize(("frames", "norm"), [(1, "none"), (3, "layer")])
def test_the_agent_acting_step_by_step_filters_as_the_student_does_on_windows(
        frames, norm, tmp_path) -> None:
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset("tiny", 5, 1))
    student = Student(student_preset("tiny", teacher.config, image_size=64, frames=frames,
                                     norm=norm))
    # Through a saved bundle: its config must rebuild the same encoder.
    agent = Agent.load(Agent.from_models(student, teacher).save(tmp_path / "agent.pt")).eval()
    assert agent.student.config.cnn.norm == norm
    images = torch.randint(0, 256, (1, 5, 64, 64, 3), dtype=torch.uint8)
    torch.manual_seed(1)  # both paths draw their latent samples in the same order
    state, logits, actions = None, [], []
    for t in range(5):
        action, state = agent.act(images[0, t].numpy(), state)
        logits.append(state.latent["logits"])
        actions.append(torch.as_tensor(action))
    # A window's action at step t is the one taken before it (zeroed at the first step).
    previous = torch.stack([torch.zeros(1), *actions[:-1]])[None].float()
    torch.manual_seed(1)
    is_first = torch.tensor([[True, False, False, False, False]])
    with torch.no_grad():
        post, _ = student.observe(images, previous, is_first)
    torch.testing.assert_close(torch.cat(logits), post["logits"][0])
    assert student.rssm.obs_out[0].in_features == (
        student.config.rssm.deter + frames * student.perception.encoder.out_dim)


def test_an_agent_acting_on_posterior_means_is_the_students_filter_on_means() -> None:
    objective, batch = _objective(imagined=False)
    agent = Agent.from_models(objective.student, objective.teacher).eval()
    images, state, logits, actions = batch["image"][:1], None, [], []
    for t in range(images.shape[1]):
        action, state = agent.act(images[0, t].numpy(), state, posterior="mean")
        torch.testing.assert_close(state.latent["stoch"], torch.softmax(state.latent["logits"], -1))
        logits.append(state.latent["logits"])
        actions.append(torch.as_tensor(action))
    previous = torch.stack([torch.zeros(1), *actions[:-1]])[None].float()
    with torch.no_grad():  # no draw reaches a filter on means
        post, _ = objective.student.observe(images, previous, batch["is_first"][:1], read="mean")
    torch.testing.assert_close(torch.cat(logits), post["logits"][0])


def test_a_resident_copy_of_d_feeds_the_loaders_windows(distil_inputs, tmp_path) -> None:
    from twist_data.sampler import ResidentWindows, WindowDataset

    dataset, teacher = distil_inputs
    config = distil_preset("tiny", resident_data="on")
    sampler = config.sampler("train", 7)
    loader = iter(DataLoader(WindowDataset(dataset, sampler), batch_size=None, num_workers=0))
    resident = iter(ResidentWindows(dataset, sampler))
    for _ in range(3):
        want, got = next(loader), next(resident)
        for key in ("image", "state", "action", "is_first", "start"):
            assert torch.equal(got[key], want[key]), key
    # The run itself trains from it (its torch draws differ: a DataLoader seeds itself from
    # the global generator, so the losses are not compared).
    summary = distil(dataset, tmp_path / "on", config, teacher=teacher)
    losses = pd.read_csv(tmp_path / "on" / "metrics.csv")["loss"]
    assert len(losses) > 0 and np.isfinite(losses).all() and summary.updates == config.steps
    with pytest.raises(ConfigError, match="resident_data must be one of"):
        distil_preset("tiny", resident_data="sometimes")


def test_replace_fields_reaches_nested_configs_and_names_unknown_fields() -> None:
    config = distil_preset("tiny")
    changed = replace_fields(config, {"steps": 9, "optim.eps": 1e-3})
    assert changed.steps == 9 and changed.optim.eps == 1e-3
    assert changed.optim.grad_clip == config.optim.grad_clip  # the nested rest is kept
    assert dataclasses.replace(changed, steps=config.steps, optim=config.optim) == config
    with pytest.raises(ConfigError, match=r"^OptimConfig has no field 'nope'$"):
        replace_fields(config, {"optim.nope": 1})
    with pytest.raises(ConfigError, match=r"DistilConfig.steps is not a nested config"):
        replace_fields(config, {"steps.x": 1})
    with pytest.raises(ConfigError, match="grad_clip must be > 0"):
        replace_fields(config, {"optim.grad_clip": 0.0})  # the nested config's own checks
    assert "optim.grad_clip" in field_types(DistilConfig)
