"""GRPO with Flow-SDE (docs/algorithm.md §7): PPO's likelihood and clipped surrogate
(``stepnft.algos.likelihood``) without a critic. The collector starts groups of G episodes of a task
from one initial state (``RolloutSpec.group_size``); every call of an episode gets the episode's
success normalised within its group. A group whose episodes all succeeded or all failed gives 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from stepnft.algos.base import Algorithm
from stepnft.algos.likelihood import LikelihoodConfig, call_rewards, policy_gradient_update
from stepnft.batch import Batch


@dataclass
class GRPOConfig(LikelihoodConfig):
    """Hyperparameters of GRPO with Flow-SDE."""

    defaults = {"name": "grpo", "group_size": 4}

    def check(self) -> None:
        super().check()
        if self.group_size < 2:
            raise self.fail("{group_size} must be >= 2 for GRPO: it normalises success within each group",
                            self.group_size)


def episode_scores(batch: Batch, cfg: GRPOConfig) -> Tensor:
    """``[E]`` what GRPO normalises: the sum of an episode's call rewards (``reward: sparse``: its
    success 0/1; ``shaped``: success plus its last level minus its first, ``shaped_rewards`` with
    ``γ = 1``)."""
    return torch.zeros(batch.num_episodes).index_add_(0, batch.episode, call_rewards(batch, cfg))


def group_advantages(batch: Batch, eps: float = 1e-6, score: Tensor | None = None) -> Tensor:
    """``[E]`` per episode: ``(score - group mean) / (group std + eps)``, ``score`` ``[E]`` (None:
    success), groups keyed by ``(episode_task, episode_seed)``; std is the sample std (``n - 1``);
    0 in a group whose scores are all equal."""
    key = torch.stack([batch.episode_task, batch.episode_seed], dim=1)
    if bool((batch.episode_seed < 0).any()):
        raise ValueError("GRPO needs episodes grouped by a shared reset seed (RolloutSpec.group_size >= 2)")
    _, group = key.unique(dim=0, return_inverse=True)
    score = batch.episode_success.float() if score is None else score
    adv = torch.zeros_like(score)
    for g in group.unique():
        members = group == g
        if int(members.sum()) < 2:
            raise ValueError("a GRPO group holds a single episode: every group needs >= 2 episodes")
        s = score[members]
        if bool((s != s[0]).any()):  # equal scores give 0 exactly, not rounding over eps
            adv[members] = (s - s.mean()) / (s.std() + eps)
    return adv


class GRPO(Algorithm):
    """GRPO with Flow-SDE: the policy acts (no EMA), group-normalised success (or shaped return), no critic."""

    name = "grpo"
    config_class = GRPOConfig

    def update(self, batch: Batch) -> dict[str, float]:
        episode_adv = group_advantages(batch, score=episode_scores(batch, self.cfg))
        self.policy.train()
        metrics = policy_gradient_update(self.policy, self.optimizer, batch, episode_adv[batch.episode], self.cfg,
                                         self.generator, guard=self.guard)
        return metrics | {"charts/informative_episode_frac": float((episode_adv != 0).float().mean())}
