"""Distillation recipes: the per-frame terms of the ``dense`` recipe against hand computations,
the teacher's targets against its own filter and finite differences, gradients that reach the
student's encoder and never the teacher, and the recipe's name through config, run folder,
agent bundle and CLI."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import run_command
from twist_data.errors import ConfigError
from twist_data.reader import open_dataset
from twist_data.synth import SynthConfig, write_synthetic_dataset
from twist_models.agent import Agent
from twist_models.config import student_preset, teacher_preset
from twist_models.distillation import RECIPES, Distillation, distil_preset
from twist_models.frame_targets import (
    FrameBatches,
    actor_sensitivity,
    frame_agreement,
    frame_terms,
    teacher_latent_before,
    teacher_targets,
)
from twist_models.losses import frame_posterior_loss, weighted_state_loss
from twist_models.student import Student
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline.distil import distil, load_student, stored_config

DATA = SynthConfig(episodes=8, steps=30, views=2, image_size=64, seed=5, length_jitter=6)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Teacher]:
    """(dataset, teacher checkpoint, the teacher): synthetic episodes of varying length and a
    small random-weights teacher."""
    root = tmp_path_factory.mktemp("recipes")
    dataset = write_synthetic_dataset(root / "ds", DATA)
    torch.manual_seed(3)
    teacher = Teacher(teacher_preset("tiny", 5, 1)).eval()
    return dataset, save_teacher(root / "teacher.pt", teacher), teacher


def _log_softmax(x: np.ndarray) -> np.ndarray:
    x = x - x.max(-1, keepdims=True)
    return x - np.log(np.exp(x).sum(-1, keepdims=True))


def test_frame_posterior_loss_is_the_mean_kl_summed_over_latents() -> None:
    g = torch.Generator().manual_seed(0)
    student, teacher = torch.randn(3, 4, 5, 6, generator=g), torch.randn(3, 4, 5, 6, generator=g)
    lp, lq = _log_softmax(student.double().numpy()), _log_softmax(teacher.double().numpy())
    expected = (np.exp(lp) * (lp - lq)).sum((-2, -1)).mean()
    assert float(frame_posterior_loss(student, teacher)) == pytest.approx(expected, rel=1e-5)
    assert float(frame_posterior_loss(teacher, teacher)) == pytest.approx(0.0, abs=1e-6)


def test_weighted_state_loss_by_hand() -> None:
    prediction = torch.tensor([[1.0, 2.0], [0.0, -1.0]])
    state = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    weight = torch.tensor([[2.0, 0.5], [0.0, 3.0]])
    # Row 0: 2 * 1 + 0.5 * 4 = 4; row 1: 0 * 1 + 3 * 4 = 12; mean 8.
    assert float(weighted_state_loss(prediction, state, weight)) == pytest.approx(8.0)
    prediction.requires_grad_(True)
    weighted_state_loss(prediction, state, weight).backward()
    # d/dp of mean_rows sum_i w (p - s)^2 = w (p - s) (2 / 2 rows)
    assert torch.allclose(prediction.grad, weight * (prediction.detach() - state))


def test_actor_sensitivity_matches_finite_differences(inputs: tuple[Path, Path, Teacher]) -> None:
    teacher = inputs[2]
    g = torch.Generator().manual_seed(1)
    deter = torch.randn(6, teacher.world_model.rssm.config.deter, generator=g, dtype=torch.float64)
    state = torch.randn(6, 5, generator=g, dtype=torch.float64)
    teacher64 = Teacher(teacher.config).double()
    teacher64.load_state_dict(teacher.state_dict())
    weight = actor_sensitivity(teacher64, deter, state)

    def action(s: torch.Tensor) -> torch.Tensor:
        wm = teacher64.world_model
        logits = wm.rssm.posterior_logits(deter, wm.encoder(s))
        feature = torch.cat([deter, torch.softmax(logits, -1).flatten(-2)], -1)
        return teacher64.actor_critic.actor(feature).mode

    eps, expected = 1e-6, torch.zeros_like(state)
    with torch.no_grad():
        for i in range(5):
            step = torch.zeros_like(state)
            step[:, i] = eps
            expected[:, i] = (((action(state + step) - action(state - step)) / (2 * eps)) ** 2).sum(-1)
    assert torch.allclose(weight, expected, rtol=1e-5, atol=1e-10)
    assert expected.abs().sum() > 0  # the check is not vacuous


def test_teacher_targets_follow_each_episode_from_its_start(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    episodes = np.array([0, 2, 3, 5])
    targets = teacher_targets(teacher, data, episodes, read="mean", chunk=3)
    wm = teacher.world_model
    row = 0
    for e in episodes.tolist():
        start, end = int(data.episode_starts[e]), int(data.episode_ends[e])
        state = torch.as_tensor(data.column("state")[start:end])[None]
        action = torch.as_tensor(data.column("action")[start:end])[None]
        is_first = torch.zeros(1, end - start, dtype=torch.bool)
        is_first[0, 0] = True
        with torch.no_grad():
            post, _ = wm.rssm.observe(wm.embed(state), action, is_first, read="mean")
        n = end - start
        assert np.array_equal(targets.steps[row:row + n], np.arange(start, end))
        assert np.all(targets.episode_start[row:row + n] == start)
        assert torch.allclose(targets.deter[row:row + n], post["deter"][0], atol=1e-5)
        row += n
    assert row == len(targets)
    assert float(targets.sensitivity.mean()) == pytest.approx(1.0, rel=1e-5)
    raw = actor_sensitivity(teacher, targets.deter, targets.state)
    assert torch.allclose(targets.sensitivity * targets.scale, raw, rtol=1e-4, atol=1e-12)


def test_frame_batches_stack_the_steps_before_within_the_episode(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    targets = teacher_targets(teacher, data, np.arange(data.n_episodes))
    batches = FrameBatches(data, targets, batch_size=64, frames=3, view=1, seed=0)
    batch = batches.batch()
    assert batch["image"].shape == (64, 3, 64, 64, 3)
    # Recover each row from its state, then check the frames against the reader directly.
    states = targets.state.numpy()
    checked_start = 0
    for i in range(64):
        row = int(np.flatnonzero((states == batch["state"][i].numpy()).all(1))[0])
        step, first = int(targets.steps[row]), int(targets.episode_start[row])
        assert torch.equal(batch["deter"][i], targets.deter[row])
        for j in range(3):
            expected = np.empty((1, *data.spec.image_shape), np.uint8)
            data.read_frames(np.array([max(step - j, first)]), np.array([1]), expected)
            assert np.array_equal(batch["image"][i, j].numpy(), expected[0])
        checked_start += step - first < 2
    assert checked_start > 0  # some rows did reach back past their episode's start


def test_frame_batches_from_a_resident_copy_are_the_decoded_batches(
        inputs: tuple[Path, Path, Teacher]) -> None:
    from twist_data.sampler import resident_images

    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    targets = teacher_targets(teacher, data, np.arange(data.n_episodes))
    images = resident_images(data)
    copy = images.clone()
    assert images.shape == (data.n_steps, data.spec.views, *data.spec.image_shape)
    decoded = FrameBatches(data, targets, batch_size=32, frames=2, seed=3)
    resident = FrameBatches(data, targets, batch_size=32, frames=2, seed=3, images=images)
    for _ in range(3):
        a, b = decoded.batch(), resident.batch()
        assert a.keys() == b.keys()
        assert all(torch.equal(a[k], b[k]) for k in a)
        b["image"].zero_()  # a batch is the trainer's to change (mirroring) ...
    assert torch.equal(images, copy)  # ... without touching the copy


def test_gradients_reach_the_encoder_and_never_the_teacher(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    config = distil_preset("tiny", "dense")
    student = Student(student_preset("tiny", teacher.config, 64, norm="layer", state_head=True))
    targets = teacher_targets(teacher, data, np.arange(data.n_episodes))
    # First stage: single frames.
    batch = FrameBatches(data, targets, batch_size=8, seed=1).batch()
    embed = student.perception.encoder(batch["image"]).flatten(1)
    terms = frame_terms(student, teacher, embed, batch["deter"], batch["state"],
                        batch["sensitivity"])
    (terms["frame_post_kl"] + terms["state"]).backward()
    assert student.perception.encoder.net[0].weight.grad.abs().sum() > 0
    assert student.state_head.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in teacher.parameters())
    # Second stage: the terms beside Eq. 3/4 on windows.
    student.zero_grad(set_to_none=True)
    from twist_data.sampler import WindowSampler

    windows = WindowSampler(data, config.sampler("all", 0)).batch()
    objective = Distillation(student, teacher, config, targets.scale)
    loss, terms = objective({k: torch.as_tensor(windows[k]) for k in
                             ("image", "state", "action", "is_first")})
    assert {"frame_post_kl", "state", "h", "post_kl"} <= set(terms)
    loss.backward()
    assert student.perception.encoder.net[0].weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in teacher.parameters())


def test_frame_agreement_is_perfect_for_a_student_reading_the_teachers_posterior(
        inputs: tuple[Path, Path, Teacher]) -> None:
    teacher = inputs[2]
    wm = teacher.world_model
    g = torch.Generator().manual_seed(2)
    deter = torch.randn(40, wm.rssm.config.deter, generator=g)
    state = torch.randn(40, 5, generator=g)
    # A "student" whose posterior head is the teacher's and whose embedding is the state's.
    student = Student(student_preset("tiny", teacher.config, 64))
    student.rssm.obs_out = wm.rssm.obs_out
    with torch.no_grad():
        same = frame_agreement(student, teacher, wm.encoder(state), deter, state)
        other = frame_agreement(student, teacher, wm.encoder(state.flip(0)), deter, state)
    assert same["frame_action_rmse"] == pytest.approx(0.0, abs=1e-6)
    assert same["frame_action_corr"] == pytest.approx(1.0, abs=1e-5)
    assert other["frame_action_rmse"] > 1e-4


def test_windows_start_from_the_teachers_latent_before_them(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    episodes = np.array([1, 4])
    targets = teacher_targets(teacher, data, episodes, read="mean")
    first = int(data.episode_starts[4])
    starts = np.array([first + 7, first, int(data.episode_starts[1]) + 3])
    torch.manual_seed(0)
    start = teacher_latent_before(teacher, targets, starts)
    row = int(np.flatnonzero(targets.steps == first + 6)[0])
    assert torch.equal(start["deter"][0], targets.deter[row])
    # z is a one-hot draw from the teacher's posterior at that h and state.
    wm = teacher.world_model
    logits = wm.rssm.posterior_logits(targets.deter[row], wm.embed(targets.state[row]))
    drawn = start["stoch"][0].argmax(-1)
    one_hot = torch.nn.functional.one_hot(drawn, logits.shape[-1]).float()
    assert torch.allclose(start["stoch"][0], one_hot, atol=1e-6)
    assert torch.all(torch.softmax(logits, -1).gather(-1, drawn[:, None]) > 0)
    # An episode's first step starts from zeros (the filter resets there anyway).
    assert not start["deter"][1].any() and not start["stoch"][1].any()
    with pytest.raises(ValueError, match="not a step"):
        teacher_latent_before(teacher, targets, np.array([int(data.episode_starts[0]) + 2]))


def test_a_window_from_the_teachers_latent_continues_its_filter(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    config = distil_preset("tiny", "dense", window_start="teacher")
    targets = teacher_targets(teacher, data, np.arange(data.n_episodes))
    from twist_data.sampler import WindowSampler

    windows = WindowSampler(data, config.sampler("all", 0)).batch()
    batch = {k: torch.as_tensor(windows[k]) for k in ("image", "state", "action", "is_first")}
    start = teacher_latent_before(teacher, targets, windows["start"])
    batch.update(start_deter=start["deter"], start_stoch=start["stoch"])
    student = Student(student_preset("tiny", teacher.config, 64, norm="layer", state_head=True))
    objective = Distillation(student, teacher, config, targets.scale)
    with torch.no_grad():
        _, t_post, _, _ = objective.filter(batch)
    # The teacher's first h is its GRU on the start latent, so the window follows its filter
    # from the episode's start, not from h = 0.
    rssm = teacher.world_model.rssm
    mid = ~batch["is_first"][:, 0]
    assert mid.any()
    expected = rssm._deter({"deter": start["deter"], "stoch": start["stoch"]},
                           batch["action"][:, 0])
    assert torch.allclose(t_post["deter"][mid, 0], expected[mid], atol=1e-5)
    with torch.no_grad():
        _, zero_post, _, _ = Distillation(student, teacher, dataclasses.replace(
            config, window_start="zero"), targets.scale).filter(
            {k: v for k, v in batch.items() if not k.startswith("start_")})
    assert not torch.allclose(zero_post["deter"][mid, 0], expected[mid], atol=1e-3)


def test_the_recipe_travels_with_the_run_and_the_bundle(
        inputs: tuple[Path, Path, Teacher], tmp_path: Path) -> None:
    dataset, teacher_path, _ = inputs
    config = distil_preset("tiny", "dense", frame_steps=4, frame_eval_every=2)
    assert (config.weights.frame_post, config.weights.state) == (1.0, 1.0)
    assert config.window_start == "teacher" and not config.shared_draws
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    assert stored_config(tmp_path / "run") == config
    assert stored_config(tmp_path / "run").recipe == "dense"
    student, extra = load_student(summary.student)
    assert student.state_head is not None and extra["distil"]["recipe"] == "dense"
    agent = Agent.load(summary.agent)
    assert agent.info["recipe"] == "dense" and agent.info["frame_updates"] == 4
    assert agent.student.state_head is None  # a training target only
    frames = (tmp_path / "run" / "frame-metrics.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in frames[1:]] == ["2", "4"]
    # The paper's recipe adds nothing: no head, no first stage.
    paper = distil_preset("tiny")
    assert paper.recipe == "paper" and not paper.frame_terms and paper.frame_steps == 0
    assert paper.window_start == "zero" and paper.shared_draws
    assert set(RECIPES) >= {"paper", "dense"}


def test_a_frame_stage_without_frame_terms_is_refused() -> None:
    with pytest.raises(ConfigError, match="frame_steps=5"):
        dataclasses.replace(distil_preset("tiny"), frame_steps=5)


def test_an_unknown_recipe_is_refused_in_one_line(inputs: tuple[Path, Path, Teacher],
                                                  tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown recipe 'fast'; valid recipes are: paper"):
        distil_preset("quick", "fast")
    result = run_command("distil", "--dataset", str(inputs[0]), "--out", str(tmp_path / "run"),
                         "--preset", "tiny", "--recipe", "fast")
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "unknown recipe 'fast'" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()


def test_a_badly_typed_setting_is_refused_in_one_line(inputs: tuple[Path, Path, Teacher],
                                                      tmp_path: Path) -> None:
    result = run_command("distil", "--dataset", str(inputs[0]), "--out", str(tmp_path / "run"),
                         "--preset", "tiny", "--set", "batch_size=abc")
    assert result.returncode == 2
    assert result.stderr.strip() == "error: --set batch_size must be an integer, got 'abc'"
    assert not (tmp_path / "run").exists()


def test_bfloat16_autocast_changes_the_arithmetic_not_the_objective(
        inputs: tuple[Path, Path, Teacher]) -> None:
    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    from twist_data.sampler import WindowSampler

    windows = WindowSampler(data, distil_preset("tiny").sampler("all", 0)).batch()
    batch = {k: torch.as_tensor(windows[k]) for k in ("image", "state", "action", "is_first")}
    torch.manual_seed(0)
    student = Student(student_preset("tiny", teacher.config, 64, norm="layer"))
    losses = {}
    for precision in ("float32", "bfloat16"):
        config = distil_preset("tiny", precision=precision, imagined=False)
        torch.manual_seed(1)  # the same sampling draws
        with torch.no_grad():
            _, _, terms, embed = Distillation(student, teacher, config).filter(batch)
        assert embed.dtype == torch.float32  # the RSSM always reads float32
        losses[precision] = terms
    for key, value in losses["float32"].items():
        assert float(losses["bfloat16"][key]) == pytest.approx(float(value), rel=0.05), key
    # bfloat16 keeps 8 bits of mantissa: the embeddings differ, if only slightly.
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        low = student.perception.encoder(batch["image"][:, :2])
    assert low.dtype == torch.bfloat16
    with torch.no_grad():
        assert not torch.equal(low.float(), student.perception.encoder(batch["image"][:, :2]))


def test_compile_settings_pick_the_whole_objective_or_its_filters_in_pieces(
        inputs: tuple[Path, Path, Teacher]) -> None:
    """:func:`compiled_objective` compiles nothing for eager, wraps the whole objective for
    CUDA graphs, and on a CPU compiles the two filters in pieces and trains the objective
    itself (nothing is compiled until a call, so this runs in a moment)."""
    import copy

    from twist_models.distillation import compiled_objective
    from twist_models.rssm import FILTER_CHUNK

    teacher = copy.deepcopy(inputs[2])
    student = Student(student_preset("tiny", teacher.config, 64))
    objective = Distillation(student, teacher, distil_preset("tiny"))
    assert compiled_objective(objective, None) is objective
    whole = compiled_objective(objective, "reduce-overhead")
    assert whole is not objective and whole._orig_mod is objective
    for rssm in (student.rssm, teacher.world_model.rssm):  # a whole graph leaves them alone
        assert rssm._filter_chunk is None and rssm._filter_fn == rssm._filter
    assert compiled_objective(objective, "default") is objective
    for rssm in (student.rssm, teacher.world_model.rssm):
        assert rssm._filter_chunk == FILTER_CHUNK and rssm._filter_fn != rssm._filter


@pytest.mark.slow
@pytest.mark.parametrize("whole", [True, False], ids=["whole", "pieces"])
def test_the_compiled_objective_gives_the_eager_loss_gradients_and_step(
        inputs: tuple[Path, Path, Teacher], whole: bool) -> None:
    """``compile=true`` (:func:`compiled_objective`, whole or its filters in pieces): the same
    loss, gradients and optimiser step as eager, on the same windows and (with inductor
    drawing its random numbers as eager does) the same draws. Slow: the first compiled call
    compiles for minutes on a CPU."""
    import copy

    import torch._inductor.config as inductor

    from twist_models.distillation import compiled_objective

    dataset, _, teacher = inputs
    data = open_dataset(dataset)
    # float32: bfloat16 autocast rounds differently once inductor fuses the convolutions' neighbours.
    config = distil_preset("tiny", "dense", shared_draws=False, precision="float32")
    targets = teacher_targets(teacher, data, np.arange(data.n_episodes))
    from twist_data.sampler import WindowSampler

    windows = WindowSampler(data, config.sampler("all", 0)).batch()
    batch = {k: torch.as_tensor(windows[k]) for k in ("image", "state", "action", "is_first")}
    start = teacher_latent_before(teacher, targets, windows["start"])
    batch.update(start_deter=start["deter"], start_stoch=start["stoch"])
    torch.manual_seed(0)
    eager = Student(student_preset("tiny", teacher.config, 64, norm="layer", state_head=True))
    twin = copy.deepcopy(eager)
    before = [p.detach().clone() for p in eager.parameters()]
    results = []
    # The pieces compile the teacher's filter too: the twin's teacher is a copy, so that the
    # fixture's stays eager.
    for student, mentor, mode in ((eager, teacher, None), (twin, copy.deepcopy(teacher),
                                                          "default")):
        objective = compiled_objective(Distillation(student, mentor, config, targets.scale),
                                       mode, whole)
        optimiser = torch.optim.Adam(student.parameters(), 1e-3)
        torch.manual_seed(7)
        with inductor.patch(fallback_random=True):
            loss, terms = objective(batch)
        loss.backward()
        grads = [p.grad.clone() for p in student.parameters() if p.grad is not None]
        optimiser.step()
        results.append((loss.detach(), {k: v.detach() for k, v in terms.items()}, grads,
                        [p.detach().clone() for p in student.parameters()]))
    (loss_e, terms_e, grads_e, after_e), (loss_c, terms_c, grads_c, after_c) = results
    assert torch.allclose(loss_e, loss_c, rtol=1e-4, atol=1e-5)
    assert terms_e.keys() == terms_c.keys()
    for key in terms_e:
        assert torch.allclose(terms_e[key], terms_c[key], rtol=1e-4, atol=1e-5), key
    assert len(grads_e) == len(grads_c) > 0
    for g_e, g_c in zip(grads_e, grads_c, strict=True):
        assert torch.allclose(g_e, g_c, rtol=1e-3, atol=1e-5)
    for p_e, p_c in zip(after_e, after_c, strict=True):
        assert torch.allclose(p_e, p_c, rtol=1e-4, atol=1e-6)
    assert any(not torch.equal(p, q) for p, q in zip(before, after_e, strict=True))
