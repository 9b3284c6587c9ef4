"""How well does a read-out student read cartpole's pole in scenes it never saw?

A read-out student's closed-loop return on held-out scenes is a noisy measure of how its CNN
generalises (10 episodes, one scene each, and a fall decides an episode). This script
measures the read-out itself, offline, on the frames of D's held-out episodes (never trained
on: every ``holdout_every``-th episode), rendered again from their stored physics states
under each DR setting asked for: ``stored`` (D's own views, the training DR), ``train`` (new
scenes of the training families), ``heldout`` (the procedural held-out families), ``photo``
(a folder of photographs, ``--backgrounds``), or ``eval``: the held-out scenes of
``twist-eval --dr heldout --seeds 0``'s episodes, the i-th episode's scene on D's i-th held-out
episode, so that a scene's read-out error can be set beside the return the student scored in
it. One scene per episode, as ``twist-eval`` draws them.

Per setting it prints one JSON line: ``near_sine_rmse``, the read sine's RMS error over the
frames within ``--near`` degrees of upright (what the teacher's actor needs; a lean's sine),
``x_rmse`` over the same frames, ``scene_near_sine_rmse``, ``scene_sine_bias`` (the mean
error) and ``scene_x_rmse`` per episode (scene), and the number of scenes whose error
exceeds ``--bad`` (a scene where the pole is not read). With ``--trajectories`` it prints
one line per evaluated episode instead: the errors along the agent's own states before the
pole first leans past ``--near`` degrees, and after.

With ``--components`` (any task, not cartpole's lean alone) it prints per setting each read
component's RMS error in the state's units and the median and worst scene's RMS error in D's
robust spreads (the read-out's training units): a gap between ``train`` and ``heldout`` is
what the CNN loses on background kinds it never saw, apart from any closed-loop effect.

``python research/probes/readout_scenes.py AGENT.pt DATASET [--settings stored,heldout]
[--backgrounds DIR] [--episodes 30] [--near 10] [--bad 0.05] [--trajectories EVAL/trajectories]
[--components]``
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from twist_data.reader import open_dataset
from twist_data.sampler import heldout_episodes
from twist_data.seeding import derived_seed, evaluation_episode_seed
from twist_models.agent import Agent
from twist_sim.randomisation import dr_preset
from twist_sim.render import DRRenderer
from twist_sim.rerender import render_blocks

#: Cartpole's state layout: cart x, cos θ, sin θ, then the velocities.
X, COS, SIN = 0, 1, 2


@torch.no_grad()
def read_positions(agent: Agent, images: np.ndarray, batch: int = 256) -> np.ndarray:
    """The student's read-out of uint8 frames [N, H, W, 3] -> [N, R] (the pair on the circle)."""
    student, out = agent.student, []
    for i in range(0, len(images), batch):
        image = torch.from_numpy(images[i:i + batch])[:, None]
        features = student.perception.encoder(image).flatten(1).float()
        out.append(student.perception.readout.positions(features).numpy())
    return np.concatenate(out)


def rendered(dataset, episodes: np.ndarray, setting: str, backgrounds: str | None,
             seed: int) -> list[np.ndarray]:
    """Each episode's frames [T, H, W, 3] under ``setting`` (one scene per episode)."""
    spec = dataset.spec
    if setting == "stored":
        frames = []
        for index in episodes:
            frames.append(dataset.episode(int(index)).image[:, 0])
        return frames
    supersample = int(render_blocks(spec)[0]["supersample"])
    config = dr_preset("train" if setting == "train" else "heldout",
                       backgrounds if setting == "photo" else None).replace(resample="episode")
    frames = []
    with DRRenderer(spec.task, config, spec.image_height, 1, supersample) as renderer:
        sampler = renderer.sampler(seed)
        for i, index in enumerate(episodes):
            episode = dataset.episode(int(index))
            sampler.begin_episode(evaluation_episode_seed(seed, i) if setting == "eval"
                                  else derived_seed(seed, int(index)))
            images = np.empty((len(episode), spec.image_height, spec.image_width, 3), np.uint8)
            for t in range(len(episode)):
                renderer.render(episode.physics[t], sampler.sample(), out=images[t:t + 1])
            frames.append(images)
    return frames


def trajectory_errors(agent: Agent, dataset, folder: Path, name: str, seed: int,
                      near_sine: float) -> None:
    """Along each trajectory ``twist-eval --save-trajectories`` wrote for agent ``name``
    (seed ``seed``): its states rendered again in that episode's held-out scene, read, and
    compared with the truth; one JSON line per episode."""
    spec = dataset.spec
    supersample = int(render_blocks(spec)[0]["supersample"])
    read_index = list(agent.student.perception.readout.config.read)
    with DRRenderer(spec.task, dr_preset("heldout"), spec.image_height, 1,
                    supersample) as renderer:
        sampler = renderer.sampler(seed)
        for path in sorted(folder.glob(f"{name}-seed{seed}-episode*.npz"),
                           key=lambda p: int(p.stem.rsplit("episode", 1)[1])):
            episode = int(path.stem.rsplit("episode", 1)[1])
            state = np.load(path)["state"]
            sampler.begin_episode(evaluation_episode_seed(seed, episode))
            angle = np.arctan2(state[:, SIN], state[:, COS])
            physics = np.stack([np.zeros(len(state)), state[:, X], angle, state[:, 3],
                                state[:, 4]], 1)
            images = np.empty((len(state), spec.image_height, spec.image_width, 3), np.uint8)
            for t in range(len(state)):
                renderer.render(physics[t], sampler.sample(), out=images[t:t + 1])
            read = read_positions(agent, images)
            sine_error = read[:, read_index.index(SIN)] - state[:, SIN]
            x_error = read[:, read_index.index(X)] - state[:, X]
            near = (state[:, COS] > 0) & (np.abs(state[:, SIN]) < near_sine)
            fall = int(np.argmin(near)) if not near.all() else len(state)
            before = slice(0, fall)
            print(json.dumps({
                "episode": episode, "fall_step": fall,
                "sine_rmse_before_fall": round(float(np.sqrt(np.mean(sine_error[before] ** 2))), 4),
                "sine_bias_before_fall": round(float(np.mean(sine_error[before])), 4),
                "x_rmse_before_fall": round(float(np.sqrt(np.mean(x_error[before] ** 2))), 3),
                "sine_rmse_after": (round(float(np.sqrt(np.mean(sine_error[fall:] ** 2))), 3)
                                    if fall < len(state) else None)}), flush=True)


def component_errors(agent: Agent, dataset, episodes: np.ndarray, settings: list[str],
                     backgrounds: str | None, seed: int) -> None:
    """One JSON line per setting: each read component's RMS error and the scenes' errors in
    robust spreads."""
    readout = agent.student.perception.readout
    read = list(readout.config.read)
    scale = readout.scale.numpy().astype(np.float64)
    for setting in settings:
        frames = rendered(dataset, episodes, setting, backgrounds, seed)
        errors, scenes = [], []
        for index, images in zip(episodes, frames, strict=True):
            error = read_positions(agent, images) - dataset.episode(int(index)).state[:, read]
            errors.append(error)
            scenes.append(float(np.sqrt(np.mean((error / scale) ** 2))))
        error = np.concatenate(errors).astype(np.float64)
        print(json.dumps({"setting": setting, "episodes": len(scenes), "read_components": read,
                          "rmse": np.sqrt((error ** 2).mean(0)).round(4).tolist(),
                          "scene_rms_spreads_median": round(float(np.median(scenes)), 3),
                          "scene_rms_spreads_worst": round(float(np.max(scenes)), 3)}),
              flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("agent")
    parser.add_argument("dataset")
    parser.add_argument("--settings", default="stored,heldout")
    parser.add_argument("--backgrounds", default=None, help="photographs for the 'photo' setting")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--near", type=float, default=10.0)
    parser.add_argument("--bad", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trajectories", type=Path, default=None,
                        help="twist-eval --save-trajectories folder: read along its episodes")
    parser.add_argument("--name", default="readout", help="the agent's name there")
    parser.add_argument("--components", action="store_true",
                        help="every read component's error, for any task")
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    agent = Agent.load(args.agent)
    if agent.student.perception.readout is None:
        raise SystemExit(f"{args.agent} is not a read-out student")
    dataset = open_dataset(args.dataset)
    if args.trajectories is not None:
        trajectory_errors(agent, dataset, args.trajectories, args.name, args.seed,
                          math.sin(math.radians(args.near)))
        return
    held = np.flatnonzero(heldout_episodes(dataset.n_episodes, args.holdout_every))
    episodes = held[:args.episodes]
    if args.components:
        component_errors(agent, dataset, episodes, args.settings.split(","), args.backgrounds,
                         args.seed)
        return
    read_index = list(agent.student.perception.readout.config.read)
    near_sine = math.sin(math.radians(args.near))
    for setting in args.settings.split(","):
        frames = rendered(dataset, episodes, setting, args.backgrounds, args.seed)
        sq_sine, sq_x, scenes, biases, x_scenes = [], [], [], [], []
        for index, images in zip(episodes, frames, strict=True):
            state = dataset.episode(int(index)).state
            read = read_positions(agent, images)
            near = (state[:, COS] > 0) & (np.abs(state[:, SIN]) < near_sine)
            if not near.any():
                continue
            sine_error = read[near, read_index.index(SIN)] - state[near, SIN]
            x_error = read[near, read_index.index(X)] - state[near, X]
            sq_sine.append(sine_error ** 2)
            sq_x.append(x_error ** 2)
            scenes.append(float(np.sqrt(np.mean(sine_error ** 2))))
            biases.append(float(np.mean(sine_error)))
            x_scenes.append(float(np.sqrt(np.mean(x_error ** 2))))
        print(json.dumps({
            "setting": setting, "episodes": len(scenes),
            "near_sine_rmse": round(float(np.sqrt(np.mean(np.concatenate(sq_sine)))), 4),
            "x_rmse": round(float(np.sqrt(np.mean(np.concatenate(sq_x)))), 4),
            "scene_near_sine_rmse_median": round(float(np.median(scenes)), 4),
            "bad_scenes": int(np.sum(np.array(scenes) > args.bad)),
            "scene_near_sine_rmse": [round(s, 4) for s in scenes],
            "scene_sine_bias": [round(b, 4) for b in biases],
            "scene_x_rmse": [round(x, 3) for x in x_scenes]}), flush=True)


if __name__ == "__main__":
    main()
