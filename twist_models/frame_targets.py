"""Per-frame targets from the frozen teacher: what the ``dense`` recipe teaches the student's
encoder one frame at a time, without the recurrence (not in the paper).

Eq. 3 reaches the encoder only through a KL to the teacher's posterior and an h error passed
back through the GRU. Each training step t of D offers more: the teacher's own filter over
the exact states gives h^T_t, and from it two targets a single frame can be checked against:

* **the teacher's posterior at its own h**: q_T(z_t | h^T_t, e(s_t)). The student's posterior
  head, fed h^T_t and the image's embedding, should give the same distribution;
* **the privileged state** s_t, read out linearly from the image's embedding, each component
  weighted by the teacher actor's squared sensitivity to it at that step,
  w_{t,i} = sum_a (d a_t / d s_{t,i})^2 (through the teacher's encoder and posterior at
  h^T_t). Errors then count where the actor responds to them: a pole that has fallen (a
  saturated actor) weighs nothing, the near-upright lean the actor balances on weighs most.
  Standardising by D's spread does the opposite: it divides the lean's errors by the spread
  of falling poles.

:func:`teacher_targets` computes h^T and w for every training step of D once (the teacher is
frozen, so they never change); :class:`FrameBatches` draws single frames with them for the
recipe's first stage, and :func:`frame_terms` gives both losses for any frames whose teacher
h is at hand (the same terms are added to Eq. 3 on windows in the second stage).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from twist_data.reader import MatchingDataset
from twist_data.schema import PAIR_IMAGE
from twist_models.losses import frame_posterior_loss, weighted_state_loss
from twist_models.rssm import State, sample_one_hot
from twist_models.student import Student
from twist_models.teacher import Teacher

log = logging.getLogger(__name__)


def actor_sensitivity(teacher: Teacher, deter: torch.Tensor, state: torch.Tensor
                      ) -> torch.Tensor:
    """sum_a (d a / d s_i)^2 of the teacher's action mode at ``deter`` [..., D] and ``state``
    [..., S], through its state encoder, posterior head (z read as the class probabilities,
    so the map is differentiable) and actor, h held fixed -> [..., S]. Exact states: the
    sensitivity is to the state itself, not to the noise a ``state_noise`` teacher reads (0
    for the components it never reads, ``state_hidden``)."""
    wm, actor = teacher.world_model, teacher.actor_critic.actor
    deter = deter.detach()
    with torch.enable_grad():
        state = state.detach().clone().requires_grad_(True)
        logits = wm.rssm.posterior_logits(deter, wm.encoder(wm.visible(state)))
        feature = torch.cat([deter, F.softmax(logits, -1).flatten(-2)], -1)
        action = actor(feature).mode
        weight = torch.zeros_like(state)
        for k in range(action.shape[-1]):
            (grad,) = torch.autograd.grad(action[..., k].sum(), state,
                                          retain_graph=k + 1 < action.shape[-1])
            weight = weight + grad**2
    return weight.detach()


@dataclass
class FrameRows:
    """Steps of D's training episodes, one row per step, with their states: what a
    per-frame stage draws from."""

    steps: np.ndarray
    """int64 [N]: each row's global step index in D."""
    episode_start: np.ndarray
    """int64 [N]: global step index of each row's episode start."""
    state: torch.Tensor
    """float32 [N, S]: the privileged state."""

    def __len__(self) -> int:
        return int(self.steps.size)

    def subset(self, keep: np.ndarray) -> FrameRows:
        """The rows where ``keep`` (bool [N]) holds, every per-row field with them (a
        subclass's too; other fields unchanged)."""
        mask = torch.as_tensor(keep)
        rows = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return dataclasses.replace(self, **{
            name: value[keep] if isinstance(value, np.ndarray)
            else value[mask.to(value.device)] if torch.is_tensor(value) else value
            for name, value in rows.items()})

    @classmethod
    def of(cls, data: MatchingDataset, episodes: np.ndarray,
           device: torch.device | str = "cpu") -> FrameRows:
        """Every step of ``episodes`` (global indices) of ``data``, in order."""
        starts = data.episode_starts[episodes]
        lengths = data.episode_ends[episodes] - starts
        rows = np.concatenate([np.arange(s, s + n) for s, n in zip(starts, lengths, strict=True)])
        return cls(steps=rows.astype(np.int64),
                   episode_start=np.repeat(starts, lengths).astype(np.int64),
                   state=torch.as_tensor(data.column("state")[rows], device=device))


@dataclass
class TeacherTargets(FrameRows):
    """The teacher's filter over D's training episodes, one row per step."""

    deter: torch.Tensor
    """float32 [N, D]: the teacher's h_t, filtered from its episode's start."""
    sensitivity: torch.Tensor
    """float32 [N, S]: :func:`actor_sensitivity` divided by ``scale``."""
    scale: float
    """The mean raw sensitivity over rows and components: the weights above (and those of
    any later batch) are divided by it, so they average 1 over D."""


@torch.no_grad()
def teacher_targets(teacher: Teacher, data: MatchingDataset, episodes: np.ndarray,
                    read: str = "sample", seed: int = 0, chunk: int = 64) -> TeacherTargets:
    """Run the frozen ``teacher``'s filter over each episode of ``data`` in ``episodes``
    (global indices) from its start, reading z from its posterior by ``read``, with draws
    seeded by ``seed``; ``chunk`` episodes at a time (padded at the end: the filter is
    causal, so padding never reaches a real step)."""
    wm = teacher.world_model
    device = next(teacher.parameters()).device
    states, actions = data.column("state"), data.column("action")
    starts = data.episode_starts[episodes]
    lengths = data.episode_ends[episodes] - starts
    generator = torch.Generator().manual_seed(seed)
    deters: list[torch.Tensor] = []
    table = FrameRows.of(data, episodes, device)
    for lo in range(0, len(episodes), chunk):
        first, count = starts[lo:lo + chunk], lengths[lo:lo + chunk]
        longest = int(count.max())
        index = np.minimum(first[:, None] + np.arange(longest), (first + count - 1)[:, None])
        is_first = torch.zeros(len(first), longest, dtype=torch.bool)
        is_first[:, 0] = True
        state = torch.as_tensor(states[index], device=device)
        uniform = torch.rand(len(first), longest, wm.rssm.config.stoch, 1,
                             generator=generator).to(device)
        post, _ = wm.rssm.observe(wm.embed(state), torch.as_tensor(actions[index], device=device),
                                  is_first.to(device), uniform=uniform, read=read)
        deters += [post["deter"][i, :n] for i, n in enumerate(count.tolist())]
    deter, state = torch.cat(deters), table.state
    raw = torch.cat([actor_sensitivity(teacher, deter[i:i + 4096], state[i:i + 4096])
                     for i in range(0, len(table), 4096)])
    scale = float(raw.mean().clamp_min(1e-12))
    log.info("teacher targets for %d steps; mean actor sensitivity per state component: %s",
             len(table), [round(float(w), 3) for w in raw.mean(0) / scale])
    return TeacherTargets(steps=table.steps, episode_start=table.episode_start, state=state,
                          deter=deter, sensitivity=raw / scale, scale=scale)


@torch.no_grad()
def teacher_latent_before(teacher: Teacher, targets: TeacherTargets, starts: np.ndarray
                          ) -> State:
    """The teacher's latent at the step before each of ``starts`` (global steps [B] of
    training episodes): its h there from ``targets`` and z drawn from its posterior at that h
    and state -> {``deter`` [B, D], ``stoch`` [B, S, C]}; zeros for a start that is its
    episode's first step (the filter resets there anyway)."""
    rows = np.searchsorted(targets.steps, starts)
    found = (rows < len(targets)) & (targets.steps[np.minimum(rows, len(targets) - 1)] == starts)
    if not found.all():
        raise ValueError(f"window start {int(starts[~found][0])} is not a step of the "
                         "episodes the teacher's targets cover")
    first = torch.as_tensor(targets.episode_start[rows] == starts, device=targets.deter.device)
    before = torch.as_tensor(np.maximum(rows - 1, 0), device=targets.deter.device)
    wm = teacher.world_model
    deter = targets.deter[before]
    logits = wm.rssm.posterior_logits(deter, wm.embed(targets.state[before]))
    stoch = sample_one_hot(logits)
    keep = (~first).to(deter.dtype)
    return {"deter": deter * keep[:, None], "stoch": stoch * keep[:, None, None]}


class FrameBatches:
    """Batches of single training frames with their teacher targets: a random row of the
    table and a random view (or ``view``), plus the ``frames - 1`` steps before it (the first
    step of the episode repeated before its start, as :func:`~twist_models.perception.stack_frames`).

    A batch: ``image`` uint8 [B, frames, H, W, 3] (most recent first), ``state`` [B, S],
    from teacher targets ``deter`` [B, D] and ``sensitivity`` [B, S], and with ``pairs``
    ``pair`` uint8 [B, H, W, 3], the frame's pair frame (D's ``pair_image``) in its view.

    ``images``, D's images decoded once (:func:`twist_data.sampler.resident_images`), are
    gathered from on their device instead of decoding each batch: the same rows and views
    for the same seed, so the same batches (``pair_images``: the pair frames, likewise)."""

    def __init__(self, data: MatchingDataset, targets: FrameRows, batch_size: int,
                 frames: int = 1, view: int | None = None, seed: int = 0,
                 images: torch.Tensor | None = None, pairs: bool = False,
                 pair_images: torch.Tensor | None = None) -> None:
        if pairs:
            data.require_pairs("frame batches with frame pairs")
        self.data, self.targets, self.batch_size = data, targets, batch_size
        self.frames, self.view, self.images = frames, view, images
        self.pairs, self.pair_images = pairs, pair_images
        self.rng = np.random.default_rng(seed)
        self._images = np.empty((batch_size * frames, *data.spec.image_shape), np.uint8)

    def batch(self) -> dict[str, torch.Tensor]:
        t, b = self.targets, self.batch_size
        rows = self.rng.integers(0, len(t), b)
        views = (np.full(b, self.view) if self.view is not None
                 else self.rng.integers(0, self.data.spec.views, b))
        back = np.arange(self.frames)
        steps = np.maximum(t.steps[rows][:, None] - back, t.episode_start[rows][:, None])
        shape = (b, self.frames, *self._images.shape[1:])
        if self.images is not None:
            device = self.images.device
            image = self.images[torch.as_tensor(steps.reshape(-1), device=device),
                                torch.as_tensor(np.repeat(views, self.frames), device=device)]
            image = image.reshape(shape)
        else:
            self.data.read_frames(steps.reshape(-1), np.repeat(views, self.frames), self._images)
            image = torch.from_numpy(self._images.reshape(shape)).clone()
        index = torch.as_tensor(rows)
        batch = {"image": image, "state": t.state[index]}
        if self.pairs:
            batch["pair"] = self._pair_frames(steps[:, 0], views)
        if isinstance(t, TeacherTargets):
            batch.update(deter=t.deter[index], sensitivity=t.sensitivity[index])
        return batch

    def _pair_frames(self, steps: np.ndarray, views: np.ndarray) -> torch.Tensor:
        if self.pair_images is not None:
            device = self.pair_images.device
            return self.pair_images[torch.as_tensor(steps, device=device),
                                    torch.as_tensor(views, device=device)]
        pair = np.empty((steps.size, *self.data.spec.image_shape), np.uint8)
        self.data.read_frames(steps, views, pair, key=PAIR_IMAGE)
        return torch.from_numpy(pair)

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        while True:
            yield self.batch()


def frame_terms(student: Student, teacher: Teacher, embed: torch.Tensor, deter: torch.Tensor,
                state: torch.Tensor, sensitivity: torch.Tensor,
                teacher_logits: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Both per-frame losses: the student's posterior input ``embed`` [..., E'], the teacher's
    ``deter`` [..., D], the ``state`` [..., S] and its ``sensitivity`` weights [..., S]
    (normalised) -> {``frame_post_kl``, ``state``}, each [] (``state`` only for a student
    with a state head). ``teacher_logits`` [..., S, C] is the teacher's posterior there when
    already at hand (else computed)."""
    if teacher_logits is None:
        with torch.no_grad():
            wm = teacher.world_model
            teacher_logits = wm.rssm.posterior_logits(deter, wm.embed(state))
    student_logits = student.rssm.posterior_logits(deter.detach(), embed)
    terms = {"frame_post_kl": frame_posterior_loss(student_logits, teacher_logits)}
    if student.state_head is not None:
        terms["state"] = weighted_state_loss(student.read_state(embed), state, sensitivity)
    return terms


@torch.no_grad()
def frame_agreement(student: Student, teacher: Teacher, embed: torch.Tensor,
                    deter: torch.Tensor, state: torch.Tensor) -> dict[str, float]:
    """What the teacher's actor makes of single frames: its action mode read from the
    student's posterior and from its own, both at the teacher's h and on the class
    probabilities, over ``embed`` [..., E'], ``deter`` [..., D], ``state`` [..., S] ->
    {``frame_action_rmse``, ``frame_action_corr``}: the RMS difference (over steps and action
    components) and their correlation. It measures what the actor needs from a frame, free of
    the recurrence's errors."""
    wm, actor = teacher.world_model, teacher.actor_critic.actor
    t_logits = wm.rssm.posterior_logits(deter, wm.embed(state))
    s_logits = student.rssm.posterior_logits(deter, embed)

    def act(logits: torch.Tensor) -> torch.Tensor:
        return actor(torch.cat([deter, F.softmax(logits, -1).flatten(-2)], -1)).mode.flatten()

    t_action, s_action = act(t_logits), act(s_logits)
    rmse = float(((t_action - s_action) ** 2).mean().sqrt())
    corr = float(torch.corrcoef(torch.stack([t_action, s_action]))[0, 1])
    return {"frame_action_rmse": rmse, "frame_action_corr": corr if np.isfinite(corr) else 0.0}

