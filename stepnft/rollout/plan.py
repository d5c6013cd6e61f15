"""What a collector plays: how to sample (:class:`RolloutSpec`, the algorithm's say) and which
episodes (:class:`EpisodePlan`, drawn by the collector or fixed by evaluation).

An episode of the plan is a task, a reset seed (its initial state) and a noise seed (its
sampler's generator): with the policy, these decide everything the episode does, whichever
sub-env plays it and whenever it does. A batch lists its episodes in plan order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from stepnft.settings import EVAL_SEEDS_END


@dataclass
class RolloutSpec:
    """How the collector samples and what it records for the update."""

    noise_level: float
    """Flow-SDE noise level ``a`` of the rollouts (0: ODE)."""
    stochastic_steps: Literal["all", "one"] = "all"
    """Every denoising step stochastic, or only the recorded one (the others ODE)."""
    record_steps: Literal["one", "all"] = "one"
    """Store one random denoising step per policy call, or all K of them."""
    group_size: int = 1
    """Episodes per group started from the same task and initial state (GRPO); 1: no groups."""
    mean_correction: bool = True
    """Flow-SDE steps with the drift correction that keeps the flow's marginals (False: the
    noise added to the plain Euler step, π-StepNFT's exploration ablation)."""


TRAINING_SEEDS = (EVAL_SEEDS_END, 2**31)
"""Reset seeds of training episodes: far above evaluation seeds and below demonstration seeds
(``stepnft.data.demos``)."""


@dataclass
class EpisodePlan:
    """Episodes to play, in the order the batch will hold them: ``task``, ``seed`` (reset seed)
    and ``noise_seed`` (seed of the episode's sampler generator), each ``[E]`` int64."""

    task: np.ndarray
    seed: np.ndarray
    noise_seed: np.ndarray

    def __post_init__(self) -> None:
        self.task, self.seed, self.noise_seed = (np.asarray(a, dtype=np.int64).reshape(-1)
                                                 for a in (self.task, self.seed, self.noise_seed))
        if not len(self.task) == len(self.seed) == len(self.noise_seed):
            raise ValueError("an episode plan needs one task, seed and noise seed per episode")

    def __len__(self) -> int:
        return len(self.task)

    def take(self, rows: np.ndarray) -> "EpisodePlan":
        """The episodes ``rows`` of this plan, in that order."""
        return EpisodePlan(self.task[rows], self.seed[rows], self.noise_seed[rows])

    def generators(self) -> list[torch.Generator]:
        """One sampler generator per episode, seeded by its noise seed."""
        return [torch.Generator().manual_seed(int(s)) for s in self.noise_seed]

    @classmethod
    def fixed(cls, num_tasks: int, episodes: int, seed: int) -> "EpisodePlan":
        """Evaluation: episode ``e`` of every task starts from initial state ``seed + e`` and
        samples with a generator seeded the same, so its outcome depends only on the policy and
        that seed (paired across runs). Task-major order."""
        task = np.repeat(np.arange(num_tasks), episodes)
        seeds = np.tile(seed + np.arange(episodes), num_tasks)
        return cls(task, seeds, seeds)

    @classmethod
    def draw(cls, task_episodes: list[int], group_size: int, generator: torch.Generator) -> "EpisodePlan":
        """Training: ``task_episodes[k]`` episodes of task ``k`` (each a multiple of
        ``group_size``), consecutive groups of ``group_size`` sharing one reset seed, every
        episode its own noise seed, all drawn from ``generator``. Task-major order."""
        if any(n % group_size for n in task_episodes):
            raise ValueError(f"episodes per task must be multiples of the group size {group_size}, got {task_episodes}")
        total = sum(task_episodes)
        groups = torch.randint(*TRAINING_SEEDS, (total // group_size,), generator=generator)
        noise = torch.randint(0, 2**62, (total,), generator=generator)
        task = np.repeat(np.arange(len(task_episodes)), task_episodes)
        return cls(task, groups.repeat_interleave(group_size).numpy(), noise.numpy())
