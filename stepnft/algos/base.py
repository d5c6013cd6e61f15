"""The algorithm interface: what the training loop asks of π-StepNFT, PPO, GRPO, ...

An algorithm owns everything it learns with (optimizer, EMA copy, critic, ...) and tells the
collector how to roll out. The loop, per iteration::

    batch = collector.collect(algo.acting_policy(), episodes, algo.rollout)
    metrics = algo.update(batch)          # stable names: losses/..., charts/...
    metrics |= algo.end_iteration(it)     # e.g. the EMA update
    ... evaluate algo.eval_policy() ...

``state_dict()`` / ``load_state_dict()`` cover everything the algorithm owns, so a checkpoint
resumes it exactly. ``algo.name`` in the config picks the class from ``ALGORITHMS``.
"""

from __future__ import annotations

import importlib
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor, nn

from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.policies.base import Policy
from stepnft.rollout.plan import RolloutSpec  # noqa: F401 - what an algorithm tells the collector

ALGORITHMS: dict[str, str] = {
    "stepnft": "stepnft.algos.stepnft:StepNFT",
    "ppo": "stepnft.algos.ppo:PPO",
    "grpo": "stepnft.algos.grpo:GRPO",
}
"""Registered algorithms by ``algo.name`` (imported on first use). A new algorithm adds a line."""


@dataclass
class AlgoConfig:
    """Settings every algorithm has: its name and the optimizer of the policy."""

    name: str = "stepnft"
    """Which algorithm: the keys of ``stepnft.algos.base.ALGORITHMS``."""
    lr: float = 1e-4
    """AdamW learning rate of the policy."""
    adam_betas: tuple[float, float] = (0.9, 0.95)
    """AdamW (beta1, beta2)."""
    adam_eps: float = 1e-8
    """AdamW epsilon."""
    weight_decay: float = 0.0
    """AdamW weight decay."""
    grad_clip: float = 1.0
    """Global gradient-norm clip."""
    update_epochs: int = 2
    """Passes over each iteration's samples."""
    minibatch_size: int = 128
    """Samples per gradient step."""
    nonfinite_patience: int = 20
    """Optimizer steps in a row whose loss or gradient is not finite (each is skipped and counted
    as ``losses/skipped_nonfinite``) before the run stops with its last checkpoint intact."""

    def check(self) -> dict[str, bool]:
        """Named validity checks; subclasses add theirs. ``__post_init__`` raises on the first failure."""
        return {
            "name": self.name in ALGORITHMS and algorithm_class(self.name).config_class is type(self),
            "lr": 0 < self.lr < math.inf,
            "adam_betas": len(self.adam_betas) == 2 and all(0 <= b < 1 for b in self.adam_betas),
            "adam_eps": 0 < self.adam_eps < math.inf,
            "weight_decay": 0 <= self.weight_decay < math.inf,
            "grad_clip": 0 < self.grad_clip < math.inf,
            "update_epochs": self.update_epochs >= 1,
            "minibatch_size": self.minibatch_size >= 1,
            "nonfinite_patience": self.nonfinite_patience >= 1,
        }

    def __post_init__(self) -> None:
        self.adam_betas = tuple(self.adam_betas)
        if self.name not in ALGORITHMS:
            raise ValueError(f"unknown algorithm {self.name!r}; choose one of: {', '.join(ALGORITHMS)}")
        bad = [k for k, ok in self.check().items() if not ok]
        if bad:
            k = bad[0]
            raise ValueError(f"algo.{k}={getattr(self, k)!r} is invalid (see `stepnft train --help` for the allowed range)")


class RunDiverged(RuntimeError):
    """Training produced non-finite values too often to go on; the last checkpoint is intact."""


class NonFiniteGuard:
    """Skips optimizer steps whose loss or gradient is not finite, counts them, and stops the
    run after ``patience`` in a row (before anything non-finite reaches the weights)."""

    def __init__(self, cfg: AlgoConfig):
        self.cfg, self.in_a_row, self.skipped = cfg, 0, 0

    def step(self, loss: torch.Tensor, params: list[torch.Tensor], optimizer: torch.optim.Optimizer) -> float | None:
        """Backpropagate ``loss``, clip, and step if everything is finite; returns the gradient
        norm, or None for a skipped step."""
        optimizer.zero_grad(set_to_none=True)
        grad_norm = None
        if torch.isfinite(loss):
            loss.backward()
            grad_norm = float(torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip))
        if grad_norm is None or not math.isfinite(grad_norm):
            optimizer.zero_grad(set_to_none=True)
            self.skipped += 1
            self.in_a_row += 1
            if self.in_a_row >= self.cfg.nonfinite_patience:
                raise RunDiverged(
                    f"the loss or its gradient was not finite for {self.in_a_row} optimizer steps in a row: the "
                    f"learning rate (algo.lr={self.cfg.lr:g}) or another scale of algo.* is likely too large; "
                    "the last checkpoint is intact")
            return None
        self.in_a_row = 0
        optimizer.step()
        return grad_norm

    def take_skipped(self) -> int:
        """Steps skipped since the last call (for ``losses/skipped_nonfinite``)."""
        skipped, self.skipped = self.skipped, 0
        return skipped


def make_optimizer(params, cfg: AlgoConfig) -> torch.optim.Optimizer:
    """AdamW with every setting from the config."""
    return torch.optim.AdamW(params, lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps, weight_decay=cfg.weight_decay)


def step_velocity(learner: nn.Module, policy: Policy, batch: Batch, rows: Tensor) -> Tensor:
    """The learner's velocity ``[R, H, A]`` at recorded steps ``rows`` of ``batch`` (which stays
    on the CPU): their observations processed on the CPU, the forward pass on the policy's device."""
    x_t, t = to_device((batch.x_t[rows], batch.t[rows]), policy.device)
    return learner(policy.prepare(batch.steps_obs(rows)), x_t, t)


class Algorithm(ABC):
    """One RL fine-tuning method (see the module doc for the loop that drives it)."""

    name: ClassVar[str]
    config_class: ClassVar[type[AlgoConfig]]

    def __init__(self, policy: Policy, cfg: AlgoConfig, iterations: int, generator: torch.Generator):
        self.policy, self.cfg, self.iterations, self.generator = policy, cfg, iterations, generator

    @property
    @abstractmethod
    def rollout(self) -> RolloutSpec:
        """How the collector should sample and record."""

    @abstractmethod
    def acting_policy(self) -> Policy:
        """The policy that acts in training rollouts."""

    def eval_policy(self) -> Policy:
        """The policy that evaluation and ``policy/`` report (default: the trained one)."""
        return self.policy

    @abstractmethod
    def update(self, batch: Batch) -> dict[str, float]:
        """Learn from one iteration's batch; returns metrics under stable names."""

    def end_iteration(self, iteration: int) -> dict[str, float]:
        """Called once after each iteration's update (0-based ``iteration``); returns metrics."""
        return {}

    @abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """Everything the algorithm owns beyond the policy weights (tensors and JSON values)."""

    @abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""


def algorithm_class(name: str) -> type[Algorithm]:
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; choose one of: {', '.join(ALGORITHMS)}")
    module, cls = ALGORITHMS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def config_class(name: str) -> type[AlgoConfig]:
    """The config dataclass of algorithm ``name``."""
    return algorithm_class(name).config_class


def make_algorithm(cfg: AlgoConfig, policy: Policy, iterations: int, generator: torch.Generator) -> Algorithm:
    return algorithm_class(cfg.name)(policy, cfg, iterations, generator)
