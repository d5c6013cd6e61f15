"""A policy network of one's own: stepnft's flow policy with a residual velocity network.

A policy type is a ``stepnft.policies.base.Policy`` subclass with a saved ``type`` and a config
class (a ``stepnft.policies.configuration.PolicyConfig`` dataclass: every field typed, ranged
and documented, as stepnft's own settings are). ``--policy.type residual_flow`` then builds it
from scratch, its fields are the ``--policy.*`` flags, and a saved folder loads it by its type.
Here the flow policy's observation encoding and processor are kept, and only the velocity MLP
is replaced.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, ClassVar

from torch import Tensor, nn

from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.settings import Range


@dataclass
class ResidualFlowConfig(FlowPolicyConfig):
    """The flow policy's settings, with the velocity network made of residual blocks."""

    type: ClassVar[str] = "residual_flow"
    blocks: Annotated[int, Range(ge=1, le=64)] = 2
    """Residual blocks (LayerNorm, Linear, SiLU, Linear, plus the input) of width hidden_dim."""


class ResidualBlock(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.body = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, width), nn.SiLU(), nn.Linear(width, width))

    def forward(self, h: Tensor) -> Tensor:
        return h + self.body(h)


class ResidualFlowPolicy(FlowPolicy):
    type = "residual_flow"
    config_class = ResidualFlowConfig

    def __init__(self, config: ResidualFlowConfig):
        super().__init__(config)  # the encoders, the processor and an MLP, replaced below
        c = config
        in_dim = self.net[0].in_features
        blocks = [ResidualBlock(c.hidden_dim) for _ in range(c.blocks)]
        self.net = nn.Sequential(nn.Linear(in_dim, c.hidden_dim), *blocks, nn.SiLU(),
                                 nn.Linear(c.hidden_dim, c.horizon * c.action_dim))
