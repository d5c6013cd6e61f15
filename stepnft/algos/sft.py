"""Few-shot behaviour cloning: the flow-matching SFT loss over demonstration chunks (SPEC §1)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from stepnft.losses import flow_matching_loss
from stepnft.sampling import flow_matching_pair, sample_flow_time


@dataclass
class SFTConfig:
    """Hyperparameters of flow-matching behaviour cloning."""

    steps: int = 3000
    """Gradient steps."""
    batch_size: int = 256
    """Chunks per gradient step."""
    lr: float = 3e-4
    """AdamW learning rate."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    time_law: str = "uniform"
    """Law of the flow time t during training: ``uniform`` or ``beta`` (π0's)."""

    def __post_init__(self) -> None:
        if self.steps < 0 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError("sft.steps must be >= 0, sft.batch_size >= 1 and sft.lr > 0")
        if self.time_law not in ("uniform", "beta"):
            raise ValueError(f"sft.time_law must be 'uniform' or 'beta', got {self.time_law!r}")


def sft_train(
    policy: nn.Module,
    data: dict[str, Tensor],
    cfg: SFTConfig,
    generator: torch.Generator | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Fit ``policy`` to demonstration chunks; returns the loss of every step.

    ``data``: ``state`` [N, S], ``lang`` [N, L] (optional), ``actions`` [N, H, A] in [-1, 1],
    ``mask`` [N, H] (False on positions padded past an episode's end).
    """
    optimizer = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    n = data["actions"].shape[0]
    losses: list[float] = []
    policy.train()
    for step in range(cfg.steps):
        idx = torch.randint(0, n, (min(cfg.batch_size, n),), generator=generator)
        actions = data["actions"][idx]
        t = sample_flow_time(len(idx), generator, cfg.time_law)
        noise = torch.randn(actions.shape, generator=generator)
        x_t, v_target = flow_matching_pair(actions, t, noise)
        lang = data["lang"][idx] if "lang" in data else None
        loss = flow_matching_loss(policy(data["state"][idx], lang, x_t, t), v_target, data["mask"][idx])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        if on_step is not None:
            on_step(step, losses[-1])
    return losses
