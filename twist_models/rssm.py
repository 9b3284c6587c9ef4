"""DreamerV2's recurrent state-space model with discrete latents.

A model state is a dict of tensors with any leading shape [...]:
``deter`` [..., D] the GRU state h_t, ``logits`` [..., S, C] of the distribution z_t was drawn
from, and ``stoch`` [..., S, C] the one-hot sample z_t (straight-through gradients).
Time convention (as the dataset): ``action[t]`` is the action that led to step t, so
``obs_step(state[t-1], action[t], embed[t])`` gives state[t]; where ``is_first[t]`` the previous
state and action are zeroed, which starts a new episode from the initial state.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torch.nn import functional as F

from twist_data.errors import ConfigError
from twist_models.config import RSSMConfig
from twist_models.networks import LayerNormGRUCell, full_precision

State = dict[str, torch.Tensor]
#: Maps a detached model feature [N, F] to an action [N, A].
Policy = Callable[[torch.Tensor], torch.Tensor]
#: How an acting agent reads z_t from its posterior: a one-hot ``sample`` (DreamerV2 and the
#: paper), the one-hot ``mode``, or the ``mean`` (the class probabilities).
POSTERIOR_READS = ("sample", "mode", "mean")


def require_posterior_read(read: str, what: str = "posterior read") -> None:
    """Raise ConfigError unless ``read`` is one of :data:`POSTERIOR_READS`."""
    if read not in POSTERIOR_READS:
        raise ConfigError(f"unknown {what} {read!r}; valid: {', '.join(POSTERIOR_READS)}")


def sample_one_hot(logits: torch.Tensor, uniform: torch.Tensor | None = None) -> torch.Tensor:
    """Straight-through one-hot sample of categorical ``logits`` [..., C]: the forward value is
    a one-hot sample, the gradient is that of the probabilities.

    ``uniform`` [..., 1] in [0, 1) is the draw to use (fresh when None). Two models given the
    same draws sample the same class wherever their distributions agree, which is how teacher
    and student share their samples in distillation."""
    probs = F.softmax(logits, -1)
    # Inverse-CDF sampling: the class is the number of cumulative probabilities below a uniform
    # draw. An order of magnitude faster on CPU than torch.multinomial, whose exponential noise
    # dominated the imagination loop (21 ms vs 1.5 ms for 800 x 32 x 32); the clamp absorbs a
    # last cumulative probability that rounds below 1.
    if uniform is None:
        uniform = torch.rand(*probs.shape[:-1], 1, device=probs.device, dtype=probs.dtype)
    below = probs.detach().cumsum(-1) < uniform
    index = below.sum(-1).clamp_max(probs.shape[-1] - 1)
    sample = F.one_hot(index, probs.shape[-1]).to(probs.dtype)
    return sample + probs - probs.detach()


def stack_states(states: list[State], dim: int) -> State:
    return {k: torch.stack([s[k] for s in states], dim) for k in states[0]}


#: Filter steps per compiled piece (:meth:`RSSM.compile_filter`). Measured on the `quick`
#: teacher's filter (B=32, 50 steps, forward and backward, 2-core AMD EPYC): eager 83 ms;
#: pieces of 5 steps 34.7 ms after 40 s of compiling, of 10 steps 33.1 ms after 66 s, of 25
#: 30.9 ms after 155 s; the 50 steps compiled unrolled 48.6 ms after 199 s.
FILTER_CHUNK = 5


class RSSM(nn.Module):
    """Prior p(z_t | h_t), posterior q(z_t | h_t, e_t), h_t = GRU(h_{t-1}, z_{t-1}, a_t)."""

    def __init__(self, config: RSSMConfig, action_dim: int, embed_dim: int) -> None:
        super().__init__()
        self.config = config
        c = config
        latent = c.stoch * c.classes
        self.img_in = nn.Sequential(nn.Linear(latent + action_dim, c.hidden), nn.ELU())
        self.gru = LayerNormGRUCell(c.hidden, c.deter)
        self.img_out = nn.Sequential(nn.Linear(c.deter, c.hidden), nn.ELU(),
                                     nn.Linear(c.hidden, latent))
        self.obs_out = nn.Sequential(nn.Linear(c.deter + embed_dim, c.hidden), nn.ELU(),
                                     nn.Linear(c.hidden, latent))
        self.action_dim = action_dim
        self.compile_filter(None)

    # -- states -----------------------------------------------------------------------------
    def initial(self, batch_shape: tuple[int, ...] | int, device: torch.device | None = None) -> State:
        """The all-zeros state every episode starts from."""
        shape = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        c = self.config
        device = device or self.img_in[0].weight.device
        zeros = torch.zeros(*shape, c.stoch, c.classes, device=device)
        return {"deter": torch.zeros(*shape, c.deter, device=device), "logits": zeros,
                "stoch": zeros.clone()}

    def feature(self, state: State) -> torch.Tensor:
        """[..., D + S*C]: the input of decoders, heads and the actor."""
        return torch.cat([state["deter"], state["stoch"].flatten(-2)], -1)

    def _logits(self, raw: torch.Tensor) -> torch.Tensor:
        # float32 under autocast too: sampling compares cumulative probabilities with a draw.
        return full_precision(raw).unflatten(-1, (self.config.stoch, self.config.classes))

    # -- one step ---------------------------------------------------------------------------
    def img_step(self, prev: State, action: torch.Tensor, sample: bool = True,
                 uniform: torch.Tensor | None = None) -> State:
        """Prior state after taking ``action`` [..., A] in ``prev``; ``uniform`` [..., S, 1]
        are the sampling draws (see :func:`sample_one_hot`)."""
        return self._prior(self._deter(prev, action), sample, uniform)

    def obs_step(self, prev: State, action: torch.Tensor, embed: torch.Tensor,
                 is_first: torch.Tensor | None = None) -> tuple[State, State]:
        """(posterior, prior) at a step with observation embedding ``embed`` [..., E]."""
        post = self.post_step(prev, action, embed, is_first)
        return post, self._prior(post["deter"])

    def _deter(self, prev: State, action: torch.Tensor) -> torch.Tensor:
        x = self.img_in(torch.cat([prev["stoch"].flatten(-2), action], -1))
        return self.gru(x, prev["deter"])

    def _prior(self, deter: torch.Tensor, sample: bool = True,
               uniform: torch.Tensor | None = None) -> State:
        logits = self.prior_logits(deter)
        stoch = sample_one_hot(logits, uniform) if sample else _mode(logits)
        return {"deter": deter, "logits": logits, "stoch": stoch}

    def post_step(self, prev: State, action: torch.Tensor, embed: torch.Tensor,
                  is_first: torch.Tensor | None = None,
                  uniform: torch.Tensor | None = None, read: str = "sample") -> State:
        """The posterior state alone: what acting needs (the prior head is not run). ``read``
        (one of :data:`POSTERIOR_READS`) is how ``stoch`` is taken from the posterior."""
        if is_first is not None:
            keep = (~is_first.bool()).to(action.dtype)
            prev = {k: v * keep.reshape(*keep.shape, *([1] * (v.dim() - keep.dim())))
                    for k, v in prev.items()}
            action = action * keep.unsqueeze(-1)
        deter = self._deter(prev, action)
        logits = self.posterior_logits(deter, embed)
        if read == "sample":
            stoch = sample_one_hot(logits, uniform)
        elif read == "mode":
            stoch = _mode(logits)
        elif read == "mean":
            stoch = F.softmax(logits, -1)
        else:
            require_posterior_read(read)
        return {"deter": deter, "logits": logits, "stoch": stoch}

    def prior_logits(self, deter: torch.Tensor) -> torch.Tensor:
        """p(z_t | h_t) as logits [..., S, C] from ``deter`` [..., D]."""
        return self._logits(self.img_out(deter))

    def posterior_logits(self, deter: torch.Tensor, embed: torch.Tensor) -> torch.Tensor:
        """q(z_t | h_t, e_t) as logits [..., S, C] from ``deter`` [..., D] and ``embed``
        [..., E]: the posterior head alone, for any h (a per-frame target reads it at the
        teacher's h)."""
        return self._logits(self.obs_out(torch.cat([deter, embed], -1)))

    # -- sequences --------------------------------------------------------------------------
    def observe(self, embed: torch.Tensor, action: torch.Tensor, is_first: torch.Tensor,
                state: State | None = None, uniform: torch.Tensor | None = None,
                read: str = "sample") -> tuple[State, State]:
        """Filter a sequence: embed [B, T, E], action [B, T, A], is_first [B, T] ->
        (posterior, prior), each {k: [B, T, ...]}. ``state`` continues a previous call;
        ``uniform`` [B, T, S, 1] are the posterior's sampling draws (fresh when None);
        ``read`` is how z is taken from the posterior (:meth:`post_step`). The prior's
        ``stoch`` is its mode: nothing downstream of the prior reads a sample of it."""
        b, t = embed.shape[:2]
        state = state if state is not None else self.initial(b, embed.device)
        length = self._filter_chunk or t
        parts = []
        for s in range(0, t, length):
            steps = slice(s, s + length)
            part = self._filter_fn(state, embed[:, steps], action[:, steps], is_first[:, steps],
                                   None if uniform is None else uniform[:, steps], read)
            state = {k: v[:, -1] for k, v in part.items()}
            parts.append(part)
        post = parts[0] if len(parts) == 1 else {k: torch.cat([p[k] for p in parts], 1)
                                                 for k in parts[0]}
        # Nothing in the recurrence reads the prior, so its head runs once on all [B, T]
        # deterministic states instead of inside the sequential loop (fewer, larger matmuls).
        return post, self._prior(post["deter"], sample=False)

    def _filter(self, state: State, embed: torch.Tensor, action: torch.Tensor,
                is_first: torch.Tensor, uniform: torch.Tensor | None, read: str) -> State:
        """Posterior states {k: [B, T, ...]} of T steps from ``state``: the sequential loop."""
        posts = []
        for i in range(embed.shape[1]):
            draws = None if uniform is None else uniform[:, i]
            state = self.post_step(state, action[:, i], embed[:, i], is_first[:, i], draws,
                                   read)
            posts.append(state)
        return stack_states(posts, 1)

    def compile_filter(self, chunk: int | None, mode: str | None = "default") -> None:
        """Filter ``chunk`` steps at a time, each piece through one function that
        ``torch.compile`` compiles in ``mode`` (None: eager pieces, the same arithmetic);
        ``chunk`` None: one eager loop over every step, the reference. Why pieces: the loop
        compiled unrolled takes minutes to compile, pieces of a few steps a minute, and on a
        CPU they ran the filter faster still (:data:`FILTER_CHUNK`)."""
        if chunk is not None and chunk < 1:
            raise ConfigError(f"a filter piece must be at least 1 step, got {chunk}")
        self._filter_chunk = chunk
        self._filter_fn = (self._filter if chunk is None or mode is None
                           else torch.compile(self._filter, mode=mode))

    def imagine(self, start: State, horizon: int, policy: Policy | None = None,
                actions: torch.Tensor | None = None,
                uniform: torch.Tensor | None = None) -> tuple[State, torch.Tensor]:
        """Roll the prior forward from ``start`` ({k: [N, ...]}) for ``horizon`` steps.

        Actions come from ``policy(feature.detach())`` or from ``actions`` [N, H, A] (the
        student replaying the teacher's actions). Returns (states {k: [N, H+1, ...]} with
        ``start`` first, actions [N, H, A]) where action i was taken in state i.
        ``uniform`` [N, H, S, 1] are the prior's sampling draws (fresh when None).
        """
        if (policy is None) == (actions is None):
            raise ValueError("imagine needs exactly one of policy and actions")
        if actions is not None and actions.shape[1] != horizon:
            raise ValueError(f"actions cover {actions.shape[1]} steps, horizon is {horizon}")
        states, taken = [start], []
        state = start
        for i in range(horizon):
            action = policy(self.feature(state).detach()) if policy is not None else actions[:, i]
            state = self.img_step(state, action, uniform=None if uniform is None else uniform[:, i])
            states.append(state)
            taken.append(action)
        return stack_states(states, 1), torch.stack(taken, 1)


def _mode(logits: torch.Tensor) -> torch.Tensor:
    return F.one_hot(logits.argmax(-1), logits.shape[-1]).to(logits.dtype)
