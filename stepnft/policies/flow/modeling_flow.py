"""A small π0-style flow-matching action expert: ``v_θ(x_t, t | o)`` over a chunk ``[H, A]``.

The observation context is the processed state vector, optionally a projection of the frozen
instruction embedding and, for camera policies (``config.cameras``), the features of a small CNN
over each view (``stepnft.policies.vision``); an MLP maps (context, flattened ``x_t``, time
embedding) to the velocity.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from stepnft.policies.base import Policy
from stepnft.policies.flow.configuration_flow import FlowPolicyConfig
from stepnft.policies.processor import ObservationProcessor
from stepnft.policies.vision import ImageEncoder


def time_embedding(t: Tensor, dim: int) -> Tensor:
    """Sinusoidal features of the flow time ``t`` ``[B] -> [B, dim]``."""
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / max(half - 1, 1))
    angles = 2 * math.pi * t[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class FlowPolicy(Policy):
    """Velocity MLP over action chunks, conditioned on state (+ instruction) features."""

    type = "flow"
    config_class = FlowPolicyConfig

    def __init__(self, config: FlowPolicyConfig):
        super().__init__(config)
        c = config
        self.lang_proj = nn.Linear(c.lang_dim, c.lang_proj_dim) if c.lang_dim > 0 else None
        self.image_encoder = (ImageEncoder(len(c.cameras), c.image_size, c.image_channels, c.image_features)
                              if c.cameras else None)
        in_dim = c.state_dim + (c.lang_proj_dim if c.lang_dim > 0 else 0) + c.horizon * c.action_dim + c.time_embed_dim
        in_dim += self.image_encoder.out_dim if self.image_encoder is not None else 0
        layers: list[nn.Module] = []
        for i in range(c.num_layers):
            layers += [nn.Linear(in_dim if i == 0 else c.hidden_dim, c.hidden_dim), nn.SiLU()]
        layers.append(nn.Linear(c.hidden_dim, c.horizon * c.action_dim))
        self.net = nn.Sequential(*layers)

    @staticmethod
    def make_processor(config: FlowPolicyConfig) -> ObservationProcessor:
        return ObservationProcessor(config.state_dim, config.lang_dim, config.language_encoder,
                                    config.state_clip, config.state_min_std,
                                    image_size=config.image_size if config.cameras else 0)

    def encode(self, obs: dict[str, Tensor]) -> Tensor:
        """Observation features ``[B, F]`` from processed ``state`` ``[B, S]``, ``lang`` ``[B, L]``
        and ``image`` ``[B, V, 3, S, S]``."""
        feats = [obs["state"]]
        if self.lang_proj is not None:
            feats.append(self.lang_proj(obs["lang"]))
        if self.image_encoder is not None:
            feats.append(self.image_encoder(obs["image"]))
        return torch.cat(feats, dim=-1)

    def denoise(self, context: Tensor, x_t: Tensor, t: Tensor) -> Tensor:
        temb = time_embedding(t, self.config.time_embed_dim)
        h = torch.cat([context, x_t.flatten(1), temb], dim=-1)
        return self.net(h).view_as(x_t)
