"""Input processing outside the network (LeRobot's processors): raw observations from the
collector -> model inputs.

Raw observation dict (``stepnft.batch``): ``state`` float32 [B, S], ``task`` int64 [B] (an index
into the instructions the processor was bound to), optionally ``instruction`` int64 [B] (which
of the task's instruction variants: semantic perturbations) and ``image`` uint8
[B, V, 3, H, W] (camera policies). Model inputs: ``state`` normalised with statistics fitted on
the demonstrations and clamped, ``lang`` the frozen instruction embedding [B, L] (when the policy
takes language), ``image`` float [B, V, 3, S, S] in [-1, 1] (``stepnft.policies.vision``).
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import Tensor

from stepnft.policies.language import LanguageEncoder
from stepnft.policies.vision import prepare_images


class ObservationProcessor:
    """State normalisation, instruction lookup and image preparation."""

    def __init__(self, state_dim: int, lang_dim: int = 0, language_encoder: str = "default",
                 state_clip: float = 5.0, state_min_std: float = 0.05, image_size: int = 0):
        self.lang_dim, self.language_encoder = lang_dim, language_encoder
        self.state_clip, self.state_min_std = state_clip, state_min_std
        self.image_size = image_size
        self.state_mean = torch.zeros(state_dim)
        self.state_std = torch.ones(state_dim)
        self.instructions: list[str] = []
        self.instruction_variants: list[list[str]] = []
        self.instruction_table: Tensor | None = None
        self._first_variant = torch.zeros(0, dtype=torch.int64)
        self._variant_count = torch.zeros(0, dtype=torch.int64)

    @torch.no_grad()
    def fit(self, states: Tensor) -> None:
        """Fit state normalisation on ``states`` ``[N, S]`` (std floored: few demonstrations give
        tiny spreads on goal and object dimensions)."""
        self.state_mean = states.mean(dim=0)
        self.state_std = states.std(dim=0).clamp(min=self.state_min_std)

    def bind_instructions(self, instructions: Sequence[str | Sequence[str]], cache_dir: str | Path | None = None) -> None:
        """Embed the instructions that raw ``task`` indices refer to (cached on disk under
        ``cache_dir``). An entry may be a list of the task's instruction variants (a vector
        env's ``instruction_variants``): the raw ``instruction`` index picks one, the first when
        absent. ``instruction_table`` holds every variant, task after task."""
        variants = [[item] if isinstance(item, str) else list(item) for item in instructions]
        self.instruction_variants = variants
        self.instructions = [v[0] for v in variants]
        counts = torch.tensor([len(v) for v in variants], dtype=torch.int64)
        self._variant_count, self._first_variant = counts, torch.cumsum(counts, 0) - counts
        if self.lang_dim == 0:
            return
        table = LanguageEncoder(self.language_encoder, cache_dir=cache_dir).embed([t for v in variants for t in v])
        if table.shape[1] != self.lang_dim:
            raise ValueError(f"language encoder {self.language_encoder!r} gives {table.shape[1]}-d embeddings "
                             f"but policy.lang_dim is {self.lang_dim}")
        self.instruction_table = table

    @contextmanager
    def bound(self, instructions: Sequence[str | Sequence[str]], cache_dir: str | Path | None = None):
        """Within the block, bound to ``instructions`` (e.g. a suite's variants); restored after."""
        saved = (self.instructions, self.instruction_variants, self.instruction_table, self._first_variant,
                 self._variant_count)
        try:
            self.bind_instructions(instructions, cache_dir)
            yield self
        finally:
            (self.instructions, self.instruction_variants, self.instruction_table, self._first_variant,
             self._variant_count) = saved

    def __call__(self, raw: dict[str, Tensor]) -> dict[str, Tensor]:
        out = {"state": ((raw["state"] - self.state_mean) / self.state_std).clamp(-self.state_clip, self.state_clip)}
        if self.lang_dim > 0:
            if self.instruction_table is None:
                raise ValueError("this policy is conditioned on language: bind_instructions() before use")
            out["lang"] = self.instruction_table[self._instruction_rows(raw)]
        if self.image_size:
            if "image" not in raw:
                raise ValueError("this policy sees camera images: the env must render them (env.cameras)")
            out["image"] = prepare_images(raw["image"], self.image_size)
        return out

    def _instruction_rows(self, raw: dict[str, Tensor]) -> Tensor:
        task = raw["task"]
        if "instruction" not in raw:
            return self._first_variant[task]
        variant = raw["instruction"]
        if bool((variant >= self._variant_count[task]).any()):
            raise ValueError("an instruction variant index is out of range: bind the vector env's instruction_variants")
        return self._first_variant[task] + variant

    def state_dict(self) -> dict[str, Tensor]:
        return {"state_mean": self.state_mean, "state_std": self.state_std}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        for key in ("state_mean", "state_std"):
            if state[key].shape != self.state_mean.shape:
                raise ValueError(f"processor {key} has shape {tuple(state[key].shape)}, expected {tuple(self.state_mean.shape)}")
            if not bool(torch.isfinite(state[key]).all()):
                raise ValueError(f"processor {key} holds non-finite values")
        if not bool((state["state_std"] > 0).all()):
            raise ValueError("processor state_std must be > 0 everywhere")
        self.state_mean, self.state_std = state["state_mean"].float(), state["state_std"].float()
