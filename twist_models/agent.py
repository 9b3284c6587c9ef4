"""The deployable agent: the student's encoder and RSSM with the teacher's actor.

``Agent.load(path).act(image, state)`` is all an evaluator or a robot needs: the bundle holds
both models' weights and configs and the task it was trained for, and loads without
unpickling code (it is a twist checkpoint of kind ``agent``).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from twist_models.actor_critic import Actor
from twist_models.checkpoint import Checkpoint, read_checkpoint, restore, save_checkpoint
from twist_models.config import AgentConfig, from_json
from twist_models.rssm import State
from twist_models.student import Student
from twist_models.teacher import Teacher


@dataclass
class AgentState:
    """What the agent carries between steps of one episode (batch N)."""

    latent: State
    """The student's posterior state {k: [N, ...]}."""
    action: torch.Tensor
    """The previous action [N, A]."""
    frames: torch.Tensor | None = None
    """Embeddings of the previous ``frames - 1`` images, most recent first
    [N, frames - 1, E], or a read-out student's history (its last read-out [N, R] and what
    :class:`~twist_models.perception.StateReading` keeps beside it); None before the
    episode's first image."""


class Agent(nn.Module):
    """Acts from images: student filter -> teacher actor."""

    def __init__(self, config: AgentConfig, info: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.config = config
        self.student = Student(config.student)
        self.actor = Actor(config.student.rssm.feature_dim, config.student.action_dim,
                           config.actor_critic)
        self.info = dict(info or {})

    @classmethod
    def from_models(cls, student: Student, teacher: Teacher,
                    info: dict[str, Any] | None = None) -> Agent:
        """Bundle a trained student with its teacher's actor (weights are copied). A state
        head, a training target only, is left out."""
        acting = dataclasses.replace(student.config, state_dim=0)
        agent = cls(AgentConfig(student=acting, actor_critic=teacher.config.actor_critic), info)
        agent.student.load_state_dict({k: v for k, v in student.state_dict().items()
                                       if not k.startswith("state_head.")})
        agent.actor.load_state_dict(teacher.actor_critic.actor.state_dict())
        return agent.to(next(student.parameters()).device)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # inference_mode: ~15% less per-call overhead than no_grad on this batch-1 path.
    @torch.inference_mode()
    def act(self, image: np.ndarray | torch.Tensor, state: AgentState | None = None,
            explore: bool = False, posterior: str = "sample",
            uniform: torch.Tensor | None = None) -> tuple[np.ndarray, AgentState]:
        """One step: ``image`` uint8 [H, W, 3] (or a batch [N, H, W, 3]) and the state the
        previous call returned (None at the start of an episode) -> (action [A] or [N, A] in
        [-1, 1], next state). ``explore`` samples the actor instead of taking its mode;
        ``posterior`` (one of :data:`~twist_models.rssm.POSTERIOR_READS`) is how the latent
        takes z from the student's posterior (an unknown one raises ConfigError there);
        ``uniform`` [N, S, 1] its sampling draws (fresh when None)."""
        image = torch.as_tensor(np.asarray(image), device=self.device)
        single = image.dim() == 3
        if single:
            image = image[None]
        n = image.shape[0]
        rssm = self.student.rssm
        first = torch.full((n,), state is None, dtype=torch.bool, device=self.device)
        if state is None:
            state = AgentState(rssm.initial(n, self.device),
                               torch.zeros(n, self.config.student.action_dim, device=self.device))
        embed, history = self.student.step_embed(image, state.frames)
        latent = rssm.post_step(state.latent, state.action, embed, first, read=posterior,
                                uniform=uniform)
        dist = self.actor(rssm.feature(latent))
        action = (dist.rsample() if explore else dist.mode).clamp(-1.0, 1.0)
        out = action.cpu().numpy()
        return (out[0] if single else out), AgentState(latent, action, history)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the bundle (weights, configs and ``info``) atomically."""
        return save_checkpoint(path, "agent", self, self.config, extra=self.info)

    @classmethod
    def load(cls, path: str | os.PathLike[str], device: str | torch.device = "cpu") -> Agent:
        """Read a bundle written by :meth:`save` (no code is unpickled)."""
        return cls.from_checkpoint(read_checkpoint(path, kind="agent"), device)

    @classmethod
    def from_checkpoint(cls, checkpoint: Checkpoint, device: str | torch.device = "cpu"
                        ) -> Agent:
        """:meth:`load` for a bundle already read."""
        config = from_json(AgentConfig, checkpoint.config)
        agent = cls(config, checkpoint.extra)
        restore(checkpoint, agent, config)
        return agent.to(device).eval()
