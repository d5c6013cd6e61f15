"""PPO with Flow-SDE, the πRL baseline (docs/algorithm.md §7): the current policy acts with
Flow-SDE, the denoising chain is part of the decision, so a policy call's log-likelihood is the
Gaussian log-density of its stochastic denoising step(s); a value head on the observation
features gives GAE advantages over policy calls from the sparse success reward; the clipped
surrogate and the value regression update policy and critic. Reads top to bottom: configs, the
likelihood of a call, GAE, the update (shared with GRPO, ``stepnft.algos.grpo``), the critic, the
class the training loop drives.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Annotated, Any, Callable

import torch
from torch import Tensor, nn

from stepnft.algos.base import AlgoConfig, Algorithm, NonFiniteGuard, RolloutSpec, make_optimizer, step_velocity
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
    the stochastic denoising steps. ``minibatch_size`` counts policy calls."""

    defaults = {"noise_level": 0.5}

    clip_coef: Annotated[float, Range(gt=0)] = 0.2
    """PPO clip range ε of the ratio ``exp(log π - log π_old)``."""
    target_kl: Annotated[float | None, Range(gt=0)] = None
    """Skip the rest of an iteration's updates once a minibatch's approx-KL exceeds this (looked
    at before stepping); None: off."""

    def check(self) -> None:
        super().check()
        if self.noise_level == 0:
            raise self.fail("{noise_level} must be > 0 for PPO and GRPO: their likelihood needs noise (the ODE "
                            "ablation is π-StepNFT's)", self.noise_level)


@dataclass
class PPOConfig(LikelihoodConfig):
    """Hyperparameters of PPO with Flow-SDE (πRL). ``minibatch_size`` counts policy calls."""

    defaults = {"name": "ppo"}

    gamma: Annotated[float, Range(ge=0, le=1)] = 0.99
    """Discount per policy call."""
    gae_lambda: Annotated[float, Range(ge=0, le=1)] = 0.95
    """GAE λ."""
    norm_adv: bool = True
    """Normalise the advantages over the iteration's calls (mean 0, std 1)."""
    critic_lr: Annotated[float, Range(gt=0)] = 1e-3
    """Adam learning rate of the value head (its own optimizer)."""
    critic_hidden_dim: Annotated[int, Range(ge=1)] = 256
    """Width of the value head's two hidden layers."""


# --- the likelihood of a policy call ------------------------------------------------------------
def call_step_rows(batch: Batch) -> Tensor:
    """``[C, k]``: the rows of the recorded denoising steps of every policy call (k per call)."""
    counts = torch.bincount(batch.call, minlength=batch.num_calls)
    if batch.num_calls == 0 or bool((counts != counts[0]).any()) or int(counts[0]) == 0:
        raise ValueError("every policy call needs the same number (>= 1) of recorded denoising steps")
    return torch.argsort(batch.call, stable=True).view(batch.num_calls, int(counts[0]))


def steps_log_prob(batch: Batch, rows: Tensor, v: Tensor, noise_level: float) -> Tensor:
    """``[R]`` log-density of recorded steps ``rows`` under velocity ``v`` ``[R, H, A]``, over
    the chunk positions their call executed (on ``v``'s device)."""
    x_next, x_t, t, dt, mask = to_device((batch.x_next[rows], batch.x_t[rows], batch.t[rows], batch.dt[rows],
                                          batch.mask[batch.call[rows]]), v.device)
    return sde_step_log_prob(x_next, x_t, v, t, dt, noise_level, mask)


# --- advantages ---------------------------------------------------------------------------------
def success_rewards(batch: Batch) -> Tensor:
    """``[C]`` sparse reward: 1 at the last call of a successful episode, 0 elsewhere."""
    return (batch.done & batch.episode_success[batch.episode]).float()


def gae(reward: Tensor, value: Tensor, done: Tensor, episode: Tensor, gamma: float,
        lam: float) -> tuple[Tensor, Tensor]:
    """Advantages and returns ``[C]`` by GAE over policy calls: ``δ_n = r_n + γ V_{n+1} - V_n``,
    ``A_n = δ_n + γ λ A_{n+1}``, where ``n+1`` is the next call of the same episode (the calls of
    an episode are in row order, as the collector writes them). Nothing follows the call that
    ends an episode (``done``): the step cap is treated as the end too, the observation holding
    no clock."""
    r, v, d, e = reward.tolist(), value.tolist(), done.tolist(), episode.tolist()
    adv = [0.0] * len(r)
    following: dict[int, tuple[float, float]] = {}  # episode -> (advantage, value) of its next call
    for n in reversed(range(len(r))):
        next_adv, next_value = (0.0, 0.0) if d[n] else following.get(e[n], (0.0, 0.0))
        adv[n] = r[n] + gamma * next_value - v[n] + gamma * lam * next_adv
        following[e[n]] = (adv[n], v[n])
    advantages = torch.tensor(adv, dtype=value.dtype)
    return advantages, advantages + value


# --- the update ---------------------------------------------------------------------------------
def policy_gradient_update(
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    advantages: Tensor,
    cfg: LikelihoodConfig,
    generator: torch.Generator | None = None,
    extra_step: Callable[[Tensor], dict[str, float]] | None = None,
    guard: NonFiniteGuard | None = None,
) -> dict[str, float]:
    """``cfg.update_epochs`` epochs of clipped-surrogate steps over minibatches of policy calls,
    ``advantages`` ``[C]`` per call. ``log π_old`` comes from the recorded ``v_old`` (the acting
    policy is the policy itself, so no extra forward pass). ``extra_step(calls)`` runs after each
    policy step on the same calls (PPO's critic). Steps with a non-finite loss or gradient are
    skipped (``guard``). Returns metrics averaged over minibatches. Under ``torchrun`` the
    processes share each minibatch (``stepnft.distributed``)."""
    guard = guard or NonFiniteGuard(cfg)
    learner = data_parallel(policy)
    rows = call_step_rows(batch)
    per_call = rows.shape[1]
    with torch.no_grad():
        old_log_prob = steps_log_prob(batch, rows.flatten(), batch.v_old[rows.flatten()],
                                      cfg.noise_level).view_as(rows).sum(dim=1)
    sums: dict[str, float] = defaultdict(float)
    seen = steps = skipped = 0
    stopped = False
    for _ in range(cfg.update_epochs):
        for calls in torch.randperm(batch.num_calls, generator=generator).split(cfg.minibatch_size):
            if not bool(advantages[calls].any()):
                skipped += 1  # nothing to learn (e.g. GRPO's uniform groups); Adam would still move
                continue
            step_rows = rows[calls].flatten()
            v = shard_forward(lambda part: step_velocity(learner, policy, batch, part), step_rows)
            log_prob = steps_log_prob(batch, step_rows, v, cfg.noise_level).view(len(calls), per_call).sum(dim=1)
            loss, metrics = clipped_policy_loss(log_prob, *to_device((old_log_prob[calls], advantages[calls]), v.device),
                                                cfg.clip_coef)
            for k, val in metrics.items():
                sums[k] += val
            seen += 1
            stopped = cfg.target_kl is not None and metrics["approx_kl"] > cfg.target_kl
            if stopped:
                break
            grad_norm = guard.step(loss, list(policy.parameters()), optimizer)
            if grad_norm is None:
                continue
            sums["grad_norm"] += grad_norm
            steps += 1
            if extra_step is not None:
                for k, val in extra_step(calls).items():
                    sums[k] += val
        if stopped:
            break
    # The same names every iteration, NaN (logged as null) when every minibatch was skipped.
    out = {f"losses/{k}": math.nan for k in ("policy_loss", "approx_kl", "old_approx_kl", "clipfrac", "ratio_max")}
    out |= {f"losses/{k}": v / max(seen, 1) for k, v in sums.items()}
    out |= {f"losses/{k}": sums[k] / max(steps, 1) for k in ("grad_norm", "value_loss") if k in sums}
    out |= {"losses/update_steps": float(steps), "losses/kl_stopped": float(stopped),
            "losses/skipped_empty": float(skipped), "losses/skipped_nonfinite": float(guard.take_skipped()),
            "losses/log_prob": float(old_log_prob.mean()),
            "charts/advantage_mean": float(advantages.mean()),
            "charts/advantage_std": float(advantages.std()) if len(advantages) > 1 else 0.0}
    return out


# --- the critic ---------------------------------------------------------------------------------
class ValueHead(nn.Module):
    """``V_φ(o)``: a small MLP on the policy's observation features (detached: the critic does
    not shape the policy's encoder)."""

    def __init__(self, in_dim: int, hidden_dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.Tanh(), nn.Linear(hidden_dim, hidden_dim), nn.Tanh(),
                                 nn.Linear(hidden_dim, 1))

    def forward(self, features: Tensor) -> Tensor:
        return self.net(features).squeeze(-1)


def call_features(policy: Policy, batch: Batch) -> Tensor:
    """``[C, F]`` detached observation features of every policy call (on the policy's device)."""
    with torch.no_grad():
        return policy.encode(policy.prepare(batch.obs)).flatten(1).detach()


# --- the algorithm ------------------------------------------------------------------------------
class PPO(Algorithm):
    """PPO with Flow-SDE: the policy acts (no EMA), a value head gives GAE advantages."""

    name = "ppo"
    config_class = PPOConfig

    def __init__(self, policy: Policy, cfg: PPOConfig, iterations: int, generator: torch.Generator):
        super().__init__(policy, cfg, iterations, generator)
        self.optimizer = make_optimizer(policy.parameters(), cfg)
        self.guard, self.critic_guard = NonFiniteGuard(cfg), NonFiniteGuard(cfg)
        self.critic: ValueHead | None = None  # built on the first batch, when the feature size is known
        self.critic_optimizer: torch.optim.Optimizer | None = None

    def _build_critic(self, in_dim: int) -> None:
        self.critic = ValueHead(in_dim, self.cfg.critic_hidden_dim).to(self.policy.device)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.critic_lr)

    @property
    def rollout(self) -> RolloutSpec:
        return self.cfg.rollout_spec()

    def acting_policy(self) -> Policy:
        return self.policy.eval()

    def update(self, batch: Batch) -> dict[str, float]:
        cfg = self.cfg
        features = call_features(self.policy, batch)
        if self.critic is None:
            self._build_critic(features.shape[1])
        with torch.no_grad():
            values = self.critic(features).cpu()  # GAE and the advantages: on the CPU, like the batch
        advantages, returns = gae(success_rewards(batch), values, batch.done, batch.episode, cfg.gamma, cfg.gae_lambda)
        explained = 1.0 - float((returns - values).var() / returns.var()) if returns.var() > 0 else float("nan")
        raw = {"charts/advantage_mean": float(advantages.mean()),
               "charts/advantage_std": float(advantages.std()) if len(advantages) > 1 else 0.0}
        if cfg.norm_adv and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        def critic_step(calls: Tensor) -> dict[str, float]:
            value_loss = 0.5 * (self.critic(features[calls]) - returns[calls].to(features.device)).pow(2).mean()
            self.critic_guard.step(value_loss, list(self.critic.parameters()), self.critic_optimizer)
            return {"value_loss": value_loss.item()}

        self.policy.train()
        metrics = policy_gradient_update(self.policy, self.optimizer, batch, advantages, cfg, self.generator,
                                         critic_step, self.guard)
        return metrics | raw | {"losses/explained_variance": explained, "charts/value_mean": float(values.mean())}

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"optimizer": self.optimizer.state_dict()}
        if self.critic is not None:
            state |= {"critic": self.critic.state_dict(), "critic_optimizer": self.critic_optimizer.state_dict()}
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        if "critic" in state:
            self._build_critic(state["critic"]["net.0.weight"].shape[1])
            self.critic.load_state_dict(state["critic"])
            self.critic_optimizer.load_state_dict(state["critic_optimizer"])
