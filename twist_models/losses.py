"""Loss and return functions of DreamerV2 (plain functions; shapes in the docstrings)."""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F


def categorical_kl(lhs_logits: torch.Tensor, rhs_logits: torch.Tensor) -> torch.Tensor:
    """KL(lhs || rhs) of S independent categoricals: logits [..., S, C] -> [...] (summed over S)."""
    lhs_log = F.log_softmax(lhs_logits, -1)
    rhs_log = F.log_softmax(rhs_logits, -1)
    return (lhs_log.exp() * (lhs_log - rhs_log)).sum((-2, -1))


def kl_balance_loss(post_logits: torch.Tensor, prior_logits: torch.Tensor, balance: float = 0.8,
                    free_nats: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """DreamerV2's balanced KL: ``balance`` * max(mean KL(sg(q) || p), free) trains the prior,
    (1 - ``balance``) * max(mean KL(q || sg(p)), free) trains the posterior.

    post_logits, prior_logits: [..., S, C]. Returns (loss [], mean KL(q || p) [] for logging).
    Free nats clip the batch mean, not each element, as DreamerV2 (``free_avg``).
    """
    prior_side = categorical_kl(post_logits.detach(), prior_logits).mean()
    post_side = categorical_kl(post_logits, prior_logits.detach()).mean()
    free = torch.as_tensor(free_nats, dtype=prior_side.dtype, device=prior_side.device)
    loss = balance * torch.maximum(prior_side, free) + (1 - balance) * torch.maximum(post_side, free)
    return loss, prior_side.detach()


def lambda_returns(reward: torch.Tensor, value: torch.Tensor, pcont: torch.Tensor,
                   bootstrap: torch.Tensor, lambda_: float) -> torch.Tensor:
    """TD(lambda) returns along the first axis.

    reward[t], pcont[t]: reward and discount of the transition out of state t; value[t]: value of
    state t; bootstrap: value of the state after the last transition. All [T, ...] except
    bootstrap [...]. Returns G [T, ...] with
    G[t] = reward[t] + pcont[t] * ((1 - lambda) * value[t + 1] + lambda * G[t + 1]),
    where value[T] = G[T] = bootstrap.
    """
    next_value = torch.cat([value[1:], bootstrap[None]], 0)
    inputs = reward + pcont * next_value * (1 - lambda_)
    returns = []
    last = bootstrap
    for t in reversed(range(reward.shape[0])):
        last = inputs[t] + pcont[t] * lambda_ * last
        returns.append(last)
    return torch.stack(returns[::-1], 0)


def gaussian_nll(mean: torch.Tensor, target: torch.Tensor, event_dims: int = 1) -> torch.Tensor:
    """Negative log-likelihood under a unit-variance Normal, summed over the last ``event_dims``
    dimensions: [..., *event] -> [...]."""
    nll = 0.5 * (mean - target) ** 2 + 0.5 * math.log(2 * math.pi)
    return nll.sum(tuple(range(-event_dims, 0))) if event_dims else nll
