"""PPO with Flow-SDE, the πRL baseline (docs/algorithm.md §7): the current policy acts with
Flow-SDE and a call's log-likelihood is the log-density of its stochastic denoising steps
(``stepnft.algos.likelihood``, shared with GRPO); a value head on the observation features gives
GAE advantages over policy calls from the sparse success reward (or, with ``reward: shaped``, that
plus shaping); the clipped surrogate and the value regression update policy and critic. Reads top
to bottom: config, GAE, the critic, the class the training loop drives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import torch
from torch import Tensor, nn

from stepnft.algos.base import Algorithm, NonFiniteGuard, make_optimizer
from stepnft.algos.likelihood import LikelihoodConfig, call_rewards, call_weights, policy_gradient_update
from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.policies.base import Policy
from stepnft.settings import WIDTH_MAX, Range


@dataclass
class PPOConfig(LikelihoodConfig):
    """Hyperparameters of PPO with Flow-SDE (πRL)."""

    defaults = {"name": "ppo"}

    gamma: Annotated[float, Range(ge=0, le=1)] = 0.99
    """Discount per policy call."""
    gae_lambda: Annotated[float, Range(ge=0, le=1)] = 0.95
    """GAE λ."""
    norm_adv: bool = True
    """Normalise the advantages over the iteration's calls (mean 0, std 1)."""
    critic_lr: Annotated[float, Range(gt=0, le=1)] = 1e-3
    """Adam learning rate of the value head (its own optimizer)."""
    critic_hidden_dim: Annotated[int, Range(ge=1, le=WIDTH_MAX)] = 256
    """Width of the value head's two hidden layers."""
    huber_delta: Annotated[float | None, Range(gt=0, le=1e6)] = None
    """The critic's loss: Huber with this δ (RLinf: 10), None: ``0.5 (V - R)^2``. The two agree
    while ``|V - R| < δ``."""
    value_clip: Annotated[float | None, Range(gt=0, le=1e6)] = None
    """Keep the critic's prediction within this of its value at rollout time, PPO-style: the loss
    is the larger of the clipped and unclipped errors (RLinf: 0.2); None: off."""
    critic_shares_encoder: bool = False
    """False: the value head reads the policy's features detached (only the policy's loss trains
    the encoder) and has its own Adam at ``critic_lr``. True: the value head sits on the policy's
    own features, as a value head on a VLA does (πRL), and the encoder is trained by the policy's
    loss plus ``value_coef`` times the critic's, in one backward and one step of one optimizer
    (the policy's AdamW, the value head a second parameter group at ``critic_lr`` with Adam's
    betas and no weight decay), the gradient clipped over both. Only encoder parameters that train
    receive it (a camera policy's CNN and instruction projection; a SmolVLA's VLM with ``train:
    vlm``, its state projection with ``expert+state``); with a frozen prefix (``train: expert``)
    or a state-only policy the head only reads the features."""
    value_coef: Annotated[float, Range(gt=0, le=1000)] = 0.5
    """With ``critic_shares_encoder``: the weight of the critic's loss in the joint loss
    (CleanRL's ``vf_coef``); unused otherwise (the critic then has its own optimizer)."""


# --- advantages ---------------------------------------------------------------------------------
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


# --- the critic ---------------------------------------------------------------------------------
class ValueHead(nn.Module):
    """``V_φ(o)``: a small MLP on the policy's value features (``policy.value_features``),
    detached unless ``critic_shares_encoder``."""

    def __init__(self, in_dim: int, hidden_dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.Tanh(), nn.Linear(hidden_dim, hidden_dim), nn.Tanh(),
                                 nn.Linear(hidden_dim, 1))

    def forward(self, features: Tensor) -> Tensor:
        return self.net(features).squeeze(-1)


def value_loss(value: Tensor, old_value: Tensor, returns: Tensor, cfg: PPOConfig,
               weights: Tensor | None = None) -> Tensor:
    """The critic's loss on ``[B]`` predictions ``value`` (with grad), their values at rollout
    time ``old_value`` and the GAE ``returns``: squared error or Huber (``cfg.huber_delta``), with
    ``cfg.value_clip`` the larger of the clipped and unclipped errors; mean with ``weights``."""
    def error(v: Tensor) -> Tensor:
        if cfg.huber_delta is None:
            return 0.5 * (v - returns).pow(2)
        return nn.functional.huber_loss(v, returns, reduction="none", delta=cfg.huber_delta)

    loss = error(value)
    if cfg.value_clip is not None:
        clipped = old_value + (value - old_value).clamp(-cfg.value_clip, cfg.value_clip)
        loss = torch.max(loss, error(clipped))
    return loss.mean() if weights is None else (loss * weights).mean()


CRITIC_ADAM = {"betas": (0.9, 0.999), "eps": 1e-8}
"""The value head's Adam settings (torch's defaults), its own optimizer or a group of the policy's."""


def value_features(policy: Policy, obs: dict[str, Tensor]) -> Tensor:
    """``policy.value_features`` of processed ``obs`` in the policy's precision, as float32."""
    with policy.autocast():
        return policy.value_features(obs).float()


def call_features(policy: Policy, batch: Batch) -> Tensor:
    """``[C, F]`` detached value features of every policy call (on the policy's device)."""
    with torch.no_grad():
        return value_features(policy, policy.prepare(batch.obs)).detach()


# --- the algorithm ------------------------------------------------------------------------------
class PPO(Algorithm):
    """PPO with Flow-SDE: the policy acts (no EMA), a value head gives GAE advantages."""

    name = "ppo"
    config_class = PPOConfig
    # The critic is built on the first batch, when the feature size is known.
    critic: ValueHead | None = None
    critic_optimizer: torch.optim.Optimizer | None = None
    """The value head's own Adam (None with ``critic_shares_encoder``: it is a group of ``optimizer``)."""
    critic_guard: NonFiniteGuard | None = None

    def _build_critic(self, in_dim: int) -> None:
        self.critic = ValueHead(in_dim, self.cfg.critic_hidden_dim).to(self.policy.device)
        if self.cfg.critic_shares_encoder:
            # One loss, one backward, one step: the head joins the policy's optimizer as its own group,
            # updated by Adam's rule at critic_lr as the separate critic is (AdamW without weight decay).
            self.optimizer = make_optimizer(self.policy.parameters(), self.cfg)
            self.optimizer.add_param_group({"params": list(self.critic.parameters()), "lr": self.cfg.critic_lr,
                                            **CRITIC_ADAM, "weight_decay": 0.0})
            return
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.critic_lr, **CRITIC_ADAM)
        self.critic_guard = NonFiniteGuard(self.cfg)

    def update(self, batch: Batch) -> dict[str, float]:
        cfg = self.cfg
        features = call_features(self.policy, batch)
        if self.critic is None:
            self._build_critic(features.shape[1])
        with torch.no_grad():
            values = self.critic(features).cpu()  # GAE and the advantages: on the CPU, like the batch
        advantages, returns = gae(call_rewards(batch, cfg, cfg.gamma), values, batch.done, batch.episode, cfg.gamma,
                                  cfg.gae_lambda)
        explained = 1.0 - float((returns - values).var() / returns.var()) if returns.var() > 0 else float("nan")
        raw = {"charts/advantage_mean": float(advantages.mean()),
               "charts/advantage_std": float(advantages.std()) if len(advantages) > 1 else 0.0}
        if cfg.norm_adv and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        weights = call_weights(batch, cfg)

        def critic_loss(calls: Tensor, features: Tensor) -> Tensor:
            old, target, w = to_device((values[calls], returns[calls], None if weights is None else weights[calls]),
                                       features.device)
            return value_loss(self.critic(features), old, target, cfg, w)

        def critic_step(calls: Tensor) -> dict[str, float]:
            loss = critic_loss(calls, features[calls])
            self.critic_guard.step(loss, list(self.critic.parameters()), self.critic_optimizer)
            return {"value_loss": loss.item()}

        def shared_critic_loss(calls: Tensor) -> tuple[Tensor, dict[str, float]]:
            # The value head on the encoder's current features, with their gradient (under torchrun
            # every process computes it on the whole minibatch: the same gradient, which DDP's mean keeps).
            obs = self.policy.prepare(batch.calls_obs(calls))
            loss = critic_loss(calls, value_features(self.policy, obs))
            return cfg.value_coef * loss, {"value_loss": loss.item()}

        self.policy.train()
        if cfg.critic_shares_encoder:
            metrics = policy_gradient_update(self.policy, self.optimizer, batch, advantages, cfg, self.generator,
                                             guard=self.guard, joint_loss=shared_critic_loss,
                                             joint_params=list(self.critic.parameters()))
        else:
            metrics = policy_gradient_update(self.policy, self.optimizer, batch, advantages, cfg, self.generator,
                                             critic_step, self.guard)
        return metrics | raw | {"losses/explained_variance": explained, "charts/value_mean": float(values.mean())}

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        if self.critic is not None:
            state |= {"critic": self.critic.state_dict()}
        if self.critic_optimizer is not None:
            state |= {"critic_optimizer": self.critic_optimizer.state_dict()}
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "critic" in state:  # first: a shared critic is a parameter group of the policy's optimizer
            self._build_critic(state["critic"]["net.0.weight"].shape[1])
            self.critic.load_state_dict(state["critic"])
        super().load_state_dict(state)
        if "critic" in state and self.critic_optimizer is not None:
            self.critic_optimizer.load_state_dict(state["critic_optimizer"])
