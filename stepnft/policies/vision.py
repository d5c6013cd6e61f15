"""Camera images for policies, in plain torch: the processor's image preparation, a small CNN
encoder shared by every view, and random-shift augmentation (DrQ's) for training.

Images arrive from the env as uint8 ``[B, V, 3, H, W]``; :func:`prepare_images` (in the
processor, outside the network) resizes them to the policy's ``image_size`` and scales them to
[-1, 1]; :class:`ImageEncoder` maps ``[B, V, 3, S, S]`` to ``[B, V * features]``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def prepare_images(images: Tensor, size: int) -> Tensor:
    """uint8 ``[B, V, 3, H, W]`` -> float32 ``[B, V, 3, size, size]`` in [-1, 1] (area
    resampling when the env renders at another size)."""
    if images.dtype != torch.uint8 or images.dim() != 5:
        raise ValueError(f"camera images must be uint8 [B, V, 3, H, W], got {images.dtype} {tuple(images.shape)}")
    b, v = images.shape[:2]
    x = images.flatten(0, 1).float().div_(127.5).sub_(1.0)
    if x.shape[-2:] != (size, size):
        x = F.interpolate(x, size=(size, size), mode="area")
    return x.view(b, v, 3, size, size)


def random_shift(images: Tensor, pad: int, generator: torch.Generator | None = None) -> Tensor:
    """Shift every image ``[B, V, C, H, W]`` by its own random offset of up to ``pad`` pixels
    (edges padded by replication, then cropped back to ``H x W``)."""
    if pad <= 0:
        return images
    shape = images.shape
    x = images.flatten(0, 1)
    n, c, h, w = x.shape
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, n), generator=generator)
    rows = (dy[:, None] + torch.arange(h))[:, None, :, None]
    cols = (dx[:, None] + torch.arange(w))[:, None, None, :]
    out = padded[torch.arange(n)[:, None, None, None], torch.arange(c)[None, :, None, None], rows, cols]
    return out.view(shape)


class ImageEncoder(nn.Module):
    """Four 3x3 convolutions (strides 2, 2, 2, 1) and a linear layer with LayerNorm, applied to
    each view with shared weights; the view features are concatenated in camera order."""

    def __init__(self, views: int, size: int, channels: int = 32, features: int = 64):
        super().__init__()
        layers: list[nn.Module] = []
        for i, stride in enumerate((2, 2, 2, 1)):
            layers += [nn.Conv2d(3 if i == 0 else channels, channels, 3, stride=stride, padding=1), nn.SiLU()]
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            flat = self.conv(torch.zeros(1, 3, size, size)).shape[1]
        self.head = nn.Sequential(nn.Linear(flat, features), nn.LayerNorm(features))
        self.views, self.out_dim = views, views * features

    def forward(self, images: Tensor) -> Tensor:
        """``[B, V, 3, S, S]`` (prepared) -> ``[B, V * features]``."""
        if images.shape[1] != self.views:
            raise ValueError(f"the policy sees {self.views} camera views, got images of {images.shape[1]}")
        return self.head(self.conv(images.flatten(0, 1))).view(images.shape[0], self.out_dim)
