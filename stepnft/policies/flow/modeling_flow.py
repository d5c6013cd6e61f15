"""A small π0-style flow-matching action expert: ``v_θ(x_t, t | o)`` over a chunk ``[H, A]``.

The observation is a state vector (normalised with statistics stored in the checkpoint) and,
optionally, a frozen instruction embedding. Saved as ``config.json`` + ``model.safetensors``;
loading never unpickles.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from stepnft.policies.flow.configuration_flow import FlowPolicyConfig
from stepnft.sampling import ChunkSample, sample_chunk

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"


def time_embedding(t: Tensor, dim: int) -> Tensor:
    """Sinusoidal features of the flow time ``t`` ``[B] -> [B, dim]``."""
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / max(half - 1, 1))
    angles = 2 * math.pi * t[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class FlowPolicy(nn.Module):
    """Velocity field over action chunks, conditioned on observation features."""

    def __init__(self, config: FlowPolicyConfig):
        super().__init__()
        self.config = config
        c = config
        self.register_buffer("state_mean", torch.zeros(c.state_dim))
        self.register_buffer("state_std", torch.ones(c.state_dim))
        self.lang_proj = nn.Linear(c.lang_dim, c.lang_proj_dim) if c.lang_dim > 0 else None
        in_dim = c.state_dim + (c.lang_proj_dim if c.lang_dim > 0 else 0) + c.horizon * c.action_dim + c.time_embed_dim
        layers: list[nn.Module] = []
        for i in range(c.num_layers):
            layers += [nn.Linear(in_dim if i == 0 else c.hidden_dim, c.hidden_dim), nn.SiLU()]
        layers.append(nn.Linear(c.hidden_dim, c.horizon * c.action_dim))
        self.net = nn.Sequential(*layers)

    # --- observation -----------------------------------------------------------------
    @torch.no_grad()
    def set_normalization(self, states: Tensor) -> None:
        """Fit state normalisation on ``states`` ``[N, state_dim]`` (std floored)."""
        self.state_mean.copy_(states.mean(dim=0))
        self.state_std.copy_(states.std(dim=0).clamp(min=self.config.state_min_std))

    def encode_obs(self, state: Tensor, lang: Tensor | None = None) -> Tensor:
        """Observation features ``[B, F]`` from ``state`` ``[B, S]`` and ``lang`` ``[B, L]``."""
        clip = self.config.state_clip
        feats = [((state - self.state_mean) / self.state_std).clamp(-clip, clip)]
        if self.lang_proj is not None:
            if lang is None:
                raise ValueError("this policy is conditioned on language: pass lang=[B, lang_dim]")
            feats.append(self.lang_proj(lang))
        return torch.cat(feats, dim=-1)

    # --- velocity field ----------------------------------------------------------------
    def velocity(self, obs_features: Tensor, x_t: Tensor, t: Tensor) -> Tensor:
        """``v_θ(x_t, t | o)``: ``obs_features`` ``[B, F]``, ``x_t`` ``[B, H, A]``, ``t`` ``[B]``."""
        temb = time_embedding(t, self.config.time_embed_dim)
        h = torch.cat([obs_features, x_t.flatten(1), temb], dim=-1)
        return self.net(h).view_as(x_t)

    def forward(self, state: Tensor, lang: Tensor | None, x_t: Tensor, t: Tensor) -> Tensor:
        return self.velocity(self.encode_obs(state, lang), x_t, t)

    @torch.no_grad()
    def sample(
        self,
        state: Tensor,
        lang: Tensor | None = None,
        noise_level: float = 0.0,
        generator: torch.Generator | None = None,
        stochastic_steps: str = "all",
        keep_path: bool = False,
    ) -> ChunkSample:
        """Sample chunks ``[B, H, A]``: ODE when ``noise_level = 0`` (evaluation), else Flow-SDE."""
        feats = self.encode_obs(state, lang)
        c = self.config
        return sample_chunk(
            lambda x, t: self.velocity(feats, x, t),
            (state.shape[0], c.horizon, c.action_dim),
            num_steps=c.num_inference_steps,
            noise_level=noise_level,
            generator=generator,
            stochastic_steps=stochastic_steps,
            device=state.device,
            keep_path=keep_path,
        )

    # --- save / load (LeRobot-style) ----------------------------------------------------
    def save_pretrained(self, directory: str | Path) -> Path:
        """Write ``config.json`` and ``model.safetensors`` into ``directory``."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        (directory / CONFIG_NAME).write_text(json.dumps({"type": "flow", **self.config.to_dict()}, indent=2))
        save_file({k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}, str(directory / WEIGHTS_NAME))
        return directory

    @classmethod
    def from_pretrained(cls, directory: str | Path, map_location: str = "cpu") -> "FlowPolicy":
        """Load a policy written by :meth:`save_pretrained` (safetensors only, no pickle)."""
        directory = Path(directory)
        config_path, weights_path = directory / CONFIG_NAME, directory / WEIGHTS_NAME
        if not config_path.is_file() or not weights_path.is_file():
            raise FileNotFoundError(f"no policy checkpoint at {directory}: expected {CONFIG_NAME} and {WEIGHTS_NAME}")
        try:
            data = json.loads(config_path.read_text())
            data.pop("type", None)
            policy = cls(FlowPolicyConfig.from_dict(data))
            policy.load_state_dict(load_file(str(weights_path), device=map_location))
        except (ValueError, RuntimeError, OSError, SafetensorError, json.JSONDecodeError) as err:
            raise ValueError(f"corrupt policy checkpoint at {directory}: {str(err).splitlines()[0]}") from err
        return policy
