"""An algorithm variant: π-StepNFT whose learning rate warms up linearly over its first iterations.

An algorithm is a ``stepnft.algos.base.Algorithm`` subclass whose ``config_class`` is an
``AlgoConfig`` dataclass; ``defaults`` sets its ``name`` (``--algo.name stepnft-warmup``) and any
inherited setting's default. Everything it owns beyond the policy goes in ``state_dict`` so a
resumed run continues exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

from stepnft.algos.stepnft import StepNFT, StepNFTConfig
from stepnft.batch import Batch
from stepnft.settings import Range


@dataclass
class StepNFTWarmupConfig(StepNFTConfig):
    """π-StepNFT's settings, and how long its learning rate warms up."""

    defaults: ClassVar[dict] = {**StepNFTConfig.defaults, "name": "stepnft-warmup"}
    warmup_iterations: Annotated[int, Range(ge=1, le=10**6)] = 10
    """Iterations over which the learning rate rises linearly from lr / warmup_iterations to lr."""


class StepNFTWarmup(StepNFT):
    config_class = StepNFTWarmupConfig

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.iteration = 0
        """The 0-based iteration the next update belongs to."""

    def update(self, batch: Batch) -> dict[str, float]:
        scale = min(1.0, (self.iteration + 1) / self.cfg.warmup_iterations)
        for group in self.optimizer.param_groups:
            group["lr"] = self.cfg.lr * scale
        return {**super().update(batch), "charts/learning_rate": self.cfg.lr * scale}

    def end_iteration(self, iteration: int) -> dict[str, float]:
        self.iteration = iteration + 1
        return super().end_iteration(iteration)

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "iteration": self.iteration}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.iteration = state["iteration"]
