"""What the likelihood-based baselines, PPO (``stepnft.algos.ppo``) and GRPO
(``stepnft.algos.grpo``), share (docs/algorithm.md §7): the current policy acts with Flow-SDE, the
denoising chain is part of the decision, so a policy call's log-likelihood is the Gaussian
log-density of its stochastic denoising step(s); the clipped surrogate on it, with advantages per
call, updates the policy. Reads top to bottom: config, the likelihood of a call, rewards and
weights, the update.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Callable, Literal, Sequence

import torch
from torch import Tensor

from stepnft.algos.base import (AlgoConfig, MinibatchEpochs, NonFiniteGuard, call_progress, call_step_rows,
                                episode_weights, step_velocity)
from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.distributed import data_parallel, shard_forward
from stepnft.losses import clipped_policy_loss
from stepnft.policies.base import Policy
from stepnft.sampling import sde_step_log_prob
from stepnft.settings import Range


@dataclass
class LikelihoodConfig(AlgoConfig):
    """What PPO and GRPO share besides ``AlgoConfig``: the clipped surrogate on the log-density of
    the stochastic denoising steps, and the reward they learn from."""

    defaults = {"noise_level": 0.5}

    clip_coef: Annotated[float, Range(gt=0, le=10)] = 0.2
    """PPO clip range ε of the ratio ``exp(log π - log π_old)``."""
    target_kl: Annotated[float | None, Range(gt=0, le=100)] = None
    """Skip the rest of an iteration's updates once a minibatch's approx-KL exceeds this (looked
    at before stepping); None: off."""
    reward: Literal["sparse", "shaped"] = "sparse"
    """``sparse``: 1 at the call that ends a successful episode, else 0. ``shaped``: that plus how
    far the call moved the simulator's shaped reward, as potential-based shaping (``shaped_rewards``):
    the information π-StepNFT's ``labels: progress`` reads. Needs a reward that measures progress
    (MetaWorld's does)."""

    def check(self) -> None:
        super().check()
        if self.noise_level == 0:
            raise self.fail("{noise_level} must be > 0 for PPO and GRPO: their likelihood needs noise (the ODE "
                            "ablation is π-StepNFT's)", self.noise_level)


# --- the likelihood of a policy call ------------------------------------------------------------
def steps_log_prob(batch: Batch, rows: Tensor, v: Tensor, noise_level: float) -> Tensor:
    """``[R]`` log-density of recorded steps ``rows`` under velocity ``v`` ``[R, H, A]``, over
    the chunk positions their call executed (on ``v``'s device)."""
    x_next, x_t, t, dt, mask = to_device((batch.x_next[rows], batch.x_t[rows], batch.t[rows], batch.dt[rows],
                                          batch.mask[batch.call[rows]]), v.device)
    return sde_step_log_prob(x_next, x_t, v, t, dt, noise_level, mask)


# --- rewards and weights ----------------------------------------------------------------------
def success_rewards(batch: Batch) -> Tensor:
    """``[C]`` sparse reward: 1 at the last call of a successful episode, 0 elsewhere."""
    return (batch.done & batch.episode_success[batch.episode]).float()


def shaped_rewards(batch: Batch, gamma: float) -> Tensor:
    """``[C]`` the sparse reward plus potential-based shaping ``γ L_c - L_{c-1}``, ``L_c`` the
    call's mean reward per executed env step (MetaWorld: in [0, 10], a function of the state) and
    ``L_{-1} = L_0``. Summed with discount ``γ`` over an episode's remaining calls the shaping
    telescopes to the discounted last level minus the level before: where the episode ends up
    counts, not how long it lingers near the goal, so the episodes that end at a success are not
    paid less than those that hover and run to the step cap. ``γ = 1`` gives π-StepNFT's progress
    (``call_progress`` with λ = 0)."""
    level = batch.reward / batch.mask.sum(dim=1).clamp(min=1)
    return success_rewards(batch) + call_progress(batch, 0.0) - (1.0 - gamma) * level


def call_rewards(batch: Batch, cfg: LikelihoodConfig, gamma: float = 1.0) -> Tensor:
    """``[C]`` the reward of every call as ``cfg.reward`` says (``gamma``: the discount of the
    shaping, PPO's; GRPO sums an episode's rewards undiscounted)."""
    return success_rewards(batch) if cfg.reward == "sparse" else shaped_rewards(batch, gamma)


def call_weights(batch: Batch, cfg: AlgoConfig) -> Tensor | None:
    """``[C]`` weights giving every episode the same total weight (mean 1) with
    ``episode_weighting``; None: every call weighs 1."""
    return episode_weights(batch.episode) if cfg.episode_weighting else None


# --- the update ---------------------------------------------------------------------------------
POLICY_METRICS = ("policy_loss", "approx_kl", "old_approx_kl", "clipfrac", "ratio_max")
"""The clipped surrogate's metrics (``losses/...``), logged every iteration: NaN (null in
metrics.jsonl) when every minibatch was skipped."""


def policy_gradient_update(
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    advantages: Tensor,
    cfg: LikelihoodConfig,
    generator: torch.Generator | None = None,
    extra_step: Callable[[Tensor], dict[str, float]] | None = None,
    guard: NonFiniteGuard | None = None,
    joint_loss: Callable[[Tensor], tuple[Tensor, dict[str, float]]] | None = None,
    joint_params: Sequence[Tensor] = (),
) -> dict[str, float]:
    """``cfg.update_epochs`` epochs of clipped-surrogate steps over minibatches of whole policy calls
    (``cfg.minibatch_size`` recorded steps: ``minibatch_size // K`` calls of K recorded steps),
    ``advantages`` ``[C]`` per call; with ``episode_weighting`` each call's term is weighted so
    that every episode weighs the same (folded into its advantage: a positive weight commutes with
    the clip). ``log π_old`` comes from the recorded ``v_old`` (the acting
    policy is the policy itself, so no extra forward pass). ``extra_step(calls)`` runs after each
    policy step on the same calls (PPO's critic); its metrics are averaged over steps.
    ``joint_loss(calls)`` is instead added to the policy's loss before its step (PPO's critic on
    the policy's own features), its ``joint_params`` stepped and clipped with the policy's by
    ``optimizer``. Steps with a non-finite loss or gradient are skipped (``guard``). Returns
    metrics averaged over minibatches.
    Under ``torchrun`` the processes share each minibatch (``stepnft.distributed``)."""
    guard = guard or NonFiniteGuard(cfg)
    learner = data_parallel(policy)
    rows = call_step_rows(batch)
    per_call = rows.shape[1]
    with torch.no_grad():
        old_log_prob = steps_log_prob(batch, rows.flatten(), batch.v_old[rows.flatten()],
                                      cfg.noise_level).view_as(rows).sum(dim=1)
    weights = call_weights(batch, cfg)
    weighted = advantages if weights is None else advantages * weights
    epochs = MinibatchEpochs(cfg, guard)
    for calls in epochs.minibatches(batch.num_calls, generator, per_call):
        if not bool(advantages[calls].any()):
            epochs.skip()  # nothing to learn (e.g. GRPO's uniform groups); Adam would still move
            continue
        step_rows = rows[calls].flatten()
        v = shard_forward(lambda part: step_velocity(learner, policy, batch, part), step_rows)
        log_prob = steps_log_prob(batch, step_rows, v, cfg.noise_level).view(len(calls), per_call).sum(dim=1)
        loss, metrics = clipped_policy_loss(log_prob, *to_device((old_log_prob[calls], weighted[calls]), v.device),
                                            cfg.clip_coef)
        epochs.measure(metrics)
        if epochs.stop_if(cfg.target_kl is not None and metrics["approx_kl"] > cfg.target_kl):
            break
        joint_metrics = {}
        if joint_loss is not None:
            joint, joint_metrics = joint_loss(calls)
            loss = loss + joint
        if epochs.step(loss, list(policy.parameters()) + list(joint_params), optimizer) is not None:
            epochs.measure_step(joint_metrics)
            if extra_step is not None:
                epochs.measure_step(extra_step(calls))
    out = {f"losses/{k}": float("nan") for k in POLICY_METRICS}
    out |= {f"losses/{k}": v for k, v in epochs.means().items()} | epochs.counts("kl_stopped")
    return out | {"losses/log_prob": float(old_log_prob.mean()),
                  "charts/advantage_mean": float(advantages.mean()),
                  "charts/advantage_std": float(advantages.std()) if len(advantages) > 1 else 0.0}
