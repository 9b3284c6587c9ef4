"""Building blocks: ELU MLPs, DreamerV2's layer-normalised GRU, state and image encoders/decoders.

Every module accepts any number of leading dimensions ([..., features] or [..., H, W, 3]).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from twist_models.config import CNNConfig, MLPConfig
from twist_models.losses import symlog


@contextmanager
def single_threaded() -> Iterator[None]:
    """Run torch on one thread inside the block. Acting runs the networks on one sample per
    step, far below what pays for a thread hand-off: on 2 cores the teacher's step takes
    1.0 ms on one thread and 1.7 ms (p90 6.8 ms) on two while anything else runs."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """``x`` in float32 if autocast left it in a 16-bit type; float32 and float64 unchanged."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


class MLP(nn.Sequential):
    """``layers`` x (Linear, ELU), then a linear output layer unless ``out_dim`` is None."""

    def __init__(self, in_dim: int, out_dim: int | None, config: MLPConfig) -> None:
        parts: list[nn.Module] = []
        width = in_dim
        for _ in range(config.layers):
            parts += [nn.Linear(width, config.units), nn.ELU()]
            width = config.units
        if out_dim is not None:
            parts.append(nn.Linear(width, out_dim))
        super().__init__(*parts)


class LayerNormGRUCell(nn.Module):
    """DreamerV2's GRU: one linear map of [input, state], LayerNorm, update gate biased to -1."""

    def __init__(self, in_dim: int, size: int) -> None:
        super().__init__()
        self.size = size
        self.linear = nn.Linear(in_dim + size, 3 * size, bias=False)
        self.norm = nn.LayerNorm(3 * size)

    def forward(self, inputs: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """[..., in], [..., size] -> [..., size]."""
        parts = self.norm(self.linear(torch.cat([inputs, state], -1)))
        reset, candidate, update = parts.split(self.size, -1)
        candidate = torch.tanh(torch.sigmoid(reset) * candidate)
        update = torch.sigmoid(update - 1.0)
        return update * candidate + (1.0 - update) * state


class StateEncoder(MLP):
    """Privileged state [..., S] -> embedding [..., units]: the MLP's last hidden layer, read
    through :func:`~twist_models.losses.symlog` where ``symlog``."""

    def __init__(self, state_dim: int, config: MLPConfig, symlog: bool = False) -> None:
        super().__init__(state_dim, None, config)
        self.out_dim = config.units
        self.symlog = symlog

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return super().forward(symlog(state) if self.symlog else state)


class ImageEncoder(nn.Module):
    """DreamerV2's CNN: uint8 or [-0.5, 0.5] images [..., 64, 64, 3] -> [..., 1536] (depth 48);
    ``channels`` 6 reads two frames stacked (a frame pair)."""

    def __init__(self, config: CNNConfig, channels: int = 3) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        self.channels = channels
        for i, (kernel, stride) in enumerate(zip(config.encoder_kernels,
                                                 config.encoder_strides(), strict=True)):
            out = config.depth * 2**i
            layers.append(nn.Conv2d(channels, out, kernel, stride=stride))
            if config.norm == "layer":  # one group: normalised over channels and pixels
                layers.append(nn.GroupNorm(1, out))
            layers.append(nn.ELU())
            channels = out
        size = config.encoder_map_sizes()[-1]
        self.net = nn.Sequential(*layers)
        self.image_size = config.image_size
        self.out_dim = channels * size * size

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        lead = image.shape[:-3]
        x = preprocess_image(image).reshape(-1, *image.shape[-3:]).permute(0, 3, 1, 2)
        x = x.contiguous(memory_format=torch.channels_last)
        return self.net(x).reshape(*lead, self.out_dim)


def preprocess_image(image: torch.Tensor) -> torch.Tensor:
    """uint8 [0, 255] -> float [-0.5, 0.5]; float images are assumed already scaled."""
    if image.dtype == torch.uint8:
        return image.float() / 255.0 - 0.5
    return image


class ImageDecoder(nn.Module):
    """Feature [..., F] -> mean image [..., 64, 64, 3] in [-0.5, 0.5] units."""

    def __init__(self, in_dim: int, config: CNNConfig) -> None:
        super().__init__()
        kernels = config.decoder_kernels
        self.width = 32 * config.depth
        self.linear = nn.Linear(in_dim, self.width)
        layers: list[nn.Module] = []
        channels = self.width
        for i, kernel in enumerate(kernels):
            last = i == len(kernels) - 1
            out = 3 if last else config.depth * 2 ** (len(kernels) - i - 2)
            layers.append(nn.ConvTranspose2d(channels, out, kernel, stride=2))
            if not last:
                layers.append(nn.ELU())
            channels = out
        self.net = nn.Sequential(*layers)
        self.image_size = config.image_size

    def forward(self, feature: torch.Tensor) -> torch.Tensor:
        lead = feature.shape[:-1]
        x = self.linear(feature).reshape(-1, self.width, 1, 1)
        x = self.net(x).permute(0, 2, 3, 1)
        return x.reshape(*lead, *x.shape[1:])
