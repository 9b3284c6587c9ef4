"""DreamerV2: a world model (on state or on images) with an actor-critic trained in its
imagination. The teacher is one on privileged state; the offline image baselines are others."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from twist_models.actor_critic import ActorCritic
from twist_models.checkpoint import move_optimiser_state
from twist_models.config import DreamerConfig
from twist_models.device import compiles_whole
from twist_models.rssm import FILTER_CHUNK
from twist_models.world_model import WorldModel


class Dreamer(nn.Module):
    """A world model (on state or images) + actor-critic in imagination, DreamerV2."""

    def __init__(self, config: DreamerConfig) -> None:
        super().__init__()
        self.config = config
        wm = config.world_model
        self.world_model = WorldModel(wm)
        self.actor_critic = ActorCritic(wm.rssm.feature_dim, wm.action_dim, config.actor_critic,
                                        config.optim)
        self._model_opt: torch.optim.Optimizer | None = None
        # Optimiser states read from a checkpoint before the optimisers were first needed.
        self._pending_states: Mapping[str, Any] = {}
        self.register_buffer("step", torch.zeros((), dtype=torch.int64))
        self.compiled_mode: str | None = None
        self._model_loss = self.world_model.loss

    def compile_update(self, mode: str | None, whole: bool | None = None) -> None:
        """Run the update's loops through ``torch.compile`` in ``mode`` (``reduce-overhead``:
        also captured as CUDA graphs); None: eager, the reference.

        ``whole`` (default: with CUDA graphs only) compiles the whole world-model loss and the
        imagined rollout as two graphs, which CUDA graphs want: fewest launches. Otherwise
        the loops are compiled in pieces: the filter :data:`~twist_models.rssm.FILTER_CHUNK` steps at a time,
        the overshooting rollout and the imagined rollout, the networks between them eager.
        On a 2-core CPU the pieces compile in about 3 minutes instead of 6-8 and run the
        `quick` update at ~0.94 of the whole graph's speed (docs/performance.md). The
        optimiser steps and the actor-critic's return and loss arithmetic (a few large
        kernels) stay eager either way."""
        whole = compiles_whole(mode, whole)
        self.compiled_mode = mode
        pieces = mode if mode is not None and not whole else None
        self._model_loss = (torch.compile(self.world_model.loss, mode=mode)
                            if mode is not None and whole else self.world_model.loss)
        self.world_model.rssm.compile_filter(FILTER_CHUNK if pieces else None, pieces)
        self.world_model.compile_overshoot(pieces)
        self.actor_critic.compile_imagination(mode)

    def to_device(self, device: torch.device | str) -> Dreamer:
        """Move weights and optimiser moments to ``device``."""
        self.to(device)
        if self._model_opt is not None:  # optimisers built later load onto the weights' device
            for optimiser in self.optimisers().values():
                move_optimiser_state(optimiser, device)
        return self

    @property
    def model_opt(self) -> torch.optim.Optimizer:
        return self.optimisers()["model"]

    def optimisers(self) -> dict[str, torch.optim.Optimizer]:
        """The three optimisers, built when first asked for: building one imports
        torch._dynamo (seconds), which a process that only acts (an evaluation) never needs."""
        first = self._model_opt is None
        if first:
            optim = self.config.optim
            self._model_opt = torch.optim.AdamW(self.world_model.parameters(),
                                                self.config.world_model.model_lr,
                                                eps=optim.eps, weight_decay=optim.weight_decay)
        built = {"model": self._model_opt, "actor": self.actor_critic.actor_opt,
                 "critic": self.actor_critic.critic_opt}
        if first:
            self._load_pending(built)
        return built

    def restore_optimisers(self, states: Mapping[str, Any]) -> None:
        """Load a checkpoint's optimiser ``states`` (by :meth:`optimisers` name) now if the
        optimisers exist, else when they are first built; the moments then land on the
        weights' device (``Optimizer.load_state_dict`` moves them)."""
        self._pending_states = dict(states)
        if self._model_opt is not None:
            self._load_pending(self.optimisers())

    def _load_pending(self, optimisers: Mapping[str, torch.optim.Optimizer]) -> None:
        states, self._pending_states = self._pending_states, {}
        for name, optimiser in optimisers.items():
            if name in states:
                optimiser.load_state_dict(states[name])

    def train_step(self, batch: dict[str, torch.Tensor], behaviour: bool = True
                   ) -> dict[str, float]:
        """Update the world model on ``batch`` ({k: [B, T, ...]}: state or image, action,
        reward, is_first, ...), then, with ``behaviour``, the actor-critic from imagination
        started at the posterior states. Returns scalar metrics."""
        if self.compiled_mode == "reduce-overhead":
            torch.compiler.cudagraph_mark_step_begin()
        loss, post, metrics = self._model_loss(batch)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        metrics["model_grad_norm"] = nn.utils.clip_grad_norm_(self.world_model.parameters(),
                                                              self.config.optim.grad_clip)
        self.model_opt.step()
        # A CUDA graph's outputs live in memory its next replay overwrites: what outlives
        # this step's graphs is copied (copies queue on the stream, so nothing waits here).
        metrics = {k: v.detach().clone() for k, v in metrics.items()}
        if behaviour:
            start = {k: v.detach().flatten(0, 1).clone() for k, v in post.items()}
            metrics.update(self.actor_critic.train_step(self.world_model, start))
        self.step += 1
        return {k: float(v) for k, v in metrics.items()}
