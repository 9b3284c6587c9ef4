"""World model = encoder + RSSM + decoder + reward (and optional discount) head."""

from __future__ import annotations

import torch
from torch import nn

from twist_models.config import WorldModelConfig
from twist_models.losses import gaussian_nll, kl_balance_loss, symlog
from twist_models.networks import MLP, ImageDecoder, ImageEncoder, StateEncoder, preprocess_image
from twist_models.rssm import RSSM, State


class WorldModel(nn.Module):
    """DreamerV2's world model on privileged state (the teacher) or 64x64 images (the image
    baselines).

    Batches are dicts of [B, T, ...] tensors in the dataset's time convention: ``state`` [S]
    or ``image`` [H, W, 3] uint8 (and ``state`` when the decoder reconstructs it),
    ``action`` [A] (the action that led to step t), ``reward``, ``is_first``, and
    ``is_terminal`` when the discount head is on.
    """

    def __init__(self, config: WorldModelConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        if c.obs == "state":
            self.encoder: nn.Module = StateEncoder(c.state_dim, c.state_mlp, c.symlog)
        else:
            self.encoder = ImageEncoder(c.cnn)
        self.rssm = RSSM(c.rssm, c.action_dim, self.encoder.out_dim)
        feature = c.rssm.feature_dim
        if c.decodes_state:
            self.decoder: nn.Module = MLP(feature, c.state_dim, c.state_mlp)
        else:
            self.decoder = ImageDecoder(feature, c.cnn)
        self.reward_head = MLP(feature, 1, c.head)
        self.discount_head = MLP(feature, 1, c.head) if c.discount_head else None
        if c.state_hidden:
            seen = torch.ones(c.state_dim)
            seen[list(c.state_hidden)] = 0.0
            self.register_buffer("state_seen", seen, persistent=False)
        else:
            self.state_seen = None
        self.compile_overshoot(None)

    def compile_overshoot(self, mode: str | None) -> None:
        """Run the overshooting loss through ``torch.compile`` in ``mode`` (None: eager)."""
        self._overshoot_fn = (self._overshoot_loss if mode is None
                              else torch.compile(self._overshoot_loss, mode=mode))

    @property
    def obs_key(self) -> str:
        return self.config.obs

    def embed(self, observation: torch.Tensor) -> torch.Tensor:
        """Encoder features of ``observation`` ([..., S] state or [..., H, W, 3] image); a state
        is read through ``state_noise`` (a fresh draw on every call) and without its
        ``state_hidden`` components."""
        if self.config.state_noise:
            observation = observation + self.config.state_noise * torch.randn_like(observation)
        return self.encoder(self.visible(observation))

    def visible(self, state: torch.Tensor) -> torch.Tensor:
        """``state`` [..., S] with the ``state_hidden`` components set to 0 (images pass)."""
        return state if self.state_seen is None else state * self.state_seen

    def loss(self, batch: dict[str, torch.Tensor],
             state: State | None = None) -> tuple[torch.Tensor, State, dict[str, torch.Tensor]]:
        """World-model loss of a batch -> (scalar loss, posterior states [B, T, ...], metrics)."""
        c = self.config
        obs = batch[self.obs_key]
        post, prior = self.rssm.observe(self.embed(obs), batch["action"], batch["is_first"], state)
        feature = self.rssm.feature(post)
        kl_loss, kl = kl_balance_loss(post["logits"], prior["logits"], c.rssm.kl_balance,
                                      c.rssm.free_nats)
        if c.decodes_state:
            recon = gaussian_nll(self.decoder(feature), self.state_target(batch["state"])).mean()
        else:
            recon = gaussian_nll(self.decoder(feature), preprocess_image(obs), 3).mean()
        reward = gaussian_nll(self.reward_head(feature).squeeze(-1), batch["reward"], 0).mean()
        loss = c.kl_scale * kl_loss + recon + c.reward_scale * reward
        metrics = {"kl": kl, "recon_loss": recon.detach(), "reward_loss": reward.detach()}
        if self.discount_head is not None:
            continues = (~batch["is_terminal"].bool()).float()
            discount = nn.functional.binary_cross_entropy_with_logits(
                self.discount_head(feature).squeeze(-1), continues)
            loss = loss + discount
            metrics["discount_loss"] = discount.detach()
        if c.overshoot:
            overshoot = self._overshoot_fn(post, batch)
            loss = loss + overshoot
            metrics["overshoot_loss"] = overshoot.detach()
        metrics["model_loss"] = loss.detach()
        return loss, post, metrics

    def _overshoot_loss(self, post: State, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Decoder and reward NLL of open-loop prior rollouts from random posterior states,
        driven by the recorded actions: a scalar.

        Why: the posterior sees every next state, so the one-step losses barely ask the
        deterministic path to carry an action's effect, and imagination (which is open loop)
        then under-rates how much actions matter (research/findings-full.md, "Which settings
        learn fastest on 2 cores?").
        Fitting the open-loop predictions themselves asks for exactly what imagination uses."""
        c = self.config
        batch_size, length = batch["is_first"].shape
        horizon = min(c.overshoot, length - 1)  # short windows (tests) roll out what they hold
        device = batch["is_first"].device
        rows = torch.randint(batch_size, (c.overshoot_starts, 1), device=device)
        starts = torch.randint(length - horizon, (c.overshoot_starts, 1), device=device)
        steps = starts + torch.arange(1, horizon + 1, device=device)  # [N, H]
        start = {k: v[rows[:, 0], starts[:, 0]] for k, v in post.items()}
        states, _ = self.rssm.imagine(start, horizon, actions=batch["action"][rows, steps])
        feature = self.rssm.feature(states)[:, 1:]  # [N, H, F], the start left out
        # A rollout is compared with the recording only until the recording's next episode.
        valid = (batch["is_first"][rows, steps].int().cumsum(1) == 0).float()
        nll = (gaussian_nll(self.decoder(feature), self.state_target(batch["state"][rows, steps]))
               + c.reward_scale * gaussian_nll(self.reward(feature), batch["reward"][rows, steps], 0))
        return (nll * valid).sum() / valid.sum().clamp_min(1.0)

    def state_target(self, state: torch.Tensor) -> torch.Tensor:
        """What the decoder reconstructs of ``state`` [..., S]: the state, in symlog space
        where the config's ``symlog`` asks."""
        return symlog(state) if self.config.symlog else state

    def reward(self, feature: torch.Tensor) -> torch.Tensor:
        """Predicted reward for arriving in the state of ``feature``: [..., F] -> [...]."""
        return self.reward_head(feature).squeeze(-1)

    def continuation(self, feature: torch.Tensor) -> torch.Tensor:
        """Probability the episode continues after this state ([...]); 1 without the head."""
        if self.discount_head is None:
            return torch.ones(feature.shape[:-1], device=feature.device)
        return torch.sigmoid(self.discount_head(feature).squeeze(-1))
