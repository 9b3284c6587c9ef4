"""Image augmentation for the first stage's single frames: colours, and where the camera is.

A read-out student loses the pole mostly in held-out scenes with pink, magenta or orange
poles against similar hues or fine rings, and D's K renders per state show each pose in few
colour combinations. Colour jitter re-colours whole frames, so every pose is also seen in
colours D never drew, while the geometry the read-out regresses (where the cart and pole
are) stays exactly as rendered. Measured on cartpole at the ``quick`` budget it changes
which scenes fail but not how many (research/log.md, "Where the read-out student loses
the pole"), so it is off by default.

A real camera is never exactly where the simulator's is. :func:`camera_jitter` moves and
rolls whole frames while the targets stay those of the unmoved scene, so that a read-out
cannot take a position from where it falls in the frame and must read it against the scene
(the rail, the floor), as DrQ's and RAD's random shifts do for pixel-based RL. Measured on
cartpole (moves of up to 8 pixels and rolls of up to 0.1 rad), it doubled the read-out's
error and lost the pole; rendering D with the camera moved (``train-wide-full``) held a moved
camera instead (docs/findings.md, "A moved camera and changed light"), so it is off by default.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

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


def camera_jitter(image: torch.Tensor, shift: float, roll: float,
                  generator: torch.Generator) -> torch.Tensor:
    """Move each sample of ``image`` uint8 [B, ..., H, W, 3] by up to ``shift`` pixels along
    each image axis and roll it by up to ``roll`` radians about the frame's centre (each drawn
    uniformly per sample; every frame of one sample alike), bilinearly, the border's pixels
    filling what comes into view -> uint8, the same shape."""
    b, (h, w) = image.shape[0], image.shape[-3:-1]
    angle = roll * (2 * torch.rand(b, generator=generator) - 1)
    offset = shift * (2 * torch.rand(b, 2, generator=generator) - 1)
    cos, sin = torch.cos(angle), torch.sin(angle)
    # affine_grid works in [-1, 1] coordinates: a pixel is 2 / side of them.
    theta = torch.stack([torch.stack([cos, -sin * h / w, 2 * offset[:, 1] / w], -1),
                         torch.stack([sin * w / h, cos, 2 * offset[:, 0] / h], -1)], 1)
    frames = image.reshape(b, -1, h, w, 3)
    n = frames.shape[1]
    x = frames.permute(0, 1, 4, 2, 3).reshape(b, n * 3, h, w).float()
    grid = F.affine_grid(theta, [b, n * 3, h, w], align_corners=False)
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
    out = out.reshape(b, n, 3, h, w).permute(0, 1, 3, 4, 2).reshape(image.shape)
    return out.round_().clamp_(0, 255).to(torch.uint8)


#: The largest roll :func:`camera_jitter` may be asked for: a quarter turn.
MAX_ROLL = math.pi / 2
