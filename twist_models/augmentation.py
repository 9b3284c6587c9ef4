"""Image augmentation for the first stage's single frames.

A read-out student loses the pole mostly in held-out scenes with pink, magenta or orange
poles against similar hues or fine rings, and D's K renders per state show each pose in few
colour combinations. Colour jitter re-colours whole frames, so every pose is also seen in
colours D never drew, while the geometry the read-out regresses (where the cart and pole
are) stays exactly as rendered. Measured on cartpole at the ``quick`` budget it changes
which scenes fail but not how many (docs/experiments.md, "Where the read-out student loses
the pole"), so it is off by default.
"""

from __future__ import annotations

import torch

#: Per-channel gain range and offset range (0-255 levels) of :func:`colour_jitter`.
GAIN = (0.7, 1.3)
OFFSET = 40.0


def colour_jitter(image: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Re-colour each frame of ``image`` uint8 [B, ..., H, W, 3]: a random permutation of
    its RGB channels, then a random gain (:data:`GAIN`) and offset (±:data:`OFFSET`) per
    channel, clipped to 0-255. Every frame of one sample (the ``...`` axes: its stacked
    frames) is re-coloured alike -> uint8, the same shape."""
    b = image.shape[0]
    shape = (b,) + (1,) * (image.dim() - 2) + (3,)
    order = torch.argsort(torch.rand(b, 3, generator=generator), -1).view(shape)
    x = torch.gather(image.float(), -1, order.expand(image.shape))
    gain = GAIN[0] + (GAIN[1] - GAIN[0]) * torch.rand(shape, generator=generator)
    offset = OFFSET * (2 * torch.rand(shape, generator=generator) - 1)
    return (x * gain + offset).clamp_(0, 255).round_().to(torch.uint8)
