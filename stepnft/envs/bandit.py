"""A contextual bandit with binary success, for unit tests and the core demo (not a benchmark).

The context ``c ~ U[-1, 1]^2`` sets a target action ``g(c)``; a chunk succeeds when every
executed action lies within ``radius`` of it. Demonstrations come from a biased, noisy expert,
so behaviour cloning succeeds only part of the time and RL has room to improve.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


class ContextBandit:
    """One-step episodes: context ``[B, 2]`` in, chunk ``[B, H, 2]`` out, success ``[B]`` bool."""

    context_dim = 2
    action_dim = 2

    def __init__(self, horizon: int = 2, radius: float = 0.15, demo_bias: float = 0.12, demo_noise: float = 0.08):
        self.horizon, self.radius = horizon, radius
        self.demo_bias, self.demo_noise = demo_bias, demo_noise

    def contexts(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        return torch.rand(batch, self.context_dim, generator=generator) * 2 - 1

    def target(self, context: Tensor) -> Tensor:
        """The context-dependent centre of the success region ``[B, 2]``."""
        return 0.6 * torch.stack([torch.sin(math.pi * context[:, 0]), context[:, 0] * context[:, 1]], dim=-1)

    def success(self, context: Tensor, actions: Tensor) -> Tensor:
        """True where every action of the chunk is within ``radius`` of the target."""
        dist = (actions.clamp(-1, 1) - self.target(context)[:, None]).norm(dim=-1)
        return (dist < self.radius).all(dim=-1)

    def demos(self, batch: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Biased expert chunks: ``(context [B, 2], actions [B, H, 2])``."""
        context = self.contexts(batch, generator)
        offset = torch.tensor([self.demo_bias, -self.demo_bias]) / math.sqrt(2)
        noise = self.demo_noise * torch.randn(batch, self.horizon, self.action_dim, generator=generator)
        actions = self.target(context)[:, None] + offset + noise
        return context, actions.clamp(-1, 1)
