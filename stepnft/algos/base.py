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

import dataclasses
import importlib
import math
import typing
from abc import ABC, abstractmethod
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import torch
from torch import Tensor, nn

from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.plugins import PluginRegistry
from stepnft.policies.base import Policy
from stepnft.rollout.plan import RolloutSpec  # noqa: F401 - what an algorithm tells the collector
from stepnft.settings import Range, SettingError, Settings

ALGORITHMS: dict[str, str] = PluginRegistry("stepnft.algorithms", {
    "stepnft": "stepnft.algos.stepnft:StepNFT",
    "ppo": "stepnft.algos.ppo:PPO",
    "grpo": "stepnft.algos.grpo:GRPO",
})
"""Registered algorithms by ``algo.name`` (imported on first use): stepnft's own and those of
installed packages (entry-point group ``stepnft.algorithms``, ``stepnft.plugins``)."""


PER_VARIANT = {"per_variant": True}
"""Field metadata of an :class:`AlgoConfig` setting that a variant of another algorithm does not
take from the base config (it tells the variants apart, e.g. ``ppo`` from ``ppo-one``, or its
valid values depend on the algorithm): see ``stepnft.algos.variants.SHARED_FIELDS``."""


@dataclass
class AlgoConfig(Settings):
    """Settings every algorithm has: its name, the optimizer of the policy and how rollouts
    explore. An algorithm's config class sets its own defaults of these in ``defaults``
    (e.g. ``{"name": "ppo", "noise_level": 0.5}``); the fields stay declared here, once."""

    section: ClassVar[str] = "algo"
    defaults: ClassVar[dict[str, Any]] = {}
    """This algorithm's defaults of settings declared in a base class (applied by ``__init_subclass__``)."""

    name: str = field(default="stepnft", metadata=PER_VARIANT)
    """Which algorithm: the keys of ``stepnft.algos.base.ALGORITHMS``."""
    lr: Annotated[float, Range(gt=0, le=1)] = 1e-4
    """AdamW learning rate of the policy."""
    adam_betas: tuple[Annotated[float, Range(ge=0, lt=1)], Annotated[float, Range(ge=0, lt=1)]] = (0.9, 0.95)
    """AdamW (beta1, beta2)."""
    adam_eps: Annotated[float, Range(gt=0, le=1)] = 1e-8
    """AdamW epsilon."""
    weight_decay: Annotated[float, Range(ge=0, le=1)] = 0.0
    """AdamW weight decay."""
    grad_clip: Annotated[float, Range(gt=0, le=1e6)] = 1.0
    """Global gradient-norm clip."""
    update_epochs: Annotated[int, Range(ge=1, le=1000)] = 2
    """Passes over each iteration's samples."""
    minibatch_size: Annotated[int, Range(ge=1, le=2**20)] = 128
    """Recorded denoising steps per gradient step, for every algorithm (with K recorded steps per
    policy call, PPO and GRPO take whole calls: ``minibatch_size // K`` of them, at least one; so
    does π-StepNFT with a policy that shares a call's prefix among its steps, a LeRobot VLA)."""
    nonfinite_patience: Annotated[int, Range(ge=1, le=10**6)] = 20
    """Optimizer steps in a row whose loss or gradient is not finite (each is skipped and counted
    as ``losses/skipped_nonfinite``) before the run stops with its last checkpoint intact."""
    noise_level: Annotated[float, Range(ge=0, le=10)] = 0.2
    """Flow-SDE noise level ``a`` of training rollouts (0: ODE rollouts, π-StepNFT's exploration
    ablation; PPO and GRPO need > 0: their likelihood needs noise). Default 0.2 for π-StepNFT,
    0.5 for PPO and GRPO."""
    sde_steps: Literal["all", "one"] = field(default="all", metadata=PER_VARIANT)
    """Which denoising steps of a rollout are stochastic: ``all`` (π-StepNFT's paper; PPO and GRPO
    then sum a call's log-likelihood over the K steps) or ``one`` random step per call, the others
    ODE (as πRL does; π-StepNFT then needs ``record_steps: one``: the ODE steps carry no
    exploration to learn from)."""
    group_size: Annotated[int, Range(ge=1, le=1024)] = field(default=1, metadata=PER_VARIANT)
    """Episodes started from the same task and initial state, in groups (1: every episode from
    its own state; each task's episodes come in whole groups). GRPO normalises success within
    them (>= 2, default 4); π-StepNFT balances labels within them with ``label_balance: group``."""
    episode_weighting: bool = True
    """Beyond the paper: every episode carries the same total weight, however many policy calls
    it made (failures run to the step cap and would otherwise dominate the batch: a failing
    pick-place episode stores ~4x the samples of a successful door-open one). π-StepNFT weights
    its samples; PPO and GRPO their calls' surrogate terms (and PPO its critic's loss), as RLinf's
    LIBERO losses do (``masked_mean_ratio``). Default on: measured 0.75 vs 0.65 average success
    over 3 seeds for π-StepNFT (docs/experiments.md §3b); not yet measured for PPO and GRPO."""

    def __init_subclass__(cls, **kwargs) -> None:
        """Turn the subclass's ``defaults`` into field declarations with the inherited type and
        metadata (so the type, range and docstring stay declared once, here)."""
        super().__init_subclass__(**kwargs)
        if "defaults" not in cls.__dict__:
            return
        declared = {f.name: f for f in dataclasses.fields(cls.__mro__[1])}
        hints = typing.get_type_hints(cls.__mro__[1], include_extras=True)
        cls.__annotations__ = {**{k: hints[k] for k in cls.defaults}, **cls.__dict__.get("__annotations__", {})}
        for key, value in cls.defaults.items():
            setattr(cls, key, field(default=value, metadata=declared[key].metadata))

    def check(self) -> None:
        if self.name != type(self).name or algorithm_class(self.name).config_class is not type(self):
            raise self.fail(f"{{name}} must be {type(self).name} for {type(self).__name__}", self.name)

    def rollout_spec(self) -> RolloutSpec:
        """How this algorithm's rollouts sample, and what they record: here the stochastic steps
        (with one stochastic step per call only that step has a density)."""
        return RolloutSpec(self.noise_level, self.sde_steps, self.sde_steps, self.group_size)


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


def call_step_rows(batch: Batch) -> Tensor:
    """``[C, k]``: the rows of the recorded denoising steps of every policy call (k per call)."""
    counts = torch.bincount(batch.call, minlength=batch.num_calls)
    if batch.num_calls == 0 or bool((counts != counts[0]).any()) or int(counts[0]) == 0:
        raise ValueError("every policy call needs the same number (>= 1) of recorded denoising steps")
    return torch.argsort(batch.call, stable=True).view(batch.num_calls, int(counts[0]))


def step_velocity(learner: nn.Module, policy: Policy, batch: Batch, rows: Tensor,
                  share_prefix: bool | None = None) -> Tensor:
    """The learner's velocity ``[R, H, A]`` at recorded steps ``rows`` of ``batch`` (which stays
    on the CPU): their observations processed on the CPU, the forward pass on the policy's device.
    With ``share_prefix`` (None: ``policy.shares_prefix_in_update``) each policy call among
    ``rows`` is processed and encoded once, and its steps read that context (``Policy.forward``'s
    ``context_rows``): the same velocities, a VLA's prefix encoded once instead of per step."""
    x_t, t = to_device((batch.x_t[rows], batch.t[rows]), policy.device)
    if not (policy.shares_prefix_in_update if share_prefix is None else share_prefix):
        return learner(policy.prepare(batch.steps_obs(rows)), x_t, t)
    calls, context_rows = batch.call[rows].unique(return_inverse=True)
    obs = policy.prepare(batch.calls_obs(calls))
    return learner(obs, x_t, t, context_rows=context_rows.to(policy.device))


# --- what every algorithm may read from a batch ------------------------------------------------
def episode_weights(episode: Tensor) -> Tensor:
    """``[B]`` weights giving every episode the same total weight (mean 1 over the batch)."""
    _, inverse, counts = episode.unique(return_inverse=True, return_counts=True)
    w = 1.0 / counts[inverse].float()
    return w * len(w) / w.sum()


def call_progress(batch: Batch, lam: float) -> Tensor:
    """``[C]`` how much each policy call raised the shaped reward: the λ-averaged reward level
    from this call on, ``G_c = (1 - λ) r_c + λ G_{c+1}`` (``r`` the mean reward per executed env
    step; after the episode's last call its level holds), minus the level of the call before
    (the first call: its own). With a reward that is a function of the state (a potential, as
    MetaWorld's shaping is), this is the call's effect on where the episode is heading."""
    level = (batch.reward / batch.mask.sum(dim=1).clamp(min=1)).tolist()
    episode = batch.episode.tolist()
    progress = [0.0] * len(level)
    ahead: dict[int, float] = {}  # episode -> G of its next call
    for c in reversed(range(len(level))):  # the calls of an episode are in row order
        ahead[episode[c]] = (1 - lam) * level[c] + lam * ahead.get(episode[c], level[c])
        progress[c] = ahead[episode[c]]
    before: dict[int, float] = {}
    for c in range(len(level)):
        progress[c] -= before.get(episode[c], level[c])
        before[episode[c]] = level[c]
    return torch.tensor(progress, dtype=torch.float32)


class MinibatchEpochs:
    """The minibatch loop of every algorithm's update: ``cfg.update_epochs`` passes over the
    samples, each in a fresh random order, in minibatches of ``cfg.minibatch_size`` recorded steps. It sums the
    metrics of the minibatches (``measure``) and of the optimizer steps (``step``), remembers an
    early stop (``stop_if``: looked at before stepping, so no step is taken from a policy already
    too far) and averages. An update reads::

        epochs = MinibatchEpochs(cfg, guard)
        for idx in epochs.minibatches(num_samples, generator):
            if nothing to learn from idx:
                epochs.skip()
                continue
            loss, metrics = ...
            epochs.measure(metrics)
            if epochs.stop_if(metrics["approx_kl"] > cfg.target_kl):
                break                      # ends every pass
            epochs.step(loss, params, optimizer)
        metrics = epochs.means() | epochs.counts("kl_stopped")
    """

    def __init__(self, cfg: AlgoConfig, guard: NonFiniteGuard):
        self.cfg, self.guard = cfg, guard
        self.sums: dict[str, float] = defaultdict(float)  # over measured minibatches
        self.step_sums: dict[str, float] = defaultdict(float)  # over optimizer steps taken
        self.seen = self.steps = self.skipped = 0
        self.stopped = False

    def minibatches(self, num_samples: int, generator: torch.Generator | None, steps_per_sample: int = 1
                    ) -> Iterator[Tensor]:
        """Index tensors ``[<= minibatch_size // steps_per_sample]`` (at least one sample): a sample
        holds ``steps_per_sample`` recorded steps (PPO's and GRPO's policy calls hold K), so every
        algorithm's minibatch holds about ``minibatch_size`` recorded steps. Each pass draws its
        ``torch.randperm`` when it starts."""
        size = max(1, self.cfg.minibatch_size // steps_per_sample)
        for _ in range(self.cfg.update_epochs):
            yield from torch.randperm(num_samples, generator=generator).split(size)

    def skip(self) -> None:
        """A minibatch with nothing to learn (``losses/skipped_empty``)."""
        self.skipped += 1

    def measure(self, metrics: dict[str, float]) -> None:
        """Add a minibatch's metrics to the averages over minibatches."""
        for k, v in metrics.items():
            self.sums[k] += v
        self.seen += 1

    def stop_if(self, condition: bool) -> bool:
        """Record the early-stop test of this minibatch; True: skip the rest of the update."""
        self.stopped = condition
        return condition

    def step(self, loss: Tensor, params: list[Tensor], optimizer: torch.optim.Optimizer) -> float | None:
        """One optimizer step through the guard; returns the gradient norm (None: skipped)."""
        grad_norm = self.guard.step(loss, params, optimizer)
        if grad_norm is not None:
            self.step_sums["grad_norm"] += grad_norm
            self.steps += 1
        return grad_norm

    def measure_step(self, metrics: dict[str, float]) -> None:
        """Add metrics averaged over optimizer steps (e.g. PPO's critic loss)."""
        for k, v in metrics.items():
            self.step_sums[k] += v

    def means(self) -> dict[str, float]:
        """Minibatch metrics averaged over measured minibatches, step metrics over steps taken."""
        return ({k: v / max(self.seen, 1) for k, v in self.sums.items()}
                | {k: v / max(self.steps, 1) for k, v in self.step_sums.items()})

    def counts(self, stopped_name: str) -> dict[str, float]:
        """``losses/update_steps``, ``losses/<stopped_name>``, ``losses/skipped_empty``, ``losses/skipped_nonfinite``."""
        return {"losses/update_steps": float(self.steps), f"losses/{stopped_name}": float(self.stopped),
                "losses/skipped_empty": float(self.skipped), "losses/skipped_nonfinite": float(self.guard.take_skipped())}


class Algorithm(ABC):
    """One RL fine-tuning method (see the module doc for the loop that drives it). Every one
    owns an AdamW optimizer of the policy and a NonFiniteGuard; by default the policy acts."""

    name: ClassVar[str]
    config_class: ClassVar[type[AlgoConfig]]

    def __init__(self, policy: Policy, cfg: AlgoConfig, iterations: int, generator: torch.Generator):
        self.policy, self.cfg, self.iterations, self.generator = policy, cfg, iterations, generator
        self.optimizer = make_optimizer(policy.parameters(), cfg)
        self.guard = NonFiniteGuard(cfg)

    @property
    def rollout(self) -> RolloutSpec:
        """How the collector should sample and record."""
        return self.cfg.rollout_spec()

    def acting_policy(self) -> Policy:
        """The policy that acts in training rollouts (default: the trained one, in eval mode)."""
        return self.policy.eval()

    def eval_policy(self) -> Policy:
        """The policy that evaluation and ``policy/`` report (default: the trained one)."""
        return self.policy

    @abstractmethod
    def update(self, batch: Batch) -> dict[str, float]:
        """Learn from one iteration's batch; returns metrics under stable names."""

    def end_iteration(self, iteration: int) -> dict[str, float]:
        """Called once after each iteration's update (0-based ``iteration``); returns metrics."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """Everything the algorithm owns beyond the policy weights (tensors and JSON values);
        a subclass adds what it owns besides the optimizer."""
        return {"optimizer": self.optimizer.state_dict(), "nonfinite_in_a_row": self.guard.in_a_row}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.optimizer.load_state_dict(state["optimizer"])
        self.guard.in_a_row = state.get("nonfinite_in_a_row", 0)


def algorithm_class(name: str) -> type[Algorithm]:
    if name not in ALGORITHMS:
        raise SettingError(f"{{name}} must be one of {', '.join(ALGORITHMS)}", "algo", name)
    module, cls = ALGORITHMS[name].split(":")
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as err:  # a plugin's module: one line naming it
        reason = str(err).splitlines()[0].replace("{", "(").replace("}", ")") if str(err) else type(err).__name__
        raise SettingError(f"{{name}} {name!r} ({ALGORITHMS.sources.get(name, 'stepnft')}) cannot be imported from "
                           f"{ALGORITHMS[name]}: {reason}", "algo") from None


def config_class(name: str) -> type[AlgoConfig]:
    """The config dataclass of algorithm ``name``."""
    return algorithm_class(name).config_class


def make_algorithm(cfg: AlgoConfig, policy: Policy, iterations: int, generator: torch.Generator) -> Algorithm:
    return algorithm_class(cfg.name)(policy, cfg, iterations, generator)
