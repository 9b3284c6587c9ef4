"""Actor-critic in imagination: DreamerV2 (``actor_grad: dynamics`` for continuous actions),
optionally with DreamerV3's score-function actor and return normalisation."""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from twist_models.config import ActorCriticConfig, OptimConfig
from twist_models.device import precision_autocast
from twist_models.losses import (
    gaussian_nll,
    lambda_returns,
    twohot_bins,
    twohot_loss,
    twohot_mean,
)
from twist_models.networks import MLP, full_precision
from twist_models.rssm import RSSM, State
from twist_models.world_model import WorldModel

_SQRT2 = math.sqrt(2.0)
#: DreamerV3's decay of the return-range EMA.
RETURN_RANGE_DECAY = 0.99


def _normal_cdf(x: torch.Tensor) -> torch.Tensor:
    return 0.5 * (1 + torch.erf(x / _SQRT2))


def _normal_pdf(x: torch.Tensor) -> torch.Tensor:
    return torch.exp(-0.5 * x**2) / math.sqrt(2 * math.pi)


class TruncatedNormal:
    """Normal(mean, std) truncated to [low, high], reparameterised by the inverse CDF."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, low: float = -1.0,
                 high: float = 1.0) -> None:
        self.mean, self.std, self.low, self.high = mean, std, low, high
        self._alpha = (low - mean) / std
        self._beta = (high - mean) / std
        self._z = (_normal_cdf(self._beta) - _normal_cdf(self._alpha)).clamp_min(1e-8)

    def rsample(self) -> torch.Tensor:
        """A sample with gradients to mean and std: [...]."""
        u = torch.rand_like(self.mean)
        cdf = _normal_cdf(self._alpha) + u * self._z
        x = self.mean + self.std * _SQRT2 * torch.erfinv((2 * cdf - 1).clamp(-1 + 1e-6, 1 - 1e-6))
        return x.clamp(self.low, self.high)

    def entropy(self) -> torch.Tensor:
        """Per-dimension entropy [...]."""
        a, b = self._alpha, self._beta
        return (torch.log(math.sqrt(2 * math.pi * math.e) * self.std * self._z)
                + (a * _normal_pdf(a) - b * _normal_pdf(b)) / (2 * self._z))

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.mean) / self.std
        return -0.5 * z**2 - math.log(math.sqrt(2 * math.pi)) - torch.log(self.std * self._z)

    @property
    def mode(self) -> torch.Tensor:
        return self.mean.clamp(self.low, self.high)


class ClippedNormal:
    """Normal(mean, std) whose samples are clipped to [low, high], the gradient of a clipped
    sample passed straight through (the first DreamerV3's continuous actor)."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, low: float = -1.0,
                 high: float = 1.0) -> None:
        self.mean, self.std, self.low, self.high = mean, std, low, high

    def rsample(self) -> torch.Tensor:
        """A sample with gradients to mean and std: [...]."""
        x = self.mean + self.std * torch.randn_like(self.mean)
        return x + (x.clamp(self.low, self.high) - x).detach()

    def entropy(self) -> torch.Tensor:
        """Per-dimension entropy of the unclipped normal [...]."""
        return torch.log(math.sqrt(2 * math.pi * math.e) * self.std)

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.mean) / self.std
        return -0.5 * z**2 - math.log(math.sqrt(2 * math.pi)) - torch.log(self.std)

    @property
    def mode(self) -> torch.Tensor:
        return self.mean


class Actor(nn.Module):
    """feature [..., F] -> a distribution over actions in [-1, 1]^A (``actor_dist``)."""

    def __init__(self, feature_dim: int, action_dim: int, config: ActorCriticConfig) -> None:
        super().__init__()
        self.net = MLP(feature_dim, 2 * action_dim, config.actor)
        self.dist, self.min_std, self.max_std = config.actor_dist, config.min_std, config.max_std

    def forward(self, feature: torch.Tensor) -> TruncatedNormal | ClippedNormal:
        # float32 whatever autocast the net ran in: bfloat16 would round the erfinv clamp's
        # 1 - 1e-6 to 1 and the sample to infinity.
        mean, std = full_precision(self.net(feature)).chunk(2, -1)
        if self.dist == "normal":  # DreamerV3: std (max - min) sigmoid(x + 2) + min, ~0.9 at 0
            std = (self.max_std - self.min_std) * torch.sigmoid(std + 2) + self.min_std
            return ClippedNormal(torch.tanh(mean), std)
        return TruncatedNormal(torch.tanh(mean), 2 * torch.sigmoid(std / 2) + self.min_std)


class ActorCritic(nn.Module):
    """Actor, critic and the critic's slow target, trained on imagined rollouts."""

    def __init__(self, feature_dim: int, action_dim: int, config: ActorCriticConfig,
                 optim: OptimConfig) -> None:
        super().__init__()
        self.config = config
        self.actor = Actor(feature_dim, action_dim, config)
        if config.critic_head == "twohot":
            self.register_buffer("bins", twohot_bins())
            self.critic = MLP(feature_dim, self.bins.numel(), config.critic)
            # DreamerV3 zeroes the output layer: every state starts at value 0, uniform over
            # the bins, instead of at a random value the first returns must unlearn.
            nn.init.zeros_(self.critic[-1].weight)
            nn.init.zeros_(self.critic[-1].bias)
        else:
            self.critic = MLP(feature_dim, 1, config.critic)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.grad_clip = optim.grad_clip
        self._optim = optim
        self._optimisers: tuple[torch.optim.Optimizer, torch.optim.Optimizer] | None = None
        self.register_buffer("updates", torch.zeros((), dtype=torch.int64))
        # EMA of the (5%, 95%) quantiles of imagined returns, for return_norm.
        self.register_buffer("return_range", torch.zeros(2))
        self.compile_imagination(None)

    # Built when first used: an optimiser's construction imports torch._dynamo (seconds), which
    # a process that only acts (an evaluation) never needs.
    @property
    def actor_opt(self) -> torch.optim.Optimizer:
        return self._built_optimisers()[0]

    @property
    def critic_opt(self) -> torch.optim.Optimizer:
        return self._built_optimisers()[1]

    def _built_optimisers(self) -> tuple[torch.optim.Optimizer, torch.optim.Optimizer]:
        if self._optimisers is None:
            c, o = self.config, self._optim
            self._optimisers = (
                torch.optim.AdamW(self.actor.parameters(), c.actor_lr, eps=o.eps,
                                  weight_decay=o.weight_decay),
                torch.optim.AdamW(self.critic.parameters(), c.critic_lr, eps=o.eps,
                                  weight_decay=o.weight_decay))
        return self._optimisers

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args, **kwargs) -> None:
        # Checkpoints written before return normalisation existed lack its statistics.
        state_dict.setdefault(prefix + "return_range", self.return_range.clone())
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def value(self, feature: torch.Tensor, target: bool = False) -> torch.Tensor:
        """The (slow target) critic's value of ``feature`` [..., F] -> [...]."""
        out = (self.target_critic if target else self.critic)(feature)
        if self.config.critic_head == "twohot":
            return twohot_mean(out, self.bins)
        return out.squeeze(-1)

    def _critic_loss(self, feature: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """Per-state critic loss of ``feature`` [N, H, F] against ``returns`` [H, N] -> [H, N]."""
        if self.config.critic_head == "twohot":
            logits = full_precision(self.critic(feature))
            return twohot_loss(logits.transpose(0, 1), returns, self.bins)
        return gaussian_nll(full_precision(self.value(feature)).T, returns, 0)

    def train_step(self, world_model: WorldModel, start: State) -> dict[str, torch.Tensor]:
        """One actor and one critic update from imagined rollouts of the ``start`` states
        ({k: [N, ...]}, detached; all of them, or ``imag_starts`` drawn at random). The world
        model is frozen (and differentiated through with ``actor_grad=dynamics``)."""
        c = self.config
        n = next(iter(start.values())).shape[0]
        if 0 < c.imag_starts < n:
            chosen = torch.randperm(n, device=start["deter"].device)[:c.imag_starts]
            start = {k: v[chosen] for k, v in start.items()}
        rssm = world_model.rssm
        frozen = [p for p in world_model.parameters() if p.requires_grad]
        for p in frozen:
            p.requires_grad_(False)
        try:
            with precision_autocast(c.precision, start["deter"].device):
                if c.actor_grad == "dynamics":
                    feature, entropy, _ = self._imagine_fn(rssm, start, True)
                else:
                    with torch.no_grad():
                        feature, _, actions = self._imagine_fn(rssm, start, False)
                # Heads run on the contiguous [N, H+1, F] layout (a transposed input sends
                # nn.Linear down a slow batched-matmul path); their [N, H+1] outputs go time
                # first. Returns are sums of ~100 rewards: bfloat16's 8 bits would round them
                # by ~0.5, so everything after the networks is float32.
                reward = full_precision(world_model.reward(feature)).T
                pcont = c.discount * full_precision(world_model.continuation(feature)).T
                value = full_precision(self.value(feature, target=True)).T
            feature = full_precision(feature)
            # Transition t leaves state t and arrives in t + 1, whose predicted reward and
            # continuation it earns (the dataset's convention: reward[t] is for arriving at t).
            returns = lambda_returns(reward[1:], value[:-1], pcont[1:], value[-1], c.lambda_)
            weight = torch.cumprod(torch.cat([torch.ones_like(pcont[:1]), pcont[1:-1]], 0), 0)
            weight = weight.detach()
            scale = self._return_scale(returns.detach())
            if c.actor_grad == "dynamics":
                objective = returns / scale
            else:
                policy = self.actor(feature[:, :-1])  # one batched pass over [N, H, F]
                entropy = policy.entropy().sum(-1).T
                log_prob = policy.log_prob(actions).sum(-1).T  # [H, N]
                advantage = (returns - self.value(feature[:, :-1]).T).detach() / scale
                objective = log_prob * advantage
            actor_loss = -(weight * (objective + c.entropy * entropy)).mean()
        finally:
            for p in frozen:
                p.requires_grad_(True)
        self._step(self.actor_opt, actor_loss, self.actor)
        with precision_autocast(c.precision, feature.device):
            critic_loss = (weight * self._critic_loss(feature[:, :-1].detach().contiguous(),
                                                      returns.detach())).mean()
        self._step(self.critic_opt, critic_loss, self.critic)
        self.updates += 1
        if int(self.updates) % c.slow_target_every == 0:
            self.target_critic.load_state_dict(self.critic.state_dict())
        return {"actor_loss": actor_loss.detach(), "critic_loss": critic_loss.detach(),
                "imagined_return": returns[0].mean().detach(),
                "actor_entropy": entropy.mean().detach(),
                "imagined_reward": reward[1:].mean().detach()}

    def compile_imagination(self, mode: str | None) -> None:
        """Roll out through ``torch.compile`` in ``mode`` (None: eager)."""
        self._imagine_fn = self._imagine if mode is None else torch.compile(self._imagine,
                                                                            mode=mode)

    def _imagine(self, rssm: RSSM, start: State, differentiable: bool
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Roll the actor out in the model: (features [N, H+1, F], the actor's entropy at
        each of the H decision states [H, N], actions [N, H, A])."""
        entropies: list[torch.Tensor] = []

        def act(feature: torch.Tensor) -> torch.Tensor:
            # imagine() feeds the actor detached features, so these distributions are exactly
            # those DreamerV2 recomputes for the entropy bonus: taking it here saves a second
            # actor pass over every imagined state.
            policy = self.actor(feature)
            entropies.append(policy.entropy().sum(-1))
            action = policy.rsample()
            return action if differentiable else action.detach()

        states, actions = rssm.imagine(start, self.config.horizon, policy=act)
        return rssm.feature(states), torch.stack(entropies, 0), actions

    def _return_scale(self, returns: torch.Tensor) -> torch.Tensor | float:
        """max(1, EMA of the 5-95% percentile range of ``returns``) with return_norm, else 1."""
        if not self.config.return_norm:
            return 1.0
        quantiles = torch.quantile(returns.flatten().float(),
                                   torch.tensor([0.05, 0.95], device=returns.device))
        if int(self.updates) == 0:
            self.return_range.copy_(quantiles)
        else:
            self.return_range.lerp_(quantiles, 1 - RETURN_RANGE_DECAY)
        return (self.return_range[1] - self.return_range[0]).clamp_min(1.0)

    def _step(self, optimiser: torch.optim.Optimizer, loss: torch.Tensor, module: nn.Module) -> None:
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(module.parameters(), self.grad_clip)
        optimiser.step()
