"""The read-out student (``readout`` recipe): velocities paired with what one image shows by
measurement on D, the robust standardisation and the Huber read-out loss against hand
computations, the state rebuilt from exact positions against D's own, the window and step
paths agreeing, gradients that reach the CNN and never the teacher's filter, and the recipe
through config, run folder and agent bundle."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from tests.conftest import board_events
from twist_data.errors import ConfigError, PairsMissingError
from twist_data.reader import open_dataset
from twist_data.sampler import WindowSampler
from twist_data.schema import PAIR_IMAGE
from twist_data.synth import _DT, SYNTH_MIRROR, SynthConfig, write_synthetic_dataset
from twist_models.agent import Agent
from twist_models.checkpoint import read_checkpoint
from twist_models.config import (
    CNNConfig,
    MLPConfig,
    ReadOutConfig,
    StudentConfig,
    from_json,
    replace_fields,
    student_preset,
    teacher_preset,
    to_json,
)
from twist_models.distillation import Distillation, ReadOutStage, distil_preset, split_context
from twist_models.frame_targets import FrameRows
from twist_models.losses import readout_loss
from twist_models.networks import ImageEncoder
from twist_models.readout import (
    StateReadOut,
    episode_constants,
    motion_standardisation,
    pair_velocities,
    robust_standardisation,
    training_frames,
)
from twist_models.student import Student, copy_teacher_filter
from twist_models.teacher import Teacher, save_teacher
from twist_pipeline import readout_recipe
from twist_pipeline.curves import student_progress
from twist_pipeline.distil import DistilError, distil, load_student, stored_config

DATA = SynthConfig(episodes=8, steps=30, views=2, image_size=64, seed=11, length_jitter=6)
LAYOUT = (("position", 3), ("velocity", 2))  # the synthetic cartpole's: x, cos, sin | ẋ, θ̇


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Teacher, FrameRows]:
    """(dataset, teacher checkpoint, the teacher, every step of D)."""
    root = tmp_path_factory.mktemp("readout")
    dataset = write_synthetic_dataset(root / "ds", DATA)
    torch.manual_seed(4)
    teacher = Teacher(teacher_preset("tiny", 5, 1)).eval()
    data = open_dataset(dataset)
    rows = FrameRows.of(data, np.arange(data.n_episodes))
    return dataset, save_teacher(root / "teacher.pt", teacher), teacher, rows


def _paired(rows: FrameRows) -> ReadOutConfig:
    return pair_velocities(rows.state.numpy(), rows.steps == rows.episode_start, LAYOUT,
                           MLPConfig(layers=2, units=32))


def test_velocities_are_paired_with_what_they_are_the_rate_of(inputs) -> None:
    config = _paired(inputs[3])
    assert config.read == (0, 1, 2) and config.angles == ((1, 2),)
    assert config.velocities == ((3, 0), (4, 1, 2))  # ẋ from x, θ̇ from the angle of (cos, sin)
    # The synthetic integrator moves x by DT * ẋ each step: the gain is exactly 1 / DT.
    assert config.gains == pytest.approx((1 / _DT, 1 / _DT), rel=1e-5)


def test_a_velocity_no_image_shows_is_read_from_frame_pairs(inputs) -> None:
    rows = inputs[3]
    state = rows.state.numpy().copy()
    state[:, 4] = np.random.default_rng(0).normal(size=len(state))  # θ̇ now the rate of nothing
    config = pair_velocities(state, rows.steps == rows.episode_start, LAYOUT, MLPConfig(),
                             "synth")
    assert config.moving == (4,) and config.velocities == ((3, 0),)
    state[:, 4] = 2 * state[:, 3]  # both velocities now the rate of x
    with pytest.raises(ConfigError, match="velocity components 3 and 4 of synth pair with the"):
        pair_velocities(state, rows.steps == rows.episode_start, LAYOUT, MLPConfig(), "synth")
    with pytest.raises(ConfigError, match="declares no state layout"):
        pair_velocities(state, rows.steps == rows.episode_start, (), MLPConfig())


def test_a_velocity_is_paired_down_to_min_pairing_and_read_from_pairs_below_it(inputs) -> None:
    rows = inputs[3]
    state = rows.state.numpy().astype(np.float64).copy()
    is_first = rows.steps == rows.episode_start
    # ẋ made as loosely the rate of x as a block that stops under friction within a step:
    # its correlation with x's change, measured here, lies between the two bars tried.
    noise = np.random.default_rng(1).normal(size=len(state)) * state[:, 3].std()
    state[:, 3] += 0.9 * noise
    step = ~is_first[1:]
    corr = abs(np.corrcoef(np.diff(state[:, 0])[step], state[1:, 3][step])[0, 1])
    assert 0.6 < corr < 0.8
    paired = pair_velocities(state, is_first, LAYOUT, MLPConfig(), "synth", min_pairing=0.6)
    assert paired.velocities[0] == (3, 0) and paired.moving == ()
    loose = pair_velocities(state, is_first, LAYOUT, MLPConfig(), "synth", min_pairing=0.8)
    assert loose.moving == (3,) and [v[0] for v in loose.velocities] == [4]
    assert loose.moving_pairing == pytest.approx((corr,), abs=1e-4)
    assert pair_velocities(state, is_first, LAYOUT, MLPConfig(), "synth",
                           min_pairing=corr - 0.001).velocities[0] == (3, 0)
    with pytest.raises(ConfigError, match="min_pairing must lie in"):
        ReadOutStage(min_pairing=0.0)


def _with_goal(rows: FrameRows, goal: np.ndarray) -> np.ndarray:
    """D's states with a goal component [N] put after the positions: x, cos, sin, goal |
    ẋ, θ̇."""
    state = rows.state.numpy()
    return np.concatenate([state[:, :3], goal[:, None], state[:, 3:]], 1)


GOAL_LAYOUT = (("position", 4), ("velocity", 2))


def test_a_component_no_episode_changes_is_found_and_nothing_else(inputs) -> None:
    rows = inputs[3]
    is_first = rows.steps == rows.episode_start
    episode = np.cumsum(is_first)
    state = _with_goal(rows, np.random.default_rng(0).uniform(-1, 1, 99)[episode])
    config = pair_velocities(state, is_first, GOAL_LAYOUT, MLPConfig())
    # The goal differs between episodes but stays put within each; x and the angle move.
    assert config.poolable() == (3,)
    assert episode_constants(state, is_first, range(6)) == (3,)
    moved = state.copy()
    moved[np.flatnonzero(is_first)[2] + 5, 3] += 1e-3  # one episode's goal moves once
    assert episode_constants(moved, is_first, range(6)) == ()
    with pytest.raises(ConfigError, match="must start an episode"):
        episode_constants(state[1:], is_first[1:], range(6))


def test_pooling_hands_on_the_running_mean_of_a_constant_components_readings() -> None:
    config = ReadOutConfig(state_dim=6, read=(0, 1, 2, 3), angles=((1, 2),),
                           velocities=((4, 0), (5, 1, 2)), gains=(20.0, 20.0), pooled=(3,))
    readout = StateReadOut(config, features=2)
    reading = torch.randn(2, 7, 4)  # two episodes, seven steps each
    goal = reading[..., 3].numpy()
    expected = np.cumsum(goal, 1) / np.arange(1, 8)
    history, handed = None, []
    for t in range(7):
        positions, previous, history = readout.pool_step(reading[:, t], history)
        if t > 0:  # velocities come from what was handed on the step before
            torch.testing.assert_close(previous, handed[-1])
        handed.append(positions)
    handed = torch.stack(handed, 1)
    np.testing.assert_allclose(handed[..., 3].numpy(), expected, rtol=1e-5)
    torch.testing.assert_close(handed[..., :3], reading[..., :3])  # the rest as read
    # Along windows alike; a new episode within the window starts the mean again.
    is_first = torch.zeros(2, 7, dtype=torch.bool)
    is_first[:, 0] = True
    torch.testing.assert_close(readout.pool_window(reading, is_first), handed)
    is_first[1, 4] = True
    restarted = readout.pool_window(reading, is_first)[1, 4:, 3].numpy()
    np.testing.assert_allclose(restarted, np.cumsum(goal[1, 4:]) / np.arange(1, 4), rtol=1e-5)
    # Nothing pooled: every frame handed on as read, the history that reading.
    plain = StateReadOut(dataclasses.replace(config, pooled=()), features=2)
    positions, _, history = plain.pool_step(reading[:, 1], reading[:, 0])
    assert torch.equal(positions, reading[:, 1]) and torch.equal(history, reading[:, 1])


def test_only_a_read_component_outside_angles_and_velocity_sources_is_pooled() -> None:
    base = {"state_dim": 6, "read": (0, 1, 2, 3), "angles": ((1, 2),),
            "velocities": ((4, 0), (5, 1, 2)), "gains": (20.0, 20.0)}
    for pooled in ((0,), (1,), (4,)):  # a velocity's source, an angle's cosine, a velocity
        with pytest.raises(ConfigError, match=re.escape(f"velocity, got {list(pooled)}")):
            ReadOutConfig(**base, pooled=pooled)
    with pytest.raises(ConfigError, match="pool must be one of"):
        ReadOutStage(pool="goal")


def test_robust_standardisation_by_hand() -> None:
    angle = np.array([0.0, 0.1, -0.1, 0.2, 3.0])
    x = np.array([0.0, 1.0, 2.0, 3.0, 100.0])
    states = np.stack([x, np.cos(angle), np.sin(angle), x, x], 1)
    config = ReadOutConfig(state_dim=5, read=(0, 1, 2), angles=((1, 2),),
                           velocities=((3, 0), (4, 1, 2)), gains=(1.0, 1.0))
    mean, scale = robust_standardisation(states, config)
    assert mean == pytest.approx([2.0, np.cos(0.1), np.sin(0.1)], rel=1e-6)
    # x: |x - 2| = 2, 1, 0, 1, 98 -> MAD 1. sin: the MAD of sin(angle) beats the cosine's.
    sine_mad = np.median(np.abs(np.sin(angle) - np.sin(0.1)))
    assert scale == pytest.approx([1.4826, 1.4826 * sine_mad, 1.4826 * sine_mad], rel=1e-5)


def test_readout_errors_and_loss_by_hand() -> None:
    config = ReadOutConfig(state_dim=5, read=(0, 1, 2), angles=((1, 2),),
                           velocities=((3, 0), (4, 1, 2)), gains=(1.0, 1.0),
                           encoder=MLPConfig(layers=1, units=4))
    readout = Student(StudentConfig(readout=config)).perception.readout
    readout.set_standardisation(np.zeros(3), np.array([2.0, 0.1, 0.1]))
    # x read 0.5 off; the pole read at 0.3 rad with length 2 where it is at -0.1 rad.
    read = torch.tensor([[1.5, 2 * np.cos(0.3), 2 * np.sin(0.3)]], dtype=torch.float32)
    state = torch.tensor([[1.0, np.cos(-0.1), np.sin(-0.1), 7.0, 7.0]], dtype=torch.float32)
    errors = readout.errors(read, state)
    torch.testing.assert_close(errors, torch.tensor([[0.25, 10.0, 4.0]]), rtol=1e-5, atol=1e-5)
    # Across the bottom the angle's error is the short way round.
    bottom = readout.errors(torch.tensor([[1.0, np.cos(3.1), np.sin(3.1)]]),
                            torch.tensor([[1.0, np.cos(-3.1), np.sin(-3.1), 0.0, 0.0]]))
    assert float(bottom[0, 2]) == pytest.approx((3.1 - (2 * np.pi - 3.1)) / 0.1, rel=1e-4)
    e = np.array([0.25, 10.0, 4.0])
    huber = np.where(np.abs(e) <= 1, 0.5 * e**2, np.abs(e) - 0.5)
    assert float(readout_loss(errors)) == pytest.approx(huber.mean(), rel=1e-5)


def test_the_typical_read_error_leaves_out_the_frames_the_first_stage_does() -> None:
    config = ReadOutConfig(state_dim=5, read=(0, 1, 2), angles=((1, 2),),
                           velocities=((3, 0), (4, 1, 2)), gains=(1.0, 1.0),
                           encoder=MLPConfig(layers=1, units=4))
    readout = StateReadOut(config, features=3)
    readout.set_standardisation(np.zeros(3), np.array([2.0, 0.1, 0.1]))
    with torch.no_grad():  # features are the read components in spreads
        readout.head.weight.copy_(torch.eye(3))
        readout.head.bias.zero_()
    upright = [1.0, 0.0, 0.0, 0.0]
    # x read 0.5 off at x = 1 (typical), and 50 off at x = 100, 50 spreads from the median.
    state = torch.tensor([[1.0, *upright], [100.0, *upright]])
    features = torch.tensor([[1.5 / 2, 10.0, 0.0], [0.0, 10.0, 0.0]])
    every = np.sqrt((0.25**2 + 50.0**2) / 6)
    assert readout.error(features, state) == pytest.approx(every, rel=1e-5)
    assert readout.error(features, state, ReadOutStage().typical_spreads) == pytest.approx(
        np.sqrt(0.25**2 / 3), rel=1e-5)
    assert np.isnan(readout.error(features[1:], state[1:], ReadOutStage().typical_spreads))


def test_exact_positions_rebuild_ds_state_and_the_teachers_embedding(inputs) -> None:
    _, _, teacher, rows = inputs
    config = _paired(rows)
    student = Student(student_preset("tiny", teacher.config, readout=config))
    copy_teacher_filter(student, teacher.world_model)
    episode = slice(0, int(np.flatnonzero(rows.episode_start == rows.episode_start[0]).size))
    state = rows.state[episode][None]  # [1, T, S], one whole episode
    is_first = torch.zeros(state.shape[:2], dtype=torch.bool)
    is_first[0, 0] = True
    rebuilt = student.perception.readout.window_state(state[..., :3], is_first)
    torch.testing.assert_close(rebuilt[0, 1:], state[0, 1:], atol=1e-4, rtol=1e-4)
    assert torch.equal(rebuilt[0, 0, 3:], torch.zeros(2))  # no frame before the first
    wm = teacher.world_model
    with torch.no_grad():
        torch.testing.assert_close(student.perception.embed_state(rebuilt)[0, 1:],
                                   wm.embed(state)[0, 1:], atol=1e-4, rtol=1e-4)


def test_a_window_in_mid_episode_reads_its_first_velocity_from_the_frame_before(inputs) -> None:
    _, _, teacher, rows = inputs
    student = Student(student_preset("tiny", teacher.config, readout=_paired(rows)))
    readout = student.perception.readout
    state = rows.state[5:15][None]  # [1, 10, S]: steps 5-14 of the first episode
    is_first = torch.zeros(state.shape[:2], dtype=torch.bool)
    with_before = readout.window_state(state[..., 1:, :3], is_first[:, 1:], state[:, 0, :3])
    # The synthetic integrator is exact: every step's velocity is the true one, the first too.
    torch.testing.assert_close(with_before[0], state[0, 1:], atol=1e-4, rtol=1e-4)
    without = readout.window_state(state[..., 1:, :3], is_first[:, 1:])
    assert torch.equal(without[0, 0, 3:], torch.zeros(2))
    # At an episode's first step there is no step before, whatever is handed.
    is_first[:, 1] = True
    at_first = readout.window_state(state[..., 1:, :3], is_first[:, 1:], state[:, 0, :3])
    assert torch.equal(at_first[0, 0, 3:], torch.zeros(2))


def test_a_readout_students_windows_come_with_the_frame_before_them(inputs) -> None:
    dataset, _, _, _ = inputs
    data = open_dataset(dataset)
    config = distil_preset("tiny", "readout", steps=2)
    assert config.window_context == 1
    assert replace_fields(config, {"readout_stage.first_velocity": "zero"}).window_context == 0
    assert distil_preset("tiny", "paper").window_context == 0
    drawn = WindowSampler(data, config.sampler("train", 3, batch_size=32)).batch()
    assert drawn["image"].shape[1] == config.length + 1
    windows = split_context({k: torch.as_tensor(v) for k, v in drawn.items()}, 1)
    assert windows["image"].shape[1] == windows["state"].shape[1] == config.length
    assert torch.equal(windows["start"], torch.as_tensor(drawn["start"]) + 1)
    for b in range(32):
        step, view = int(drawn["start"][b]), int(drawn["view"][b, 0])
        frame = np.empty((1, *data.spec.image_shape), np.uint8)
        data.read_frames(np.array([step]), np.array([view]), frame)
        assert np.array_equal(windows["image_before"][b].numpy(), frame[0])
        assert torch.equal(windows["state"][b, 0], torch.as_tensor(data.column("state")[step + 1]))


@pytest.mark.parametrize(("stage_optimiser", "expected"), [("reset", 2), ("keep", 4 + 2)])
def test_updates_on_windows_after_a_first_stage_start_a_fresh_optimiser(
        inputs, tmp_path: Path, stage_optimiser: str, expected: int) -> None:
    dataset, teacher_path, _, _ = inputs
    config = distil_preset("tiny", "readout", steps=2, stage_optimiser=stage_optimiser)
    distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    moments = read_checkpoint(tmp_path / "run" / "student.pt").optimisers["student"]["state"]
    # AdamW counts the steps each parameter took since its moments began.
    assert moments and {int(m["step"]) for m in moments.values()} == {expected}


def test_an_angle_difference_is_wrapped_whatever_the_pairs_length() -> None:
    config = ReadOutConfig(state_dim=5, read=(0, 1, 2), angles=((1, 2),),
                           velocities=((3, 0), (4, 1, 2)), gains=(10.0, 2.0),
                           encoder=MLPConfig(layers=1, units=4))
    readout = Student(StudentConfig(readout=config)).perception.readout
    before = torch.tensor([0.5, np.cos(3.1), np.sin(3.1)], dtype=torch.float32)
    after = torch.tensor([0.7, np.cos(-3.1), np.sin(-3.1)], dtype=torch.float32)
    state = readout.state(after, before)
    expected_turn = 2 * np.pi - 6.2  # across the bottom: +0.083, not -6.2
    torch.testing.assert_close(state, torch.tensor([0.7, np.cos(-3.1), np.sin(-3.1), 10 * 0.2,
                                                    2 * expected_turn], dtype=torch.float32))
    # A pair off the circle turns by its angle alone, whatever its length.
    longer = readout.state(torch.cat([after[:1], 3 * after[1:]]), before)
    assert float(longer[4]) == pytest.approx(2 * expected_turn, rel=1e-5)


def _handed(readout, angles: list[float], median: float = 0.0) -> torch.Tensor:
    """What ``readout.positions`` hands the filter when its head reads the cart at 0 and the
    pole at each of ``angles`` (radians), D's median angle being ``median``: the head's
    weights zeroed, so that its bias alone sets the reading."""
    readout.set_standardisation(np.array([0.0, np.cos(median), np.sin(median)]), np.ones(3))
    readout.head.weight.data.zero_()
    handed = []
    with torch.no_grad():
        for angle in angles:
            read = torch.tensor([0.0, np.cos(angle), np.sin(angle)], dtype=torch.float32)
            readout.head.bias.copy_(read - readout.mean)
            handed.append(readout.positions(torch.zeros(1, readout.head.in_features))[0])
    return torch.stack(handed)


def _angle(positions: torch.Tensor) -> torch.Tensor:
    return torch.atan2(positions[..., 2], positions[..., 1])


def test_a_leaned_readout_hands_on_the_angle_further_from_ds_median(inputs) -> None:
    config = dataclasses.replace(_paired(inputs[3]), lean=1.25)
    readout = Student(StudentConfig(readout=config)).perception.readout
    angles = [0.0, 0.1, -0.2, np.pi / 2, 3.0, -3.1]
    handed = _handed(readout, angles)
    # By hand, about D's median angle (0 here): d + 0.25 sin d; the cart's reading untouched.
    expected = torch.tensor([a + 0.25 * np.sin(a) for a in angles], dtype=torch.float32)
    torch.testing.assert_close(_angle(handed), expected, atol=1e-5, rtol=0)
    assert torch.equal(handed[:, 0], torch.zeros(len(angles)))
    # Near upright that is 1.25 times the angle; monotone round to a fallen pole, which stays.
    assert float(_angle(handed[1])) == pytest.approx(0.125, rel=2e-3)
    fine = np.linspace(-np.pi + 1e-3, np.pi - 1e-3, 721).tolist()
    assert (torch.diff(_angle(_handed(readout, fine))) > 0).all()
    # About a median of 0.3 rad (no mirror turns this angle over).
    assert float(_angle(_handed(readout, [0.4], median=0.3)[0])) == pytest.approx(
        0.4 + 0.25 * np.sin(0.1), abs=1e-5)
    # The rebuilt angular velocity is the gain times the turn of the leaned readings.
    before, after = _handed(readout, [0.1, 0.2])
    turn = (0.2 + 0.25 * np.sin(0.2)) - (0.1 + 0.25 * np.sin(0.1))
    assert float(readout.state(after, before)[4]) == pytest.approx(config.gains[1] * turn,
                                                                   rel=1e-4)


def test_a_leaned_mirror_averaged_reading_stays_mirror_symmetric(inputs) -> None:
    dataset, _, teacher, rows = inputs
    torch.manual_seed(2)
    config = dataclasses.replace(_mirrored(rows), lean=1.5)
    student = Student(student_preset("tiny", teacher.config, readout=config)).eval()
    # D's median angle off 0 must not matter: the mirror turns the angle over about 0.
    student.perception.readout.set_standardisation(np.array([0.0, np.cos(0.2), np.sin(0.2)]),
                                        np.array([1.0, 0.1, 0.1]))
    data = open_dataset(dataset)
    images = np.empty((4, *data.spec.image_shape), np.uint8)
    data.read_frames(np.arange(4), np.zeros(4, int), images)
    image = torch.as_tensor(images)
    with torch.no_grad():
        _, read = student.step_embed(image, None)
        _, read_of_mirror = student.step_embed(image.flip(-2), None)
    torch.testing.assert_close(read_of_mirror, torch.tensor(config.mirror) * read)


def test_a_lean_outside_its_range_or_without_a_readout_is_refused() -> None:
    with pytest.raises(ConfigError, match=re.escape(
            "lean must lie in (0, 2) for the reading's map to stay monotone, got 2.0")):
        ReadOutConfig(state_dim=1, lean=2.0)
    with pytest.raises(ConfigError, match=re.escape("lean must lie in (0, 2), got 0.0")):
        distil_preset("tiny", "readout", readout_lean=0.0)
    with pytest.raises(ConfigError, match=re.escape(
            "readout_stage.lean=1.25 leans a read-out's angles; only a read-out student")):
        distil_preset("tiny", "dense", readout_lean=1.25)
    # A bundle written before the lean existed reads its angles as read.
    stored = json.loads(json.dumps(to_json(StudentConfig(readout=ReadOutConfig(state_dim=1)))))
    del stored["readout"]["lean"]
    assert from_json(StudentConfig, stored).readout.lean == 1.0


def test_the_step_path_acts_on_what_the_window_path_filters(inputs) -> None:
    dataset, _, teacher, rows = inputs
    torch.manual_seed(0)
    student = Student(student_preset("tiny", teacher.config, readout=_paired(rows))).eval()
    copy_teacher_filter(student, teacher.world_model)
    data = open_dataset(dataset)
    images = np.empty((6, *data.spec.image_shape), np.uint8)
    data.read_frames(np.arange(6), np.zeros(6, int), images)
    image = torch.as_tensor(images)
    is_first = torch.tensor([[True, False, False, False, False, False]])
    with torch.no_grad():
        window = student.embed(image[None], is_first)[0]
        history = None
        for t in range(6):
            step, history = student.step_embed(image[t:t + 1], history)
            torch.testing.assert_close(step[0], window[t], atol=1e-5, rtol=1e-5)


def test_a_pooling_student_acts_on_what_its_windows_filter(inputs) -> None:
    dataset, _, _, rows = inputs
    is_first = rows.steps == rows.episode_start
    state = _with_goal(rows, np.cumsum(is_first) / 10.0)
    torch.manual_seed(0)
    teacher = Teacher(teacher_preset("tiny", 6, 1)).eval()
    config = pair_velocities(state, is_first, GOAL_LAYOUT, MLPConfig(layers=2, units=32))
    config = dataclasses.replace(config, pooled=episode_constants(state, is_first, (3,)))
    student = Student(student_preset("tiny", teacher.config, readout=config)).eval()
    copy_teacher_filter(student, teacher.world_model)
    images = np.empty((6, *open_dataset(dataset).spec.image_shape), np.uint8)
    open_dataset(dataset).read_frames(np.arange(6), np.zeros(6, int), images)
    image = torch.as_tensor(images)
    with torch.no_grad():
        window = student.embed(image[None], torch.tensor([[True] + [False] * 5]))[0]
        reading = student.perception.read_positions(image)
        history = None
        for t in range(6):
            step, history = student.step_embed(image[t:t + 1], history)
            torch.testing.assert_close(step[0], window[t], atol=1e-5, rtol=1e-5)
    # The goal handed on is the mean of the frames read so far.
    torch.testing.assert_close(history[0, 3], reading[:, 3].mean())
    assert int(history[0, -1]) == 6


def test_gradients_reach_the_cnn_and_never_the_teachers_filter(inputs) -> None:
    dataset, _, teacher, rows = inputs
    config = distil_preset("tiny", "readout")
    student = Student(student_preset("tiny", teacher.config, readout=_paired(rows)))
    copy_teacher_filter(student, teacher.world_model)
    from twist_data.sampler import WindowSampler

    windows = WindowSampler(open_dataset(dataset), config.sampler("all", 0)).batch()
    loss, _ = Distillation(student, teacher, config)(
        {k: torch.as_tensor(windows[k]) for k in ("image", "state", "action", "is_first")})
    loss.backward()
    assert student.perception.encoder.net[0].weight.grad.abs().sum() > 0
    assert student.perception.readout.head.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in student.rssm.parameters())
    assert all(p.grad is None for p in student.perception.readout.encoder.parameters())
    assert all(p.grad is None for p in teacher.parameters())
    # The first stage's term reaches the CNN too.
    student.zero_grad(set_to_none=True)
    features = student.perception.encoder(torch.as_tensor(windows["image"][:, 0]))
    student.perception.readout.loss(features, torch.as_tensor(windows["state"][:, 0]),
                         ReadOutStage().huber_delta).backward()
    assert student.perception.encoder.net[0].weight.grad.abs().sum() > 0


def test_the_readout_recipe_travels_with_the_run_and_the_bundle(inputs, tmp_path: Path) -> None:
    dataset, teacher_path, teacher, _ = inputs
    config = distil_preset("tiny", "readout", frame_eval_every=2)
    assert config.readout and config.frame_steps == 4 and config.encoder_norm == "layer"
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    assert stored_config(tmp_path / "run") == config
    student, extra = load_student(summary.student)
    assert extra["distil"]["recipe"] == "readout"
    assert from_json(StudentConfig, to_json(student.config)) == student.config
    # The filter the student acts through is still the teacher's, after training.
    for name, weight in teacher.world_model.rssm.state_dict().items():
        assert torch.equal(student.rssm.state_dict()[name], weight), name
    agent = Agent.load(summary.agent)
    assert agent.info["recipe"] == "readout" and agent.config.student.readout.velocities
    assert torch.equal(agent.student.perception.readout.scale, student.perception.readout.scale)
    assert (agent.student.perception.readout.scale != 1).all()  # D's spread, not the initial value
    first_stage = Agent.load(tmp_path / "run" / "agent-00000000.pt")
    assert first_stage.info["frame_updates"] == 4 and first_stage.info["student_updates"] == 0
    image = np.zeros((64, 64, 3), np.uint8)
    _, state = agent.act(image)
    _, state = agent.act(image, state)
    assert state.frames.shape == (1, 3)  # the last read-out: x, cos, sin
    assert "read_error" in (tmp_path / "run" / "heldout.csv").read_text().splitlines()[0]


def test_a_readout_trained_from_a_resident_copy_of_d_is_the_same_student(
        inputs, tmp_path: Path) -> None:
    dataset, teacher_path, _, _ = inputs
    students = {}
    for resident in ("off", "on"):
        config = distil_preset("tiny", "readout", resident_data=resident, readout_mirror="augment")
        summary = distil(dataset, tmp_path / resident, config, teacher=teacher_path)
        students[resident] = load_student(summary.student)[0].state_dict()
    frames = [pd.read_csv(tmp_path / r / "frame-metrics.csv") for r in ("off", "on")]
    assert len(frames[0]) > 0 and frames[0]["loss"].equals(frames[1]["loss"])
    for name, weight in students["off"].items():
        assert torch.equal(students["on"][name], weight), name


def test_a_readout_runs_agreement_curve_advances_with_its_single_frame_updates(
        inputs, tmp_path: Path) -> None:
    dataset, teacher_path, _, _ = inputs
    distil(dataset, tmp_path / "run", distil_preset("tiny", "readout", frame_eval_every=2),
           teacher=teacher_path)
    heldout = pd.read_csv(tmp_path / "run" / "heldout.csv")
    # No update on windows at all: the curve's place is the single-frame updates.
    assert list(heldout["updates"]) == [0, 0, 0]
    assert list(student_progress(heldout)) == [0, 2, 4]
    assert heldout["read_error_typical"].notna().all()
    scalars, images = board_events(tmp_path / "run")
    assert [step for step, _ in scalars["heldout/read_error"]] == [0, 2, 4]
    assert [step for step, _ in images["heldout/latent-agreement"]] == [4]
    height, width = images["heldout/latent-agreement"][-1][1]
    assert width > 3 * height  # three panels: h, the KLs and the read-out's error


def test_a_resumed_first_stage_grows_to_the_new_frame_steps(inputs, tmp_path: Path) -> None:
    dataset, teacher_path, _, _ = inputs
    config = distil_preset("tiny", "readout", frame_eval_every=2)
    first = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    longer = dataclasses.replace(config, frame_steps=8)
    summary = distil(dataset, tmp_path / "run", longer, teacher=teacher_path, resume=True)
    logged = pd.read_csv(tmp_path / "run" / "frame-metrics.csv")
    assert list(logged["frame_updates"]) == [2, 4, 6, 8]
    # Each invocation's rate is over its own updates alone: two rows of 2 updates each.
    rates = logged["updates_per_s"].to_numpy()
    assert first.frame_updates_per_second == pytest.approx(4 / (2 / rates[0] + 2 / rates[1]),
                                                           rel=1e-2)
    assert summary.frame_updates_per_second == pytest.approx(4 / (2 / rates[2] + 2 / rates[3]),
                                                             rel=1e-2)
    assert summary.updates_per_second == 0.0  # the read-out recipe trains on no windows
    assert Agent.load(summary.agent).info["frame_updates"] == 8
    assert stored_config(tmp_path / "run") == longer
    # Once windows have followed the first stage, it cannot grow any more.
    windows = dataclasses.replace(config, steps=2)
    distil(dataset, tmp_path / "windows", windows, teacher=teacher_path)
    with pytest.raises(DistilError, match=r"ended at 4 frame updates and 2 updates.*"
                                          r"frame_steps=8 cannot"):
        distil(dataset, tmp_path / "windows", dataclasses.replace(windows, frame_steps=8),
               teacher=teacher_path, resume=True)


def test_a_readout_student_reads_one_frame(inputs) -> None:
    config = _paired(inputs[3])
    with pytest.raises(ConfigError, match="frames=2"):
        StudentConfig(readout=config, frames=2)
    with pytest.raises(ConfigError, match="frames=2"):
        distil_preset("tiny", "readout", frames=2)
    with pytest.raises(ConfigError, match="cover the state's 5 components exactly once"):
        dataclasses.replace(config, read=(0, 1))


def test_a_velocity_the_teacher_never_reads_is_neither_paired_nor_read(inputs,
                                                                         tmp_path: Path) -> None:
    dataset, _, _, rows = inputs
    state = rows.state.numpy().copy()
    state[:, 4] = np.random.default_rng(0).normal(size=len(state))  # the rate of nothing
    is_first = rows.steps == rows.episode_start
    config = pair_velocities(state, is_first, LAYOUT, MLPConfig(), "synth", hidden=(4,))
    assert config.velocities == ((3, 0),) and config.hidden == (4,) and config.read == (0, 1, 2)
    assert config.moving == ()
    # A teacher of positions only: its student reads them and derives nothing.
    assert pair_velocities(state, is_first, LAYOUT, MLPConfig(), hidden=(3, 4)).velocities == ()
    with pytest.raises(ConfigError, match=r"nothing to read from an image \(hidden: \[0, 1, 2"):
        pair_velocities(state, is_first, LAYOUT, MLPConfig(), hidden=(0, 1, 2, 3, 4))
    # Such a teacher's filter, handed the exact positions and the paired velocity, embeds
    # what it embeds of D's true state, whatever the hidden velocity is there.
    base = teacher_preset("tiny", 5, 1)
    hidden = dataclasses.replace(base, world_model=dataclasses.replace(
        base.world_model, state_hidden=(4,)))
    torch.manual_seed(2)
    teacher = Teacher(hidden).eval()
    config = dataclasses.replace(config, encoder=hidden.world_model.state_mlp)
    student = Student(student_preset("tiny", teacher.config, readout=config))
    copy_teacher_filter(student, teacher.world_model)
    steps = int(np.flatnonzero(rows.episode_start == rows.episode_start[0]).size)
    truth = torch.as_tensor(state[:steps])[None].float()
    is_first_window = torch.zeros(truth.shape[:2], dtype=torch.bool)
    is_first_window[0, 0] = True
    rebuilt = student.perception.readout.window_state(truth[..., :3], is_first_window)
    assert torch.equal(rebuilt[..., 4], torch.zeros_like(rebuilt[..., 4]))
    with torch.no_grad():
        torch.testing.assert_close(student.perception.embed_state(rebuilt)[0, 1:],
                                   teacher.world_model.embed(truth)[0, 1:], atol=1e-4, rtol=1e-4)
    # And the distiller takes such a teacher, recording what its student leaves out.
    path = save_teacher(tmp_path / "hidden.pt", teacher)
    summary = distil(dataset, tmp_path / "run", distil_preset("tiny", "readout"), teacher=path)
    assert Agent.load(summary.agent).config.student.readout.hidden == (4,)


def test_the_readout_leaves_out_rare_far_frames_but_not_a_phase_of_the_task() -> None:
    # 100 frames: 5 atypical (a fallen pole, rare) or 40 (a swinging ball, a phase).
    rare = np.arange(100) >= 5
    common = np.arange(100) >= 40
    share = distil_preset("tiny", "readout").readout_stage.max_atypical_share
    assert 0.05 < share < 0.40  # the two cases straddle it
    np.testing.assert_array_equal(training_frames(rare, "auto", share), rare)
    assert training_frames(common, "auto", share).all()
    assert not training_frames(common, "auto", 0.5).all()  # a wider share keeps it typical
    np.testing.assert_array_equal(training_frames(common, "typical", share), common)
    assert training_frames(rare, "all", share).all()
    assert distil_preset("tiny", "readout").readout_stage.frames == "auto"
    with pytest.raises(ConfigError, match="frames must be one of auto, typical, all, "
                                          "got 'most'"):
        distil_preset("tiny", "readout", readout_frames="most")


def _mirrored(rows: FrameRows) -> ReadOutConfig:
    config = _paired(rows)
    return dataclasses.replace(config, mirror=tuple(SYNTH_MIRROR[i] for i in config.read))


def test_a_mirror_averaged_readout_reads_a_mirrored_view_as_the_mirrored_state(inputs) -> None:
    dataset, _, teacher, rows = inputs
    torch.manual_seed(1)
    student = Student(student_preset("tiny", teacher.config, readout=_mirrored(rows))).eval()
    data = open_dataset(dataset)
    images = np.empty((4, *data.spec.image_shape), np.uint8)
    data.read_frames(np.arange(4), np.zeros(4, int), images)
    image = torch.as_tensor(images)
    mirror = torch.tensor(student.perception.readout.config.mirror)
    with torch.no_grad():
        _, read = student.step_embed(image, None)
        _, read_of_mirror = student.step_embed(image.flip(-2), None)
        # By hand: the mean of both readings, the mirror's mirrored back, x kept and the
        # (cos, sin) pair put on the unit circle.
        ro = student.perception.readout
        mean = (ro.read(student.perception.encoder(image)) + mirror * ro.read(student.perception.encoder(
            image.flip(-2)))) / 2
    torch.testing.assert_close(read[:, 0], mean[:, 0])
    torch.testing.assert_close(read[:, 1:], mean[:, 1:] / mean[:, 1:].norm(dim=-1, keepdim=True))
    # Averaged over the mirror, the reading is mirror-symmetric whatever the weights.
    torch.testing.assert_close(read_of_mirror, mirror * read)
    plain = Student(student_preset("tiny", teacher.config, readout=_paired(rows))).eval()
    plain.load_state_dict(student.state_dict())
    with torch.no_grad():
        assert not torch.allclose(plain.step_embed(image.flip(-2), None)[1],
                                  mirror * plain.step_embed(image, None)[1], atol=1e-3)


def test_mirror_augmentation_mirrors_each_frames_state_with_it(inputs, tmp_path: Path,
                                                                monkeypatch) -> None:
    from twist_models.readout import StateReadOut

    dataset, teacher_path, _, _ = inputs
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    encode = ImageEncoder.forward

    def recording_encoder(self, image: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled():  # the first stage's training pass
            seen.append((image.detach().clone(), None))
        return encode(self, image)

    loss = StateReadOut.loss

    def recording_loss(self, features, state, *args):
        if seen and seen[-1][1] is None:
            seen[-1] = (seen[-1][0], state.clone())
        return loss(self, features, state, *args)

    monkeypatch.setattr(ImageEncoder, "forward", recording_encoder)
    monkeypatch.setattr(StateReadOut, "loss", recording_loss)
    config = distil_preset("tiny", "readout", readout_mirror="augment", frame_steps=3,
                           frame_eval_every=3, frame_batch=32)
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    assert Agent.load(summary.agent).config.student.readout.mirror == (-1.0, 1.0, -1.0)
    data = open_dataset(dataset)
    states = torch.as_tensor(data.column("state"))
    frames = np.empty((1, *data.spec.image_shape), np.uint8)
    flipped = 0
    for images, state in seen:
        for image, target in zip(images[:, 0], state, strict=True):
            # Find the frame of D this sample is (its state is D's or D's mirrored) ...
            plain = (states - target).abs().sum(-1).argmin()
            mirrored = (states * torch.tensor(SYNTH_MIRROR) - target).abs().sum(-1).argmin()
            is_mirrored = bool(torch.allclose(states[mirrored] * torch.tensor(SYNTH_MIRROR),
                                              target)
                               and not torch.allclose(states[plain], target))
            step = int(mirrored if is_mirrored else plain)
            for view in range(data.spec.views):
                data.read_frames(np.array([step]), np.array([view]), frames)
                expected = torch.as_tensor(frames[0])
                if torch.equal(image, expected.flip(-2) if is_mirrored else expected):
                    break
            else:
                raise AssertionError(f"a frame of step {step} does not match its state")
            flipped += is_mirrored
    assert 0.3 < flipped / (32 * len(seen)) < 0.7


def test_mirroring_is_refused_for_other_students_and_tasks(inputs, tmp_path: Path,
                                                           monkeypatch) -> None:
    with pytest.raises(ConfigError, match="mirror must be one of none, average, "
                                          "augment, auto, got 'flip'"):
        distil_preset("tiny", "readout", readout_mirror="flip")
    with pytest.raises(ConfigError, match="only a read-out student"):
        distil_preset("tiny", "dense", readout_mirror="average")
    with pytest.raises(ConfigError, match=r"a sign \(\+1 or -1\) per read component \(3\)"):
        dataclasses.replace(_paired(inputs[3]), mirror=(-1.0, 1.0))
    monkeypatch.setattr(readout_recipe, "state_mirror", lambda task: ())
    with pytest.raises(ConfigError, match="task 'synthetic-cartpole' declares no mirror "
                                          "symmetry for its 5-component state"):
        distil(inputs[0], tmp_path / "run", distil_preset("tiny", "readout",
                                                          readout_mirror="average"),
               teacher=inputs[1])
    assert not (tmp_path / "run").exists()


def test_auto_mirroring_follows_the_tasks_declaration(inputs, tmp_path: Path,
                                                     monkeypatch) -> None:
    dataset, teacher_path, _, _ = inputs
    config = distil_preset("tiny", "readout", readout_mirror="auto", frame_eval_every=2)
    declared = distil(dataset, tmp_path / "declared", config, teacher=teacher_path)
    assert Agent.load(declared.agent).config.student.readout.mirror == (-1.0, 1.0, -1.0)
    monkeypatch.setattr(readout_recipe, "state_mirror", lambda task: ())
    undeclared = distil(dataset, tmp_path / "undeclared", config, teacher=teacher_path)
    assert Agent.load(undeclared.agent).config.student.readout.mirror == ()


def test_a_symlog_teachers_readout_student_embeds_its_reading_as_the_teacher_does(
        inputs, tmp_path: Path) -> None:
    dataset, _, _, _ = inputs
    config = teacher_preset("tiny", 5, 1)
    torch.manual_seed(4)
    teacher = Teacher(dataclasses.replace(config, world_model=dataclasses.replace(
        config.world_model, symlog=True))).eval()
    path = save_teacher(tmp_path / "teacher.pt", teacher)
    summary = distil(dataset, tmp_path / "run", distil_preset("tiny", "readout"), teacher=path)
    agent = Agent.load(summary.agent)
    assert agent.config.student.readout.symlog
    state = torch.randn(7, 5) * 30.0  # speeds of tens, where symlog and the raw state differ
    with torch.no_grad():
        torch.testing.assert_close(agent.student.perception.embed_state(state),
                                   teacher.world_model.encoder(state))


def test_a_resume_accepts_gains_measured_again_to_the_last_digits_only(
        inputs, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The gains are measured on D again at every start; with another BLAS thread count their
    # last digits change. A resume must accept that and keep the first measurement, and still
    # refuse gains that differ.
    dataset, teacher_path, _, _ = inputs
    config = distil_preset("tiny", "readout")
    first = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    gains = Agent.load(first.agent).config.student.readout.gains
    measure = readout_recipe.pair_readout

    def measured_again(factor: float):
        def pair(*args, **kwargs) -> ReadOutConfig:
            readout = measure(*args, **kwargs)
            return dataclasses.replace(readout, gains=tuple(g * factor for g in readout.gains))
        return pair

    longer = dataclasses.replace(config, frame_steps=config.frame_steps + 2)
    monkeypatch.setattr(readout_recipe, "pair_readout", measured_again(1 + 1e-13))
    summary = distil(dataset, tmp_path / "run", longer, teacher=teacher_path, resume=True)
    assert Agent.load(summary.agent).config.student.readout.gains == gains
    assert json.loads((tmp_path / "run" / "config.json").read_text()
                      )["student"]["readout"]["gains"] == list(gains)
    monkeypatch.setattr(readout_recipe, "pair_readout", measured_again(1 + 1e-3))
    # A resume with updates left to do (one with none returns before measuring anything).
    with pytest.raises(DistilError, match="the student's sizes differ"):
        distil(dataset, tmp_path / "run", dataclasses.replace(longer, frame_steps=9),
               teacher=teacher_path, resume=True)


def test_a_student_saved_with_its_former_key_layout_loads_and_reads_alike(inputs) -> None:
    # Students saved before perception was a part of its own kept the CNN and the read-out
    # at the top level ("encoder.", "readout."); their bundles must still load and act.
    dataset, _, teacher, rows = inputs
    torch.manual_seed(0)
    saved = Student(student_preset("tiny", teacher.config, readout=_paired(rows))).eval()
    copy_teacher_filter(saved, teacher.world_model)
    read = len(saved.config.readout.read)  # standardisation is a buffer: it must load too
    saved.perception.readout.set_standardisation(np.full(read, 0.5), np.full(read, 2.0))
    former = {k.replace("perception.", "", 1): v for k, v in saved.state_dict().items()}
    assert any(k.startswith("readout.") for k in former)
    torch.manual_seed(1)
    loaded = Student(saved.config).eval()
    loaded.load_state_dict(former)
    data = open_dataset(dataset)
    images = np.empty((4, *data.spec.image_shape), np.uint8)
    data.read_frames(np.arange(4), np.zeros(4, int), images)
    with torch.no_grad():
        torch.testing.assert_close(loaded.step_embed(torch.as_tensor(images), None),
                                   saved.step_embed(torch.as_tensor(images), None))


def _embedding_change(readout, before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """Mean squared change of the teacher's embedding between two batches of states."""
    with torch.no_grad():
        return (readout.encoder(after) - readout.encoder(before)).pow(2).sum(-1).mean()


def test_teacher_units_match_the_embeddings_change_under_small_errors(inputs) -> None:
    _, _, teacher, rows = inputs
    config = _paired(rows)
    student = Student(student_preset("tiny", teacher.config, readout=config))
    copy_teacher_filter(student, teacher.world_model)
    readout = student.perception.readout
    states = rows.state[:64]
    units = readout.teacher_units(states)
    # By finite differences: each slot's error moves the read component and, through the
    # derived velocity, that velocity by g * (e_t - e_{t-1}), of variance 2 g^2 e^2.
    eps, position = 1e-3, {i: k for k, i in enumerate(config.read)}
    expected = torch.zeros(len(config.read))
    for i in config.read:
        if any(i in pair for pair in config.angles):
            continue
        moved = states.clone()
        moved[:, i] += eps
        expected[position[i]] = _embedding_change(readout, states, moved) / eps**2
    (c, s), = config.angles
    angle = torch.atan2(states[:, s], states[:, c])
    for slot, (new_c, new_s) in {
            position[s]: (torch.cos(angle + eps), torch.sin(angle + eps)),  # turned
            position[c]: ((1 + eps) * states[:, c], (1 + eps) * states[:, s])}.items():  # longer
        moved = states.clone()
        moved[:, c], moved[:, s] = new_c, new_s
        expected[slot] = _embedding_change(readout, states, moved) / eps**2
    for k, velocity in enumerate(config.velocities):
        moved = states.clone()
        moved[:, velocity[0]] += eps
        expected[position[velocity[-1]]] += (2 * config.gains[k] ** 2
                                             * _embedding_change(readout, states, moved) / eps**2)
    torch.testing.assert_close(units, expected.rsqrt(), rtol=2e-2, atol=0.0)


def test_teacher_units_spend_the_loss_on_what_the_teachers_filter_reads() -> None:
    config = ReadOutConfig(state_dim=3, read=(0, 1), angles=(), velocities=((2, 0),),
                           gains=(1.0,), encoder=MLPConfig(layers=1, units=4))
    readout = StateReadOut(config, features=2)
    with torch.no_grad():
        readout.head.weight.copy_(torch.eye(2))
        readout.head.bias.zero_()
        readout.encoder[0].weight[:, 1] = 0.0  # the filter never reads component 1
    # Component 1 barely varies over D, so in robust spreads its error dominates the loss.
    readout.set_standardisation(np.zeros(2), np.array([1.0, 0.001]))
    states = torch.randn(32, 3)
    features = torch.tensor([[0.5, 0.0]])  # component 0 read 0.5 off
    tiny_error = torch.tensor([[0.0, 0.002, 0.0]])  # component 1 read 0.002 off (2 spreads)
    robust = readout.loss(features, tiny_error, delta=17.0)
    assert float(robust.detach()) == pytest.approx((0.5**2 + 2.0**2) / 4, rel=1e-5)
    readout.weigh_by_teacher(states)
    assert float(readout.loss_weight[1]) < 1e-4  # unread: its error no longer counts
    weighted = readout.loss(features, tiny_error, delta=17.0)
    unit = float(readout.teacher_units(states)[0])
    assert float(weighted.detach()) == pytest.approx(0.5 * (0.5 / unit) ** 2 / 2, rel=1e-3)
    # The weight is the loss's alone: reading and the reported error stay in robust spreads.
    assert float(readout.error(features, tiny_error)) == pytest.approx(
        np.sqrt((0.5**2 + 2.0**2) / 2), rel=1e-5)


def test_a_readout_trained_in_teacher_units_saves_and_resumes(inputs, tmp_path: Path) -> None:
    dataset, teacher_path, _, _ = inputs
    config = distil_preset("tiny", "readout", **{"readout_stage.units": "teacher"})
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher_path)
    agent = Agent.load(summary.agent)
    # Measured anew by each run from D and the teacher, so neither saved nor needed to act.
    assert not any("loss_weight" in key for key in agent.student.state_dict())
    longer = dataclasses.replace(config, frame_steps=config.frame_steps + 2)
    resumed = distil(dataset, tmp_path / "run", longer, teacher=teacher_path, resume=True)
    assert Agent.load(resumed.agent).info["frame_updates"] == config.frame_steps + 2
    assert stored_config(tmp_path / "run").readout_stage.units == "teacher"
    with pytest.raises(ConfigError, match=r"units.*'spreads'"):
        ReadOutStage(units="spreads")


# -- velocities that only motion shows -----------------------------------------------------
TRACKED = SynthConfig(episodes=16, steps=40, views=2, image_size=32, seed=3, tracked=True)
#: A CNN small enough for 32-pixel frames (32 -> 15 -> 6 -> 2).
SMALL_CNN = CNNConfig(depth=8, image_size=32, norm="layer", encoder_kernels=(4, 4, 3))


@pytest.fixture(scope="module")
def tracked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic cartpole seen by a camera that follows the cart: its state holds no cart
    position, so the cart's speed shows only as the floor's motion between two frames."""
    return write_synthetic_dataset(tmp_path_factory.mktemp("tracked") / "ds", TRACKED)


def _tracked_student(data) -> Student:
    state, first = data.column("state"), data.column("is_first").astype(bool)
    config = pair_velocities(state, first, data.spec.state_layout, MLPConfig(layers=1, units=8),
                             data.spec.task)
    student = Student(StudentConfig(action_dim=1, cnn=SMALL_CNN, readout=config))
    student.perception.readout.set_standardisation(*robust_standardisation(state, config),
                                                   motion_standardisation(state, config))
    return student


def test_a_tracked_speed_is_read_from_frame_pairs_and_from_nothing_less(tracked: Path) -> None:
    data = open_dataset(tracked)
    student = _tracked_student(data)
    readout = student.perception.readout
    # x_dot (2) pairs with no component the state holds; theta_dot (3) with the pole's angle.
    assert readout.config.moving == (2,) and readout.config.velocities == ((3, 0, 1),)
    k, n = data.spec.views, data.n_steps
    steps, views = np.repeat(np.arange(n), k), np.tile(np.arange(k), n)
    frames = {key: np.empty((n * k, 32, 32, 3), np.uint8) for key in ("image", PAIR_IMAGE)}
    for key, out in frames.items():
        data.read_frames(steps, views, out, key=key)
    state = torch.as_tensor(data.column("state")[steps])
    episode = np.searchsorted(data.episode_starts, steps, side="right") - 1
    train, test = np.flatnonzero(episode < 12), np.flatnonzero(episode >= 12)
    image = torch.as_tensor(frames["image"])

    def held_out_error(before: torch.Tensor) -> float:
        """The moving velocity's RMS error in robust spreads on the last four episodes after
        500 updates of the motion CNN on the first twelve, reading (before, frame)."""
        torch.manual_seed(0)
        probe = _tracked_student(data).perception
        params = [*probe.motion_encoder.parameters(), *probe.readout.motion.parameters()]
        optimiser = torch.optim.Adam(params, 1e-3)
        rng = np.random.default_rng(0)
        for _ in range(500):
            b = torch.as_tensor(rng.choice(train, 32))
            motion = probe.readout.read_motion(probe.motion_features(before[b], image[b]))
            loss = readout_loss(probe.readout.motion_errors(motion, state[b]))
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
        with torch.no_grad():
            motion = probe.readout.read_motion(probe.motion_features(before[test], image[test]))
            return float(probe.readout.motion_errors(motion, state[test]).pow(2).mean().sqrt())

    # Predicting D's median errs by the held-out spread of x_dot in robust spreads (~1.3).
    median = float(readout.motion_errors(readout.motion_mean.expand(len(test), 1),
                                         state[test]).pow(2).mean().sqrt())
    from_pairs = held_out_error(torch.as_tensor(frames[PAIR_IMAGE]))
    from_one_frame = held_out_error(image)  # the frame as its own pair: no motion to see
    assert from_pairs < 0.3 * median
    assert from_one_frame > 0.9 * median


def test_the_window_and_step_paths_read_motion_alike(tracked: Path) -> None:
    """Training reads each step's stored pair frame, acting the episode's previous frame: where
    those are the same pixels, both paths hand the filter the same state."""
    data = open_dataset(tracked)
    student = _tracked_student(data).eval()
    episode = data.episode(1)
    image = torch.as_tensor(episode.image[:, 0])[None]  # one view of one episode [1, T, ...]
    pair = torch.cat([image[:, :1], image[:, :-1]], 1)  # its previous frame, as acting keeps it
    is_first = torch.as_tensor(episode.is_first)[None]
    with torch.no_grad():
        window = student.perception.window(image, is_first, pair=pair)
        history, steps = None, []
        for t in range(image.shape[1]):
            embedded, history = student.perception.step(image[:, t], history)
            steps.append(embedded)
        torch.testing.assert_close(torch.stack(steps, 1), window, atol=1e-5, rtol=1e-5)
        with pytest.raises(ConfigError, match=r"components \[2\] are read from frame pairs"):
            student.perception.window(image, is_first)


def test_a_tracked_task_distils_end_to_end_and_its_agent_reads_the_frame_before(
        tmp_path: Path) -> None:
    dataset = write_synthetic_dataset(tmp_path / "ds", dataclasses.replace(
        DATA, tracked=True, length_jitter=0))
    torch.manual_seed(4)
    teacher = save_teacher(tmp_path / "teacher.pt", Teacher(teacher_preset("tiny", 4, 1)))
    config = distil_preset("tiny", "readout", steps=2)
    summary = distil(dataset, tmp_path / "run", config, teacher=teacher)
    agent = Agent.load(summary.agent)
    assert agent.config.student.readout.moving == (2,)
    assert agent.student.perception.motion_encoder is not None
    held = pd.read_csv(tmp_path / "run" / "heldout.csv")
    assert np.isfinite(held["read_error"]).all()
    episode = open_dataset(dataset).episode(0)
    state, actions = None, []
    for t in range(4):
        action, state = agent.act(episode.image[t, 0], state)
        actions.append(action)
    assert np.isfinite(np.stack(actions)).all()
    # The history holds the frame the next step pairs with its own.
    frame = torch.as_tensor(episode.image[3, 0]).float() / 255 - 0.5
    torch.testing.assert_close(state.frames[0, -frame.numel():], frame.flatten())
    # The same D without its pairs: refused in one sentence naming the command that adds
    # them, and nothing written.
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(dataset, bare)
    for folder in bare.glob(f"*.zarr/data/{PAIR_IMAGE}"):
        shutil.rmtree(folder)
    with pytest.raises(PairsMissingError, match=r"the readout recipe on "
                       r"synthetic-cartpole-tracked \(velocity components \[2\] pair with no "
                       r"component one frame shows: best correlations \[0\.\d+\], below "
                       r"readout_stage\.min_pairing 0\.7\) needs frame pairs .* twist-data "
                       r"render .*bare OUT --reproduce --pairs"):
        distil(bare, tmp_path / "refused", config, teacher=teacher)
    assert not (tmp_path / "refused").exists()


def test_no_registered_task_is_refused_by_the_readout() -> None:
    """Every task's velocities are derived or read from frame pairs: random-policy steps of
    each registered task give a read-out that covers its whole state."""
    from twist_sim.tasks import TASKS, TaskEnv, load_task_modules

    load_task_modules()
    for name in TASKS:
        env = TaskEnv(name, max_steps=40, seed=0)
        rng = np.random.default_rng(0)
        states, first = [], []
        for episode in range(3):
            step = env.reset(seed=episode)
            while True:
                states.append(step.state)
                first.append(step.is_first)
                if step.is_last:
                    break
                step = env.step(rng.uniform(-1, 1, env.action_dim))
        config = pair_velocities(np.stack(states), np.array(first), env.state_layout,
                                 MLPConfig(layers=1, units=8), name)
        derived = {v[0] for v in config.velocities}
        names = [block for block, size in env.state_layout for _ in range(size)]
        velocities = [i for i, block in enumerate(names) if block == "velocity"]
        assert derived | set(config.moving) == set(velocities), name
