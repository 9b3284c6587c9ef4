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


# -- DreamerV3's critic: a categorical over symlog-spaced bins ---------------------------------
def symlog(x: torch.Tensor) -> torch.Tensor:
    """sign(x) log(1 + |x|), elementwise: compresses large magnitudes, ~identity near 0."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`symlog`, elementwise."""
    return torch.sign(x) * torch.expm1(x.abs())


def twohot_bins(count: int = 255, limit: float = 20.0) -> torch.Tensor:
    """``count`` bin centres evenly spaced over [-limit, limit] in symlog space (DreamerV3)."""
    return torch.linspace(-limit, limit, count)


def twohot_mean(logits: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """The value a categorical over ``bins`` [N] predicts: logits [..., N] -> [...], the
    symexp of its mean in symlog space."""
    return symexp((torch.softmax(logits, -1) * bins).sum(-1))


def twohot_loss(logits: torch.Tensor, target: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of logits [..., N] against the two-hot encoding of symlog(``target``)
    [...] over increasing ``bins`` [N]: the two bins around it share weight 1 in proportion
    to closeness, so the encoding's mean is the target exactly. Returns [...]."""
    y = symlog(target).clamp(float(bins[0]), float(bins[-1])).contiguous()
    upper = torch.searchsorted(bins, y, right=True).clamp(1, bins.numel() - 1)
    lower = upper - 1
    weight_upper = ((y - bins[lower]) / (bins[upper] - bins[lower])).clamp(0.0, 1.0)
    log_probs = F.log_softmax(logits, -1)
    return -((1 - weight_upper) * log_probs.gather(-1, lower[..., None]).squeeze(-1)
             + weight_upper * log_probs.gather(-1, upper[..., None]).squeeze(-1))


# -- TWIST distillation (the teacher's tensors are targets: no gradient reaches them) ------------
def distillation_loss(student_post: dict[str, torch.Tensor], student_prior_logits: torch.Tensor,
                      teacher_post: dict[str, torch.Tensor], teacher_prior_logits: torch.Tensor
                      ) -> dict[str, torch.Tensor]:
    """Eq. 3 of TWIST on windows of data, each term averaged over the batch and the window.

    ``*_post``: the posterior states of each model's filter over the same windows,
    ``deter`` [B, L, D] and ``logits`` [B, L, S, C]; ``*_prior_logits`` [B, L, S, C]: each
    model's prior p(z_t | h_t) at its own h_t. Returns {``h``: ||h_teacher - h_student||^2
    (summed over D), ``prior_kl``: KL(p_student || p_teacher), ``post_kl``:
    KL(q_student || q_teacher)}, all []. The paper sums over t; the mean makes the weights
    independent of L.
    """
    return {
        "h": ((student_post["deter"] - teacher_post["deter"].detach()) ** 2).sum(-1).mean(),
        "prior_kl": categorical_kl(student_prior_logits, teacher_prior_logits.detach()).mean(),
        "post_kl": categorical_kl(student_post["logits"],
                                  teacher_post["logits"].detach()).mean(),
    }


def imagined_distillation_loss(student: dict[str, torch.Tensor],
                               teacher: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Eq. 4 of TWIST along imagined rollouts that replay the same actions.

    ``student``/``teacher``: prior states ``deter`` [N, H+1, D] and ``logits``
    [N, H+1, S, C], index 0 being the posterior state imagination started from (Eq. 3
    already matches it, so it is left out). Returns {``h``: ||h_teacher - h_student||^2,
    ``prior_kl``: KL(p_student || p_teacher)}, each averaged over N and the H imagined steps.
    """
    return {
        "h": ((student["deter"][:, 1:] - teacher["deter"][:, 1:].detach()) ** 2).sum(-1).mean(),
        "prior_kl": categorical_kl(student["logits"][:, 1:],
                                   teacher["logits"][:, 1:].detach()).mean(),
    }


def action_matching_loss(student_action: torch.Tensor, teacher_action: torch.Tensor
                         ) -> torch.Tensor:
    """The teacher's actor on the student's latent against the same actor on the teacher's:
    ``*_action`` [..., A], each the actor's mode. Returns ||a_teacher - a_student||^2 summed
    over A and averaged over the rest, []. Not in the paper: it weights the latent errors by
    how much the actor the student serves responds to them."""
    return ((student_action - teacher_action.detach()) ** 2).sum(-1).mean()


# -- per-frame targets (the ``dense`` recipe; not in the paper) ----------------------------------
def frame_posterior_loss(student_logits: torch.Tensor, teacher_logits: torch.Tensor
                         ) -> torch.Tensor:
    """KL(q_student(z_t | h_t, e_image) || q_teacher(z_t | h_t, e_state)) with both posteriors
    read at the *teacher's* h_t: logits [..., S, C] -> [] (mean over the leading dims). One
    frame's encoding is judged on its own, with no error passed back through the recurrence."""
    return categorical_kl(student_logits, teacher_logits.detach()).mean()


def weighted_state_loss(prediction: torch.Tensor, state: torch.Tensor, weight: torch.Tensor
                        ) -> torch.Tensor:
    """sum_i w_i (prediction_i - state_i)^2: prediction, state, weight [..., S] -> [] (mean over
    the leading dims). With w the actor's squared sensitivity to each state component this is
    the first-order squared action error each component's read-out error alone would cause."""
    return (weight.detach() * (prediction - state.detach()) ** 2).sum(-1).mean()


def readout_loss(errors: torch.Tensor, delta: float = 1.0) -> torch.Tensor:
    """Huber loss of read-out errors in units of their robust spread, quadratic up to
    ``delta`` spreads and linear beyond: errors [..., R] -> [] (the mean over frames and
    components). Linear far out, so that a fallen pole, many robust spreads away, cannot
    outweigh the lean near upright."""
    return F.huber_loss(errors.float(), torch.zeros_like(errors, dtype=torch.float32),
                        delta=delta)
