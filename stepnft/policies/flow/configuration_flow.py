"""Configuration of the flow-matching action expert (LeRobot-style ``configuration_*.py``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import ClassVar


@dataclass
class FlowPolicyConfig:
    """Sizes and sampling settings of a :class:`FlowPolicy`; saved as ``config.json``."""

    type: ClassVar[str] = "flow"

    state_dim: int = 39
    """Proprioceptive / state observation size (MetaWorld: 39)."""
    lang_dim: int = 384
    """Size of the frozen instruction embedding (0: no language input)."""
    lang_proj_dim: int = 64
    """The instruction embedding is projected to this size before the velocity MLP."""
    language_encoder: str = "default"
    """Frozen sentence encoder of the instructions: 'default' (packaged all-MiniLM-L6-v2) or a
    local sentence-transformers folder. Saved with the policy, so evaluation embeds alike."""
    action_dim: int = 4
    """Action dimensions A."""
    horizon: int = 4
    """Chunk length H: actions predicted per policy call."""
    n_exec: int = 4
    """Actions of the chunk executed before the policy is called again (<= horizon)."""
    hidden_dim: int = 256
    """Width of the velocity MLP."""
    num_layers: int = 3
    """Hidden layers of the velocity MLP."""
    time_embed_dim: int = 64
    """Sinusoidal embedding size of the flow time t."""
    num_inference_steps: int = 4
    """Denoising steps K of the samplers."""
    state_clip: float = 5.0
    """Normalised state features are clamped to [-state_clip, state_clip]."""
    state_min_std: float = 0.05
    """Floor on the per-dimension state std used for normalisation (few demos give tiny spreads)."""

    def __post_init__(self) -> None:
        for name in ("state_dim", "action_dim", "horizon", "n_exec", "hidden_dim", "num_layers", "num_inference_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"policy.{name} must be >= 1, got {getattr(self, name)}")
        if self.n_exec > self.horizon:
            raise ValueError(f"policy.n_exec ({self.n_exec}) must be <= policy.horizon ({self.horizon})")
        if self.time_embed_dim < 2 or self.time_embed_dim % 2:
            raise ValueError(f"policy.time_embed_dim must be even and >= 2 (sine and cosine pairs), got {self.time_embed_dim}")
        if self.lang_dim < 0 or (self.lang_dim > 0 and self.lang_proj_dim < 1):
            raise ValueError(f"policy.lang_dim must be >= 0 and policy.lang_proj_dim >= 1, got {self.lang_dim}, {self.lang_proj_dim}")
        if not (0 < self.state_min_std < float("inf") and 0 < self.state_clip < float("inf")):
            raise ValueError(f"policy.state_min_std and policy.state_clip must be finite and > 0, got "
                             f"{self.state_min_std}, {self.state_clip}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "FlowPolicyConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown policy config keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**data)
