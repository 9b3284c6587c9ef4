"""Policies that act in the simulator for several stages: the teacher on privileged state (the
collector's acting and every evaluation of an oracle), a distilled agent on its own renders
(the collector's DAgger episodes) and the random pushes that show the collector's teacher
states it would not visit on its own."""

from __future__ import annotations

import numpy as np
import torch

from twist_models.agent import Agent, AgentState
from twist_models.teacher import Teacher
from twist_sim.render import DRRenderer
from twist_sim.rollout import Policy
from twist_sim.tasks import Step


class RandomPushes:
    """Random shoves of one episode: on each step without a push under way one starts with
    probability 1 / ``every``, lasts 1..``longest`` steps (uniform) and holds one action
    drawn uniform in [-1, 1]^A. Seeded, so an episode's pushes are reproducible."""

    def __init__(self, every: int, longest: int, action_dim: int, seed: int) -> None:
        self.every, self.longest, self.action_dim = every, longest, action_dim
        self.rng = np.random.default_rng(seed)
        self.left = 0
        self.action = np.zeros(action_dim, np.float32)

    def __call__(self) -> np.ndarray | None:
        """This step's push action, or None when the policy acts."""
        if self.left == 0 and self.rng.random() < 1.0 / self.every:
            self.left = int(self.rng.integers(1, self.longest + 1))
            self.action = self.rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)
        if self.left == 0:
            return None
        self.left -= 1
        return self.action


def teacher_policy(teacher: Teacher, action_dim: int, device: torch.device | str = "cpu",
                   explore: bool = True, noise: float = 0.0, pushes: RandomPushes | None = None,
                   read: str = "sample") -> Policy:
    """The teacher as a rollout policy on privileged state: it filters its latent across the
    steps of an episode (reset at ``is_first``; z taken from the posterior as ``read`` says)
    and returns actions as numpy arrays, with Gaussian noise of std ``noise`` added (clipped
    to [-1, 1]), or, while one of ``pushes`` is under way, the push's action. The filter
    always sees the action taken."""
    latent = None
    previous = torch.zeros(1, action_dim, device=device)

    def act(step: Step) -> np.ndarray:
        nonlocal latent, previous
        state = torch.as_tensor(step.state, device=device).float()[None]
        # Only a first step needs is_first's masking (~100 us of the ~1 ms acting step); a
        # check inside the RSSM would cost training a device sync per step instead.
        first = torch.tensor([True], device=device) if step.is_first else None
        action, latent = teacher.policy(state, latent, previous, first, explore=explore,
                                        read=read)
        if noise:
            action = (action + noise * torch.randn_like(action)).clamp(-1.0, 1.0)
        push = pushes() if pushes is not None else None
        if push is not None:
            action = torch.as_tensor(push, device=device)[None]
        previous = action
        return action[0].cpu().numpy()

    return act


def student_policy(agent: Agent, renderer: DRRenderer, seed: int) -> Policy:
    """A distilled agent as a rollout policy for one episode: it renders each step itself (one
    view under ``renderer``'s DR, drawn from ``seed``) and acts on that image, filtering its
    latent across the episode's steps."""
    sampler = renderer.sampler(seed)
    sampler.begin_episode(seed)
    state: AgentState | None = None

    def act(step: Step) -> np.ndarray:
        nonlocal state
        image = renderer.render(step.physics, sampler.sample())[0]
        with torch.no_grad():
            action, state = agent.act(image, state)
        return action

    return act
