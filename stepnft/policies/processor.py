"""Input processing outside the network (LeRobot's processors): raw observations from the
collector -> model inputs.

Raw observation dict (``stepnft.batch``): ``state`` float32 [B, S], ``task`` int64 [B] (an index
into the instructions the processor was bound to). Model inputs: ``state`` normalised with
statistics fitted on the demonstrations and clamped, ``lang`` the frozen instruction embedding
[B, L] (when the policy takes language).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from stepnft.policies.language import LanguageEncoder


class ObservationProcessor:
    """State normalisation and instruction lookup for state + language policies."""

    def __init__(self, state_dim: int, lang_dim: int = 0, language_encoder: str = "default",
                 state_clip: float = 5.0, state_min_std: float = 0.05):
        self.lang_dim, self.language_encoder = lang_dim, language_encoder
        self.state_clip, self.state_min_std = state_clip, state_min_std
        self.state_mean = torch.zeros(state_dim)
        self.state_std = torch.ones(state_dim)
        self.instructions: list[str] = []
        self.instruction_table: Tensor | None = None

    @torch.no_grad()
    def fit(self, states: Tensor) -> None:
        """Fit state normalisation on ``states`` ``[N, S]`` (std floored: few demonstrations give
        tiny spreads on goal and object dimensions)."""
        self.state_mean = states.mean(dim=0)
        self.state_std = states.std(dim=0).clamp(min=self.state_min_std)

    def bind_instructions(self, instructions: list[str], cache_dir: str | Path | None = None) -> None:
        """Embed the instructions that raw ``task`` indices refer to (cached on disk under ``cache_dir``)."""
        self.instructions = list(instructions)
        if self.lang_dim == 0:
            return
        table = LanguageEncoder(self.language_encoder, cache_dir=cache_dir).embed(self.instructions)
        if table.shape[1] != self.lang_dim:
            raise ValueError(f"language encoder {self.language_encoder!r} gives {table.shape[1]}-d embeddings "
                             f"but policy.lang_dim is {self.lang_dim}")
        self.instruction_table = table

    def __call__(self, raw: dict[str, Tensor]) -> dict[str, Tensor]:
        out = {"state": ((raw["state"] - self.state_mean) / self.state_std).clamp(-self.state_clip, self.state_clip)}
        if self.lang_dim > 0:
            if self.instruction_table is None:
                raise ValueError("this policy is conditioned on language: bind_instructions() before use")
            out["lang"] = self.instruction_table[raw["task"]]
        return out

    def state_dict(self) -> dict[str, Tensor]:
        return {"state_mean": self.state_mean, "state_std": self.state_std}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        for key in ("state_mean", "state_std"):
            if state[key].shape != self.state_mean.shape:
                raise ValueError(f"processor {key} has shape {tuple(state[key].shape)}, expected {tuple(self.state_mean.shape)}")
        self.state_mean, self.state_std = state["state_mean"].float(), state["state_std"].float()
