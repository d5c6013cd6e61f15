"""Configuration of the flow-matching action expert (LeRobot-style ``configuration_*.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, ClassVar

from stepnft.policies.configuration import PolicyConfig
from stepnft.settings import WIDTH_MAX, Check, Range


@dataclass
class FlowPolicyConfig(PolicyConfig):
    """Sizes and sampling settings of a :class:`FlowPolicy`; saved as ``config.json``."""

    type: ClassVar[str] = "flow"
    section: ClassVar[str] = "policy"

    state_dim: Annotated[int, Range(ge=1, le=WIDTH_MAX)] = 39
    """Proprioceptive / state observation size (MetaWorld: 39)."""
    lang_dim: Annotated[int, Range(ge=0, le=WIDTH_MAX)] = 384
    """Size of the frozen instruction embedding (0: no language input)."""
    lang_proj_dim: Annotated[int, Range(ge=1, le=WIDTH_MAX)] = 64
    """The instruction embedding is projected to this size before the velocity MLP."""
    language_encoder: Annotated[str, Check(lambda name: bool(name.strip()), "default or a folder")] = "default"
    """Frozen sentence encoder of the instructions: 'default' (packaged all-MiniLM-L6-v2) or a
    local sentence-transformers folder. Saved with the policy, so evaluation embeds alike."""
    action_dim: Annotated[int, Range(ge=1, le=1024)] = 4
    """Action dimensions A."""
    horizon: Annotated[int, Range(ge=1, le=1024)] = 4
    """Chunk length H: actions predicted per policy call."""
    n_exec: Annotated[int, Range(ge=1, le=1024)] = 4
    """Actions of the chunk executed before the policy is called again (<= horizon)."""
    hidden_dim: Annotated[int, Range(ge=1, le=WIDTH_MAX)] = 256
    """Width of the velocity MLP."""
    num_layers: Annotated[int, Range(ge=1, le=256)] = 3
    """Hidden layers of the velocity MLP."""
    time_embed_dim: Annotated[int, Range(ge=2, le=WIDTH_MAX)] = 64
    """Sinusoidal embedding size of the flow time t (even: sine and cosine pairs)."""
    num_inference_steps: Annotated[int, Range(ge=1, le=1000)] = 4
    """Denoising steps K of the samplers."""
    state_clip: Annotated[float, Range(gt=0, le=1e6)] = 5.0
    """Normalised state features are clamped to [-state_clip, state_clip]."""
    state_min_std: Annotated[float, Range(gt=0, le=1e6)] = 0.05
    """Floor on the per-dimension state std used for normalisation (few demos give tiny spreads)."""
    cameras: list[str] = field(default_factory=list)
    """Camera views the policy sees, in order (empty: a state policy); must equal env.cameras.
    A camera policy encodes each view with a small CNN (``stepnft.policies.vision``)."""
    image_size: Annotated[int, Range(ge=16, le=256)] = 64
    """Side of the square images the CNN takes (the processor resizes the env's images to it)."""
    image_channels: Annotated[int, Range(ge=1, le=4096)] = 32
    """Channels of each of the CNN's four convolutions (shared by every view)."""
    image_features: Annotated[int, Range(ge=1, le=WIDTH_MAX)] = 64
    """Features per view out of the CNN, fused with the state and instruction features."""

    def check(self) -> None:
        if self.n_exec > self.horizon:
            raise self.fail(f"{{n_exec}} ({self.n_exec}) must be <= {{horizon}} ({self.horizon})")
        if self.time_embed_dim % 2:
            raise self.fail("{time_embed_dim} must be even (sine and cosine pairs)", self.time_embed_dim)
