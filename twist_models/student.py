"""The TWIST student: a vision world model that maps randomised images into the teacher's
latent space. Only an encoder and an RSSM: it is trained by latent matching, never by
reconstruction or reward prediction, so it needs no decoder or heads."""

from __future__ import annotations

import torch
from torch import nn

from twist_models.config import StudentConfig
from twist_models.networks import ImageEncoder
from twist_models.rssm import RSSM, State


class Student(nn.Module):
    """Image encoder + RSSM with the teacher's sizes."""

    def __init__(self, config: StudentConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = ImageEncoder(config.cnn)
        self.rssm = RSSM(config.rssm, config.action_dim, self.encoder.out_dim)

    def observe(self, image: torch.Tensor, action: torch.Tensor, is_first: torch.Tensor,
                uniform: torch.Tensor | None = None) -> tuple[State, State]:
        """Filter windows of images: image uint8 [B, T, H, W, 3], action [B, T, A],
        is_first [B, T] -> (posterior, prior) states {k: [B, T, ...]}."""
        return self.rssm.observe(self.encoder(image), action, is_first, uniform=uniform)
