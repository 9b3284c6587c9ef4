"""Domain randomisation: backgrounds, parameter sampling, rendering, re-rendering."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import run_command
from twist_data.errors import ConfigError, SchemaMismatchError
from twist_data.reader import open_dataset
from twist_data.verify import verify_dataset
from twist_data.writer import ShardWriter
from twist_models.checkpoint import CheckpointError
from twist_models.teacher import find_teacher
from twist_sim import backgrounds
from twist_sim.backgrounds import (
    FAMILIES,
    background_files,
    bank_cache_path,
    blobs,
    clouds,
    directory_bank,
    draw_procedural,
    leaves,
    procedural_bank,
)
from twist_sim.errors import BackgroundError, PhysicsStateError
from twist_sim.randomisation import DR_PRESETS, VIEW_PARAMS, DRConfig, DRSampler, dr_preset
from twist_sim.render import DRRenderer
from twist_sim.render_process import RenderProcess, RenderProcessError
from twist_sim.rerender import (
    check_reproduction,
    render_blocks,
    renderer_for_block,
    reproduce_pairs,
    rerender_dataset,
)
from twist_sim.rollout import random_policy, record_episode, simulated_spec
from twist_sim.tasks import TaskEnv


@pytest.fixture
def renderer(gl: None) -> Iterator[DRRenderer]:
    with DRRenderer("cartpole-balance", dr_preset("train"), 32, 2) as r:
        yield r


# -- backgrounds ----------------------------------------------------------------------------

@pytest.mark.parametrize("source", ["train", "wide", "leaves"])
def test_training_and_heldout_banks_share_no_texture(source: str) -> None:
    train, heldout = procedural_bank(source, 50, 32), procedural_bank("heldout", 48, 32)
    assert not set(FAMILIES[source]) & set(FAMILIES["heldout"])
    families = {bank.source: {n.split("/")[0] for n in bank.names} for bank in (train, heldout)}
    assert families == {source: set(FAMILIES[source]), "heldout": set(FAMILIES["heldout"])}
    a = train.textures.reshape(len(train), -1).astype(np.int16)
    b = heldout.textures.reshape(len(heldout), -1).astype(np.int16)
    nearest = np.abs(a[:, None] - b[None]).mean(-1).min()
    assert nearest > 5, "some held-out texture is (nearly) a training texture"
    # Deterministic: the bank is a pure function of its arguments, and the seed matters.
    np.testing.assert_array_equal(procedural_bank(source, 50, 32).textures, train.textures)
    assert procedural_bank(source, 50, 32, seed=1).digest() != train.digest()


def test_a_drawn_bank_is_kept_on_disk_for_the_next_process(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    procedural_bank.cache_clear()  # as a new process starts
    drawn = draw_procedural("train", 6, 16, seed=2)
    path = bank_cache_path("train", 6, 16, 2)
    assert path.parent == tmp_path / "cache" / "twist" / "banks" and not path.exists()
    first = procedural_bank("train", 6, 16, seed=2)
    np.testing.assert_array_equal(first.textures, drawn)
    np.testing.assert_array_equal(np.load(path), drawn)
    # The next process reads the file and draws nothing.
    procedural_bank.cache_clear()
    with monkeypatch.context() as patch:
        patch.setattr(backgrounds, "draw_procedural", lambda *a: pytest.fail("drawn again"))
        again = procedural_bank("train", 6, 16, seed=2)
    assert again.digest() == first.digest() and not again.textures.flags.writeable
    # A file cut short or empty (a crash mid-write elsewhere) is drawn again and replaced.
    for damaged in (path.read_bytes()[:200], b""):
        path.write_bytes(damaged)
        procedural_bank.cache_clear()
        np.testing.assert_array_equal(procedural_bank("train", 6, 16, seed=2).textures, drawn)
        np.testing.assert_array_equal(np.load(path), drawn)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    # Another size or seed is another file; a cache that cannot be written costs only time.
    assert bank_cache_path("train", 6, 16, 3) != path != bank_cache_path("train", 6, 8, 2)
    (tmp_path / "a-file").write_text("not a folder")  # even root cannot make folders in it
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "a-file"))
    procedural_bank.cache_clear()
    try:
        np.testing.assert_array_equal(procedural_bank("train", 6, 16, seed=2).textures, drawn)
    finally:
        procedural_bank.cache_clear()


def test_wide_bank_adds_two_families_to_train_in_turn() -> None:
    assert set(FAMILIES["wide"]) == set(FAMILIES["train"]) | {"lines", "blobs"}
    bank = procedural_bank("wide", 10, 16)
    assert [n.split("/")[0] for n in bank.names] == list(FAMILIES["wide"]) * 2
    preset = DR_PRESETS["train-wide"]
    assert (preset.background, preset.background_count, preset.resample) == ("wide", 1024, "step")


def test_leaves_bank_adds_dead_leaves_to_wide_in_turn() -> None:
    assert set(FAMILIES["leaves"]) == set(FAMILIES["wide"]) | {"leaves"}
    bank = procedural_bank("leaves", 12, 16)
    assert [n.split("/")[0] for n in bank.names] == list(FAMILIES["leaves"]) * 2
    preset = DR_PRESETS["train-leaves"]
    assert (preset.background, preset.background_count, preset.resample) == ("leaves", 1024,
                                                                              "step")


def _spectrum_slope(image: np.ndarray) -> float:
    """Slope of log radially averaged amplitude against log spatial frequency."""
    grey = image.astype(np.float64).mean(-1)
    amplitude = np.abs(np.fft.fft2(grey - grey.mean()))
    k = np.fft.fftfreq(len(grey)) * len(grey)
    radius = np.hypot(k[:, None], k[None, :]).astype(int)
    radial = np.bincount(radius.ravel(), amplitude.ravel()) / np.maximum(
        np.bincount(radius.ravel()), 1)
    freqs = np.arange(4, len(grey) // 2)
    return float(np.polyfit(np.log(freqs), np.log(radial[freqs]), 1)[0])


def test_dead_leaves_have_the_amplitude_spectrum_of_photographs() -> None:
    """Photographs' amplitude falls about as 1/f (slopes -1.1 to -1.5 measured on eight at
    256 px, research/log.md); smooth textures fall faster (clouds about -1.8). Leaves
    that leave the ground bare, or blur too much, fall as fast as clouds."""
    slopes = [_spectrum_slope(leaves(np.random.default_rng([2, i]), 128)) for i in range(8)]
    assert -1.6 < float(np.median(slopes)) < -1.0, slopes
    smooth = [_spectrum_slope(clouds(np.random.default_rng([2, i]), 128)) for i in range(8)]
    assert float(np.median(smooth)) < -1.6, smooth


def test_blobs_computed_in_bounding_boxes_match_the_whole_image() -> None:
    """The same draws, each ellipse's cover computed over every pixel by hand."""
    for seed in range(4):
        rng, size = np.random.default_rng(seed), 96
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
        image = np.empty((size, size, 3), np.float32)
        image[:] = rng.uniform(0, 255, (1, 3))[0]
        for _ in range(int(rng.integers(4, 16))):
            cy, cx = rng.uniform(0, 1, 2)
            ry, rx = rng.uniform(0.03, 0.3, 2)
            angle = rng.uniform(0, np.pi)
            colour = rng.uniform(0, 255, (1, 3))[0]
            u = np.cos(angle) * (xx - cx) + np.sin(angle) * (yy - cy)
            v = np.cos(angle) * (yy - cy) - np.sin(angle) * (xx - cx)
            cover = np.clip(1.5 - (u / rx) ** 2 - (v / ry) ** 2, 0, 1)[..., None]
            image = image * (1 - cover) + cover * colour
        expected = np.clip(image, 0, 255).astype(np.uint8)
        got = blobs(np.random.default_rng(seed), size)
        assert np.abs(got.astype(int) - expected).max() <= 1
        assert len(np.unique(got.reshape(-1, 3), axis=0)) > 4, "no ellipse drawn"


def test_directory_bank_reads_images_and_video_frames(tmp_path: Path) -> None:
    red = np.zeros((40, 60, 3), np.uint8)
    red[..., 2] = 255  # BGR on disk
    cv2.imwrite(str(tmp_path / "a.png"), red)
    (tmp_path / "broken.jpg").write_bytes(b"not an image")
    (tmp_path / "notes.txt").write_text("ignored")
    writer = cv2.VideoWriter(str(tmp_path / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10,
                             (32, 32))
    for i in range(10):
        writer.write(np.full((32, 32, 3), 20 * i, np.uint8))
    writer.release()
    bank = directory_bank(tmp_path, 16, max_frames_per_video=4)
    assert bank.textures.shape == (5, 16, 16, 3)
    assert bank.names[0] == "a.png#0" and bank.names[1:] == tuple(f"clip.avi#{i}" for i in (0, 3, 6, 9))
    assert (bank.textures[0] == (255, 0, 0)).all()  # stored RGB
    assert bank.textures[4].mean() > bank.textures[1].mean() + 100


def test_background_directory_errors(tmp_path: Path) -> None:
    with pytest.raises(BackgroundError, match="does not exist"):
        directory_bank(tmp_path / "missing", 16)
    with pytest.raises(BackgroundError, match="has no images"):
        directory_bank(tmp_path, 16)
    (tmp_path / "x.png").write_bytes(b"garbage")
    with pytest.raises(BackgroundError, match=r"no file .* could be read"):
        directory_bank(tmp_path, 16)


# -- parameter sampling ---------------------------------------------------------------------

def _sampler(resample: str) -> DRSampler:
    config = DRConfig(resample=resample, friction_range=(0.5, 2.0))
    return DRSampler(config, np.full((5, 3), 0.5), views=3, n_backgrounds=10, max_offset=8, seed=0)


def test_per_step_sampling_changes_every_step() -> None:
    sampler = _sampler("step")
    sampler.begin_episode()
    a, b = sampler.sample(), sampler.sample()
    assert a["colour"].shape == (3, 5, 3) and a["background_offset"].shape == (3, 2)
    assert not np.array_equal(a["colour"], b["colour"])
    assert not np.array_equal(a["colour"][0], a["colour"][1])  # views are independent
    assert np.all(np.abs(a["colour"] - 0.5) <= 0.3 + 1e-6)
    assert a["background"].min() >= 0 and a["background"].max() < 10


def test_per_episode_sampling_is_constant_within_an_episode() -> None:
    sampler = _sampler("episode")
    dyn1 = sampler.begin_episode(seed=1)
    first = [sampler.sample() for _ in range(4)]
    for other in first[1:]:
        for key in first[0]:
            np.testing.assert_array_equal(first[0][key], other[key])
    dyn2 = sampler.begin_episode(seed=2)
    assert not np.array_equal(sampler.sample()["colour"], first[0]["colour"])
    assert dyn1 != dyn2 and 0.5 <= dyn1.friction_scale <= 2.0
    # An episode's draws are a function of its seed alone.
    again = _sampler("episode")
    assert again.begin_episode(seed=1) == dyn1
    np.testing.assert_array_equal(again.sample()["colour"], first[0]["colour"])


def test_config_validation_and_presets() -> None:
    assert DR_PRESETS["train"].resample == "step" and DR_PRESETS["train"].background == "train"
    assert DR_PRESETS["heldout"].resample == "episode" and DR_PRESETS["heldout"].background == "heldout"
    assert DRConfig.from_json(DR_PRESETS["heldout-full"].to_json()) == DR_PRESETS["heldout-full"]
    with pytest.raises(ConfigError, match="unknown DR preset 'bogus'"):
        dr_preset("bogus")
    with pytest.raises(ConfigError, match="colour_delta"):
        DRConfig(colour_delta=2.0)
    with pytest.raises(ConfigError, match="background_dir"):
        DRConfig(background="directory")
    with pytest.raises(ConfigError, match="light_range"):
        DRConfig(light_range=(2.0, 1.0))


#: Each per-factor evaluation preset and the view parameters (or, for physics, the episode's
#: dynamics) that are its factor.
FACTORS = {"heldout-camera": ("camera_shift", "camera_rotation"), "heldout-light": ("light",),
           "heldout-physics": ()}


@pytest.mark.parametrize("preset", sorted(FACTORS))
def test_a_per_factor_preset_draws_heldouts_scene_and_changes_only_its_factor(preset: str) -> None:
    def draws(name: str, seed: int) -> tuple[object, dict[str, np.ndarray]]:
        sampler = DRSampler(dr_preset(name), np.full((5, 3), 0.5), views=2, n_backgrounds=10,
                            max_offset=8)
        dynamics = sampler.begin_episode(seed)
        return dynamics, sampler.sample()

    changed = set()
    for seed in range(5):
        (dynamics, params), (base_dynamics, base) = draws(preset, seed), draws("heldout", seed)
        for key, value in params.items():
            if key in FACTORS[preset]:
                changed.add(key)
            else:
                np.testing.assert_array_equal(value, base[key], err_msg=f"{preset}: {key}")
        if preset == "heldout-physics":
            assert dynamics != base_dynamics
        else:
            assert dynamics == base_dynamics
    assert all(not np.array_equal(params[k], base[k]) for k in FACTORS[preset])
    assert changed == set(FACTORS[preset])
    assert dr_preset("heldout-full") == dr_preset("heldout").replace(
        **{f: getattr(dr_preset(p), f) for p in FACTORS for f in
           ("light_range", "camera_shift", "camera_rotation", "friction_range", "mass_range")
           if getattr(dr_preset(p), f) != getattr(dr_preset("heldout"), f)})


@pytest.mark.parametrize("preset", ["heldout-camera", "heldout-light"])
def test_a_per_factor_render_is_heldouts_with_that_factor_put_back(preset: str, gl: None) -> None:
    physics = _state()
    images = {}
    for name in ("heldout", preset):
        with DRRenderer("cartpole-balance", dr_preset(name), 32, 2) as r:
            sampler = r.sampler(4)
            sampler.begin_episode(4)
            params = sampler.sample()
            images[name] = r.render(physics, params)
            nominal = {**params, **{k: v for k, v in _nominal_view(params).items()
                                    if k in FACTORS[preset]}}
            images[name, "put back"] = r.render(physics, nominal)
    assert not np.array_equal(images[preset], images["heldout"])
    np.testing.assert_array_equal(images[preset, "put back"], images["heldout"])


def _nominal_view(params: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The camera and light parameters of an unmoved camera under nominal light."""
    return {"light": np.ones_like(params["light"]),
            "camera_shift": np.zeros_like(params["camera_shift"]),
            "camera_rotation": np.zeros_like(params["camera_rotation"])}


def _camouflage_sampler(share: float, grid: np.ndarray | None, seed: int = 0) -> DRSampler:
    config = DRConfig(low_contrast_share=share)
    return DRSampler(config, np.full((5, 3), 0.5), views=4, n_backgrounds=2, max_offset=8,
                     seed=seed, background_colours=grid)


def _two_textures() -> np.ndarray:
    """Colour grids of two 16-pixel textures: flat (0.1, 0.5, 0.9); red left half, blue right."""
    grid = np.zeros((2, 4, 4, 3), np.float32)
    grid[0] = (0.1, 0.5, 0.9)
    grid[1, :, :2], grid[1, :, 2:] = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    return grid


def test_camouflaged_bodies_take_a_colour_of_their_background_crop() -> None:
    # Nominal colours 0.5 and colour_delta 0.3: every colour lies in [0.2, 0.8].
    red, blue = (0.8, 0.2, 0.2), (0.2, 0.2, 0.8)
    sampler = _camouflage_sampler(1.0, _two_textures())
    sampler.begin_episode()
    seen = set()
    for _ in range(100):
        p = sampler.sample()
        assert np.all(np.abs(p["colour"] - 0.5) <= 0.3 + 1e-6)
        for v in range(4):
            body = tuple(round(float(c), 6) for c in p["colour"][v, 0])
            x = p["background_offset"][v, 1]
            if p["background"][v] == 0:
                assert body == (0.2, 0.5, 0.8)
            elif x == 0:  # an 8-pixel crop from column 0 shows only the red half
                assert body == red
            elif x == 8:
                assert body == blue
            else:
                assert body in (red, blue)
                seen.add(body)
    assert seen == {red, blue}


def test_low_contrast_share_is_the_share_of_camouflaged_views() -> None:
    grid = _two_textures()
    uniform, half = _camouflage_sampler(0.0, None), _camouflage_sampler(0.5, grid)
    uniform.begin_episode(seed=3)
    half.begin_episode(seed=3)
    first, camouflaged = uniform.sample(), half.sample()
    # Camouflage only redraws the body's colour: the rest is the uniform draw, same stream.
    for key in first:
        body_free = slice(None) if key != "colour" else (slice(None), slice(1, None))
        np.testing.assert_array_equal(first[key][body_free], camouflaged[key][body_free])
    flat = (0.2, 0.5, 0.8)
    hits = [np.allclose(p["colour"][v, 0], flat) for p in (half.sample() for _ in range(500))
            for v in range(4) if p["background"][v] == 0]
    assert 0.43 < np.mean(hits) < 0.57  # 0.5 +- 3 standard errors of ~1,000 draws
    with pytest.raises(ConfigError, match="colour grid"):
        _camouflage_sampler(0.5, None)
    with pytest.raises(ConfigError, match="low_contrast_share must be in"):
        DRConfig(low_contrast_share=1.5)
    with pytest.raises(ConfigError, match="needs a background bank"):
        DRConfig(background="none", low_contrast_share=0.5)


def test_colour_grid_area_averages_each_texture() -> None:
    bank = procedural_bank("train", 3, 32)
    grid = bank.colour_grid(4)
    assert grid.shape == (3, 4, 4, 3)
    expected = bank.textures[1, 8:16, 16:24].reshape(-1, 3).mean(0) / 255
    np.testing.assert_allclose(grid[1, 1, 2], expected, atol=1 / 255)


# -- rendering ------------------------------------------------------------------------------

def _state(task: str = "cartpole-balance", steps: int = 5) -> np.ndarray:
    env = TaskEnv(task)
    env.reset(seed=0)
    for _ in range(steps):
        env.step(np.full(env.action_dim, 0.5))
    return env.physics_state()


def test_render_is_deterministic_and_composites_the_background(renderer: DRRenderer) -> None:
    physics = _state()
    sampler = renderer.sampler(3)
    sampler.begin_episode()
    params = sampler.sample()
    images = renderer.render(physics, params)
    assert images.shape == (2, 32, 32, 3) and images.dtype == np.uint8
    np.testing.assert_array_equal(images, renderer.render(physics, params))
    # The top-left corner of a cartpole view is sky, so it shows the chosen texture crop.
    for v in range(2):
        y, x = params["background_offset"][v]
        texture = renderer.bank.textures[params["background"][v]]
        np.testing.assert_array_equal(images[v, 0, 0], texture[y, x])
        np.testing.assert_array_equal(images[v, 0, :4], texture[y, x:x + 4])


def test_render_parameters_change_the_picture(renderer: DRRenderer) -> None:
    physics = _state()
    sampler = renderer.sampler(0)
    sampler.begin_episode()
    params = sampler.sample()
    base = renderer.render(physics, params).astype(np.int32)
    dark = {**params, "light": np.full(2, 0.4, np.float32)}
    bright = {**params, "light": np.full(2, 1.6, np.float32)}
    assert renderer.render(physics, dark).sum() < base.sum() < renderer.render(physics, bright).sum()
    recoloured = {**params, "colour": 1.0 - params["colour"]}
    assert np.abs(renderer.render(physics, recoloured).astype(np.int32) - base).max() > 50
    moved = {**params, "camera_shift": np.tile(np.float32([0.3, 0.0, 0.0]), (2, 1))}
    assert not np.array_equal(renderer.render(physics, moved), base)


def test_render_rejects_bad_input(renderer: DRRenderer, gl: None) -> None:
    sampler = renderer.sampler(0)
    sampler.begin_episode()
    params = sampler.sample()
    with pytest.raises(PhysicsStateError, match="length 5"):
        renderer.render(np.zeros(7), params)
    with pytest.raises(ConfigError, match="'colour' must have shape"):
        renderer.render(_state(), {**params, "colour": params["colour"][:1]})
    with pytest.raises(ConfigError, match="background index out of range"):
        renderer.render(_state(), {**params, "background": np.array([0, 10_000], np.int32)})
    with pytest.raises(ConfigError, match="image_size must be a positive"):
        DRRenderer("cartpole-balance", dr_preset("train"), 0, 2)
    with pytest.raises(ConfigError, match="views"):
        DRRenderer("cartpole-balance", dr_preset("train"), 16, 0)


def _episode_states(n: int, task: str = "cartpole-balance") -> list[np.ndarray]:
    env = TaskEnv(task)
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    return [env.step(rng.uniform(-1, 1, env.action_dim)).physics for _ in range(n)]


@pytest.mark.parametrize("supersample", [1, 2])
def test_states_drawn_together_are_the_states_drawn_alone(gl: None, supersample: int) -> None:
    physics = _episode_states(6)
    with DRRenderer("cartpole-balance", dr_preset("heldout"), 32, 2, supersample) as alone, \
            DRRenderer("cartpole-balance", dr_preset("heldout"), 32, 2, supersample,
                       states=6) as together:
        sampler = alone.sampler(4)
        sampler.begin_episode()
        params = [sampler.sample() for _ in physics]
        expected = np.stack([alone.render(p, q) for p, q in zip(physics, params, strict=True)])
        batch = together.render_states(physics, params)
        assert batch.shape == (6, 2, 32, 32, 3)
        # Place 0 is where a state alone is drawn: pixel-identical. Elsewhere the rasteriser
        # rounds at another offset, so a pixel may move by one level.
        np.testing.assert_array_equal(batch[0], expected[0])
        assert np.abs(batch.astype(int) - expected).max() <= 1
        assert (batch != expected).mean() < 1e-3
        # A state's frames depend on its place, not on the states drawn beside it.
        reordered = together.render_states(physics[:0:-1], params[:0:-1], places=range(5, 0, -1))
        np.testing.assert_array_equal(reordered, batch[:0:-1])
        np.testing.assert_array_equal(together.render_states([physics[3]], [params[3]],
                                                             places=[3])[0], batch[3])
        with pytest.raises(ConfigError, match="distinct and in"):
            together.render_states(physics[:2], params[:2], places=[6, 1])
        with pytest.raises(ConfigError, match="one parameter set and place per state"):
            together.render_states(physics[:2], params[:1])


def test_closing_one_renderer_leaves_another_intact(gl: None) -> None:
    physics = _episode_states(1)[0]
    config = dr_preset("heldout")
    with DRRenderer("cartpole-balance", config, 32, 2, supersample=2) as alone:
        sampler = alone.sampler(0)
        sampler.begin_episode()
        params = sampler.sample()
        expected = alone.render(physics, params)
    closed = DRRenderer("cartpole-balance", config, 32, 2, supersample=2)
    with DRRenderer("cartpole-balance", config, 32, 2, supersample=2) as kept:
        closed.close()  # while the kept renderer's context is current
        np.testing.assert_array_equal(kept.render(physics, params), expected)


@pytest.mark.parametrize("task", ["cup-catch", "cheetah-run", "hopper-stand", "walker-walk",
                                  "finger-turn_easy"])
def test_every_task_renders_randomised_views(task: str, gl: None) -> None:
    with DRRenderer(task, dr_preset("heldout-full"), 24, 3) as r:
        sampler = r.sampler(0)
        sampler.begin_episode()
        images = r.render(_state(task, 3), sampler.sample())
    assert images.shape == (3, 24, 24, 3)
    assert images.std() > 10  # textured, not blank
    assert not np.array_equal(images[0], images[1])


def test_a_state_framed_by_another_is_seen_from_where_its_camera_stood(gl: None) -> None:
    env = TaskEnv("cheetah-run", 4, seed=0)
    env.reset()
    for _ in range(5):
        env.step(np.zeros(env.action_dim))
    current = env.physics_state()
    previous = current.copy()
    previous[1] -= 0.3  # the root 30 cm behind: physics is [time, qpos (rootx first), ...]
    with DRRenderer("cheetah-run", dr_preset("train-wide-full"), 64, 2, 2) as r:
        params = r.sampler(0).sample()
        now = r.render(current, params)
        framed = r.render_states([previous], [params], framed_by=[current])[0]
        # Its own render follows the body: the move hardly shows. Framed as the current step
        # is, it does.
        tracked = np.abs(r.render(previous, params).astype(np.int32) - now).mean()
        moved = np.abs(framed.astype(np.int32) - now).mean()
        assert moved > 3 * tracked > 0
        itself = r.render_states([current], [params], framed_by=[current])[0]
        np.testing.assert_array_equal(itself, now)
        np.testing.assert_array_equal(r.render(current, params), now)  # nothing left behind
    # A camera that tracks nothing frames both alike: the framing changes nothing.
    env = TaskEnv("cartpole-balance", 4, seed=0)
    env.reset()
    first = env.physics_state()
    second = env.step(np.ones(env.action_dim)).physics
    with DRRenderer("cartpole-balance", dr_preset("train-wide-full"), 32, 2) as r:
        params = r.sampler(1).sample()
        framed = r.render_states([first], [params], framed_by=[second])[0]
        np.testing.assert_array_equal(framed, r.render(first, params))


def test_pairs_redrawn_from_stored_physics_are_the_step_before_in_the_steps_scene(
        collected_tiny: Path) -> None:
    dataset = open_dataset(collected_tiny)
    starts = dataset.episode_starts
    steps = np.array([starts[0], starts[0] + 1, starts[1] + 7])
    pairs = reproduce_pairs(dataset, steps)
    stored = np.empty((3 * dataset.spec.views, *dataset.spec.image_shape), np.uint8)
    views = np.arange(dataset.spec.views)
    dataset.read_frames(np.repeat(steps, len(views)), np.tile(views, 3), stored)
    stored = stored.reshape(pairs.shape)
    np.testing.assert_array_equal(pairs[0], stored[0])  # a first step is its own pair
    physics, params = dataset.column("physics"), {
        p.name: dataset.column(f"dr/{p.name}") for p in VIEW_PARAMS}
    block = render_blocks(dataset.spec)[0]
    with renderer_for_block(dataset.spec.task, block) as renderer:
        for i, step in enumerate(steps[1:], 1):
            expected = renderer.render(physics[step - 1], {k: v[step] for k, v in params.items()})
            np.testing.assert_array_equal(pairs[i], expected)
            assert not np.array_equal(pairs[i], stored[i])  # the step before, not the step


# -- rendering in a child process ------------------------------------------------------------

def test_render_process_records_the_same_episode_as_in_process(gl: None) -> None:
    env = TaskEnv("cartpole-balance", max_steps=15)
    recorded = []
    for make in (DRRenderer, RenderProcess):
        # train-contrast: the child must hand the parent its bank's colours for camouflage.
        with make(env.name, dr_preset("train-contrast"), 24, 2) as r:
            provenance = r.provenance()
            # Two episodes: the second gather must not see the first one's frames.
            episodes = [record_episode(env, r, r.sampler(4), random_policy(1, seed), seed=seed)[0]
                        for seed in range(2)]
        recorded.append((provenance, episodes))
    (inline_provenance, inline), (child_provenance, child) = recorded
    assert child_provenance == inline_provenance
    for a, b in zip(inline, child, strict=True):
        assert b.image.shape == (16, 2, 24, 24, 3)
        np.testing.assert_array_equal(b.image, a.image)
        for key in a.dr:
            np.testing.assert_array_equal(b.dr[key], a.dr[key])
    assert not np.array_equal(child[0].image[:2], child[1].image[:2])


def test_render_process_reports_failures_and_recovers(gl: None) -> None:
    with RenderProcess("cartpole-balance", dr_preset("train"), 16, 2) as r:
        sampler = r.sampler(0)
        sampler.begin_episode()
        params = sampler.sample()
        r.submit(_state(), params)
        r.submit(np.zeros(7), params)  # the wrong physics length for cartpole
        with pytest.raises(RenderProcessError, match=r"PhysicsStateError.*length 5"):
            r.gather()
        r.submit(_state(), params)  # the failed batch is dropped, the next one is served
        assert r.gather().shape == (1, 2, 16, 16, 3)
        r._process.kill()
        r._process.wait()
        with pytest.raises(RenderProcessError, match="exited"):
            r.submit(_state(), params)
            r.gather()
    with pytest.raises(BackgroundError, match="nowhere"):
        RenderProcess("cartpole-balance", DRConfig(background="directory",
                                                   background_dir="/nowhere"), 16, 2)


# -- datasets: reproduce, re-render, add views ----------------------------------------------

@pytest.fixture(scope="module")
def sim_dataset(tmp_path_factory: pytest.TempPathFactory, gl: None) -> Path:
    """Two short finger episodes (target site in the physics vector), K=2, 24x24, train-full."""
    out = tmp_path_factory.mktemp("sim") / "ds"
    env = TaskEnv("finger-turn_easy", max_steps=12)
    with DRRenderer(env.name, dr_preset("train-full"), 24, 2) as r:
        sampler = r.sampler(0)
        with ShardWriter.create(out, "collector-000", simulated_spec(env, r)) as writer:
            for seed in range(2):
                writer.append(*record_episode(env, r, sampler, random_policy(2, seed), seed=seed))
    return out


def test_recorded_dataset_verifies_and_reproduces_pixel_exactly(sim_dataset: Path) -> None:
    assert verify_dataset(sim_dataset).ok
    ds = open_dataset(sim_dataset)
    assert ds.n_episodes == 2 and ds.n_steps == 26 and ds.spec.physics_dim == 13
    assert check_reproduction(ds, n_steps=26) == []
    # Per-step DR: consecutive steps have different parameters; dynamics recorded per episode.
    colour = ds.column("dr/colour")
    assert not np.array_equal(colour[0], colour[1])
    for seed in range(2):  # the episode's dynamics are the sampler's draw for its seed
        expected = DRSampler(dr_preset("train-full"), np.zeros((5, 3)), 2, 1, 0)
        friction = expected.begin_episode(seed).friction_scale
        assert ds.episode_info(seed).dr["friction_scale"] == np.float32(friction) != 1.0


def test_rerender_new_config_keeps_everything_but_images(sim_dataset: Path, tmp_path: Path) -> None:
    out = rerender_dataset(sim_dataset, tmp_path / "re", dr_preset("heldout"), views=3, seed=5)
    src, new = open_dataset(sim_dataset), open_dataset(out)
    assert new.spec.views == 3 and verify_dataset(out).ok
    for key in ("state", "physics", "action", "reward", "is_first"):
        np.testing.assert_array_equal(src.column(key), new.column(key))
    assert new.episode_info(1) == src.episode_info(1)
    background = new.column("dr/background")  # held-out: one draw per episode
    ends = new.episodes()["length"].cumsum().to_numpy()
    assert (background[: ends[0]] == background[0]).all()
    assert check_reproduction(new, n_steps=10) == []


def test_the_episode_resampled_training_preset_holds_one_scene_per_episode(
        sim_dataset: Path, tmp_path: Path) -> None:
    out = rerender_dataset(sim_dataset, tmp_path / "held", dr_preset("train-wide-episode"),
                           views=2, seed=3)
    new = open_dataset(out)
    assert DRConfig.from_json(new.spec.extra["render"][0]["config"]) == \
        dr_preset("train-wide-episode")
    ends = np.cumsum(new.episode_lengths)
    for key in ("background", "background_offset", "colour"):
        values = new.column(f"dr/{key}")
        first, second = values[:ends[0]], values[ends[0]:ends[1]]
        assert (first == first[0]).all() and (second == second[0]).all(), key
        assert not np.array_equal(first[0], second[0]), key  # drawn anew for each episode
    # Otherwise train-wide's: its bank and ranges.
    assert dataclasses.replace(dr_preset("train-wide-episode"), resample="step") == \
        dr_preset("train-wide")
    assert check_reproduction(new, n_steps=6) == []


def test_rerendering_chosen_episodes_renders_them_as_a_full_rerender_does(
        sim_dataset: Path, tmp_path: Path) -> None:
    full = open_dataset(rerender_dataset(sim_dataset, tmp_path / "all", dr_preset("heldout"),
                                         views=2, seed=5))
    last_path = rerender_dataset(sim_dataset, tmp_path / "last", dr_preset("heldout"), views=2,
                                 seed=5, episodes=[-1])
    last = open_dataset(last_path)
    assert last.n_episodes == 1 and verify_dataset(last_path).ok
    assert last.spec.extra["rerendered_episodes"] == [full.n_episodes - 1]
    np.testing.assert_array_equal(last.episode(0).image, full.episode(1).image)
    assert last.episode_info(0) == full.episode_info(1)
    assert not np.array_equal(full.episode(0).image[:5], full.episode(1).image[:5])
    with pytest.raises(ConfigError, match="dataset has 2 episodes; index 2 is out of range"):
        rerender_dataset(sim_dataset, tmp_path / "bad", dr_preset("heldout"), episodes=[0, 2])
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("preset", ["train-wide-full", "heldout-camera"])
def test_a_d_rerendered_under_a_preset_records_it_and_finds_its_sources_teacher(
        collected_tiny: Path, tmp_path: Path, preset: str) -> None:
    out = rerender_dataset(collected_tiny, tmp_path / "re", dr_preset(preset), views=1,
                           episodes=[0])
    block = render_blocks(open_dataset(out).spec)[-1]
    assert DRConfig.from_json(block["config"]) == dr_preset(preset)
    assert reproduce_check(out)
    # A re-rendered D holds no teacher of its own: it distils with its source's.
    assert find_teacher(out) == find_teacher(collected_tiny)
    # Without its source beside it or where it was recorded, none is found, and it says so.
    moved = tmp_path / "elsewhere" / "re"
    moved.parent.mkdir()
    out.rename(moved)
    assert find_teacher(moved) == find_teacher(collected_tiny)  # still where recorded
    for attributes in moved.glob("*/zarr.json"):  # as if its source had been deleted
        text = attributes.read_text()
        assert str(collected_tiny) in text
        attributes.write_text(text.replace(str(collected_tiny), str(tmp_path / "gone")))
    with pytest.raises(CheckpointError, match="expected one final teacher under"):
        find_teacher(moved)


def reproduce_check(dataset: Path) -> bool:
    """Whether the D's first steps rebuild from their stored DR draws exactly."""
    return check_reproduction(open_dataset(dataset), n_steps=4) == []


def test_rerender_add_views_keeps_the_original_views(sim_dataset: Path, tmp_path: Path) -> None:
    out = rerender_dataset(sim_dataset, tmp_path / "more", dr_preset("heldout"), views=1,
                           add_views=True)
    src, new = open_dataset(sim_dataset), open_dataset(out)
    assert new.spec.views == 3
    np.testing.assert_array_equal(new.episode(0).image[:, :2], src.episode(0).image)
    assert [b["views"] for b in new.spec.extra["render"]] == [[0, 2], [2, 3]]
    assert check_reproduction(new, n_steps=8) == []


def test_reproduction_detects_tampered_parameters(sim_dataset: Path, tmp_path: Path) -> None:
    import shutil

    import zarr

    copy = tmp_path / "copy"
    shutil.copytree(sim_dataset, copy)
    shard = zarr.open_group(str(copy / "collector-000.zarr"), mode="r+")
    light = shard["data/dr/light"]
    light[3] = light[3] * 0.5
    problems = check_reproduction(open_dataset(copy), n_steps=26)
    assert problems and all(p.startswith("step 3 view") for p in problems)


def test_a_dataset_from_another_camera_pose_is_not_re_rendered(sim_dataset: Path,
                                                              tmp_path: Path) -> None:
    import shutil

    import zarr

    ds = open_dataset(sim_dataset)
    [block] = render_blocks(ds.spec)
    env = TaskEnv(ds.spec.task, seed=0)
    camera = block["camera"]
    assert block["camera_pose"] == {"pos": env.model.cam_pos[camera].tolist(),
                                    "quat": env.model.cam_quat[camera].tolist(),
                                    "fovy": float(env.model.cam_fovy[camera])}
    copy = tmp_path / "copy"
    shutil.copytree(sim_dataset, copy)
    group = zarr.open_group(str(copy / "collector-000.zarr"), mode="r+")
    meta = dict(group.attrs["twist"])
    spec = dict(meta["spec"])
    pose = block["camera_pose"]
    moved = {**block, "camera_pose": {**pose, "fovy": pose["fovy"] + 5}}
    spec["extra"] = {**spec["extra"], "render": [moved]}
    meta["spec"] = spec
    group.attrs["twist"] = meta
    with pytest.raises(SchemaMismatchError, match=r"views 0-2 were rendered from camera pose .*fovy"):
        check_reproduction(open_dataset(copy), n_steps=4)


def test_rerender_cli_errors_leave_no_output(small_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "never"
    result = run_command("data", "render", str(small_dataset), str(out))
    assert result.returncode == 2
    assert result.stderr.strip().startswith("error: unknown task 'synthetic-cartpole'")
    assert "Traceback" not in result.stderr and not out.exists()


def test_record_cli_writes_a_verifiable_deterministic_dataset(tmp_path: Path, gl: None) -> None:
    def record(out: Path) -> None:
        done = run_command("data", "record", "cup-catch", str(out), "--episodes", "2",
                           "--max-steps", "4", "--image-size", "16", "--dr", "heldout-full",
                           "--seed", "7")
        assert done.returncode == 0, done.stderr

    record(tmp_path / "a")
    record(tmp_path / "b")
    a, b = open_dataset(tmp_path / "a"), open_dataset(tmp_path / "b")
    assert a.n_episodes == 2 and a.n_steps == 10 and a.spec.task == "cup-catch"
    assert verify_dataset(tmp_path / "a").ok
    for key in ("physics", "action", "dr/colour"):
        np.testing.assert_array_equal(a.column(key), b.column(key))
    np.testing.assert_array_equal(a.episode(1).image, b.episode(1).image)
    assert a.episodes()["env_step"].tolist() == [0, 8]  # 4 agent steps x action repeat 2


def test_a_texture_folder_holds_the_banks_families_in_turn_and_loads_as_backgrounds(
        tmp_path: Path) -> None:
    out = tmp_path / "bank"
    assert run_command("data", "textures", str(out), "--count", "7", "--size", "32",
                       "--bank", "wide").returncode == 0
    families = list(FAMILIES["wide"].items())
    files = background_files(out)
    assert [p.name for p in files] == [f"{i:05d}-{families[i % 5][0]}.png" for i in range(7)]
    for i, path in enumerate(files):  # each the family's own draw with the folder's seed
        expected = families[i % 5][1](np.random.default_rng([1, i]), 32)
        np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB),
                                      expected)
    assert len(directory_bank(out, 32).textures) == 7
    before = sorted(p.name for p in out.iterdir())
    refused = run_command("data", "textures", str(out), "--count", "2")
    assert refused.returncode != 0 and "already exists" in refused.stderr
    assert sorted(p.name for p in out.iterdir()) == before
    refused = run_command("data", "textures", str(tmp_path / "other"), "--bank", "nope")
    assert refused.returncode != 0 and "unknown texture bank 'nope'" in refused.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bank"]  # nothing half-written


def test_a_photo_folder_holds_matplotlibs_photograph_as_it_ships(tmp_path: Path) -> None:
    import matplotlib.cbook
    assert run_command("data", "photos", str(tmp_path / "photos")).returncode == 0
    shipped = cv2.imread(str(matplotlib.cbook.get_sample_data("grace_hopper.jpg",
                                                              asfileobj=False)))
    written = cv2.imread(str(tmp_path / "photos" / "grace_hopper.png"))
    np.testing.assert_array_equal(written, shipped)  # PNG keeps the decoded pixels exactly
    assert background_files(tmp_path / "photos")
